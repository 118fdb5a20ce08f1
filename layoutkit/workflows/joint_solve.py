"""What ``layoutkit solve FRAMES --stations S`` does: frame table → joint windows → poses.

Frame table (:mod:`layoutkit.io.frames`: ``t``, ``station``, ``th_x_<id>``, ``th_y_<id>``; radians,
empty = not seen; LH1-equivalent sweep angles for every station, LH2 rows turned into light-plane
angles here so that each station's calibrated forward model applies) → joint time windows
(:func:`layoutkit.joint.group_windows`, 20 ms) → :func:`layoutkit.joint.solve_joint`, optionally with
the motion model of ``replay --solve joint``; the report splits precision from accuracy
(:mod:`layoutkit.workflows.accuracy`). ``layoutkit calibrate`` (:mod:`layoutkit.workflows.calibrate`)
uses the same windows.
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ..layout import Layout

__all__ = ["StationFrames", "read_station_frames", "station_index", "frame_file_stations", "to_station_convention",
           "window_table", "window_velocity", "motion_angle_rms", "solve_joint_frames", "solve_station_file",
           "window_angles_of"]


class StationFrames:
    """Rows of a frame table: ``t (R,)`` s, ``station (R,)`` text, ``angles (R, n, 2)`` rad in the
    layout's sensor order (NaN = not seen); ``station_column``: False when the file had no ``station``
    column (every row station 0)."""

    def __init__(self, t, station, angles, station_column: bool = True):
        self.t, self.station, self.angles = t, station, angles
        self.station_column = station_column


def read_station_frames(path, layout: Layout) -> StationFrames:
    """Read a frame table (:func:`layoutkit.io.frames.read_frame_table`; no ``station`` column = every
    row station 0). ValueError naming the file, line and field. Infinite angles count as not seen."""
    from ..io.frames import read_frame_table

    fr = read_frame_table(path, layout.ids)
    ang = np.array(fr.angles, float)
    ang[~np.isfinite(ang)] = np.nan
    st = fr.stations() if hasattr(fr, "stations") else (fr.station if fr.station is not None else np.zeros(len(fr.t), int))
    return StationFrames(np.asarray(fr.t, float), np.asarray([str(int(x)) for x in st]), ang,
                         station_column=getattr(fr, "station", None) is not None)


def station_index(labels, stations) -> np.ndarray:
    """Frame-table station labels → indices into ``stations`` (by id, else by integer position);
    -1 for a label that matches neither."""
    ids = {str(s.id): k for k, s in enumerate(stations)}
    out = np.full(len(labels), -1)
    for lab in np.unique(labels):
        k = ids.get(str(lab))
        if k is None:
            try:
                v = int(float(lab))
                k = v if 0 <= v < len(stations) else None
            except ValueError:
                k = None
        if k is not None:
            out[np.asarray(labels) == lab] = k
    return out


def frame_file_stations(frames_path, stations_path) -> int:
    """How many of the stations file's stations appear in the frame table's ``station`` column."""
    from ..io.stations import read_stations

    stations = read_stations(stations_path)
    path = Path(frames_path)
    try:
        with open(path, newline="") as fh:
            rd = csv.reader(fh)
            header = next(rd, None) or []
            if "station" not in header:
                return 1
            k = header.index("station")
            labels = {r[k].strip() for r in rd if len(r) > k}
    except (OSError, UnicodeDecodeError):
        raise ValueError(f"{path}: cannot read the frame table") from None
    return int(len(set(station_index(sorted(labels), stations).tolist()) - {-1}))


def to_station_convention(angles, stations, sidx) -> np.ndarray:
    """Frame-table angles (LH1-equivalent sweep angles for every station, docs/frames.md) → each row's
    station convention: LH2 stations get light-plane angles (:func:`layoutkit.lighthouse.sweep_to_lh2_angles`)."""
    from ..lighthouse import sweep_to_lh2_angles

    out = np.array(angles, float)
    for q, st in enumerate(stations):
        if st.kind == "lh2":
            m = sidx == q
            out[m] = sweep_to_lh2_angles(out[m])
    return out


def window_table(fr: StationFrames, stations, window_s):
    """A frame table's rows → joint windows: ``rows (W, S)``, ``t_window (W,)``, angles ``(W, S, n, 2)``
    in each station's convention (:func:`to_station_convention`); ValueError when no row's station
    label matches the stations."""
    return _windows(fr, stations, window_s)


def _windows(fr: StationFrames, stations, window_s):
    from ..joint import group_windows, window_angles

    sidx = station_index(fr.station, stations)
    if not np.any(sidx >= 0):
        raise ValueError(f"no frame-table station label matches the stations given "
                         f"({', '.join(sorted(set(map(str, fr.station))))[:80]} vs "
                         f"{', '.join(str(s.id) for s in stations)})")
    rows, tw = group_windows(fr.t, sidx, len(stations), window_s)
    return rows, tw, window_angles(to_station_convention(fr.angles, stations, sidx), rows)


def window_velocity(tw, res, max_gap_s: float = 0.05, max_dev_m: float = 0.02, max_dev_rad: float = np.deg2rad(3.0)):
    """Body velocity of each window from the solved poses (offline: the least-squares slope over the
    solved windows within ``max_gap_s`` before and after it, the window itself included — both sides
    known, unlike replay's causal fit).

    tw (W,) s; res : the joint :class:`~layoutkit.pnp.PnPResult` (world frame). Returns ``omega (W, 3)``
    rad/s (world frame, left perturbation: ``R(t + d) = exp([omega d]x) R(t)``), ``v (W, 3)`` m/s and
    ``known (W,)`` bool: False where fewer than 3 windows qualify, where the neighbours stray from the
    fitted line by more than ``max_dev_m`` / ``max_dev_rad`` (not one smooth motion: unrelated poses,
    e.g. simulated random frames 1/60 s apart, or a sharp turn), or where the velocity exceeds replay's
    continuity limits (:class:`layoutkit.live.pipeline.LiveConfig` ``max_speed_m_s``,
    ``max_rate_deg_s``: not a motion, a jump)."""
    from ..geometry import matrix_to_rotvec
    from ..live.pipeline import LiveConfig

    lim = LiveConfig()
    W = len(tw)
    omega, vel = np.zeros((W, 3)), np.zeros((W, 3))
    known = np.zeros(W, bool)
    g = np.flatnonzero(res.success & np.all(np.isfinite(res.translation), 1))
    if g.size < 3:
        return omega, vel, known
    t = tw[g]
    lo = np.searchsorted(t, t - max_gap_s, side="left")
    hi = np.searchsorted(t, t + max_gap_s, side="right")
    for q, k in enumerate(g):
        nb = g[lo[q]:hi[q]]
        if nb.size < 3:
            continue
        dt = tw[nb] - tw[k]
        dtc = dt - dt.mean()
        den = float(dtc @ dtc)
        if den <= 0:
            continue
        dp = res.translation[nb] - res.translation[k]
        dr = matrix_to_rotvec(res.rotation[nb] @ res.rotation[k].T)
        v = dtc @ dp / den
        w = dtc @ dr / den
        if np.linalg.norm(v) > lim.max_speed_m_s or np.linalg.norm(w) > np.deg2rad(lim.max_rate_deg_s):
            continue
        fit_p = dp.mean(0) + dtc[:, None] * v[None]
        fit_r = dr.mean(0) + dtc[:, None] * w[None]
        if (np.linalg.norm(dp - fit_p, axis=1).max() > max_dev_m
                or np.linalg.norm(dr - fit_r, axis=1).max() > max_dev_rad):
            continue
        vel[k], omega[k], known[k] = v, w, True
    return omega, vel, known


def motion_angle_rms(points_body, translation, omega, vel, dt, have, stations) -> np.ndarray:
    """RMS angle change (rad) the motion ``(omega, vel)`` makes over each window's measurement times:
    per station and axis ``(|v| + |omega| L) |dt| / r`` (L the largest sensor distance from the body
    origin, r the station's distance), RMS over the present station axes; (W,). The rule of
    ``replay --solve joint`` (:data:`layoutkit.live.joint_stream.MOTION_MIN_SIGMA`)."""
    P = np.asarray(points_body, float)
    L = float(np.max(np.linalg.norm(P, axis=1))) if len(P) else 0.0
    speed = np.linalg.norm(vel, axis=-1) + np.linalg.norm(omega, axis=-1) * L
    org = np.array([np.asarray(st.translation, float) for st in stations])
    r = np.linalg.norm(np.nan_to_num(translation)[:, None, :] - org[None], axis=-1)
    d = np.asarray(dt, float)
    d = d if d.ndim == 3 else d[..., None] * np.ones(2)
    m = np.broadcast_to(np.asarray(have, bool)[..., None], d.shape)
    x = speed[:, None, None] * np.abs(d) / np.maximum(r, 1e-6)[..., None]
    return np.sqrt(np.where(m, x * x, 0.0).sum((1, 2)) / np.maximum(m.sum((1, 2)), 1))


def solve_joint_frames(fr: StationFrames, layout: Layout, stations, *, window_s: float | None = None,
                       motion_compensation: bool = False, sigma: float | None = None):
    """Joint poses of every window: ``(t_window (W,), PnPResult (world frame), rows (W, S), info)``;
    info: ``angles (W, S, n, 2)`` (each station's convention), and the ``dt``/``velocity`` of the
    motion-compensated pass (None without it), ``compensated (W,)`` bool.

    motion_compensation : the model of ``replay --solve joint``: each station's angles were taken at
    their row's time (and, when the frame table gives it, the second axis ``dt_y`` later), the body
    moving at constant velocity across the window (:func:`layoutkit.joint.solve_joint` ``dt`` /
    ``velocity``); the velocity from the first pass' poses (:func:`window_velocity`: offline, so
    central differences rather than replay's causal fit); only windows whose motion changes the
    angles by more than ``MOTION_MIN_SIGMA`` sigma (:func:`motion_angle_rms`; at rest the velocity is
    noise) get the second pass, from the first pass' pose. sigma : rad (default the paper's).
    """
    from ..joint import WINDOW_S, solve_joint
    from ..live.joint_stream import MOTION_MIN_SIGMA
    from ..units import SIGMA_THETA_PAPER

    rows, tw, ang = _windows(fr, stations, WINDOW_S if window_s is None else window_s)
    res = solve_joint(layout.positions, ang, stations=stations)
    info = {"angles": ang, "dt": None, "velocity": None, "compensated": np.zeros(len(tw), bool)}
    if motion_compensation and len(tw) >= 3:
        have = rows >= 0
        dt = np.where(have, fr.t[np.maximum(rows, 0)] - tw[:, None], 0.0)
        dt = np.stack([dt, dt], -1)
        dty = getattr(fr, "dt_y", None)
        if dty is not None:                                  # the second axis' own time
            dt[..., 1] += np.where(have, np.nan_to_num(np.asarray(dty, float)[np.maximum(rows, 0)]), 0.0)
        omega, vel, known = window_velocity(tw, res)
        sm = motion_angle_rms(layout.positions, res.translation, omega, vel, dt, have, stations)
        use = res.success & known & (sm > MOTION_MIN_SIGMA * (SIGMA_THETA_PAPER if sigma is None else sigma))
        fix = np.flatnonzero(use)
        if fix.size:
            sol = solve_joint(layout.positions, ang[fix], stations=stations, dt=dt[fix],
                              velocity=(omega[fix], vel[fix]), initial=(res.rotation[fix], res.translation[fix]))
            res = _replace_rows(res, fix, sol)
            info["compensated"][fix] = True
        info.update(dt=dt, velocity=(omega, vel))
    return tw, res, rows, info


def _replace_rows(res, idx, sol):
    """``res`` with the rows ``idx`` taken from ``sol`` (a PnPResult of len(idx) frames)."""
    from dataclasses import replace

    kw = {}
    for f in ("rotation", "translation", "success", "status", "residual_rms", "iterations"):
        a = np.array(getattr(res, f), copy=True)
        a[idx] = getattr(sol, f)
        kw[f] = a
    for f in ("alt_rotation", "alt_translation", "alt_residual_rms"):
        a = getattr(res, f)
        if a is not None:
            a = np.array(a, copy=True)
            b = getattr(sol, f)
            a[idx] = b if b is not None else np.nan
            kw[f] = a
    return replace(res, **kw)


def solve_station_file(frames_path, layout: Layout, stations_path, *, out=None, mode: str | None = None,
                       sigma: float | None = None, rho: float = 0.0, motion_compensation: bool = False,
                       ignore_calibration: bool = False) -> dict:
    """``layoutkit solve FRAMES --stations S [--solve joint|per-station]``: poses in the stations' world
    frame through each station's forward model (calibration included).

    mode : "joint" (one pose per window, station ``joint``), "per-station" (one pose per row, the
    row's station) or None (joint when the file has several stations). Writes the pose table to
    ``out`` (t, station, status, rx, ry, rz, tx, ty, tz, residual_rms; rad, m) and returns a summary
    with status counts and, with ``sigma``, the DOP-predicted position precision of the geometry.
    ignore_calibration : drop the stations' calibrations (the ideal model, for comparison).
    """
    from ..dop import pose_dop
    from ..geometry import matrix_to_rotvec
    from ..io.poses import JOINT, PoseTable, write_poses
    from ..io.stations import read_stations
    from ..joint import solve_joint
    from ..pnp import STATUS_NAMES

    stations = list(read_stations(stations_path))
    if ignore_calibration:
        from dataclasses import replace

        stations = [replace(s, calibration=None) for s in stations]
    fr = read_station_frames(frames_path, layout)
    sidx = station_index(fr.station, stations)
    present = sorted(set(sidx[sidx >= 0].tolist()))
    if mode is None:
        mode = "joint" if len(present) > 1 else "per-station"
    if mode == "joint":
        t, res, rows, info = solve_joint_frames(fr, layout, stations, motion_compensation=motion_compensation,
                                                sigma=sigma)
        st_col = np.full(len(t), JOINT)
        vis = np.all(np.isfinite(window_angles_of(fr, rows)), -1)
        ang = info["angles"]
    else:
        if not present:
            raise ValueError(f"{frames_path}: no row's station matches the stations given")
        ang = np.full((len(fr.t), len(stations), layout.n, 2), np.nan)
        ok = sidx >= 0
        ang[np.flatnonzero(ok), sidx[ok]] = to_station_convention(fr.angles, stations, sidx)[ok]
        res = solve_joint(layout.positions, ang, stations=stations)
        t, st_col = fr.t, sidx
        vis = np.all(np.isfinite(ang), -1)
        info = {"dt": None, "velocity": None}
    rv = matrix_to_rotvec(np.where(np.isfinite(res.rotation), res.rotation, np.eye(3)))
    rv = np.where(np.isfinite(res.translation[:, :1]), rv, np.nan)
    if out:
        write_poses(out, PoseTable(t, rv, res.translation, station=st_col, status=res.status,
                                   residual_rms=res.residual_rms))
    counts = {STATUS_NAMES.get(int(k), str(int(k))): int(v) for k, v in zip(*np.unique(res.status, return_counts=True))}
    summary = {"mode": mode, "rows": int(len(fr.t)), "poses": int(len(t)), "solved": int(res.success.sum()),
               "status_counts": counts, "stations": [str(s.id) for s in stations],
               "median_residual_rms_rad": float(np.nanmedian(res.residual_rms)) if res.success.any() else None}
    if res.success.any():
        tr = res.translation[res.success]
        summary["position_scatter_m"] = float(np.sqrt(np.mean(np.sum((tr - tr.mean(0)) ** 2, 1))))
        if sigma is not None:
            g = np.flatnonzero(res.success)
            d = pose_dop(layout.positions, res.rotation[g], res.translation[g], rho=rho, stations=stations,
                         visible=vis[g])
            fin = np.isfinite(d.pdop)
            if fin.any():
                summary["predicted_position_sigma_m"] = float(np.sqrt(np.mean(d.pdop[fin] ** 2)) * sigma)
                summary["predicted_attitude_sigma_deg"] = float(np.sqrt(np.mean(d.adop[fin] ** 2)) * sigma)
    if res.success.any():
        from .accuracy import precision_accuracy

        summary["precision_accuracy"] = precision_accuracy(
            layout.positions, stations, res.rotation, res.translation, ang, ok=res.success, ids=layout.ids,
            sigma=sigma, rho=rho, dt=info["dt"], velocity=info["velocity"])
    if not res.success.any():
        summary["reason"] = f"no pose solved ({res.message})"
    return summary


def window_angles_of(fr: StationFrames, rows):
    from ..joint import window_angles

    return window_angles(fr.angles, rows)
