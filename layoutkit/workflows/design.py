"""Design-flow orchestration with files: mesh + envelope (+ layout) in, visibility summaries out.

Reused by the CLI (``layoutkit mesh-info / candidates / visibility``), the optimiser and the render
commands, and by ``studies/``. Warnings raised while loading (wrong-unit size, open mesh) are
collected into ``DesignInputs.warnings`` so that callers can print them their own way.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

__all__ = ["DesignInputs", "load_design_inputs", "mesh_info", "make_candidates", "visibility_summary",
           "visibility_report"]


@dataclass(frozen=True)
class DesignInputs:
    """What a design step needs, loaded and checked.

    mesh : trimesh.Trimesh (m, body frame); envelope : Envelope or None; layout : Layout or None;
    rotations (P, 3, 3), translations (P, 3) : body poses in the WORLD frame (empty without an
    envelope); stations : tuple of Station; warnings : messages emitted while loading.
    """

    mesh: object
    envelope: object = None
    layout: object = None
    rotations: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    translations: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    stations: tuple = ()
    warnings: tuple = ()

    def visibility(self, layout=None, **kw) -> np.ndarray:
        """(P, S, n) visibility of ``layout`` (default ``self.layout``) over the envelope; kw → envelope_visibility."""
        from ..visibility import envelope_visibility

        lay = layout if layout is not None else self.layout
        if lay is None or self.envelope is None:
            raise ValueError("visibility: needs both a layout and an envelope")
        return envelope_visibility(self.mesh, lay.positions, lay.normals, self.rotations, self.translations,
                                   self.stations, **kw)


def load_design_inputs(mesh_path, units: str = "m", envelope_path=None, layout_path=None,
                       check_size: bool = True) -> DesignInputs:
    """Load a mesh (``units`` of the file), optionally an envelope TOML and a layout JSON.

    Raises ``ValueError`` with a file-naming message on bad input; mesh warnings are returned in
    ``.warnings`` (and not re-emitted), except a size that says ``units`` is wrong
    (:class:`layoutkit._validate.OddSizeWarning`), which is re-emitted when ``check_size`` (the
    CLI stops on it unless ``--allow-odd-size``).
    """
    from .._validate import OddSizeWarning
    from ..envelope import load_envelope
    from ..layout import load_layout
    from ..mesh import load_mesh

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mesh = load_mesh(mesh_path, units=units)
    env = load_envelope(envelope_path) if envelope_path is not None else None
    layout = load_layout(layout_path) if layout_path is not None else None
    odd = [w for w in caught if check_size and issubclass(w.category, OddSizeWarning)]
    for w in odd:
        warnings.warn(w.message, stacklevel=2)
    msgs = tuple(str(w.message) for w in caught if w not in odd)
    if layout is not None:
        from ..mesh import mesh_hash

        want = layout.metadata.get("mesh_sha256")
        if want and want != mesh_hash(mesh):
            msgs += (f"{layout_path}: made on a different mesh (mesh_sha256 differs from {mesh_path})",)
    if env is None:
        return DesignInputs(mesh, None, layout, warnings=msgs)
    R, t = env.poses()
    return DesignInputs(mesh, env, layout, R, t, env.stations, msgs)


def mesh_info(mesh_path, units: str = "m") -> dict:
    """``describe_mesh`` of the file plus the load warnings (``"warnings": [...]``)."""
    from ..mesh import describe_mesh

    inp = load_design_inputs(mesh_path, units, check_size=False)  # reports the size warning, never stops
    return {"file": str(mesh_path), "units": units, **describe_mesh(inp.mesh), "warnings": list(inp.warnings)}


def make_candidates(mesh_path, *, spacing, units: str = "m", keepout=(), flat_only=False, normal_filter=None,
                    seed=0, max_count=None, out=None):
    """Sample candidate sites on a mesh file; write them to ``out`` (layout JSON) if given.

    Returns ``(layout, warnings)``.
    """
    from ..candidates import sample_candidates
    from ..layout import save_layout

    inp = load_design_inputs(mesh_path, units)
    lay = sample_candidates(inp.mesh, spacing=spacing, keepout=keepout, flat_only=flat_only,
                            normal_filter=normal_filter, rng=np.random.default_rng(seed), max_count=max_count)
    if out is not None:
        save_layout(lay, out)
    return lay, inp.warnings


def visibility_summary(visible: np.ndarray, ids, station_ids, min_lit: int = 4) -> dict:
    """Summarise a (P, S, n) visibility array.

    Per sensor: fraction of poses lit by each station and by any station. Per pose: the lit count
    of the best station (PnP needs ≥ ``min_lit`` sensors from one station); the minimum of it over
    the poses and the number of poses below ``min_lit``.
    """
    v = np.asarray(visible, bool)
    P, S, n = v.shape
    per_station = v.sum(-1)  # (P, S)
    best = per_station.max(-1) if S else np.zeros(P, int)
    return {
        "poses": P, "stations": list(station_ids), "sensors": n, "min_lit_required": min_lit,
        "sensor_lit_fraction": [{"id": sid, "any": float(v[:, :, k].any(1).mean()),
                                 **{str(s): float(v[:, j, k].mean()) for j, s in enumerate(station_ids)}}
                                for k, sid in enumerate(ids)],
        "lit_count_min": int(best.min()) if P else 0,
        "lit_count_median": float(np.median(best)) if P else 0.0,
        "lit_count_histogram": np.bincount(best).tolist(),  # index = lit count of the best station
        "poses_below_min_lit": int(np.count_nonzero(best < min_lit)),
        "fraction_below_min_lit": float(np.mean(best < min_lit)) if P else 0.0,
    }


def visibility_report(mesh_path, layout_path, envelope_path, *, units: str = "m", sensor_half_angle_deg=60.0,
                      max_range=None, min_lit: int = 4) -> dict:
    """Load mesh, layout and envelope; compute visibility over the envelope; return the summary dict."""
    inp = load_design_inputs(mesh_path, units, envelope_path, layout_path)
    v = inp.visibility(sensor_half_angle_deg=sensor_half_angle_deg, max_range=max_range)
    out = visibility_summary(v, inp.layout.ids, [s.id for s in inp.stations], min_lit)
    out.update(mesh=str(mesh_path), layout=str(layout_path), envelope=str(envelope_path),
               sensor_half_angle_deg=sensor_half_angle_deg, max_range_m=max_range, warnings=list(inp.warnings))
    return out
