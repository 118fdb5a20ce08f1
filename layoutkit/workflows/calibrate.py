"""What ``layoutkit calibrate`` does with files.

One or several devices' frame tables (:mod:`layoutkit.workflows.joint_solve`: the joint windows,
each station's convention) → the bundle adjustment over all devices at once and its
cross-validation (:mod:`layoutkit.workflows.calibrate_devices`, :mod:`layoutkit.calibrate`) →
``stations.json``, the adjusted layout(s), ``report.json``, ``residuals.png``.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..layout import Layout
from .joint_solve import (StationFrames, frame_file_stations, read_station_frames, solve_joint_frames,  # noqa: F401
                          solve_station_file, station_index, window_table)

__all__ = ["calibrate_files", "residual_summary",
           # the frame-table side lives in joint_solve (re-exported: older imports keep working)
           "StationFrames", "read_station_frames", "station_index", "frame_file_stations", "solve_joint_frames",
           "solve_station_file", "window_table"]


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


def _device_name(path, taken) -> str:
    p = Path(path)
    name = p.parent.name if p.stem == "frames" and p.parent.name else p.stem
    base, k = name or "device", 2
    while name in taken:
        name, k = f"{base}_{k}", k + 1
    return name


def _residual_layout(parts, devs):
    """A stand-in with the stacked sensors' ids (``<device> <id>``) for :func:`residual_summary`."""
    from types import SimpleNamespace

    return SimpleNamespace(ids=tuple(f"{d.name} {i}" for d in devs for i in d.layout.ids) if len(devs) > 1
                           else devs[0].layout.ids)


def _nothing_to_calibrate(frames_paths, stations_path, stations, res, reference_path, station_columns) -> str:
    """The error of a run that adjusts nothing: what the data lacked, which files, what to give."""
    files = ", ".join(str(p) for p in frames_paths)
    note = ""
    if not any(station_columns):
        note = (f"; {'the frame table has no' if len(frames_paths) == 1 else 'no frame table has a'} 'station' "
                f"column, so every row is the first station ({stations[0].id!r} of {stations_path})")
    gauge = "" if reference_path is not None else (
        f"; the first station's pose fixes the frame, so {'it has' if len(stations) == 1 else 'the others have'} "
        f"only {'its calibration terms' if len(stations) == 1 else 'their poses and calibration terms'} to adjust")
    return (f"{files}: nothing to calibrate: {res.message}{note}{gauge}. Give frames from two stations or more "
            f"(a 'station' column naming {stations_path}'s ids), more or moving frames, or --reference poses")


def calibrate_files(frames_path, layout_path, stations_path, out_dir, *, reference_path=None,
                    sensor_offsets: bool = False, sensor_timing: bool = False, sigma: float,
                    offset_prior: float = 1e-3, offset_bound: float = 5e-3, calibration_prior: float = 0.1,
                    timing_prior: float = 1e-7, station_prior=None, hold_station_prior: bool = True,
                    layout_sigma: float | None = None,
                    window_s: float | None = None, reference_tolerance_s: float = 0.01,
                    reference_sigma=(1e-3, 1e-3), max_samples: int | None = None, seed: int = 0,
                    cross_validation: bool = True, segments: bool = True) -> dict:
    """``layoutkit calibrate``: read, adjust, cross-validate, write ``stations.json``, the adjusted
    layout(s), ``report.json`` and ``residuals.png`` into ``out_dir``; returns the report dict.

    frames_path, layout_path : one frame table and its layout, or lists (several devices of one
    recording, in the stations' world frame; one layout for all, or one per frame table). Every device's
    windows are adjusted together (:func:`layoutkit.workflows.calibrate_devices.fit_devices`: shared
    station poses and calibration; each device's sensor offsets / latency with ``sensor_offsets`` /
    ``sensor_timing``); a device at rest gives one pose per static segment (``segments``).
    station_prior : ``(rad, m)`` prior sd of the station poses around the given ones (None: free);
    components the data do not determine are held there (docs/calibration.md), or with
    ``hold_station_prior=False`` every component stays adjusted under the prior (the MAP estimate).
    cross_validation : the device and time folds of
    :func:`~layoutkit.workflows.calibrate_devices.cross_validate`; when a held-out evaluation gets
    worse, ``stations.json`` holds the given (factory) stations, ``stations_fitted.json`` the fit, and
    the report's ``transfer`` says ``does_not_transfer`` and why.
    max_samples : at most this many windows per device (a random subset, ``seed``).
    ValueError naming the file for bad input; a run that cannot adjust anything raises ValueError saying why.
    """
    from ..io.atomic import atomic_write_text
    from ..io.stations import read_stations, write_stations
    from ..joint import WINDOW_S
    from ..layout import load_layout
    from .calibrate_devices import NO_FIT, cross_validate, device_windows, fit_devices, joint_residual

    frames_paths = [frames_path] if isinstance(frames_path, (str, Path)) else list(frames_path)
    layout_paths = [layout_path] if isinstance(layout_path, (str, Path)) else list(layout_path)
    if not frames_paths:
        raise ValueError("calibrate: no frame table given")
    if len(layout_paths) not in (1, len(frames_paths)):
        raise ValueError(f"--layout: give one layout for all frame tables or one per table "
                         f"({len(frames_paths)} tables, {len(layout_paths)} layouts)")
    if len(layout_paths) == 1:
        layout_paths = layout_paths * len(frames_paths)
    if reference_path is not None and len(frames_paths) > 1:
        raise ValueError(f"{reference_path}: a reference pose table belongs to one device; give one frame table with it")
    stations = list(read_stations(stations_path))
    if not stations:
        raise ValueError(f"{stations_path}: no stations")
    win = WINDOW_S if window_s is None else window_s
    devs, names, frs = [], [], []
    for fp, lp in zip(frames_paths, layout_paths):
        layout = load_layout(lp)
        fr = read_station_frames(fp, layout)
        frs.append(fr)
        name = _device_name(fp, names)
        names.append(name)
        try:
            devs.append(device_windows(name, fr, layout, stations, window_s=win,
                                       segments=segments and reference_path is None))
        except ValueError as exc:
            raise ValueError(f"{fp}: {exc}") from None
    for fp, d in zip(frames_paths, devs):
        if d.usable.sum() < 2:
            raise ValueError(f"{fp}: {int(d.usable.sum())} of {len(d.t)} samples have a start pose "
                             f"({d.start.message}); nothing to calibrate")
    ba_kw = dict(sensor_offsets=sensor_offsets, sensor_timing=sensor_timing, offset_prior=offset_prior,
                 offset_bound=offset_bound, calibration_prior=calibration_prior, timing_prior=timing_prior,
                 station_prior=station_prior, hold_station_prior=hold_station_prior, layout_sigma=layout_sigma)
    selects = None
    if reference_path is not None:
        d = devs[0]
        rng = np.random.default_rng(seed)
        sel = d.usable.copy()
        idx = np.flatnonzero(sel)
        if max_samples is not None and idx.size > max_samples:
            sel[:] = False
            sel[np.sort(rng.choice(idx, max_samples, replace=False))] = True
        reference = _reference_poses(reference_path, d.t[sel], reference_tolerance_s)
        if reference[2].sum() < 3:
            raise ValueError(f"{reference_path}: only {int(reference[2].sum())} reference pose(s) within "
                             f"{reference_tolerance_s} s of a sample")
        selects = [sel]
        ba_kw.update(reference=reference, reference_sigma=reference_sigma)
    res, parts = fit_devices(devs, stations, selects, sigma=sigma, max_windows=None if selects else max_samples,
                             seed=seed, **ba_kw)
    if res.status in NO_FIT:
        raise ValueError(_nothing_to_calibrate(frames_paths, stations_path, stations, res, reference_path,
                                               [f.station_column for f in frs]))
    folds = []
    if cross_validation and reference_path is None:
        folds = cross_validate(devs, stations, sigma=sigma, max_windows=max_samples, seed=seed, **ba_kw)
    worse = [f for f in folds if f["verdict"] == "worse"]
    transfer = {"status": "does_not_transfer" if worse else ("ok" if folds else "not_tested"),
                "folds": folds,
                "message": ("; ".join(f"{f['held_out']}: {f['factory_rad']:.3g} rad with the given stations, "
                                      f"{f['calibrated_rad']:.3g} rad calibrated on {', '.join(f['fit_on'])}"
                                      for f in worse) if worse else
                            ("every held-out evaluation is as good or better with the calibrated stations"
                             if folds else "no cross-validation (--no-cross-validation or a reference run)"))}
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if worse:
        write_stations(out / "stations.json", stations)
        write_stations(out / "stations_fitted.json", res.stations)
    else:
        write_stations(out / "stations.json", res.stations)
    layouts_out = {}
    for d in devs:
        sl = parts[d.name]["sensors"]
        adj = Layout(res.points_body[sl], d.layout.normals, d.layout.ids, dict(d.layout.metadata), d.layout.extra)
        path = out / ("layout.json" if len(devs) == 1 else f"layout_{d.name}.json")
        atomic_write_text(path, json.dumps(adj.to_dict(), indent=2) + "\n")
        layouts_out[d.name] = str(path)
    _plot(res.residual_before, res.residual_after, stations, out / "residuals.png")
    # each device: the joint residual with the given stations, the fitted ones (nominal layout), and the
    # fitted ones with its own adjusted layout and latency (the device's terms, fitted on it)
    devices = {}
    for d in devs:
        sl = parts[d.name]["sensors"]
        lat = res.extra["timing_s"][sl]
        at_rest = _at_rest(d)
        devices[d.name] = {
            "windows": int(len(d.t)), "windows_with_start": int(d.usable.sum()),
            "windows_used": int(parts[d.name]["windows"].sum()), "body_poses": parts[d.name]["poses"],
            "static_poses": parts[d.name]["static_poses"], "at_rest": at_rest,
            "joint_residual_median_rad": {
                "given_stations": joint_residual(d, stations)["median_rad"],
                "calibrated_stations": joint_residual(d, res.stations)["median_rad"],
                "calibrated_stations_and_own_layout": joint_residual(d, res.stations, res.points_body[sl],
                                                                     latency=lat)["median_rad"]},
            "own_terms_note": ("at rest: its sensor offsets / latency are determined at this one pose, where they "
                               "also absorb every other error of the model; nothing here tests them elsewhere")
            if at_rest and (sensor_offsets or sensor_timing) else None}
    rl = _residual_layout(parts, devs)
    determined = _determined(res.parameters)
    start_rms = np.concatenate([d.start.residual_rms[d.usable] for d in devs])
    report = {
        "frames": str(frames_paths[0]) if len(frames_paths) == 1 else [str(p) for p in frames_paths],
        "samples": int(sum(len(d.t) for d in devs)), "samples_with_start": int(sum(d.usable.sum() for d in devs)),
        "stations": [str(s.id) for s in stations], "sensors": int(sum(d.layout.n for d in devs)),
        "sigma_rad": float(sigma), "window_s": float(win),
        "sensor_offsets": bool(sensor_offsets), "sensor_timing": bool(sensor_timing),
        "station_prior": None if station_prior is None else [float(x) for x in station_prior],
        "station_prior_mode": None if station_prior is None else ("hold" if hold_station_prior else "map"),
        "reference": None if reference_path is None else str(reference_path),
        "gauge": "reference poses" if reference_path is not None else f"station {stations[0].id} pose held as given",
        "success": bool(res.success), "status": res.status, "message": res.message,
        "residual_scale_sigma": res.sigma_scale,
        "median_sample_residual_rms_rad": {
            "raw": _raw_median(devs, stations),
            "start": float(np.nanmedian(start_rms)) if np.isfinite(start_rms).any() else None,
            "after": residual_summary(res.residual_after, stations, rl)["median_sample_rms_rad"]},
        "layout_sigma_m": None if sensor_offsets else float(offset_prior if layout_sigma is None else layout_sigma),
        "devices": devices,
        "transfer": transfer,
        "stations_written": ("given (the fit did not transfer; the fit is in stations_fitted.json)" if worse
                             else "fitted" if any(p.name.startswith("station") and p.status in ("ok", "suspect")
                                                  or (p.name.startswith("station") and p.status == "prior_dominated"
                                                      and p.value != p.start) for p in res.parameters)
                             else "fitted (= the given: the data determine no station term)"),
        "determined": determined,
        "parameters": [{"name": p.name, "value": p.value, "std": p.std, "start": p.start, "unit": p.unit,
                        "status": p.status, "correlation": p.correlation} for p in res.parameters],
        "unobservable": [p.name for p in res.parameters if p.status == "unobservable"],
        "weakly_observable": [p.name for p in res.parameters if p.status == "weakly_observable"],
        "prior_dominated": [p.name for p in res.parameters if p.status == "prior_dominated"],
        "suspect": [p.name for p in res.parameters if p.status == "suspect"],
        "residuals_before": residual_summary(res.residual_before, stations, rl),
        "residuals_after": residual_summary(res.residual_after, stations, rl),
        "outputs": {"stations": str(out / "stations.json"), "layout": layouts_out[devs[0].name] if len(devs) == 1
                    else layouts_out, "report": str(out / "report.json"), "plot": str(out / "residuals.png"),
                    **({"stations_fitted": str(out / "stations_fitted.json")} if worse else {})},
    }
    from ..io.jsonfile import to_jsonable

    atomic_write_text(out / "report.json", json.dumps(to_jsonable(report), indent=2) + "\n")
    return report


def _at_rest(d) -> bool:
    """At least 90 % of the device's usable windows lie in static segments."""
    u = d.usable
    return bool(u.any() and d.static.size and np.mean(d.static[d.pose_of[u]]) >= 0.9)


def _raw_median(devs, stations):
    """Median per-window residual RMS through the ideal model (the stations without calibration)."""
    from dataclasses import replace

    from ..joint import solve_joint

    if not any(s.calibration is not None for s in stations):
        rms = np.concatenate([d.start.residual_rms[d.usable] for d in devs])
    else:
        raw = [replace(s, calibration=None) for s in stations]
        rms = np.concatenate([solve_joint(d.layout.positions, d.angles[d.usable], stations=raw).residual_rms for d in devs])
    return float(np.nanmedian(rms)) if np.isfinite(rms).any() else None


def _determined(parameters) -> dict:
    """Which terms the data determine, by group: counts of each status (``ok``/``suspect`` = fitted;
    ``unobservable``/``weakly_observable`` = held at the start; ``fixed`` = not adjusted;
    ``prior_dominated`` = a device's sensor term adjusted, but its sd is > half its prior)."""
    groups: dict = {}
    for p in parameters:
        words = p.name.split()
        if words[0] == "station":
            key = f"station {words[1]} {'pose' if words[2] == 'pose' else 'calibration'}"
        elif words[-1] == "timing":
            key = f"{' '.join(words[1:-2]) or 'sensor'} latency" if len(words) > 3 else "sensor latency"
        else:
            key = f"{' '.join(words[1:-3]) or 'sensor'} offsets" if len(words) > 4 else "sensor offsets"
        g = groups.setdefault(key, {})
        g[p.status] = g.get(p.status, 0) + 1
    return groups


