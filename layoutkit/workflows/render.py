"""Render orchestration with files: what ``layoutkit render`` does, reusable by ``studies/``.

Loads a mesh (+ layout, candidates, envelope), computes what the pictures are coloured by
(per-sensor lit fraction over the envelope, the tracking-quality map, visibility at one station
pose) and writes PNGs through :mod:`layoutkit.render`.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["RenderOptions", "parse_pose", "lit_fraction", "render_design", "sensor_tilts"]


@dataclass(frozen=True)
class RenderOptions:
    """Options of :func:`render_design` (CLI edge units in the names).

    size : (width, height) px. views : standard view names (``layoutkit.render.VIEWS``).
    quality_map : also compute and draw the tracking-quality map (needs a layout).
    map_kinds : ``("mollweide",)``, ``("sphere",)`` or both. distance_m : station range for the map.
    rho : same-rotor angle correlation (Chen eq. 19; paper 0.8717). grid_deg : map cell size, deg.
    roll_samples : station rolls per direction. station_view_pose : None, 6 numbers
    ``(rx, ry, rz) deg rotation vector + (tx, ty, tz) m`` (body pose in the station frame) or
    ``"envelope:K"`` (pose K of the envelope, in the frame of its reference station).
    view_angle_deg : station-view vertical view angle (None: fit the target).
    sensor_half_angle_deg : photodiode acceptance half-angle (None: the layout's recorded one, else 60).
    sigma_theta : rad, for map labels.
    """

    size: tuple = (1600, 1200)
    views: tuple = ("iso", "front", "top", "side")
    quality_map: bool = False
    map_kinds: tuple = ("mollweide",)
    distance_m: float = 2.0
    rho: float = 0.0
    grid_deg: float = 4.0
    roll_samples: int = 6
    station_view_pose: object = None
    view_angle_deg: "float | None" = None
    sensor_half_angle_deg: "float | None" = None
    sigma_theta: "float | None" = None


def parse_pose(spec: str):
    """``"rx,ry,rz,tx,ty,tz"`` (deg, m) or ``"envelope:K"`` → 6 floats or ``("envelope", K)``."""
    spec = str(spec).strip()
    if spec.startswith("envelope:"):
        try:
            return ("envelope", int(spec.split(":", 1)[1]))
        except ValueError:
            raise ValueError(f"station view pose: expected 'envelope:K' with an integer K, got {spec!r}") from None
    try:
        vals = tuple(float(x) for x in spec.split(","))
    except ValueError:
        vals = ()
    if len(vals) != 6 or not np.all(np.isfinite(vals)):
        raise ValueError(f"station view pose: expected 'rx,ry,rz,tx,ty,tz' (rotation vector deg, "
                         f"translation m) or 'envelope:K', got {spec!r}")
    return vals


def lit_fraction(visible) -> np.ndarray:
    """Fraction of the envelope poses in which each sensor is lit by at least one station.

    visible : (P, S, n) bool (``envelope_visibility``) → (n,) float in [0, 1].
    """
    v = np.asarray(visible, bool)
    if v.ndim != 3:
        raise ValueError(f"visible: expected shape (P, S, n), got {v.shape}")
    if v.shape[0] == 0:
        return np.zeros(v.shape[-1])
    return v.any(axis=1).mean(axis=0)


def _station_pose(problem, spec):
    """Body pose (R, t) in the station frame from a parsed pose spec."""
    from ..geometry import rotvec_to_matrix

    if isinstance(spec, tuple) and len(spec) == 2 and spec[0] == "envelope":
        if problem.envelope is None:
            raise ValueError("station view pose 'envelope:K' needs --envelope")
        k = spec[1]
        P = problem.P
        if not 0 <= k < P:
            raise ValueError(f"station view pose: envelope has {P} poses, got index {k}")
        st = problem.stations[problem.envelope.reference_station]
        R, t = st.world_to_station(problem.rotations[k], problem.translations[k])
        return np.asarray(R, float), np.asarray(t, float)
    v = np.asarray(spec, float)
    return rotvec_to_matrix(np.deg2rad(v[:3])), v[3:]


def _sources(mesh_path, layout_path, envelope_path, options):
    """Mesh path, layout, envelope and half-angle: the arguments, else what the layout records
    (:func:`layoutkit.optimize.design.layout_sources`); ``ValueError`` if no mesh can be found."""
    from ..layout import load_layout
    from ..optimize.design import layout_sources

    lay = load_layout(layout_path) if layout_path is not None else None
    src = layout_sources(lay, str(layout_path)) if lay is not None else {"mesh": None, "envelope": None,
                                                                           "half_angle_deg": None, "units": None}
    if mesh_path is None:
        mesh_path = src["mesh"]
        if mesh_path is None:
            raise ValueError("render: give a MESH (or a --layout written by `layoutkit optimize`, which records it)")
    envelope = envelope_path if envelope_path is not None else src["envelope"]
    half = options.sensor_half_angle_deg
    if half is None:
        half = src["half_angle_deg"] if src["half_angle_deg"] is not None else 60.0
    return mesh_path, lay, envelope, float(half), src


def render_design(mesh_path=None, *, out_dir, units: "str | None" = None, layout_path=None, candidates_path=None,
                  envelope_path=None, options: RenderOptions = RenderOptions()) -> dict:
    """Write the design pictures of a mesh (and layout, candidates, envelope) to ``out_dir``.

    A layout written by ``layoutkit optimize`` records its mesh, envelope and half-angle: ``mesh_path``,
    ``envelope_path`` and ``options.sensor_half_angle_deg`` left at None are taken from it.
    Files (``stem`` = mesh file stem): ``{stem}_{view}.png`` (mesh, candidates, layout coloured by
    lit fraction when an envelope is given; tilted sensors drawn along their own axes);
    ``{stem}_coverage_{view}.png`` (candidates coloured by lit fraction, when candidates and an envelope
    are given without a layout); ``{stem}_quality_map.png`` / ``{stem}_quality_sphere.png``
    (tracking-quality map); ``{stem}_station_view.png``.
    Returns ``{"paths": [...], "warnings": [...], "lit_fraction": {...}, "quality_map": {...}, ...}``.
    Raises ``ValueError`` for bad inputs and ``RenderingUnavailable`` without an OpenGL back end.
    """
    from .. import render
    from ..layout import load_layout
    from .design import load_design, load_mesh_checked

    mesh_path, lay, envelope, half, src = _sources(mesh_path, layout_path, envelope_path, options)
    units = units or src.get("units") or "m"
    mesh, msgs = load_mesh_checked(mesh_path, units)
    inp, more = load_design(mesh, units, envelope, lay, half_angle_deg=half)
    cand = load_layout(candidates_path) if candidates_path is not None else None
    out_dir = Path(out_dir)
    stem = Path(mesh_path).stem
    result: dict = {"mesh": str(mesh_path), "out": str(out_dir), "paths": [], "warnings": list(msgs + more)}
    kw = dict(sensor_half_angle_deg=half)

    if lay is not None:
        frac = lit_fraction(inp.visible) if inp.envelope is not None else None
        if frac is not None:
            result["lit_fraction"] = dict(zip(lay.ids, frac.tolist()))
        meta_name = lay.metadata.get("name")  # not "layout layout" for a file called layout.json
        name = f"'{meta_name}'" if meta_name else f"from {Path(layout_path).name}"
        tilt, surf = sensor_tilts(mesh, lay)
        if tilt is not None:
            result["tilted_sensors"] = int((tilt > 0).sum())
        result["paths"] += render.render_layout_views(
            mesh, lay.positions, lay.normals, frac, candidates=None if cand is None else cand.positions,
            views=options.views, size=options.size, out_dir=out_dir, prefix=stem, ids=lay.ids,
            title=f"{stem}: layout {name}" + (" (colour: envelope coverage)" if frac is not None else ""),
            tilt_deg=tilt, surface_normals=surf)
    elif cand is not None and inp.envelope is not None:
        frac = lit_fraction(load_design(mesh, units, inp.envelope, cand, half_angle_deg=half)[0].visible)
        result["candidate_coverage"] = {"min": float(frac.min()), "median": float(np.median(frac)),
                                        "max": float(frac.max()), "never_lit": int(np.sum(frac == 0))}
        env_name = inp.envelope.name or Path(str(envelope_path)).stem
        result["paths"] += render.render_layout_views(
            mesh, cand.positions, cand.normals, frac, views=options.views, size=options.size,
            out_dir=out_dir, prefix=f"{stem}_coverage", arrows=False, labels=False, what="candidate sites",
            sensor_radius=0.3 * float(cand.metadata.get("spacing_m", 0.02 * _diag(mesh))),
            title=f"{stem}: candidate-site coverage over envelope '{env_name}'")
    else:
        result["paths"] += render.render_layout_views(
            mesh, np.zeros((0, 3)), np.zeros((0, 3)), None,
            candidates=None if cand is None else cand.positions, views=options.views, size=options.size,
            out_dir=out_dir, prefix=stem, title=stem, what="sensors")

    if options.quality_map:
        if lay is None:
            raise ValueError("--quality-map needs a layout (--layout)")
        from ..quality import tracking_quality_map

        n_lat = max(1, int(round(180.0 / options.grid_deg)))
        q = tracking_quality_map(mesh, lay.positions, lay.normals, distance=options.distance_m, rho=options.rho,
                                 grid=(n_lat, 2 * n_lat), roll_samples=options.roll_samples, **kw)
        result["quality_map"] = q.summary()
        for kind in options.map_kinds:
            fname = "quality_map" if kind == "mollweide" else "quality_sphere"
            result["paths"].append(render.render_tracking_map(
                q, out=out_dir / f"{stem}_{fname}.png", kind=kind, size=options.size, sigma_theta=options.sigma_theta,
                title=f"{stem}: tracking quality over all viewing directions"))

    if options.station_view_pose is not None:
        if lay is None:
            raise ValueError("--station-view-pose needs a layout (--layout)")
        from ..visibility import visible_sensors

        spec = options.station_view_pose
        if isinstance(spec, str):
            spec = parse_pose(spec)
        R, t = _station_pose(inp, spec)
        fov = inp.stations[inp.envelope.reference_station].fov_deg if inp.envelope is not None else 120.0
        lit = visible_sensors(mesh, lay.positions, lay.normals, R[None], t[None], fov_deg=fov, **kw)[0]
        free = visible_sensors(mesh, lay.positions, lay.normals, R[None], t[None], fov_deg=fov, occlusion=False,
                               **kw)[0]
        result["station_view"] = {"lit": int(lit.sum()), "shadowed": int((free & ~lit).sum()), "n": int(lit.size),
                                  "range_m": float(np.linalg.norm(t))}
        result["paths"].append(render.render_station_view(
            mesh, lay.positions, lay.normals, R, t, lit, fov_deg=options.view_angle_deg, size=options.size,
            out=out_dir / f"{stem}_station_view.png", ids=lay.ids, title=f"{stem}: view from the lighthouse",
            shadowed=free & ~lit))

    result["paths"] = [str(p) for p in result["paths"]]
    return result


def sensor_tilts(mesh, layout):
    """``(tilt_deg (n,), surface_normals (n, 3))`` of a layout's sensors: the tilt the optimiser recorded
    (per-sensor ``x-tilt-deg``) and the normal of the mesh face nearest each sensor; ``(None, None)`` for a
    layout without tilt records."""
    if not any("x-tilt-deg" in e for e in layout.extra):
        return None, None
    import trimesh

    tilt = np.array([float(e.get("x-tilt-deg", 0.0)) for e in layout.extra])
    _, _, face = trimesh.proximity.closest_point(mesh, layout.positions)
    return tilt, np.asarray(mesh.face_normals[face], float)


def _diag(mesh) -> float:
    b = np.asarray(mesh.bounds, float)
    return float(np.linalg.norm(b[1] - b[0]))
