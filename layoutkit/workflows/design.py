"""Design-flow orchestration with files: mesh + envelope (+ layout) in, visibility summaries out.

Reused by the CLI (``layoutkit mesh-info / candidates / visibility``), the render command and by
``studies/``. A mesh with a layout and an envelope is loaded into one
:class:`layoutkit.optimize.DesignProblem` (the layout's sensors as its candidates; visibility computed
once). Warnings raised while loading (wrong-unit size, open mesh) are returned beside it so that
callers can print them their own way.
"""
from __future__ import annotations

import warnings

import numpy as np

__all__ = ["load_mesh_checked", "load_design", "mesh_info", "make_candidates", "visibility_summary",
           "visibility_report"]


def load_mesh_checked(mesh_path, units: str = "m", check_size: bool = True):
    """``(mesh, warnings)``: the mesh (``units`` of the file) and the messages emitted while loading.

    Raises ``ValueError`` with a file-naming message on bad input; mesh warnings are returned (and not
    re-emitted), except a size that says ``units`` is wrong (:class:`layoutkit._validate.OddSizeWarning`),
    which is re-emitted when ``check_size`` (the CLI stops on it unless ``--allow-odd-size``).
    """
    from .._validate import OddSizeWarning
    from ..mesh import load_mesh

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mesh = load_mesh(mesh_path, units=units)
    odd = [w for w in caught if check_size and issubclass(w.category, OddSizeWarning)]
    for w in odd:
        warnings.warn(w.message, stacklevel=3)
    return mesh, tuple(str(w.message) for w in caught if w not in odd)


def load_design(mesh, units: str = "m", envelope=None, layout=None, *, check_size: bool = True,
                half_angle_deg=60.0, max_range=None):
    """``(problem, warnings)``: a :class:`layoutkit.optimize.DesignProblem` whose candidates are the
    sensors of ``layout`` (path or Layout; none: no candidates) over ``envelope`` (path, Envelope or None),
    visibility with the acceptance ``half_angle_deg`` and optional ``max_range`` (m), and the load warnings
    (a layout made on another mesh, by its ``mesh_sha256``, is one). ``mesh``: path (``units``) or Trimesh.
    """
    from ..layout import Layout, load_layout
    from ..mesh import mesh_hash
    from ..optimize import DesignProblem

    msgs = ()
    mesh_name = str(mesh)
    if not hasattr(mesh, "vertices"):
        mesh, msgs = load_mesh_checked(mesh, units, check_size)
    lay = layout if isinstance(layout, Layout) or layout is None else load_layout(layout)
    if lay is not None:
        want = lay.metadata.get("mesh_sha256")
        if want and want != mesh_hash(mesh):
            msgs += (f"{layout}: made on a different mesh (mesh_sha256 differs from {mesh_name})",)
    cand = lay if lay is not None else Layout(np.zeros((0, 3)), np.zeros((0, 3)), ())
    problem = DesignProblem.load(mesh, envelope, candidates=cand, units=units, half_angle_deg=half_angle_deg,
                                 max_range_m=max_range)
    return problem, msgs


def mesh_info(mesh_path, units: str = "m") -> dict:
    """``describe_mesh`` of the file plus the load warnings (``"warnings": [...]``)."""
    from ..mesh import describe_mesh

    mesh, msgs = load_mesh_checked(mesh_path, units, check_size=False)  # reports the size warning, never stops
    return {"file": str(mesh_path), "units": units, **describe_mesh(mesh), "warnings": list(msgs)}


def make_candidates(mesh_path, *, spacing, units: str = "m", keepout=(), flat_only=False, normal_filter=None,
                    seed=0, max_count=None, out=None):
    """Sample candidate sites on a mesh file; write them to ``out`` (layout JSON) if given.

    Returns ``(layout, warnings)``.
    """
    from ..candidates import sample_candidates
    from ..layout import save_layout

    mesh, msgs = load_mesh_checked(mesh_path, units)
    lay = sample_candidates(mesh, spacing=spacing, keepout=keepout, flat_only=flat_only,
                            normal_filter=normal_filter, rng=np.random.default_rng(seed), max_count=max_count)
    if out is not None:
        save_layout(lay, out)
    return lay, msgs


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
    problem, msgs = load_design(mesh_path, units, envelope_path, layout_path, half_angle_deg=sensor_half_angle_deg,
                                max_range=max_range)
    out = visibility_summary(problem.visible, problem.candidates.ids, [s.id for s in problem.stations], min_lit)
    out.update(mesh=str(mesh_path), layout=str(layout_path), envelope=str(envelope_path),
               sensor_half_angle_deg=sensor_half_angle_deg, max_range_m=max_range, warnings=list(msgs))
    return out
