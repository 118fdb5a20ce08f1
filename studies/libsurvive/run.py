"""Every public libsurvive recording through layoutkit (issue 26 item 6).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python studies/libsurvive/run.py            # every recording
    OPENBLAS_NUM_THREADS=1 .venv/bin/python studies/libsurvive/run.py --only lh1_test_cal --no-calibrate
    # the committed results (calibration only where the study needs it: ~25 min on a loaded 2-core machine)
    OPENBLAS_NUM_THREADS=1 .venv/bin/python studies/libsurvive/run.py --calibrate-only lh1_test_cal index-yank

Recordings: ``/work/shared/data/libsurvive/*.rec.gz`` and ``~/.cache/layoutkit-realdata/survive/*.rec.gz``
(``jdavidberger/libsurvive-extras-data``, MIT; the cache is made by ``shared/realdata/prepare.sh``;
none of it is copied here — only results). A name found in both places is the same file.

Per device (``layoutkit import libsurvive`` → frame table, layout from the device's CONFIG,
stations from the recording's ``.json`` / ``LH_POSE``, factory calibration):

- **statuses** of the joint solve (20 ms windows, every station through its calibrated model) and
  of the per-station solve; windows whose pose used exactly 6 angles (no redundancy: angles =
  unknowns, the residual is ~0 whatever the error) are counted;
- **residuals**: median per-window RMS, joint and per station (the per-station solve);
- **motion**: the body speed of each window (central differences of our joint poses) and the
  joint residual per speed bin with and without motion compensation (each station's rows at
  their own time, constant velocity across the window: ``solve --solve joint --motion-compensation``),
  and again through the stations the recording's calibration wrote (where it was calibrated);
- **libsurvive's own poses** (``POSE`` lines, else its ``EXTERNAL_POSE`` replay solution) reprojected
  on the same recorded angles through the same stations, per speed bin. libsurvive reports the pose
  of its own body frame (the IMU / head frame), a constant transform from the layout's frame; that
  transform is fitted here to minimise libsurvive's own reprojection residual (6 parameters for the
  whole recording: the comparison favours libsurvive);
- **precision vs accuracy** (:func:`layoutkit.workflows.accuracy.precision_accuracy`);
- **the IMU-aided filter** (:func:`layoutkit.workflows.imu_filter.filter_recording`) on every device with
  ``i`` lines that moved: each sweep's residual before its own update (the pose predicted from the
  IMU and the earlier sweeps) and after, per speed bin, beside libsurvive's poses on the same sweeps —
  with the factory stations and with the stations this recording's calibration wrote;
- **calibration** (per recording, all its devices at once: ``layoutkit calibrate`` with
  ``--sensor-offsets --station-prior-deg 1 --station-prior-mm 30``): each device's joint residual
  with the given stations, the calibrated ones, and with its own fitted terms, and the
  cross-validation folds (device folds: the held-out device with its nominal layout; time fold).

Outputs in ``studies/libsurvive/results/``: ``results.json``, ``results.md`` (tables) and figures.
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")   # before numpy: BLAS threads only fight on a shared machine
import numpy as np  # noqa: E402

HERE = Path(__file__).parent
OUT = HERE / "results"
SOURCES = (Path("/work/shared/data/libsurvive"), Path.home() / ".cache" / "layoutkit-realdata" / "survive")
SPEED_BINS = (0.0, 0.05, 0.2, 0.5, 1.0, np.inf)          # m/s
CAL_PRIOR = (np.deg2rad(1.0), 0.03)                     # station prior of the study's calibrate runs
CAL_MAX_WINDOWS = 60                                      # per device
MIN_WINDOWS_FOR_CAL = 50


def recordings(only=None):
    seen = {}
    for src in SOURCES:
        for p in sorted(src.glob("*.rec.gz")):
            if p.name not in seen and (only is None or any(o in p.name for o in only)):
                seen[p.name] = p
    return list(seen.values())


def _stats(x):
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return {"n": int(x.size), "median": float(np.median(x)) if x.size else None,
            "p90": float(np.percentile(x, 90)) if x.size else None}


def _speed(tw, res):
    """Body speed (m/s) of each window: central differences of the solved positions over windows
    less than 0.1 s apart (NaN elsewhere)."""
    ok = res.success & np.all(np.isfinite(res.translation), 1)
    v = np.full(len(tw), np.nan)
    g = np.flatnonzero(ok)
    if g.size < 3:
        return v
    t, p = tw[g], res.translation[g]
    for k in range(1, g.size - 1):
        if t[k + 1] - t[k - 1] < 0.1:
            v[g[k]] = np.linalg.norm(p[k + 1] - p[k - 1]) / (t[k + 1] - t[k - 1])
    return v


def _by_speed(speed, value):
    out = []
    for lo, hi in zip(SPEED_BINS[:-1], SPEED_BINS[1:]):
        m = (speed >= lo) & (speed < hi) & np.isfinite(value)
        out.append({"lo_m_s": lo, "hi_m_s": None if not np.isfinite(hi) else hi, "windows": int(m.sum()),
                    "median_rad": float(np.median(value[m])) if m.any() else None})
    return out


def _reference(ddir: Path, dev: str, root: Path):
    """libsurvive's poses of the device: POSE lines (``reference.csv``), else the EXTERNAL_POSE replay
    solution of ``replay_<dev>``; (label, PoseTable) or None."""
    from layoutkit.io.poses import read_poses

    for label, path in (("POSE", ddir / "reference.csv"), ("EXTERNAL_POSE", root / f"replay_{dev}" / "reference_external.csv"),
                        ("EXTERNAL_POSE", ddir / "reference_external.csv")):
        if path.exists():
            tab = read_poses(path)
            if len(tab.t) >= 10:
                return label, tab
    return None


def libsurvive_reprojection(positions, stations, tw, angles, ref, max_fit: int = 200, seed: int = 0):
    """Per-window RMS residual (rad) of libsurvive's poses on the recorded ``angles (W, S, n, 2)``,
    interpolated to the window times ``tw`` (slerp; only inside its time range and gaps < 0.1 s),
    after the constant body-frame transform that minimises that residual (fitted, soft-L1, on at most
    ``max_fit`` windows). Returns ``(rms (W,), transform {rotvec_deg, translation_mm})``."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation, Slerp

    from layoutkit.joint import model_angles_jacobian

    o = np.argsort(ref.t)
    t = ref.t[o]
    rv, tr = ref.rotvec[o], ref.translation[o]
    keep = np.concatenate([[True], np.diff(t) > 0]) & np.all(np.isfinite(rv), 1) & np.all(np.isfinite(tr), 1)
    t, rv, tr = t[keep], rv[keep], tr[keep]
    out = np.full(len(tw), np.nan)
    if t.size < 2:
        return out, None
    k = np.clip(np.searchsorted(t, tw), 1, t.size - 1)
    inside = (tw >= t[0]) & (tw <= t[-1]) & (t[k] - t[k - 1] < 0.1)
    inside &= np.isfinite(angles).any(axis=(1, 2, 3))
    if inside.sum() < 5:
        return out, None
    Rl = Slerp(t, Rotation.from_rotvec(rv))(tw[inside]).as_matrix()
    Tl = np.stack([np.interp(tw[inside], t, tr[:, c]) for c in range(3)], 1)
    A = angles[inside]

    def resid(x, idx):
        Rx = Rotation.from_rotvec(x[:3]).as_matrix()
        R = Rl[idx] @ Rx
        T = Tl[idx] + Rl[idx] @ x[3:]
        pred, _, _ = model_angles_jacobian(positions, R, T, stations, jacobian=False)
        r = (A[idx] - pred + np.pi) % (2 * np.pi) - np.pi
        return r, R, T

    rng = np.random.default_rng(seed)
    fit = np.arange(inside.sum())
    if fit.size > max_fit:
        fit = np.sort(rng.choice(fit, max_fit, replace=False))
    # start: libsurvive frame → layout frame as the median of the per-window transforms is not known
    # here; start from identity and from the four 180-degree turns (IMU frames are often flipped)
    f = lambda x: np.nan_to_num(resid(x, fit)[0][np.isfinite(A[fit])], nan=0.0)  # noqa: E731
    starts = [np.array(r0 + [0.0, 0.0, 0.0], float) for r0 in ([0, 0, 0], [np.pi, 0, 0], [0, np.pi, 0], [0, 0, np.pi])]
    x0 = min(starts, key=lambda x: float(np.sum(np.log1p((f(x) / 1e-3) ** 2))))   # the best start only
    best = least_squares(f, x0, loss="soft_l1", f_scale=1e-3, max_nfev=100)
    r, _, _ = resid(best.x, np.arange(inside.sum()))
    out[inside] = np.sqrt(np.nanmean(r.reshape(len(r), -1) ** 2, axis=1))
    return out, {"rotvec_deg": np.degrees(best.x[:3]).tolist(), "translation_mm": (best.x[3:] * 1e3).tolist()}


def study_device(name, ddir: Path, root: Path, stations):
    from layoutkit.layout import load_layout
    from layoutkit.pnp import STATUS_NAMES
    from layoutkit.status import LOW_REDUNDANCY
    from layoutkit.workflows.accuracy import precision_accuracy
    from layoutkit.workflows.joint_solve import read_station_frames, solve_joint_frames, station_index, to_station_convention
    from layoutkit.joint import solve_joint

    lay = load_layout(ddir / "layout.json")
    fr = read_station_frames(ddir / "frames.csv", lay)
    tw, res, rows, info = solve_joint_frames(fr, lay, stations)
    ang = info["angles"]
    used = (np.isfinite(ang) & np.isfinite(res.translation[:, 0])[:, None, None, None]).sum(axis=(1, 2, 3))
    counts = {STATUS_NAMES.get(int(k), str(int(k))): int(v) for k, v in zip(*np.unique(res.status, return_counts=True))}
    ok = res.success
    out = {"rows": int(len(fr.t)), "windows": int(len(tw)), "sensors": int(lay.n),
           "duration_s": float(tw[-1] - tw[0]) if len(tw) else 0.0,
           "joint": {"status_counts": counts, "solved": int(ok.sum()),
                     "no_redundancy_ok": int(np.sum(ok & (used == 6))),
                     "one_spare_angle_ok": int(np.sum(ok & (used == 7))),
                     "status_ok_below_8_angles": int(np.sum((res.status == 0) & (used < 8))),
                     "low_redundancy": int(np.sum(res.status == LOW_REDUNDANCY)),
                     "residual": _stats(res.residual_rms[ok])}}
    # per-station solve: each row alone through its station's model
    sidx = station_index(fr.station, stations)
    A1 = np.full((len(fr.t), len(stations), lay.n, 2), np.nan)
    m = sidx >= 0
    A1[np.flatnonzero(m), sidx[m]] = to_station_convention(fr.angles, stations, sidx)[m]
    r1 = solve_joint(lay.positions, A1, stations=stations)
    used1 = np.isfinite(A1).sum(axis=(1, 2, 3))
    out["per_station"] = {}
    for q, st in enumerate(stations):
        mm = sidx == q
        if not mm.any():
            continue
        c = {STATUS_NAMES.get(int(k), str(int(k))): int(v) for k, v in zip(*np.unique(r1.status[mm], return_counts=True))}
        out["per_station"][str(st.id)] = {"rows": int(mm.sum()), "status_counts": c,
                                          "no_redundancy_ok": int(np.sum(mm & r1.success & (used1 == 6))),
                                          "low_redundancy": int(np.sum(mm & (r1.status == LOW_REDUNDANCY))),
                                          "status_ok_below_8_angles": int(np.sum(mm & (r1.status == 0) & (used1 < 8))),
                                          "residual": _stats(r1.residual_rms[mm & r1.success])}
    # `layoutkit solve --solve per-station` (the PnP path, which can solve 3 sensors = 6 angles from
    # scratch): its status counts, where a pose without redundancy is now low_redundancy, not ok
    from layoutkit.status import NAMES
    from layoutkit.workflows.frames import solve_frame_file

    sps = solve_frame_file(ddir / "frames.csv", lay, stations_path=root / "stations.json")
    sc = {NAMES.get(int(k), str(k)): int(v) for k, v in sps["status_counts"].items()}
    out["solve_per_station"] = {"status_counts": sc, "frames": int(sum(sc.values())),
                                "low_redundancy": sc.get("low_redundancy", 0), "ok": sc.get("ok", 0)}
    # motion: speed per window, joint residual by speed with and without motion compensation
    speed = _speed(tw, res)
    _, resm, _, _ = solve_joint_frames(fr, lay, stations, motion_compensation=True)
    out["speed"] = _stats(speed)
    out["residual_by_speed"] = {"static_model": _by_speed(speed, np.where(ok, res.residual_rms, np.nan)),
                                "motion_compensated": _by_speed(speed, np.where(resm.success, resm.residual_rms, np.nan))}
    # libsurvive's own poses on the same angles
    ref = _reference(ddir, name, root)
    if ref is not None:
        rms, xf = libsurvive_reprojection(lay.positions, stations, tw, ang, ref[1])
        both = ok & np.isfinite(rms)
        out["libsurvive"] = {"source": ref[0], "poses": int(len(ref[1].t)), "body_transform": xf,
                             "windows_compared": int(both.sum()),
                             "reprojection": _stats(rms[both]), "ours_same_windows": _stats(res.residual_rms[both]),
                             "ours_motion_same_windows": _stats(resm.residual_rms[both & resm.success]),
                             "by_speed": _by_speed(speed, np.where(both, rms, np.nan))}
    pa = precision_accuracy(lay.positions, stations, res.rotation, res.translation, ang, ok=ok, ids=lay.ids)
    pa.get("sensor_bias", {}).pop("per_sensor_axis", None)
    out["precision_accuracy"] = pa
    return out, {"tw": tw, "speed": speed, "res": res.residual_rms, "ok": ok, "resm": resm.residual_rms,
                 "okm": resm.success, "libsurvive": out.get("libsurvive") and rms}


def speed_with_stations(ddir: Path, stations, speed):
    """The joint residual by speed (``speed (W,)`` from the factory-station solve, same windows) with
    and without motion compensation through ``stations`` (e.g. the calibrated ones)."""
    from layoutkit.layout import load_layout
    from layoutkit.workflows.joint_solve import read_station_frames, solve_joint_frames

    lay = load_layout(ddir / "layout.json")
    fr = read_station_frames(ddir / "frames.csv", lay)
    _, res, _, _ = solve_joint_frames(fr, lay, stations)
    _, resm, _, _ = solve_joint_frames(fr, lay, stations, motion_compensation=True)
    return {"static_model": _by_speed(speed, np.where(res.success, res.residual_rms, np.nan)),
            "motion_compensated": _by_speed(speed, np.where(resm.success, resm.residual_rms, np.nan))}


def imu_filter_device(path: Path, dev: str, stations, ref, label: str):
    """The IMU-aided filter on one device: per speed bin (the filter's own speed), the median per-sweep
    residual RMS before the sweep's update (prior: predicted from the IMU and earlier sweeps) and
    after it, and libsurvive's poses on the same sweeps."""
    from layoutkit.workflows.imu_filter import filter_recording

    r = filter_recording(path, dev, stations=stations)
    s = r["sweeps"]
    speed = np.linalg.norm(s["velocity"], axis=1)
    acc = s["accepted"]
    out = {"stations": label, "summary": r["summary"],
           "prior_by_speed": _by_speed(speed, np.where(acc, s["prior_rms"], np.nan)),
           "posterior_by_speed": _by_speed(speed, np.where(acc, s["posterior_rms"], np.nan)),
           "prior_all_sweeps_by_speed": _by_speed(speed, np.where(np.isfinite(s["nis"]), s["prior_rms"], np.nan))}
    if ref is not None:
        K, S, n = len(s["t"]), len(stations), r["layout"].n
        grid = np.full((K, S, n, 2), np.nan)
        grid[np.arange(K), s["station"], :, s["axis"]] = s["angles"]
        rms, xf = libsurvive_reprojection(r["layout"].positions, stations, s["t"], grid, ref[1])
        out["libsurvive_by_speed"] = _by_speed(speed, np.where(np.isfinite(s["nis"]), rms, np.nan))
        out["libsurvive_body_transform"] = xf
    series = {"speed": speed, "prior": np.where(acc, s["prior_rms"], np.nan), "t": s["t"],
              "posterior": np.where(acc, s["posterior_rms"], np.nan)}
    return out, series


def calibrate_recording(root: Path, devices, stations_path, cal_dir: Path):
    from layoutkit.units import ARCSEC
    from layoutkit.workflows.calibrate import calibrate_files

    frames = [root / d / "frames.csv" for d in devices]
    layouts = [root / d / "layout.json" for d in devices]
    t0 = time.time()
    rep = calibrate_files(frames, layouts, stations_path, cal_dir, sigma=4.0 * ARCSEC, sensor_offsets=True,
                          station_prior=CAL_PRIOR, max_samples=CAL_MAX_WINDOWS, seed=0)
    keep = ("samples", "samples_with_start", "message", "residual_scale_sigma", "devices", "transfer",
            "stations_written", "determined", "median_sample_residual_rms_rad")
    out = {k: rep[k] for k in keep}
    out["seconds"] = time.time() - t0
    out["stations_file"] = str(cal_dir / "stations.json")
    return out


def study_recording(path: Path, work: Path, calibrate: bool):
    from layoutkit.io.stations import read_stations
    from layoutkit.workflows.importers import import_libsurvive

    t0 = time.time()
    out = {"file": str(path), "bytes": path.stat().st_size}
    root = work / path.name.replace(".rec.gz", "")
    try:
        summ = import_libsurvive(path, root)
    except ValueError as exc:
        out["import_error"] = str(exc)
        return out, {}
    out["truncated"] = summ["truncated"]
    out["ended"] = summ["ended"]
    st_info = summ.get("stations", {})
    out["stations"] = [{k: i[k] for k in ("id", "source_id", "kind", "pose_source", "channel")} for i in st_info.get("stations", [])]
    if not st_info:
        out["error"] = "no stations (no light data or config)"
        return out, {}
    stations = list(read_stations(root / "stations.json"))
    out["devices"] = {}
    series = {}
    for dev, info in summ["devices"].items():
        if "frames_file" not in info:
            if "frames_error" in info or "layout_error" in info:
                out["devices"][dev] = {"skipped": info.get("frames_error") or info.get("layout_error")}
            continue
        if info.get("frames", 0) < 20:
            out["devices"][dev] = {"skipped": f"{info.get('frames', 0)} frames"}
            continue
        d, s = study_device(dev, root / dev, root, stations)
        out["devices"][dev] = d
        series[dev] = s
    usable = [dev for dev, d in out["devices"].items() if d.get("joint", {}).get("solved", 0) >= MIN_WINDOWS_FOR_CAL]
    if calibrate and usable:
        try:
            out["calibration"] = calibrate_recording(root, usable, root / "stations.json", work / (root.name + "_cal"))
        except ValueError as exc:
            out["calibration"] = {"error": str(exc)}
    # motion with the calibrated stations: the factory stations' error (1e-3 rad on index-yank) hides
    # what motion compensation does; through the stations the calibration wrote it shows
    cal = out.get("calibration", {})
    if cal.get("stations_file") and Path(cal["stations_file"]).exists():
        cal_st = list(read_stations(cal["stations_file"]))
        for dev, d in out["devices"].items():
            if "speed" in d and (d["speed"]["p90"] or 0) > 0.2:
                d["residual_by_speed_calibrated"] = speed_with_stations(root / dev, cal_st, series[dev]["speed"])
                d["residual_by_speed_calibrated"]["stations"] = cal.get("stations_written")
    # the IMU-aided filter on the devices that moved and have IMU lines
    for dev, d in out["devices"].items():
        if "speed" not in d or not (d["speed"]["p90"] or 0) > 0.2 or summ["line_types"].get("i", 0) == 0:
            continue
        ref = _reference(root / dev, dev, root)
        sets = [("factory", stations)]
        cal = out.get("calibration", {})
        if cal.get("stations_file") and Path(cal["stations_file"]).exists():
            sets.append(("calibrated on this recording", list(read_stations(cal["stations_file"]))))
        d["imu_filter"] = []
        for label, sts in sets:
            try:
                fo, fs = imu_filter_device(path, dev, sts, ref, label)
            except ValueError as exc:
                fo, fs = {"stations": label, "error": str(exc)}, None
            d["imu_filter"].append(fo)
            if fs is not None:
                series[dev][f"imu {label}"] = fs
    out["seconds"] = time.time() - t0
    return out, series


def _fmt(v, f="{:.3g}"):
    return "–" if v is None else f.format(v)


def write_markdown(results, path: Path):
    L = ["# libsurvive recordings through layoutkit (issue 26)", "",
         "Generated by `studies/libsurvive/run.py`; numbers in rad unless marked. Joint = one pose per 20 ms window "
         "from every station through its factory-calibrated model. *low-red.* = windows with status `low_redundancy` "
         "(6 or 7 seen angles: the pose is returned but not ok; before issue 26 item 2 these were ok) and, in brackets, "
         "`ok` windows with fewer than 8 angles (0 everywhere = none slips through). The joint model needs 4 sensors "
         "of one station to start, so its 3-sensor rows are `too_few_lit`; `layoutkit solve --solve per-station` "
         "(PnP, solves 3 sensors from scratch) is where the no-redundancy poses were `ok` before. libsurvive = its own poses "
         "reprojected on the same angles (its body frame fitted to favour it).", "",
         "| recording | device | windows | solved | low-red. joint (ok < 8 angles) | `solve --solve per-station`: low-red. / ok / frames | joint-model per station: low-red. of rows (ok < 8 angles) | joint median | per-station medians | libsurvive median | speed p90 m/s |",
         "|---|---|---|---|---|---|---|---|---|---|---|"]
    for rec in results:
        name = Path(rec["file"]).name
        if "import_error" in rec or "error" in rec:
            L.append(f"| {name} | – | – | – | – | – | – | – | – | – | {rec.get('import_error') or rec.get('error')} |")
            continue
        for dev, d in rec["devices"].items():
            if "skipped" in d:
                L.append(f"| {name} | {dev} | skipped: {d['skipped']} | | | | | | | | |")
                continue
            ps = ", ".join(f"{k}: {_fmt(v['residual']['median'])}" for k, v in d["per_station"].items())
            nr = ", ".join(f"{k}: {v.get('low_redundancy', '–')} of {v['rows']} ({v.get('status_ok_below_8_angles', '–')})"
                           for k, v in d["per_station"].items())
            jl = f"{d['joint'].get('low_redundancy', '–')} ({d['joint'].get('status_ok_below_8_angles', '–')})"
            sp = d.get("solve_per_station")
            sp = "–" if sp is None else f"{sp['low_redundancy']} / {sp['ok']} / {sp['frames']}"
            ls = d.get("libsurvive", {}).get("reprojection", {}).get("median")
            L.append(f"| {name} | {dev} | {d['windows']} | {d['joint']['solved']} | {jl} | {sp} | {nr} | "
                     f"{_fmt(d['joint']['residual']['median'])} | {ps} | {_fmt(ls)} | {_fmt(d['speed']['p90'], '{:.2f}')} |")
    L += ["", "## Joint residual by speed (median per-window RMS): static model / motion-compensated / libsurvive", "",
          "| recording | device | " + " | ".join(f"{lo}-{hi if np.isfinite(hi) else '∞'} m/s" for lo, hi in
                                                zip(SPEED_BINS[:-1], SPEED_BINS[1:])) + " |",
          "|---|---|" + "---|" * (len(SPEED_BINS) - 1)]
    for rec in results:
        for dev, d in rec.get("devices", {}).items():
            if "residual_by_speed" not in d:
                continue
            a, b = d["residual_by_speed"]["static_model"], d["residual_by_speed"]["motion_compensated"]
            c = d.get("libsurvive", {}).get("by_speed") or [{"median_rad": None}] * len(a)
            cells = [f"{_fmt(x['median_rad'])} / {_fmt(y['median_rad'])} / {_fmt(z['median_rad'])} (n={x['windows']})"
                     for x, y, z in zip(a, b, c)]
            L.append(f"| {Path(rec['file']).name} | {dev} | " + " | ".join(cells) + " |")
            if "residual_by_speed_calibrated" in d:
                a, b = d["residual_by_speed_calibrated"]["static_model"], d["residual_by_speed_calibrated"]["motion_compensated"]
                cells = [f"{_fmt(x['median_rad'])} / {_fmt(y['median_rad'])} / – (n={x['windows']})" for x, y in zip(a, b)]
                L.append(f"| {Path(rec['file']).name} | {dev}, stations calibrated on this recording "
                         f"({d['residual_by_speed_calibrated'].get('stations')}) | " + " | ".join(cells) + " |")
    L += ["", "## Calibration (all devices of a recording at once) and cross-validation", "",
          "| recording | device | given stations | calibrated stations | + own terms | folds (held out: given → calibrated, verdict) | stations written |",
          "|---|---|---|---|---|---|---|"]
    for rec in results:
        cal = rec.get("calibration")
        if not cal:
            continue
        if "error" in cal:
            L.append(f"| {Path(rec['file']).name} | – | {cal['error']} | | | | |")
            continue
        folds = "; ".join(f"{f['held_out']}: {_fmt(f['factory_rad'])} → {_fmt(f['calibrated_rad'])} {f['verdict']}"
                          for f in cal["transfer"]["folds"])
        for k, (dev, d) in enumerate(cal["devices"].items()):
            j = d["joint_residual_median_rad"]
            L.append(f"| {Path(rec['file']).name} | {dev}{' (at rest)' if d['at_rest'] else ''} | {_fmt(j['given_stations'])} | "
                     f"{_fmt(j['calibrated_stations'])} | {_fmt(j['calibrated_stations_and_own_layout'])} | "
                     f"{folds if k == 0 else ''} | {cal['stations_written'] if k == 0 else ''} |")
    L += ["", "## IMU-aided filter: per-sweep residual by speed (median RMS): before the sweep's update / after / "
          "libsurvive on the same sweeps", "",
          "| recording | device | stations | sweeps accepted / rejected / restarts | " +
          " | ".join(f"{lo}-{hi if np.isfinite(hi) else '∞'} m/s" for lo, hi in zip(SPEED_BINS[:-1], SPEED_BINS[1:])) + " |",
          "|---|---|---|---|" + "---|" * (len(SPEED_BINS) - 1)]
    for rec in results:
        for dev, d in rec.get("devices", {}).items():
            for fo in d.get("imu_filter", []):
                if "error" in fo:
                    L.append(f"| {Path(rec['file']).name} | {dev} | {fo['stations']} | {fo['error']} |" + " |" * len(SPEED_BINS))
                    continue
                c = fo["summary"]["sweeps"]
                ls = fo.get("libsurvive_by_speed") or [{"median_rad": None}] * (len(SPEED_BINS) - 1)
                cells = [f"{_fmt(a['median_rad'])} / {_fmt(b['median_rad'])} / {_fmt(z['median_rad'])} (n={a['windows']})"
                         for a, b, z in zip(fo["prior_by_speed"], fo["posterior_by_speed"], ls)]
                L.append(f"| {Path(rec['file']).name} | {dev} | {fo['stations']} | {c['accepted']} / {c['rejected']} / "
                         f"{c['restarts']} | " + " | ".join(cells) + " |")
    L += ["", "## Precision vs accuracy (per device)", ""]
    for rec in results:
        for dev, d in rec.get("devices", {}).items():
            if "precision_accuracy" in d:
                L.append(f"- {Path(rec['file']).name} {dev}: {d['precision_accuracy']['message']}")
    path.write_text("\n".join(L) + "\n")


def figures(results, series, out: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from layoutkit.io.figures import save_figure

    # 1. residual vs speed, with / without motion, libsurvive, for devices that moved
    moving = [(r, dev) for r in results for dev, d in r.get("devices", {}).items()
              if d.get("speed", {}).get("p90") and d["speed"]["p90"] > 0.2 and (Path(r["file"]).name, dev) in series]
    if moving:
        n = len(moving)
        nc = min(3, n)
        nr = -(-n // nc)
        fig, axes = plt.subplots(nr, nc, figsize=(4.2 * nc, 3.4 * nr), squeeze=False)
        for ax in axes.ravel()[n:]:
            ax.set_visible(False)
        for ax, (r, dev) in zip(axes.ravel(), moving):
            s = series[(Path(r["file"]).name, dev)]
            sp = s["speed"]
            ax.loglog(np.clip(sp, 1e-3, None)[s["ok"]], s["res"][s["ok"]], ".", ms=1.5, alpha=0.35, label="static model")
            ax.loglog(np.clip(sp, 1e-3, None)[s["okm"]], s["resm"][s["okm"]], ".", ms=1.5, alpha=0.35, label="motion-compensated")
            if s["libsurvive"] is not None:
                ax.loglog(np.clip(sp, 1e-3, None), s["libsurvive"], ".", ms=1.5, alpha=0.35, label="libsurvive's poses")
            for key, fs in s.items():
                if key.startswith("imu calibrated") and fs is not None:
                    ax.loglog(np.clip(fs["speed"], 1e-3, None), fs["prior"], ".", ms=1.5, alpha=0.35,
                              label="IMU filter, before each sweep (calibrated stations)")
            ax.set_xlabel("body speed (m/s)")
            ax.set_ylabel("joint residual RMS (rad)")
            ax.set_title(f"{Path(r['file']).name.replace('.rec.gz', '')}\n{dev}", fontsize=8)
            ax.legend(fontsize=6, markerscale=5)
        fig.suptitle("Joint residual vs body speed (libsurvive recordings)", fontsize=9)
        fig.tight_layout()
        save_figure(fig, out / "residual_vs_speed.png",
                    caption="Per-window joint residual RMS against the body speed: our joint solve with the static "
                            "model, with motion compensation, libsurvive's own poses reprojected on the same angles, and "
                            "the IMU-aided filter's pose predicted before each sweep (per sweep).")
    # 2. joint residual per device: ours, libsurvive, calibrated
    rows = [(Path(r["file"]).name.replace(".rec.gz", ""), dev, d) for r in results
            for dev, d in r.get("devices", {}).items() if "joint" in d]
    if rows:
        fig, ax = plt.subplots(figsize=(max(6.0, 0.55 * len(rows)), 3.6))
        x = np.arange(len(rows))
        ours = [d["joint"]["residual"]["median"] or np.nan for _, _, d in rows]
        ls = [d.get("libsurvive", {}).get("reprojection", {}).get("median") or np.nan for _, _, d in rows]
        ax.bar(x - 0.2, ours, 0.4, label="ours (joint, factory stations)")
        ax.bar(x + 0.2, ls, 0.4, label="libsurvive's poses")
        ax.set_yscale("log")
        ax.set_xticks(x, [f"{a}\n{b}" for a, b, _ in rows], rotation=90, fontsize=6)
        ax.set_ylabel("median per-window residual RMS (rad)")
        ax.set_xlabel("recording / device")
        ax.set_title("Joint residual per device: ours vs libsurvive's poses", fontsize=9)
        ax.legend(fontsize=7)
        fig.tight_layout()
        save_figure(fig, out / "residual_per_device.png",
                    caption="Median per-window residual RMS of every device: our joint poses and libsurvive's own "
                            "poses on the same recorded angles and stations.")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", nargs="*", help="recordings whose name contains one of these")
    ap.add_argument("--part", default=None, help="K/N: every N-th recording from the K-th (split a run over processes)")
    ap.add_argument("--no-calibrate", action="store_true")
    ap.add_argument("--calibrate-only", nargs="*", default=None,
                    help="calibrate only the recordings whose name contains one of these (the others: --no-calibrate)")
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument("--markdown-only", action="store_true", help="rewrite results.md from OUT/results.json")
    ap.add_argument("--merge", nargs="+", default=None,
                    help="merge the results.json + series.npz of these --part runs into --out (tables, figures)")
    a = ap.parse_args()
    out = Path(a.out)
    if a.markdown_only:
        write_markdown(json.loads((out / "results.json").read_text())["recordings"], out / "results.md")
        return
    if a.merge:
        merge(a.merge, out)
        return
    out.mkdir(parents=True, exist_ok=True)
    results, series = [], {}
    with tempfile.TemporaryDirectory(prefix="libsurvive_study_") as tmp:
        recs = recordings(a.only)
        if a.part:
            k, n = (int(x) for x in a.part.split("/"))
            recs = recs[k::n]
        for p in recs:
            print(f"{p.name} ...", flush=True)
            try:
                cal = not a.no_calibrate and (a.calibrate_only is None or any(c in p.name for c in a.calibrate_only))
                r, s = study_recording(p, Path(tmp), cal)
            except Exception as exc:  # a study records what broke and goes on with the next recording
                import traceback

                r, s = {"file": str(p), "error": f"{type(exc).__name__}: {exc}",
                        "traceback": traceback.format_exc(limit=4)}, {}
            results.append(r)
            for dev, v in s.items():
                series[(p.name, dev)] = v
            print(f"  done in {r.get('seconds', 0):.0f} s", flush=True)
            from layoutkit.io.jsonfile import to_jsonable
            from layoutkit.io.atomic import atomic_write_text

            atomic_write_text(out / "results.json", json.dumps(to_jsonable({"recordings": results}), indent=1) + "\n")
            save_series(series, out / "series.npz")
    write_markdown(results, out / "results.md")
    figures(results, series, out)


def save_series(series, path: Path):
    """The per-window / per-sweep arrays the figures need (not part of results.json)."""
    flat = {}
    for (rec, dev), s in series.items():
        for k, v in s.items():
            if isinstance(v, dict):
                for kk, vv in v.items():
                    flat[f"{rec}|{dev}|{k}|{kk}"] = np.asarray(vv)
            elif v is not None:
                flat[f"{rec}|{dev}|{k}"] = np.asarray(v)
    np.savez_compressed(path, **flat)


def load_series(path: Path) -> dict:
    series: dict = {}
    with np.load(path) as z:
        for key in z.files:
            parts = key.split("|")
            s = series.setdefault((parts[0], parts[1]), {"libsurvive": None})
            if len(parts) == 3:
                s[parts[2]] = z[key]
            else:
                s.setdefault(parts[2], {})[parts[3]] = z[key]
    return series


def merge(dirs, out: Path):
    """One results.json / results.md / figures from several --part runs (recording order of each)."""
    from layoutkit.io.atomic import atomic_write_text
    from layoutkit.io.jsonfile import to_jsonable

    byname, series = {}, {}
    for d in dirs:                                  # a recording in a later dir replaces an earlier one
        d = Path(d)
        for r in json.loads((d / "results.json").read_text())["recordings"]:
            byname[Path(r["file"]).name] = r
        if (d / "series.npz").exists():
            series.update(load_series(d / "series.npz"))
    results = list(byname.values())
    names = [p.name for p in recordings()]
    results.sort(key=lambda r: names.index(Path(r["file"]).name) if Path(r["file"]).name in names else 99)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "results.json", json.dumps(to_jsonable({"recordings": results}), indent=1) + "\n")
    write_markdown(results, out / "results.md")
    figures(results, series, out)


if __name__ == "__main__":
    main()
