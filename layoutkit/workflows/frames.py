"""Frame workflows: simulate sweep-angle frames (``layoutkit simulate``) and solve them
(``layoutkit solve``). The file format itself is :mod:`layoutkit.io.frames` (THE frame table).
"""
from __future__ import annotations

import numpy as np

from ..geometry import matrix_to_rotvec
from ..io.frames import Frames, read_frame_table, write_frame_table
from ..layout import Layout

__all__ = ["Frames", "simulate_frames", "write_frames", "read_frames", "solve_frames", "solution_table",
           "simulate_frame_file", "solve_frame_file"]

GROSS_DEG = 1.0


def simulate_frames(layout: Layout, frames: int, *, seed: int, sigma: float, rho: float,
                    half_angle_deg: float = 60.0, min_lit: int = 4, rate_hz: float = 60.0,
                    quantize: bool = True) -> Frames:
    """Static random poses on the paper's area in front of the station, ≥ ``min_lit`` lit."""
    from ..simulate import poses_in_front, simulate_angles
    from ..visibility import facing_mask

    rng = np.random.default_rng(seed)
    Rs, ts, vs = [], [], []
    n_have = 0
    while n_have < frames:
        R, t = poses_in_front(max(64, 2 * frames), rng)
        v = facing_mask(layout.positions, layout.normals, R, t, half_angle_deg=half_angle_deg)
        k = v.sum(1) >= min_lit
        Rs.append(R[k]); ts.append(t[k]); vs.append(v[k])
        n_have += int(k.sum())
    R = np.concatenate(Rs)[:frames]
    t = np.concatenate(ts)[:frames]
    v = np.concatenate(vs)[:frames]
    ang = simulate_angles(layout.positions, R, t, sigma=sigma, rho=rho, rng=rng, quantize=quantize)
    ang[~v] = np.nan
    return Frames(np.arange(frames) / rate_hz, ang, layout.ids, R, t)


def write_frames(fr: Frames, path) -> None:
    """Write a frame table (:func:`layoutkit.io.frames.write_frame_table`)."""
    write_frame_table(fr, path)


def read_frames(path, layout: Layout) -> Frames:
    """Read a frame table in the layout's sensor order (ValueError naming file and column)."""
    return read_frame_table(path, layout.ids)


def solution_table(res: dict):
    """The per-frame results of :func:`solve_frames` as a pose table (:mod:`layoutkit.io.poses`)."""
    from ..io.poses import PoseTable

    return PoseTable(res["t"], res["rotvec"], res["translation"], status=res["status"],
                     residual_rms=res["residual_rms"])


def solve_frames(fr: Frames, layout: Layout, *, sigma: float | None = None, rho: float = 0.0,
                 method: str = "lm") -> dict:
    """Solve every frame; summary with statuses, and errors against truth when the file has it.

    method : a key of :data:`layoutkit.pnp.PNP_SOLVERS`.
    """
    from ..dop import pose_dop, pose_errors, rms
    from ..pnp import solve_pnp

    from ..pnp import STATUS_AMBIGUOUS, STATUS_NAMES

    vis = np.all(np.isfinite(fr.angles), -1)
    sol = solve_pnp(layout.positions, fr.angles, vis, method=method,
                    **({} if sigma is None else {"sigma": sigma, "rho": rho}))
    out = {"frames": int(len(fr.t)), "solved": int(np.sum(sol.success)),
           "status_counts": {int(k): int(v) for k, v in zip(*np.unique(sol.status, return_counts=True))},
           "t": fr.t, "rotvec": matrix_to_rotvec(sol.rotation), "translation": sol.translation,
           "success": sol.success, "status": sol.status, "residual_rms": sol.residual_rms}
    if fr.truth_rotation is not None:
        ok = np.asarray(sol.success)
        e_r, e_t = pose_errors(sol.rotation[ok], sol.translation[ok], fr.truth_rotation[ok], fr.truth_translation[ok])
        # gross: > 1 deg off — with 4 coplanar lit sensors the planar two-fold ambiguity is
        # undecidable under noise for some poses (docs/pnp.md), so report them apart
        gross = np.degrees(e_r) > GROSS_DEG
        good = ~gross
        out.update(rms_rot_deg=float(np.degrees(rms(e_r))), rms_trans_m=float(rms(e_t)),
                   max_rot_deg=float(np.degrees(e_r.max())) if ok.any() else None,
                   gross_failures=int(gross.sum()),
                   gross_failures_by_status={STATUS_NAMES[0]: int(gross.sum())},
                   rms_rot_deg_without_gross=float(np.degrees(rms(e_r[good]))),
                   rms_trans_m_without_gross=float(rms(e_t[good])))
        amb = np.flatnonzero(np.asarray(sol.status) == STATUS_AMBIGUOUS)
        if amb.size:  # neither candidate is reported as the pose; say how often the truth is among them
            e1, _ = pose_errors(sol.rotation[amb], sol.translation[amb], fr.truth_rotation[amb], fr.truth_translation[amb])
            e2, _ = pose_errors(sol.alt_rotation[amb], sol.alt_translation[amb], fr.truth_rotation[amb],
                                fr.truth_translation[amb])
            out["gross_failures_by_status"]["ambiguous (best candidate)"] = int(np.sum(np.degrees(e1) > GROSS_DEG))
            out["ambiguous"] = {"frames": int(amb.size),
                                "truth_within_1deg_of_a_candidate": int(np.sum(np.degrees(np.minimum(e1, e2)) <= GROSS_DEG))}
        if sigma is not None:
            sel = np.flatnonzero(ok)[good]
            d = pose_dop(layout.positions, fr.truth_rotation[sel], fr.truth_translation[sel], rho=rho, visible=vis[sel])
            out.update(predicted_rms_rot_deg=float(np.sqrt(np.mean(d.adop**2)) * sigma),
                       predicted_rms_trans_m=float(np.sqrt(np.mean(d.pdop**2)) * sigma))
    return out


def simulate_frame_file(layout: Layout, frames: int, out, *, seed: int, sigma: float, rho: float,
                        quantize: bool = True) -> dict:
    """What ``layoutkit simulate`` does: :func:`simulate_frames`, written to ``out`` (.csv or .npz).

    Returns the summary ``{out, frames, mean_lit, min_lit}`` (lit sensors per frame).
    """
    fr = simulate_frames(layout, frames, seed=seed, sigma=sigma, rho=rho, quantize=quantize)
    write_frames(fr, out)
    lit = np.all(np.isfinite(fr.angles), -1).sum(1)
    return {"out": str(out), "frames": int(frames), "mean_lit": float(lit.mean()), "min_lit": int(lit.min())}


def solve_frame_file(frames_path, layout: Layout, *, out=None, sigma: float | None = None, rho: float = 0.0,
                     method: str = "lm", filter_settings: dict | None = None) -> dict:
    """What ``layoutkit solve`` does: read a frame file, solve every frame, write the pose table to ``out``
    (:mod:`layoutkit.io.poses`: t, station, status, rx, ry, rz, tx, ty, tz, residual_rms; rad, m).

    filter_settings : None, or keywords of :class:`layoutkit.filter.EkfConfig` (see
    :func:`layoutkit.workflows.filter.filter_config`): the frames also go through the tracking
    filter, ``out`` then holds the filtered poses and the summary a ``filter`` entry.
    Returns the JSON-ready summary of :func:`solve_frames` (without the per-frame arrays).
    ValueError (naming the file) for an unreadable frame file or filter settings.
    """
    fr = read_frames(frames_path, layout)
    res = solve_frames(fr, layout, sigma=sigma, rho=rho, method=method)
    fres = None
    if filter_settings is not None:
        from .filter import filter_config, filter_frames

        try:
            fres = filter_frames(fr, layout, filter_config(filter_settings, sigma, rho))
        except ValueError as exc:
            raise ValueError(f"{frames_path}: {exc}") from None
    if out:
        from ..io.poses import write_poses

        if fres is None:
            write_poses(out, solution_table(res))
        else:
            from .filter import filter_table

            write_poses(out, filter_table(fres))
    summary = {k: v for k, v in res.items()
               if k not in ("t", "rotvec", "translation", "success", "status", "residual_rms")}
    if fres is not None:
        summary["filter"] = {k: v for k, v in fres.items()
                             if k not in ("t", "rotvec", "translation", "status", "cov_rot_deg", "cov_pos_m")}
    return summary
