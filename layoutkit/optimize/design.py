"""The design problem: mesh + envelope + candidate sites (+ stations), loaded once (:class:`DesignProblem`).

Everything an optimisation, a score or a render needs about *where the sensors could go and where the
target will be* lives in one frozen object: the candidates (with their tilted orientations when tilt is
a design variable, :mod:`layoutkit.optimize.tilt`), the design poses, the stations, the visibility of
every candidate at every design pose (ray-cast once), the angle Jacobians (Chen eqs. 10–14, computed
on first use), the "one orientation per site" conflicts, and the provenance that the layout JSON records
(mesh path and hash, envelope, candidates, stations) so that ``render`` and ``score`` can find them again.

Visibility of a selection at the design poses is a slice of what was computed (``visible[:, :, sel]``);
only new poses (a dense or held-out set) are ray-cast again (:meth:`DesignProblem.visibility_at`).
Frames: positions and normals in the body frame (m); poses ``p_world = R p_body + t`` (world frame, the
stations' poses in it).
"""
from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["DesignProblem", "layout_visibility", "mean_station_direction", "expand_tilt", "layout_sources",
           "default_spacing"]


def layout_visibility(mesh, positions, normals, R, t, stations, half_angle_deg=60.0, max_range=None):
    """``(P, S, n)`` bool visibility of sensors ``positions, normals (n, 3)`` at world poses ``R (P, 3, 3),
    t (P, 3)`` from ``stations``; without a mesh: acceptance cone and field of view only (exact for a
    convex body, no occlusion)."""
    from ..visibility import envelope_visibility

    kw = {} if max_range is None else {"max_range": max_range}
    if mesh is None:
        return envelope_visibility(None, positions, normals, R, t, stations, sensor_half_angle_deg=half_angle_deg,
                                   occlusion=False, surface_offset=0.0, **kw)
    return envelope_visibility(mesh, positions, normals, R, t, stations, sensor_half_angle_deg=half_angle_deg, **kw)


def mean_station_direction(rotations, translations, stations):
    """Mean unit direction (3,) from the body to the stations, body frame, over poses
    ``rotations (P, 3, 3)``, ``translations (P, 3)`` (body-to-world, m) and every station: the axis the
    envelope looks at the body from (for meridional tilts, ``tilt_toward="station"``)."""
    R, t = np.asarray(rotations, float), np.asarray(translations, float)
    d = np.stack([np.einsum("pji,pj->pi", R, st.translation[None, :] - t) for st in stations])
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    m = d.reshape(-1, 3).mean(axis=0)
    return m / np.linalg.norm(m)


def expand_tilt(cand, max_tilt_deg, directions=4, toward=None):
    """Sites ``cand`` (:class:`layoutkit.layout.Layout`) → (site, orientation) candidates.

    Returns ``(Layout, site (M,) int, tilt_deg (M,))``: the plain sites first (their ids), then each site's
    tilted orientations with ids ``<site>~t<j>`` (j = 1, 2, ... per site) and per-candidate extras
    ``x-site``, ``x-tilt-deg`` (:func:`layoutkit.optimize.tilt.tilt_orientations`; ``toward`` (3,) body
    axis: meridional tilts only)."""
    from ..layout import Layout
    from .tilt import tilt_orientations

    if not max_tilt_deg or max_tilt_deg <= 0:
        return cand, np.arange(cand.n), np.zeros(cand.n)
    pos, axes, site, tilt = tilt_orientations(cand.positions, cand.normals, float(max_tilt_deg), int(directions),
                                              toward=toward)
    occ = np.zeros(cand.n, int)
    ids = []
    for s in site:  # the plain sites come first, then each site's tilted orientations in order
        ids.append(cand.ids[s] if occ[s] == 0 else f"{cand.ids[s]}~t{occ[s]}")
        occ[s] += 1
    lay = Layout(pos, axes, tuple(ids), dict(cand.metadata),
                 tuple({"x-site": cand.ids[s], "x-tilt-deg": float(tt)} for s, tt in zip(site, tilt)))
    return lay, site, tilt


def _resolve_toward(toward, R, t, stations):
    if isinstance(toward, str):
        if toward != "station":
            raise ValueError(f"tilt_toward: expected 'station' or a 3-vector, got {toward!r}")
        return mean_station_direction(R, t, stations)
    return toward


def _abs(p) -> str:
    return str(Path(p).resolve())


#: Poisson-disk sampling at spacing s puts about this many sites per (area / s²) on a surface (measured:
#: 695 sites at 6 mm on a 0.0426 m² headset hull, 394 at 8 mm)
_SITES_PER_AREA_OVER_S2 = 0.59


def default_spacing(mesh, k=None) -> float:
    """Candidate spacing (m) when none is given: 1 % of the mesh's largest extent, but never so fine that
    the mesh holds more than about ``clamp(25 k, 400, 1500)`` sites (k sensors; the relaxation's time grows
    with the candidates × poses, and above ~2,000 candidates it no longer fits a few minutes)."""
    s = 0.01 * float(np.max(mesh.extents))
    if k is not None:
        n = min(max(25 * int(k), 400), 1500)
        s = max(s, float(np.sqrt(_SITES_PER_AREA_OVER_S2 * float(mesh.area) / n)))
    return s


def _load_candidates(mesh, candidates, spacing, keepout, seed, max_candidates, k=None):
    """Candidate Layout and its provenance entry."""
    from ..candidates import sample_candidates
    from ..layout import Layout, load_layout

    if isinstance(candidates, Layout):
        return candidates, {"given": candidates.n}
    if candidates is not None:
        return load_layout(candidates), {"file": _abs(candidates)}
    if mesh is None:
        raise ValueError("candidates: give a candidate file or a mesh to sample sites on")
    chosen = spacing is None
    if chosen:
        spacing = default_spacing(mesh, k)
    cand = sample_candidates(mesh, spacing=spacing, keepout=keepout, rng=seed, max_count=max_candidates)
    return cand, {"sampled": {"spacing_m": float(spacing), "spacing_chosen": bool(chosen),
                              "keepout": cand.metadata.get("keepout", []), "seed": seed, "max_count": max_candidates}}


@dataclass(frozen=True, eq=False)
class DesignProblem:
    """A design problem loaded once (module docstring). Build with :meth:`load` (files / objects) or
    :meth:`from_arrays` (arrays of one station at the origin, the array API).

    candidates : :class:`layoutkit.layout.Layout` of the N candidates (tilted orientations after the
        plain sites); site (N,) int: the site of each candidate; tilt_deg (N,): its tilt from the normal.
    rotations (P, 3, 3), translations (P, 3) m : the design poses, body in the world frame.
    stations : tuple of :class:`layoutkit.lighthouse.Station`. visible (P, S, N) bool : lit candidates.
    mesh : trimesh (occlusion) or None (acceptance cone and field of view only).
    envelope : the :class:`layoutkit.envelope.Envelope` of the poses, or None.
    half_angle_deg, max_tilt_deg, tilt_toward, tilt_directions, max_range_m : how visibility and the
        orientations were made (an :class:`OptimizeSpec` must agree, :meth:`check_spec`).
    provenance : JSON-able record of the inputs (mesh path + hash, envelope, candidates, stations).
    """

    candidates: object
    rotations: np.ndarray
    translations: np.ndarray
    stations: tuple
    visible: np.ndarray
    site: np.ndarray
    tilt_deg: np.ndarray
    mesh: object = None
    envelope: object = None
    half_angle_deg: float = 60.0
    max_tilt_deg: float = 0.0
    tilt_toward: object = None
    tilt_directions: int = 4
    max_range_m: "float | None" = None
    provenance: dict = field(default_factory=dict)

    @classmethod
    def load(cls, mesh, envelope=None, *, candidates=None, spacing=None, keepout=(), units="m", seed=0,
             max_candidates=None, half_angle_deg=60.0, max_tilt_deg=0.0, tilt_toward=None, tilt_directions=4,
             stations=None, max_range_m=None, k=None) -> "DesignProblem":
        """Load and compute everything once.

        mesh : path (``units`` of the file), ``trimesh.Trimesh`` (m) or None (no occlusion);
        envelope : path or :class:`layoutkit.envelope.Envelope` (None: no poses);
        candidates : layout JSON path or :class:`Layout` of candidate sites, else sampled on the mesh
        ``spacing`` (m, default :func:`default_spacing` for ``k`` sensors) apart, outside ``keepout``, with
        ``seed``, at most ``max_candidates``. stations : replaces the envelope's. Tilt and half-angle as in
        :class:`layoutkit.optimize.spec.OptimizeSpec`. Mesh warnings (odd size, open mesh) propagate.
        """
        from ..envelope import Envelope, load_envelope
        from ..mesh import load_mesh, mesh_hash

        prov = {"mesh": None, "mesh_sha256": None, "units": units}
        if isinstance(mesh, (str, Path)):
            prov["mesh"] = _abs(mesh)
            mesh = load_mesh(mesh, units)
        if mesh is not None:
            prov["mesh_sha256"] = mesh_hash(mesh)
        env = envelope
        if envelope is not None and not isinstance(envelope, Envelope):
            env = load_envelope(envelope)
            prov["envelope_file"] = _abs(envelope)
        cand, prov["candidates"] = _load_candidates(mesh, candidates, spacing, keepout, seed, max_candidates, k)
        if env is not None:
            if stations is not None:
                env = dataclasses.replace(env, stations=tuple(stations))
            R, t = env.poses()
            stations = env.stations
            prov["envelope"] = env.to_dict()
        else:
            R, t, stations = np.zeros((0, 3, 3)), np.zeros((0, 3)), tuple(stations or ())
        toward = _resolve_toward(tilt_toward, R, t, stations) if max_tilt_deg and max_tilt_deg > 0 else None
        cand, site, tilt = expand_tilt(cand, max_tilt_deg, tilt_directions, toward)
        vis = (layout_visibility(mesh, cand.positions, cand.normals, R, t, stations, half_angle_deg, max_range_m)
               if len(stations) else np.zeros((len(R), 0, cand.n), bool))
        prov.update(stations=[s.id for s in stations], half_angle_deg=float(half_angle_deg),
                    max_range_m=max_range_m, candidate_count=int(cand.n),
                    tilt={"max_tilt_deg": float(max_tilt_deg or 0.0), "toward": _jsonable_toward(tilt_toward),
                          "axis": None if toward is None else [float(x) for x in toward],
                          "directions": int(tilt_directions)})
        return cls(cand, R, t, tuple(stations), vis, site, tilt, mesh, env, float(half_angle_deg),
                   float(max_tilt_deg or 0.0), _norm_toward(tilt_toward), int(tilt_directions), max_range_m, prov)

    @classmethod
    def for_spec(cls, mesh, envelope, spec, **kw) -> "DesignProblem":
        """:meth:`load` with the half-angle, tilt, sampling seed and sensor count (for the default candidate
        spacing) of ``spec`` (an :class:`OptimizeSpec`)."""
        return cls.load(mesh, envelope, half_angle_deg=spec.half_angle_deg, max_tilt_deg=spec.max_tilt_deg,
                        tilt_toward=spec.tilt_toward, tilt_directions=spec.tilt_directions,
                        seed=kw.pop("seed", spec.seed), k=kw.pop("k", spec.k), **kw)

    @classmethod
    def from_arrays(cls, positions, normals, visible, rotations, translations, *, half_angle_deg=60.0,
                    fov_deg=120.0, max_tilt_deg=0.0, tilt_directions=4) -> "DesignProblem":
        """The array API's problem: one station at the origin with field of view ``fov_deg``.

        positions, normals (N, 3) body frame; visible (P, N) bool (the plain sites); rotations (P, 3, 3),
        translations (P, 3): body pose in the station frame. With ``max_tilt_deg > 0`` every site also
        takes its normal tilted towards ``tilt_directions`` azimuths, lit by the acceptance cone and field
        of view test (:func:`layoutkit.visibility.facing_mask`: exact for convex bodies, no occlusion).
        Candidate ids are the indices as strings (``"3"``, tilted: ``"3~t1"``)."""
        from ..layout import Layout
        from ..lighthouse import Station
        from ..visibility import facing_mask
        from .tilt import tilt_orientations

        pos, nor = np.asarray(positions, float), np.asarray(normals, float)
        R, t = np.asarray(rotations, float), np.asarray(translations, float)
        N = len(pos)
        vis = np.asarray(visible, bool)
        site, tilt, axes = np.arange(N), np.zeros(N), nor
        if max_tilt_deg and max_tilt_deg > 0:
            pos, axes, site, tilt = tilt_orientations(pos, nor, float(max_tilt_deg), int(tilt_directions))
            vt = facing_mask(pos[N:], axes[N:], R, t, half_angle_deg=half_angle_deg, fov_deg=fov_deg)
            vis = np.concatenate([vis, vt], axis=1)
        occ = np.zeros(N, int)
        ids = []
        for s in site:
            ids.append(str(s) if occ[s] == 0 else f"{s}~t{occ[s]}")
            occ[s] += 1
        cand = Layout(pos, axes, tuple(ids))
        return cls(cand, R, t, (Station(fov_deg=float(fov_deg)),), vis[:, None, :], site, tilt, None, None,
                   float(half_angle_deg), float(max_tilt_deg or 0.0), None, int(tilt_directions), None,
                   {"source": "arrays", "stations": ["A"], "half_angle_deg": float(half_angle_deg)})

    # -- sizes and derived arrays -----------------------------------------------------------------
    @property
    def N(self) -> int:
        return self.candidates.n

    @property
    def P(self) -> int:
        return len(self.rotations)

    @property
    def S(self) -> int:
        return len(self.stations)

    @functools.cached_property
    def jac(self) -> np.ndarray:
        """(P, S, N, 2, 6) angle Jacobians of every candidate at every design pose (Chen eqs. 10–14)."""
        return self.jacobians_at(self.rotations, self.translations)

    def jacobians_at(self, R, t) -> np.ndarray:
        """(P', S, N, 2, 6) angle Jacobians of every candidate at world poses ``R, t`` (new rows)."""
        from .core import candidate_jacobians

        return candidate_jacobians(self.candidates.positions, R, t, self.stations)

    # -- what a selection is ----------------------------------------------------------------------
    def indices(self, ids) -> np.ndarray:
        """Candidate indices of ``ids``; ``ValueError`` naming the unknown ones."""
        idmap = {c: i for i, c in enumerate(self.candidates.ids)}
        missing = [f for f in ids if f not in idmap]
        if missing:
            raise ValueError(f"fixed: unknown candidate id(s) {missing}; ids look like {self.candidates.ids[0]!r}")
        return np.asarray([idmap[f] for f in ids], int)

    def conflicts(self, min_spacing_m=0.0):
        """(N, N) bool pairs that cannot both be chosen: closer than ``min_spacing_m`` (m), or two
        orientations of one site when tilt is on; None if there are none."""
        from .core import spacing_conflicts

        conflict = spacing_conflicts(self.candidates.positions, min_spacing_m)
        if self.max_tilt_deg > 0:
            from .tilt import site_conflicts

            conflict = site_conflicts(self.site, conflict)
        return conflict

    def cliques(self) -> list:
        """Index arrays of the orientations of each site that has several (at most one may be chosen)."""
        if self.max_tilt_deg <= 0:
            return []
        order = np.argsort(self.site, kind="stable")
        _, starts, counts = np.unique(self.site[order], return_index=True, return_counts=True)
        return [order[a:a + c] for a, c in zip(starts, counts) if c >= 2]

    def check_spec(self, spec) -> None:
        """``ValueError`` if ``spec`` asks for another half-angle or tilt than this problem was built with."""
        mine = (self.half_angle_deg, self.max_tilt_deg, self.tilt_toward if self.max_tilt_deg > 0 else None,
                self.tilt_directions if self.max_tilt_deg > 0 else None)
        theirs = (float(spec.half_angle_deg), float(spec.max_tilt_deg),
                  _norm_toward(spec.tilt_toward) if spec.max_tilt_deg > 0 else None,
                  int(spec.tilt_directions) if spec.max_tilt_deg > 0 else None)
        if mine != theirs:
            raise ValueError(f"spec: half-angle/tilt {theirs} differ from the problem's {mine} (half_angle_deg, "
                             "max_tilt_deg, tilt_toward, tilt_directions); build it with DesignProblem.for_spec")

    def visibility_at(self, sel, R, t) -> np.ndarray:
        """(P', S, k) bool visibility of candidates ``sel`` (None: all) at NEW world poses ``R, t``
        (ray-cast; at the design poses use ``visible[:, :, sel]``)."""
        c = self.candidates
        idx = slice(None) if sel is None else np.asarray(sel, int)
        return layout_visibility(self.mesh, c.positions[idx], c.normals[idx], R, t, self.stations,
                                 self.half_angle_deg, self.max_range_m)

    def evaluate(self, sel, R=None, t=None, *, rho, min_visible=4, coverage="any-station"):
        """Per-pose ADOP (P,) deg/rad, PDOP (P,) m/rad (exact metric, Chen eq. 18 with ``rho``, lit sensors,
        every station: :func:`layoutkit.dop_batch.batch_dop`) and covered (P,) bool (``min_visible`` lit by
        the ``coverage`` rule) of candidate subset ``sel`` at world poses ``R, t`` — default the design
        poses, whose visibility is a slice of :attr:`visible` (no new ray-cast)."""
        from ..coverage_rule import covered, layout_counts
        from ..dop_batch import batch_dop

        sel = np.asarray(sel, int)
        if R is None:
            R, t, vis = self.rotations, self.translations, self.visible[:, :, sel]
        else:
            vis = self.visibility_at(sel, R, t)
        d = batch_dop(self.candidates.positions[sel], R, t, rho=rho, visible=vis, stations=self.stations)
        return d.adop, d.pdop, covered(layout_counts(vis, coverage), min_visible)

    def layout(self, sel, metadata=None):
        """:class:`layoutkit.layout.Layout` of candidate subset ``sel``: sensors ``S01``, ``S02``, ... with
        per-sensor ``candidate`` (id), ``x-site`` and ``x-tilt-deg``; ``metadata`` as its top-level keys."""
        from ..layout import Layout

        sel = [int(i) for i in sel]
        c = self.candidates
        return Layout(c.positions[sel], c.normals[sel], tuple(f"S{i + 1:02d}" for i in range(len(sel))),
                      dict(metadata or {}),
                      tuple({"candidate": c.ids[i], "x-site": c.ids[int(self.site[i])],
                             "x-tilt-deg": float(self.tilt_deg[i])} for i in sel))


def _norm_toward(v):
    if v is None or isinstance(v, str):
        return v
    return tuple(float(x) for x in np.asarray(v, float).reshape(3))


def _jsonable_toward(v):
    v = _norm_toward(v)
    return list(v) if isinstance(v, tuple) else v


def layout_sources(layout, where="layout") -> dict:
    """What a layout written by the optimiser says about its inputs (its ``"provenance"`` and ``"spec"``):
    ``{"mesh": path or None, "mesh_sha256", "units", "envelope": Envelope or None, "half_angle_deg",
    "spec": dict or None}``; every value None for a layout without provenance. ``ValueError`` naming
    ``where`` if the record is malformed."""
    from ..envelope import Envelope

    meta = getattr(layout, "metadata", {}) or {}
    prov = meta.get("provenance")
    out = {"mesh": None, "mesh_sha256": None, "units": "m", "envelope": None, "half_angle_deg": None,
           "spec": meta.get("spec") if isinstance(meta.get("spec"), dict) else None}
    if prov is None:
        return out
    if not isinstance(prov, dict):
        raise ValueError(f"{where}: 'provenance': expected an object, got {type(prov).__name__}")
    out.update(mesh=prov.get("mesh"), mesh_sha256=prov.get("mesh_sha256"), units=prov.get("units", "m"),
               half_angle_deg=prov.get("half_angle_deg"))
    if prov.get("envelope") is not None:
        try:
            out["envelope"] = Envelope.from_dict(prov["envelope"])
        except ValueError as exc:
            raise ValueError(f"{where}: 'provenance.envelope': {exc}") from None
    return out
