"""What ``layoutkit calibrate`` and ``layoutkit solve --solve joint`` do with files.

Frame table (:mod:`layoutkit.io.frames`: ``t``, ``station``, ``th_x_<id>``, ``th_y_<id>``; radians,
empty = not seen; LH1-equivalent sweep angles for every station, LH2 rows turned into light-plane
angles here so that each station's calibrated forward model applies) →
joint time windows (:func:`layoutkit.joint.group_windows`, 20 ms) → the bundle adjustment of
:mod:`layoutkit.calibrate` or the joint solve of :mod:`layoutkit.joint`.
"""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from ..layout import Layout

__all__ = ["StationFrames", "read_station_frames", "station_index", "calibrate_files", "solve_joint_frames",
           "solve_station_file",
           "residual_summary"]


class StationFrames:
    """Rows of a frame table: ``t (R,)`` s, ``station (R,)`` text, ``angles (R, n, 2)`` rad in the
    layout's sensor order (NaN = not seen)."""

    def __init__(self, t, station, angles):
        self.t, self.station, self.angles = t, station, angles


def read_station_frames(path, layout: Layout) -> StationFrames:
    """Read a frame table (:func:`layoutkit.io.frames.read_frame_table`; no ``station`` column = every
    row station 0). ValueError naming the file, line and field. Infinite angles count as not seen."""
    from ..io.frames import read_frame_table

    fr = read_frame_table(path, layout.ids)
    ang = np.array(fr.angles, float)
    ang[~np.isfinite(ang)] = np.nan
    st = fr.stations() if hasattr(fr, "stations") else (fr.station if fr.station is not None else np.zeros(len(fr.t), int))
    return StationFrames(np.asarray(fr.t, float), np.asarray([str(int(x)) for x in st]), ang)


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


def residual_summary(res, stations, layout: Layout) -> dict:
    """Residuals ``(K, S, n, 2)`` rad → median |r|, RMS, median per-sample RMS; per station and sensor."""
    def stats(x):
        x = x[np.isfinite(x)]
        if x.size == 0:
            return {"count": 0, "median_abs_rad": None, "rms_rad": None}
        return {"count": int(x.size), "median_abs_rad": float(np.median(np.abs(x))), "rms_rad": float(np.sqrt(np.mean(x * x)))}

    per_sample = np.sqrt(np.nanmean(res.reshape(res.shape[0], -1) ** 2, axis=1))
    out = stats(res)
    out["median_sample_rms_rad"] = float(np.nanmedian(per_sample)) if np.isfinite(per_sample).any() else None
    out["per_station"] = {str(st.id): stats(res[:, s]) for s, st in enumerate(stations)}
    out["per_sensor"] = {sid: {str(st.id): {ax: stats(res[:, s, i, k])["rms_rad"] for k, ax in enumerate("xy")}
                               for s, st in enumerate(stations)} for i, sid in enumerate(layout.ids)}
    return out


def _windows(fr: StationFrames, stations, window_s):
    from ..joint import group_windows, window_angles

    sidx = station_index(fr.station, stations)
    if not np.any(sidx >= 0):
        raise ValueError(f"no frame-table station label matches the stations given "
                         f"({', '.join(sorted(set(map(str, fr.station))))[:80]} vs "
                         f"{', '.join(str(s.id) for s in stations)})")
    rows, tw = group_windows(fr.t, sidx, len(stations), window_s)
    return rows, tw, window_angles(to_station_convention(fr.angles, stations, sidx), rows)


def solve_joint_frames(fr: StationFrames, layout: Layout, stations, *, window_s: float | None = None,
                       motion_compensation: bool = False):
    """Joint poses of every window: ``(t_window (W,), PnPResult (world frame), rows (W, S))``.

    motion_compensation : a second pass with the constant-velocity model, the velocity from the
    central differences of the first pass' poses, each station's rows at their own time.
    """
    from ..geometry import matrix_to_rotvec
    from ..joint import WINDOW_S, solve_joint

    rows, tw, ang = _windows(fr, stations, WINDOW_S if window_s is None else window_s)
    res = solve_joint(layout.positions, ang, stations=stations)
    if motion_compensation and len(tw) >= 3:
        ok = res.success
        rv = matrix_to_rotvec(np.where(ok[:, None, None], res.rotation, np.eye(3)))
        tr = np.where(ok[:, None], res.translation, np.nan)
        omega = np.zeros((len(tw), 3))
        vel = np.zeros((len(tw), 3))
        g = np.flatnonzero(ok)
        if g.size >= 3:
            for comp, src in ((vel, tr), (omega, rv)):
                for c in range(3):
                    comp[:, c] = np.interp(tw, tw[g], np.gradient(src[g, c], tw[g]))
        dt = np.where(rows >= 0, fr.t[np.maximum(rows, 0)] - tw[:, None], 0.0)
        res = solve_joint(layout.positions, ang, stations=stations, dt=dt, velocity=(omega, vel),
                          initial=(res.rotation, res.translation))
    return tw, res, rows


def _reference_poses(path, tw, tol_s):
    """Reference table rows nearest each window time (within ``tol_s``): (R, t, have)."""
    from ..geometry import rotvec_to_matrix
    from ..io.poses import read_poses

    tab = read_poses(path, min_rows=1)
    order = np.argsort(tab.t)
    tt = tab.t[order]
    k = np.clip(np.searchsorted(tt, tw), 1, len(tt) - 1) if len(tt) > 1 else np.zeros(len(tw), int)
    if len(tt) > 1:
        k = np.where(np.abs(tt[k - 1] - tw) < np.abs(tt[k] - tw), k - 1, k)
    have = np.abs(tt[k] - tw) <= tol_s
    rv = tab.rotvec[order][k]
    tr = tab.translation[order][k]
    have &= np.all(np.isfinite(rv), 1) & np.all(np.isfinite(tr), 1)
    R = rotvec_to_matrix(np.where(have[:, None], rv, 0.0))
    return R, np.where(have[:, None], tr, 0.0), have


def _plot(before, after, stations, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io.figures import save_figure

    fig, axes = plt.subplots(1, len(stations), figsize=(4.5 * len(stations), 3.4), squeeze=False)
    for s, (ax, st) in enumerate(zip(axes[0], stations)):
        b = np.abs(before[:, s][np.isfinite(before[:, s])])
        a = np.abs(after[:, s][np.isfinite(after[:, s])])
        lo = max(min(b.min() if b.size else 1e-9, a.min() if a.size else 1e-9), 1e-9)
        hi = max(b.max() if b.size else 1e-3, a.max() if a.size else 1e-3)
        bins = np.geomspace(lo, hi * 1.01, 60)
        ax.hist(b, bins, alpha=0.6, label=f"before (median {np.median(b) if b.size else float('nan'):.2e})")
        ax.hist(a, bins, alpha=0.6, label=f"after (median {np.median(a) if a.size else float('nan'):.2e})")
        ax.set_xscale("log")
        ax.set_xlabel("|angle residual| (rad)")
        ax.set_ylabel("angles")
        ax.set_title(f"station {st.id}")
        ax.legend(fontsize=7)
    fig.suptitle("Angle residuals before / after calibrate")
    fig.tight_layout(rect=(0, 0.05, 1, 0.95))
    save_figure(fig, path, caption="Histogram of |measured - predicted| sweep angles per station, with the starting "
                                   "parameters (before) and the bundle-adjusted ones (after).")


def calibrate_files(frames_path, layout_path, stations_path, out_dir, *, reference_path=None,
                    sensor_offsets: bool = False, sigma: float, offset_prior: float = 1e-3,
                    offset_bound: float = 5e-3, calibration_prior: float = 0.1, window_s: float | None = None,
                    reference_tolerance_s: float = 0.01, reference_sigma=(1e-3, 1e-3), max_samples: int | None = None,
                    seed: int = 0) -> dict:
    """``layoutkit calibrate``: read, adjust, write ``stations.json``, ``layout.json``, ``report.json``
    and ``residuals.png`` into ``out_dir``; returns the report dict. ValueError naming the file for
    bad input; a run that cannot adjust anything raises ValueError saying why."""
    from ..calibrate import bundle_adjust
    from ..io.atomic import atomic_write_text
    from ..io.stations import read_stations, write_stations
    from ..joint import WINDOW_S, solve_joint
    from ..layout import load_layout
    from ..lighthouse import Station

    layout = load_layout(layout_path)
    stations = list(read_stations(stations_path))
    if not stations:
        raise ValueError(f"{stations_path}: no stations")
    fr = read_station_frames(frames_path, layout)
    rows, tw, ang = _windows(fr, stations, WINDOW_S if window_s is None else window_s)
    if max_samples is not None and len(tw) > max_samples:
        keep = np.sort(np.random.default_rng(seed).choice(len(tw), max_samples, replace=False))
        rows, tw, ang = rows[keep], tw[keep], ang[keep]
    P = layout.positions
    start = solve_joint(P, ang, stations=stations)
    usable = start.success | (start.status == 3)
    if usable.sum() < 2:
        raise ValueError(f"{frames_path}: {int(usable.sum())} of {len(tw)} samples have a start pose "
                         f"({start.message}); nothing to calibrate")
    raw_stations = [Station(id=s.id, rotation=s.rotation, translation=s.translation, kind=s.kind,
                            rotor_rpm=s.rotor_rpm, clock_hz=s.clock_hz, fov_deg=s.fov_deg) for s in stations]
    raw = solve_joint(P, ang, stations=raw_stations) if any(s.calibration is not None for s in stations) else start
    reference = None
    if reference_path is not None:
        reference = _reference_poses(reference_path, tw, reference_tolerance_s)
        if reference[2].sum() < 3:
            raise ValueError(f"{reference_path}: only {int(reference[2].sum())} reference pose(s) within "
                             f"{reference_tolerance_s} s of a sample")
    init = (np.where(usable[:, None, None], start.rotation, np.nan), np.where(usable[:, None], start.translation, np.nan))
    res = bundle_adjust(P, ang, stations, sigma=sigma, initial_poses=init, sensor_offsets=sensor_offsets,
                        offset_prior=offset_prior, offset_bound=offset_bound, calibration_prior=calibration_prior,
                        reference=reference, reference_sigma=reference_sigma)
    if res.status == "too_few":
        raise ValueError(f"{frames_path}: {res.message}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_stations(out / "stations.json", res.stations)
    adj = Layout(res.points_body, layout.normals, layout.ids, dict(layout.metadata), layout.extra)
    atomic_write_text(out / "layout.json", json.dumps(adj.to_dict(), indent=2) + "\n")
    _plot(res.residual_before, res.residual_after, stations, out / "residuals.png")
    report = {
        "frames": str(frames_path), "samples": int(len(tw)), "samples_with_start": int(usable.sum()),
        "stations": [str(s.id) for s in stations], "sensors": int(layout.n), "sigma_rad": float(sigma),
        "window_s": float(WINDOW_S if window_s is None else window_s),
        "sensor_offsets": bool(sensor_offsets), "reference": None if reference_path is None else str(reference_path),
        "gauge": "reference poses" if reference is not None else f"station {stations[0].id} pose held as given",
        "success": bool(res.success), "status": res.status, "message": res.message,
        "residual_scale_sigma": res.sigma_scale,
        "median_sample_residual_rms_rad": {
            "raw": float(np.nanmedian(raw.residual_rms)) if np.isfinite(raw.residual_rms).any() else None,
            "start": float(np.nanmedian(start.residual_rms)) if np.isfinite(start.residual_rms).any() else None,
            "after": residual_summary(res.residual_after, stations, layout)["median_sample_rms_rad"]},
        "layout_sigma_m": None if sensor_offsets else float(offset_prior),
        "parameters": [{"name": p.name, "value": p.value, "std": p.std, "start": p.start, "unit": p.unit,
                        "status": p.status, "correlation": p.correlation} for p in res.parameters],
        "unobservable": [p.name for p in res.parameters if p.status == "unobservable"],
        "weakly_observable": [p.name for p in res.parameters if p.status == "weakly_observable"],
        "suspect": [p.name for p in res.parameters if p.status == "suspect"],
        "residuals_before": residual_summary(res.residual_before, stations, layout),
        "residuals_after": residual_summary(res.residual_after, stations, layout),
        "outputs": {"stations": str(out / "stations.json"), "layout": str(out / "layout.json"),
                    "report": str(out / "report.json"), "plot": str(out / "residuals.png")},
    }
    from ..io.jsonfile import to_jsonable

    atomic_write_text(out / "report.json", json.dumps(to_jsonable(report), indent=2) + "\n")
    return report


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
        t, res, rows = solve_joint_frames(fr, layout, stations, motion_compensation=motion_compensation)
        st_col = np.full(len(t), JOINT)
        vis = np.all(np.isfinite(window_angles_of(fr, rows)), -1)
    else:
        if not present:
            raise ValueError(f"{frames_path}: no row's station matches the stations given")
        ang = np.full((len(fr.t), len(stations), layout.n, 2), np.nan)
        ok = sidx >= 0
        ang[np.flatnonzero(ok), sidx[ok]] = to_station_convention(fr.angles, stations, sidx)[ok]
        res = solve_joint(layout.positions, ang, stations=stations)
        t, st_col = fr.t, sidx
        vis = np.all(np.isfinite(ang), -1)
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
    if not res.success.any():
        summary["reason"] = f"no pose solved ({res.message})"
    return summary


def window_angles_of(fr: StationFrames, rows):
    from ..joint import window_angles

    return window_angles(fr.angles, rows)
