"""Issue 25 items 2, 3, 5 on the real Crazyflie logs (bitcraze/positioning_dataset, LH2 sets): the
live side's must-show figures, with the commands that produce them.

    python studies/bitcraze_live/run.py --data ~/.cache/layoutkit-realdata/bitcraze [--out studies/bitcraze_live]

The dataset has no licence: nothing of it is stored here, only these results. Metrics are the
dataset's own (jitter = RMS of consecutive position differences; error vs motion capture after its
temporal offset + rate and Arun rigid alignment, per method), computed by the study module
:mod:`layoutkit.studies.bitcraze_dataset` (``jitter``, ``coverage``, ``align_to_mocap``,
``firmware_series``). What this script adds: every replay is the CLI's workflow
(:func:`layoutkit.workflows.live.replay_capture`, the same as ``layoutkit replay``) with

1. the stations estimated once from the ten static LH2 captures of the set-up (they share one
   system config): ``layoutkit replay <static log> --system-config Y --solve joint --refine-stations
   --refine-from <the other nine> --report OUT/calibration`` -> ``OUT/calibration/stations_refined.json``
   (item 3; poses only);
2. ``--stations OUT/calibration/stations_refined.json --solve joint`` for the joint poses (item 2:
   only ``ok`` poses count) and ``--filter ekf`` for the filter (item 5; session defaults: the
   paper's sigma and rho, the adaptive bank), on every log.

Static logs: good poses / s, joint jitter vs the firmware's crossing beam on the same log (its
``lhCrossingBeam`` events; the Kalman logs have none, there the firmware's crossing-beam method on
the same decoded angles, :func:`layoutkit.live.joint_stream.crossing_beam_windows`), filter jitter
and its share of 100 ms intervals tracking. Moving and flight logs: RMS error vs motion capture of
the joint ok poses, the filter's ok poses, the firmware's crossing beam and EKF; coverage. The
filter's real-time factor (stream seconds per filter CPU second).

3. ``--filter ekf --imu`` (the IMU-aided filter on the log's own gyro and accelerometer events,
   :mod:`layoutkit.filter.imu_tracker`) beside ``--filter ekf --no-imu`` (the lighthouse-only
   filter) on every log: the ``imu_*`` columns and the table's "IMU-aided filter" section
   (``--no-imu`` skips these replays).

4. ``--filter ekf --imu --smooth`` (the offline fixed-lag smoother of the IMU-aided filter,
   :mod:`layoutkit.filter.smoother`) on the moving and flight logs: the ``smooth_*`` columns (the
   same figures as ``imu_*``, from the smoothed JSON lines: gap poses included) and the table's
   "Offline smoother" section, with both replays' wall time and filter CPU time of the same run
   (``--no-smooth`` skips these replays).

``--filter-set KEY=VALUE`` (repeatable) replays the filter with other EkfConfig keywords, e.g. the
measured alternative in ``adaptive_rho0/`` (``--filter-set adaptive_rho=0 --out OUT`` on the moving,
flight and three static logs; docs/live.md says why it is not the default).
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from layoutkit.studies.bitcraze_dataset import (DECK_LAYOUT, align_to_mocap, coverage, discover,  # noqa: E402
                                                 firmware_series, jitter)


class _Lines(io.TextIOBase):
    """``json_out`` sink: every solved pose of a replay's JSON lines, (t, x, y, z, status,
    stations used, predicted 1-sigma position m): joint lines carry ``stations_used`` and
    ``sigma_position_m`` (PDOP sigma_theta), the filter's ``cov_pos_m`` (per axis; its norm here)."""

    def __init__(self):
        self.buf, self.t, self.p, self.status, self.used, self.sigma, self.lines = "", [], [], [], [], [], 0
        self.station, self.angles = [], []  # the filter's lines: the sweep's station and its angles (used + rejected)

    def writable(self):
        return True

    def write(self, s):
        self.buf += s
        *lines, self.buf = self.buf.split("\n")
        for ln in lines:
            if ln.startswith("{"):
                d = json.loads(ln)
                self.lines += 1
                tr = d.get("translation")
                if tr is None or any(v is None for v in tr):
                    continue
                self.t.append(d["t"])
                self.p.append(tr)
                self.status.append(d.get("status"))
                self.used.append(int(d.get("stations_used") or 0))
                if d.get("cov_pos_m") is not None:
                    sig = float(np.linalg.norm(d["cov_pos_m"]))
                else:
                    sig = d.get("sigma_position_m")
                self.sigma.append(np.nan if sig is None else float(sig))
                st = d.get("station")
                self.station.append(st if isinstance(st, int) else -1)
                self.angles.append(int(d.get("used") or 0) + int(d.get("rejected") or 0))
        return len(s)

    def arrays(self):
        return {"t": np.asarray(self.t, float), "p": np.asarray(self.p, float).reshape(-1, 3),
                "status": np.asarray(self.status, str), "used": np.asarray(self.used, int),
                "sigma": np.asarray(self.sigma, float), "station": np.asarray(self.station, int),
                "angles": np.asarray(self.angles, int)}


def replay(log, yml, *, stations=None, filt=False, filter_settings=None, **kw):
    """``layoutkit replay LOG --system-config YML --solve joint [--stations S] [--filter ekf]``:
    (summary, the sink's arrays, wall seconds). filter_settings : EkfConfig keywords beside the
    session's sigma / rho (``--filter-set``; default none: the filter's defaults)."""
    from layoutkit.filter import EkfConfig
    from layoutkit.live.pipeline import LiveConfig
    from layoutkit.workflows.live import replay_capture

    cfg = LiveConfig()
    if filt:
        cfg = replace(cfg, filter=EkfConfig(sigma_theta=cfg.sigma_theta, rho=cfg.rho, **(filter_settings or {})))
    sink = _Lines()
    t0 = time.perf_counter()
    with contextlib.redirect_stderr(io.StringIO()):
        s = replay_capture(log, str(DECK_LAYOUT), system_config=yml, stations=stations, solve="joint", options=cfg,
                           json_out=sink, **kw)
    return s, sink.arrays(), time.perf_counter() - t0


def errors_by_alignment(al, mocap, on, off, t_ok, p_ok, t, p):
    """Errors (m) of the poses ``(t, p)`` vs motion capture under the alignment ``al`` found for the ok
    poses ``(t_ok, p_ok)`` (same time offsets, rate and Arun rigid fit: the other statuses are judged
    in the ok poses' frame, not given a fit of their own). NaN where the motion capture has no sample."""
    from layoutkit.studies.bitcraze_dataset import _arun, _mocap_at

    tm = (mocap[:, 0] - mocap[0, 0]) / 1000.0
    pm = mocap[:, 1:4]
    t0, t1 = on + al["start_ms"] / 1000.0, off + al["end_ms"] / 1000.0
    q = _mocap_at(tm, pm, (t_ok - t0) * al["rate"])
    use = np.all(np.isfinite(q), 1) & (t_ok >= t0) & (t_ok <= t1)
    R, tr = _arun(p_ok[use], q[use])
    q = _mocap_at(tm, pm, (t - t0) * al["rate"])
    e = np.linalg.norm(p @ R.T + tr - q, axis=1)
    e[~((t >= t0) & (t <= t1))] = np.nan
    return e


def firmware_crossing_beam(log, yml):
    """The firmware's crossing-beam method on our decode of the log (system-config stations)."""
    from layoutkit.io.systemconfig import read_system_config
    from layoutkit.layout import load_layout
    from layoutkit.live.joint_stream import JointWindower, crossing_beam_windows
    from layoutkit.live.pipeline import PosePipeline
    from layoutkit.live.session import RunSetup, calibrated_setup, make_decoder
    from layoutkit.workflows.importers import cfusdlog_replay_source

    cfg = read_system_config(yml)
    usd = cfusdlog_replay_source(log, stations=cfg.station_list(), system_config=cfg)
    lay = load_layout(DECK_LAYOUT)
    setup = RunSetup.from_sidecar(usd["sidecar"], lay, stations=cfg.station_list(), system_config=cfg)
    sts, opts, _ = calibrated_setup(setup)
    dec = make_decoder(setup.protocol, lay.n, sts, opts)
    pairer = PosePipeline(lay.positions, replace(setup.config, solve="joint"), sts).pairer
    win = JointWindower(len(sts), setup.config.window_s)
    ws = []
    for m in dec.feed(usd["bytes"]) + dec.flush():
        f = pairer.push(m)
        if f is not None:
            ws += win.push(f)
    ws += win.flush()
    return crossing_beam_windows(ws, sts, lay.n)


def _interval_stations(F, on: float, off: float, interval: float = 0.1):
    """Per line of the filter's JSON lines ``F`` its 100 ms interval of ``[on, off)`` (``k``, -1
    outside), and per interval the number of stations whose sweeps carried angles in it (a lost
    filter's lines count: it does not update)."""
    n = int(np.floor((off - on) / interval))
    k = np.floor((F["t"] - on) / interval).astype(np.int64)
    use = (k >= 0) & (k < n)
    seen = np.zeros((n, 2), bool)
    lit = use & ((F["angles"] > 0) | (F["status"] == "lost")) & (F["station"] >= 0) & (F["station"] < 2)
    seen[k[lit], F["station"][lit]] = True
    return np.where(use, k, -1), seen.sum(1)


def ok_errors_by_interval_stations(F, e_ok, on: float, off: float) -> dict:
    """The honesty check of the filter's ok outputs: their errors vs motion capture ``e_ok`` (m, one
    per ok line of ``F``, NaN where the motion capture has none), split by how many stations' sweeps
    the output's 100 ms interval had (1: the filter carries the other station's fix with its motion
    model; its ok status claims a position known better than one station gives). Per split: outputs,
    RMS and 95th percentile error (mm) and the RMS of error / predicted 1-sigma (root trace)."""
    k, ns = _interval_stations(F, on, off)
    okF = F["status"] == "ok"
    kk, sg = k[okF], F["sigma"][okF]
    out = {}
    for label, want in (("1_station", 1), ("2_stations", 2)):
        m = (kk >= 0) & np.isfinite(e_ok)
        m[m] = ns[kk[m]] == want
        if m.sum() < 3:
            out[label] = {"n": int(m.sum())}
            continue
        e = e_ok[m]
        q = np.isfinite(sg[m])
        out[label] = {"n": int(m.sum()), "rms_mm": mm(np.sqrt(np.mean(e ** 2))), "p95_mm": mm(np.percentile(e, 95)),
                      "err_over_sigma_rms": round(float(np.sqrt(np.mean((e[q] / sg[m][q]) ** 2))), 2) if q.any() else None}
    return out


def interval_causes(F, on: float, off: float, interval: float = 0.1) -> dict:
    """Why the filter's 100 ms intervals of a log are not ok, from its JSON lines ``F`` (one per
    sweep once started: station, status, angles the sweep carried): each interval of ``[on, off)``
    is ``ok`` (an ok output), else by the stations whose sweeps carried angles in it (``none`` /
    ``1 station`` / ``2 stations``; before the filter's first start and for sweeps it dropped as late:
    ``none`` as well, no line; a lost filter's lines count as sweeps, it does not update) and
    the filter's state (``lost``, else ``uncertain``). Counts, and the coverage over all intervals
    and over the intervals with sweeps."""
    n = int(np.floor((off - on) / interval))
    # a lost filter does not update (used = rejected = 0): its lines count as sweeps of their station
    k, ns = _interval_stations(F, on, off, interval)
    use = k >= 0
    ok = np.zeros(n, bool)
    ok[k[use & (F["status"] == "ok")]] = True
    lost = np.zeros(n, bool)
    lost[k[use & (F["status"] == "lost")]] = True
    out = {"intervals": n, "ok": int(ok.sum()), "with_sweeps_2_stations": int((ns == 2).sum()),
           "with_sweeps_1_station": int((ns == 1).sum()), "without_sweeps": int((ns == 0).sum())}
    for label, m in (("1 station", ns == 1), ("2 stations", ns == 2)):
        out[f"not_ok_{label.replace(' ', '_')}_lost"] = int((~ok & m & lost).sum())
        out[f"not_ok_{label.replace(' ', '_')}_uncertain"] = int((~ok & m & ~lost).sum())
    out["coverage_all"] = round(float(ok.mean()), 4) if n else None
    out["coverage_with_sweeps"] = round(float(ok.sum() / max((ns > 0).sum(), 1)), 4)
    return out


def imu_metrics(s, F, wall, it, fw, span, prefix: str = "imu_") -> dict:
    """The IMU-aided filter's figures of one log (``replay LOG ... --filter ekf --imu``: the summary ``s``,
    its JSON lines ``F``, wall seconds): the lighthouse-only filter's columns under ``imu_*`` — static
    jitter, error vs motion capture of the ok outputs (own alignment), 100 ms coverage, err/σ, the
    intervals' causes and the ok outputs' errors by the stations their interval had — and the
    filter's health (IMU samples, rate, gravity, mean NIS per dof, gate rejections, restarts, angle
    noise) and speed. ``prefix``: "smooth_" for the smoothed replay (``--smooth``; its ``smoother``
    summary as ``smooth_smoother``)."""
    if s is None:
        return {f"{prefix}error": wall}
    f = s.get("filter") or {}
    imu = f.get("imu") or {}
    h = imu.get("health") or {}
    okF = F["status"] == "ok"
    tf, pf = F["t"][okF], F["p"][okF]
    on, off = fw["markers"] if fw["markers"] else (tf[0] if len(tf) else 0.0, tf[-1] if len(tf) else 1.0)
    row = {f"{prefix}used": (s.get("imu") or {}).get("used"), f"{prefix}samples": imu.get("samples"),
           f"{prefix}rate_hz": round(imu["rate_hz"], 2) if imu.get("rate_hz") else None,
           f"{prefix}gravity": imu.get("gravity"), f"{prefix}health": h,
           f"{prefix}filter_ok_outputs": int(okF.sum()),
           f"{prefix}filter_by_status": {k: int((F["status"] == k).sum()) for k in np.unique(F["status"])},
           f"{prefix}filter_coverage_100ms": round(coverage(tf, on, off), 4),
           f"{prefix}filter_cpu_s": f.get("filter_cpu_seconds"), f"{prefix}replay_wall_s": round(wall, 1),
           f"{prefix}filter_real_time_x": round(span / f["filter_cpu_seconds"], 1) if f.get("filter_cpu_seconds") else None,
           f"{prefix}filter_angle_noise_rad": f.get("angle_noise_rad")}
    if f.get("smoother"):
        row[f"{prefix}smoother"] = f["smoother"]
    if it.scenario == "jitter":
        row[f"{prefix}filter_jitter_mm"] = mm(jitter(pf))
        return row
    if it.mocap is None or not fw["markers"]:
        return row
    row[f"{prefix}filter_interval_causes"] = interval_causes(F, on, off)
    if len(tf) < 10:
        return row
    mc = np.load(it.mocap)
    al = align_to_mocap(tf, pf, mc, on, off)
    if al.get("status") != "ok":
        row[f"{prefix}filter_alignment"] = al.get("message")
        return row
    row.update({f"{prefix}filter_rms_mm": mm(al["rms_m"]), f"{prefix}filter_median_mm": mm(al["median_m"]),
                f"{prefix}filter_max_mm": mm(al["max_m"]), f"{prefix}filter_samples": al["samples"]})
    e = errors_by_alignment(al, mc, on, off, tf, pf, tf, pf)
    sg = F["sigma"][okF]
    k = np.isfinite(e) & np.isfinite(sg)
    row[f"{prefix}filter_error_over_sigma_rms"] = round(float(np.sqrt(np.mean((e[k] / sg[k]) ** 2))), 2)
    row[f"{prefix}filter_ok_errors_by_interval_stations"] = ok_errors_by_interval_stations(F, e, on, off)
    return row


def mm(v):
    return None if v is None or not np.isfinite(v) else round(float(v) * 1e3, 3)


def _groups(a):
    """Masks of a joint replay's poses: ok, imprecise, high_residual, and by stations used."""
    return {"ok": a["status"] == "ok", "imprecise": a["status"] == "imprecise",
            "high_residual": a["status"] == "high_residual", "one_station": a["used"] == 1,
            "two_stations": a["used"] >= 2, "ok_one_station": (a["status"] == "ok") & (a["used"] == 1)}


def _err_stats(e, sig):
    k = np.isfinite(e)
    if k.sum() < 3:
        return None
    return {"n": int(k.sum()), "rms_mm": mm(np.sqrt(np.mean(e[k] ** 2))), "median_mm": mm(np.median(e[k])),
            "predicted_rms_sigma_mm": mm(np.sqrt(np.nanmean(sig[k] ** 2))) if np.isfinite(sig[k]).any() else None}


def _f(v, nd=1):
    return "–" if v is None else (f"{v:.{nd}f}" if isinstance(v, float) else str(v))


def _err_cell(r, k):
    """'RMS / median / max' mm of the ``k`` series' error vs motion capture, or a dash."""
    return ("–" if r.get(f"{k}_rms_mm") is None else
            f"{_f(r[f'{k}_rms_mm'])} / {_f(r[f'{k}_median_mm'])} / {_f(r[f'{k}_max_mm'], 0)}")


def _honest_cell(x):
    """'n, RMS / p95 mm, err/sigma' of a group of ok outputs (``ok_errors_by_interval_stations``), or a dash."""
    return "–" if not x or x.get("rms_mm") is None else (
        f"{x['n']}, {_f(x['rms_mm'])} / {_f(x['p95_mm'])}, {_f(x.get('err_over_sigma_rms'))}")


def _cause_table(logs: dict, k: str, what: str) -> list:
    """Markdown lines: why ``what`` 100 ms intervals are not ok (``{k}_interval_causes`` of each log)."""
    L = ["", f"### Why {what} 100 ms intervals are not ok", "",
         "| log | intervals | ok all / with sweeps | sweeps of 2 stations / 1 / none | not ok, 1 station: uncertain / "
         "lost | not ok, 2 stations: uncertain / lost |", "|---|---|---|---|---|---|"]
    for name, r in logs.items():
        c = r.get(f"{k}_interval_causes")
        if not c:
            continue
        L.append(f"| {name} | {c['intervals']} | {c['coverage_all']:.3f} / {c['coverage_with_sweeps']:.3f} | "
                 f"{c['with_sweeps_2_stations']} / {c['with_sweeps_1_station']} / {c['without_sweeps']} | "
                 f"{c['not_ok_1_station_uncertain']} / {c['not_ok_1_station_lost']} | "
                 f"{c['not_ok_2_stations_uncertain']} / {c['not_ok_2_stations_lost']} |")
    return L


def imu_tables(logs: dict) -> list:
    """The IMU-aided filter beside the lighthouse-only one (``replay ... --filter ekf --imu`` vs
    ``--no-imu``): markdown lines."""
    L = ["", "## IMU-aided filter (the log's gyro and accelerometer) beside the lighthouse-only filter", "",
         "`layoutkit replay LOG --layout DECK --system-config system-config.yaml --stations "
         "calibration/stations_refined.json --solve joint --filter ekf --imu` (the IMU-aided error-state filter, "
         "layoutkit/filter/imu_tracker.py, on the log's `fixedFrequency` gyro.x/y/z deg/s and acc.x/y/z g at ~100 Hz) "
         "vs `--no-imu` (the lighthouse-only filter of the tables above). Same ok rule for both (1-sigma within the "
         "filter's limits and within the best single station's PDOP sigma_theta; not just started; gates not "
         "starving).", "",
         "### Static logs (mm, ok outputs)", "",
         "| log | filter jitter: lighthouse / IMU | 100 ms coverage: lighthouse / IMU | IMU restarts | IMU mean NIS/dof |",
         "|---|---|---|---|---|"]
    for name, r in logs.items():
        if r["scenario"] != "jitter":
            continue
        h = r.get("imu_health") or {}
        L.append(f"| {name} | {_f(r.get('filter_jitter_mm'), 3)} / {_f(r.get('imu_filter_jitter_mm'), 3)} | "
                 f"{_f(r.get('filter_coverage_100ms'), 3)} / {_f(r.get('imu_filter_coverage_100ms'), 3)} | "
                 f"{h.get('restarts', '–')} | {_f(h.get('mean_nis_per_dof'), 2)} |")
    L += ["", "### Moving and flying logs: error vs motion capture (mm, RMS / median / max; ok outputs, each "
          "filter's own alignment) and 100 ms coverage", "",
          "| log | lighthouse filter | IMU filter | coverage: lighthouse / IMU | err/σ RMS: lighthouse / IMU | "
          "IMU ok outputs in 1-station intervals: n, RMS / p95 mm, err/σ | IMU restarts | IMU gate rejections, "
          "mean NIS/dof | gravity |", "|---|---|---|---|---|---|---|---|---|"]

    for name, r in logs.items():
        if r["scenario"] == "jitter":
            continue
        h = r.get("imu_health") or {}
        g = (r.get("imu_gravity") or {}).get("from", "–")
        one = (r.get("imu_filter_ok_errors_by_interval_stations") or {}).get("1_station")
        rej = h.get("share_rejected")
        L.append(f"| {name} | {_err_cell(r, 'filter')} | {_err_cell(r, 'imu_filter')} | {_f(r.get('filter_coverage_100ms'), 3)} / "
                 f"{_f(r.get('imu_filter_coverage_100ms'), 3)} | {_f(r.get('filter_error_over_sigma_rms'))} / "
                 f"{_f(r.get('imu_filter_error_over_sigma_rms'))} | {_honest_cell(one)} | {h.get('restarts', '–')} | "
                 f"{'–' if rej is None else f'{100 * rej:.1f} %'}, {_f(h.get('mean_nis_per_dof'), 2)} | {g} |")
    L += _cause_table(logs, "imu_filter", "the IMU filter's")
    L += ["", "### Speed (stream seconds per filter CPU second, this run's shared machine; the IMU filter includes "
          "the lighthouse-only tracker it runs until its first start and after a hard restart)", "", "| log | lighthouse filter × real time | IMU filter × real time | "
          "IMU replay wall s (end to end) |", "|---|---|---|---|"]
    for name, r in logs.items():
        L.append(f"| {name} | {_f(r.get('filter_real_time_x'))} | {_f(r.get('imu_filter_real_time_x'))} | "
                 f"{_f(r.get('imu_replay_wall_s'))} |")
    return L


def smooth_tables(logs: dict) -> list:
    """The offline smoother beside the causal IMU-aided filter (``replay ... --filter ekf --imu
    --smooth`` vs without ``--smooth``, same run): markdown lines."""
    lag = next((r["smooth_smoother"]["lag_s"] for r in logs.values() if r.get("smooth_smoother")), None)
    L = ["", "## Offline smoother (replay --smooth) beside the causal IMU-aided filter", "",
         "`layoutkit replay LOG --layout DECK --system-config system-config.yaml --stations "
         "calibration/stations_refined.json --solve joint --filter ekf --imu --smooth`: the fixed-lag "
         f"Rauch-Tung-Striebel smoother of the IMU-aided filter (layoutkit/filter/smoother.py; lag {lag} s, blocks "
         "of twice the lag; poses inside sweep gaps every 20 ms of IMU propagation). Same ok rule as the causal "
         "filter, on the smoothed covariance (1-sigma within the filter's limits and the position root trace within "
         "the best single station's PDOP sigma_theta at the smoothed pose; not just started; gates not starving). "
         "Errors vs motion capture in each series' own alignment (mm, RMS / median / max of the ok outputs).", "",
         "| log | 100 ms coverage: causal / smoothed | error: causal | error: smoothed | err/σ RMS: causal / smoothed "
         "| ok outputs in 1-station intervals, causal: n, RMS / p95 mm, err/σ | smoothed | gap poses: ok / all |",
         "|---|---|---|---|---|---|---|---|"]

    for name, r in logs.items():
        if "smooth_filter_coverage_100ms" not in r and "smooth_error" not in r:
            continue
        sm = r.get("smooth_smoother") or {}
        one_c = (r.get("imu_filter_ok_errors_by_interval_stations") or {}).get("1_station")
        one_s = (r.get("smooth_filter_ok_errors_by_interval_stations") or {}).get("1_station")
        L.append(f"| {name} | {_f(r.get('imu_filter_coverage_100ms'), 3)} / {_f(r.get('smooth_filter_coverage_100ms'), 3)} "
                 f"| {_err_cell(r, 'imu_filter')} | {_err_cell(r, 'smooth_filter')} | {_f(r.get('imu_filter_error_over_sigma_rms'))} / "
                 f"{_f(r.get('smooth_filter_error_over_sigma_rms'))} | {_honest_cell(one_c)} | {_honest_cell(one_s)} | "
                 f"{sm.get('gap_ok', '–')} / {sm.get('gap_poses', '–')} |")
    L += _cause_table(logs, "smooth_filter", "the smoothed")
    L += ["", "### Speed of the same run (stream seconds per filter CPU second; replay wall seconds end to end, "
          "decode and joint solve included; shared machine, load in results.json)", "",
          "| log | filter × real time: causal / smoothed | replay wall s: causal / smoothed | smoother: steps, blocks, "
          "max buffer (steps) |", "|---|---|---|---|"]
    for name, r in logs.items():
        if "smooth_filter_coverage_100ms" not in r:
            continue
        sm = r.get("smooth_smoother") or {}
        L.append(f"| {name} | {_f(r.get('imu_filter_real_time_x'))} / {_f(r.get('smooth_filter_real_time_x'))} | "
                 f"{_f(r.get('imu_replay_wall_s'))} / {_f(r.get('smooth_replay_wall_s'))} | {sm.get('steps', '–')}, "
                 f"{sm.get('blocks', '–')}, {sm.get('max_buffer', '–')} |")
    return L


def write_table(res: dict, out: Path) -> Path:
    """``OUT/table.md`` from the results: the must-show tables of issue 25 for the live side."""
    logs = res["logs"]
    L = ["# Issue 25 on the real Bitcraze LH2 logs: joint statuses, station refinement, tracking filter", "",
         "Generated by `python studies/bitcraze_live/run.py --data ~/.cache/layoutkit-realdata/bitcraze` (results.json "
         "beside it). Every number comes from `layoutkit replay LOG --layout models/crazyflie_lighthouse_deck.layout.json "
         "--system-config system-config.yaml --stations calibration/stations_refined.json --solve joint [--filter ekf]` "
         "(the workflow `replay_capture`), session defaults (sigma_theta, rho of the session; the filter's adaptive "
         "bank), **ok poses only**. Metrics are the dataset's (jitter = RMS of consecutive position differences; error "
         "vs motion capture after its temporal offset + rate and Arun rigid alignment, per method: "
         "`layoutkit.studies.bitcraze_dataset`).", ""]
    if res.get("note"):
        L += [f"Run note: {res['note']}", ""]
    if res.get("filter_settings"):
        L += ["Filter settings beyond the defaults (`--filter-set`): " +
              ", ".join(f"`{k}={json.dumps(v)}`" for k, v in res["filter_settings"].items()), ""]
    cal = (res.get("calibration") or {})
    ref = cal.get("refinement") or {}
    L += ["## Stations from the data (item 3)", "", f"`{cal.get('command', '')}`", ""]
    for st in ref.get("stations") or ():
        if st.get("held_as_given"):
            continue
        sd = st.get("sd_translation_m") or []
        L.append(f"- station {st['id']}: moved {1e3 * st['moved_norm_m']:.0f} mm, rotated {st['rotated_deg']:.2f} deg "
                 f"against the system config (1-sigma per coordinate "
                 f"{', '.join('–' if v is None else f'{1e3 * v:.0f}' for v in sd)} mm, incl. the deck layout's own "
                 "uncertainty)")
    if ref:
        L.append(f"- residual scale {ref.get('residual_scale_before', float('nan')):.2f} sigma with the system config, "
                 f"{ref.get('residual_scale_after', float('nan')):.2f} after; contradicted: {ref.get('contradicted')}; "
                 f"{ref.get('samples')} windows of the ten static logs")
    L += ["", "## Honest joint statuses (item 2)", "",
          "A window's pose is ok only when its predicted 1-sigma position (PDOP sigma_theta at the pose and lit sets) "
          "is below the per-pose default limit (geometric mean of the best single station's and all stations' "
          "prediction). Errors of every pose are measured in the ok poses' motion-capture alignment.", "",
          "| log | windows 1 station / 2 | ok with 1 station | ok: RMS err (pred. 1σ) mm | imprecise: RMS err (pred. 1σ) mm | "
          "high_residual: RMS err mm | static: ok / imprecise jitter mm |", "|---|---|---|---|---|---|---|"]
    for name, r in logs.items():
        w = r.get("joint_windows_by_stations_used") or {}
        g = r.get("joint_errors_by_group") or {}

        def ge(k):
            x = g.get(k)
            return "–" if not x else f"{_f(x['rms_mm'])} ({_f(x['predicted_rms_sigma_mm'], 2)})"
        stat = ("–" if r["scenario"] != "jitter" else
                f"{_f(r.get('joint_jitter_mm'), 3)} / {_f(r.get('joint_imprecise_jitter_mm'), 2)}")
        L.append(f"| {name} | {w.get('1', 0)} / {w.get('2', 0)} | {r.get('joint_ok_with_one_station')} | {ge('ok')} | "
                 f"{ge('imprecise')} | {_f((g.get('high_residual') or {}).get('rms_mm'))} | {stat} |")
    L += ["", "## Static jitter (mm, ok poses)", "",
          "| log | joint good/s | joint | filter | fw crossing beam | fw EKF | filter 100 ms coverage |",
          "|---|---|---|---|---|---|---|"]
    for name, r in logs.items():
        if r["scenario"] != "jitter":
            continue
        L.append(f"| {name} | {_f(r['joint_good_per_s'])} | {_f(r.get('joint_jitter_mm'), 3)} | "
                 f"{_f(r.get('filter_jitter_mm'), 3)} | {_f(r.get('fw_crossing_beam_jitter_mm'), 3)} | "
                 f"{_f(r.get('fw_ekf_jitter_mm'), 3)} | {_f(r.get('filter_coverage_100ms'), 3)} |")
    L += ["", "fw crossing beam on the kalman sets: the firmware's method on our decode (no lhCrossingBeam events).", "",
          "## Moving and flying: error vs motion capture (mm, RMS / median / max; ok poses)", "",
          "| log | joint | filter | fw crossing beam | fw EKF | coverage 100 ms joint / filter | filter inits | "
          "filter err/σ RMS |", "|---|---|---|---|---|---|---|---|"]
    for name, r in logs.items():
        if r["scenario"] == "jitter":
            continue

        def e(k):
            return ("–" if r.get(f"{k}_rms_mm") is None else
                    f"{_f(r[f'{k}_rms_mm'])} / {_f(r[f'{k}_median_mm'])} / {_f(r[f'{k}_max_mm'], 0)}")
        L.append(f"| {name} | {e('joint')} | {e('filter')} | {e('fw_crossing_beam')} | {e('fw_ekf')} | "
                 f"{_f(r.get('joint_coverage_100ms'), 2)} / {_f(r.get('filter_coverage_100ms'), 2)} | "
                 f"{r.get('filter_inits')} | {_f(r.get('filter_error_over_sigma_rms'), 1)} |")
    L += ["", "## Why the filter's 100 ms intervals are not ok (moving and flying logs)", "",
          "Per interval of the log (between its markers): ok (an ok filter output), else by the stations whose sweeps "
          "carried angles in it and whether the filter was lost there (`interval_causes`). *Uncertain* with 2 stations "
          "= the filter's position 1-sigma above what one station would give at the session's sigma/rho (all but 0-6 "
          "per log; its angle-noise scale, fitted to the innovations, sits near its cap in this fast motion: "
          "docs/live.md), or velocity not yet known after a start; with 1 station the range is not known to the ok "
          "limit. The last two columns check the ok outputs: their error vs motion capture by the stations their "
          "interval had (`ok_errors_by_interval_stations`; err/σ with the root-trace 1-sigma).", "",
          "| log | intervals | ok all / with sweeps | sweeps of 2 stations / 1 / none | not ok, 1 station: uncertain / lost "
          "| not ok, 2 stations: uncertain / lost | ok outputs in 1-station intervals: n, RMS / p95 err mm, err/σ | "
          "in 2-station intervals |", "|---|---|---|---|---|---|---|---|"]

    def hon(x):
        return "–" if not x or x.get("rms_mm") is None else (
            f"{x['n']}, {_f(x['rms_mm'])} / {_f(x['p95_mm'])}, {_f(x.get('err_over_sigma_rms'))}")
    for name, r in logs.items():
        c = r.get("filter_interval_causes")
        if not c:
            continue
        h = r.get("filter_ok_errors_by_interval_stations") or {}
        L.append(f"| {name} | {c['intervals']} | {c['coverage_all']:.3f} / {c['coverage_with_sweeps']:.3f} | "
                 f"{c['with_sweeps_2_stations']} / {c['with_sweeps_1_station']} / {c['without_sweeps']} | "
                 f"{c['not_ok_1_station_uncertain']} / {c['not_ok_1_station_lost']} | "
                 f"{c['not_ok_2_stations_uncertain']} / {c['not_ok_2_stations_lost']} | "
                 f"{hon(h.get('1_station'))} | {hon(h.get('2_stations'))} |")
    L += ["", "## Filter speed (stream seconds per filter CPU second, this run's machine load)", "",
          "| log | stream s | filter CPU s | × real time |", "|---|---|---|---|"]
    for name, r in logs.items():
        L.append(f"| {name} | {_f(r['stream_s'])} | {_f(r.get('filter_cpu_s'), 2)} | {_f(r.get('filter_real_time_x'))} |")
    if any("imu_filter_coverage_100ms" in r or "imu_error" in r for r in logs.values()):
        L += imu_tables(logs)
    if any("smooth_filter_coverage_100ms" in r or "smooth_error" in r for r in logs.values()):
        L += smooth_tables(logs)
    L += ["", "## Reading the tables", "",
          "- *ok* means precise, not accurate: the predicted 1-sigma of an ok joint pose (~0.25 mm) is the angle "
          "noise's share; the error against motion capture (6-17 mm) is dominated by what the noise model does not "
          "hold (station geometry and calibration after the refinement, the rigid and temporal alignment, the markers' "
          "own placement). The filter's covariance is likewise 4-11x below its error vs motion capture (err/σ).",
          "- *ok with 1 station* counts the joint poses called ok although one station only saw the deck: the honest "
          "status rule wants 0; their errors (the *imprecise* column) are 3-6x those of the ok poses.",
          "- Filter speed is stream seconds per CPU second of the filter alone, on the machine of this run (shared; "
          "see the load in results.json); `benchmarks/bench_replay_filter.py` measures replay end to end."]
    path = out / "table.md"
    path.write_text("\n".join(L) + "\n")
    return path


def main():
    from layoutkit.studies.bitcraze_dataset import _valid_ekf

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="the dataset's data folder (the sets)")
    ap.add_argument("--out", default=str(Path(__file__).parent))
    ap.add_argument("--logs", nargs="*", help="only these logs (SET/logNN); default every LH2 log")
    ap.add_argument("--reuse-calibration", action="store_true",
                    help="use OUT/calibration/stations_refined.json as it is (skip step 1)")
    ap.add_argument("--table-only", action="store_true", help="rewrite OUT/table.md from OUT/results.json")
    ap.add_argument("--no-imu", action="store_true", help="skip the IMU-aided filter's replays (replay --filter ekf --imu)")
    ap.add_argument("--no-smooth", action="store_true",
                    help="skip the smoother's replays (replay --filter ekf --imu --smooth)")
    ap.add_argument("--note", help="a line recorded in results.json and the table (e.g. which code ran)")
    ap.add_argument("--filter-set", action="append", default=[], metavar="KEY=VALUE",
                    help="an EkfConfig keyword for the filter's replays, VALUE as JSON (e.g. adaptive_rho=0, "
                         "hit_time_noise=false); repeatable; recorded in results.json")
    a = ap.parse_args()
    out = Path(a.out)
    settings = {}
    for kv in a.filter_set:
        key, sep, val = kv.partition("=")
        if not sep:
            ap.error(f"--filter-set {kv!r}: expected KEY=VALUE")
        try:
            settings[key] = json.loads(val)
        except json.JSONDecodeError:
            ap.error(f"--filter-set {kv!r}: VALUE is not JSON (numbers, true/false, null, [lists])")
    if a.table_only:
        res = json.loads((out / "results.json").read_text())
        if a.note:
            res["note"] = a.note
            (out / "results.json").write_text(json.dumps(res, indent=2) + "\n")
        print("wrote", write_table(res, out))
        return
    items, skipped = discover(a.data)
    lh2 = [it for it in items if it.kind == "lh2"]
    static = [it for it in lh2 if it.scenario == "jitter"]
    res = {"data": "bitcraze/positioning_dataset (not stored: no licence)", "logs": {}, "skipped": skipped,
           "note": a.note, "filter_settings": settings}
    try:
        import os

        res["load_average_1min_at_start"] = os.getloadavg()[0]
    except OSError:
        pass
    # 1. the stations from the static captures (item 3)
    t0 = time.perf_counter()
    prev = out / "results.json"
    if a.reuse_calibration and (out / "calibration" / "stations_refined.json").is_file():
        old = json.loads(prev.read_text()) if prev.is_file() else {}
        res["calibration"] = old.get("calibration") or {"refinement": {"status": "reused"}}
        res["logs"] = old.get("logs", {})
    else:
        s, *_ = replay(static[0].log, static[0].system_config, refine_stations=True,
                       refine_from=[it.log for it in static[1:]], report_dir=out / "calibration")
        res["calibration"] = {"command": "layoutkit replay " + static[0].name + " --layout DECK --system-config "
                          "system-config.yaml --solve joint --refine-stations " +
                          " ".join("--refine-from " + it.name for it in static[1:]) + " --report calibration",
                          "seconds": round(time.perf_counter() - t0, 1),
                          "refinement": {k: v for k, v in s["station_refinement"].items() if k != "file"}}
        ref = res["calibration"]["refinement"]  # the logs by set/name, not this machine's paths
        ref["refined_from"] = ["/".join(Path(x).parts[-2:]) for x in ref.get("refined_from") or ()]
    stations = str(out / "calibration" / "stations_refined.json")
    print("calibration", json.dumps(res["calibration"]["refinement"].get("status")), flush=True)
    for it in lh2:
        if a.logs and it.name not in a.logs:
            continue
        fw = firmware_series(it.log)
        row = {"set": it.set, "scenario": it.scenario}
        sj, J, wj = replay(it.log, it.system_config, stations=stations)
        sf, F, wf = replay(it.log, it.system_config, stations=stations, filt=True, filter_settings=settings, imu=False)
        if not a.no_imu:
            try:
                si, I, wi = replay(it.log, it.system_config, stations=stations, filt=True, filter_settings=settings,
                                   imu=True)
            except ValueError as exc:
                si, I, wi = None, None, str(exc)
        smooth = not a.no_imu and not a.no_smooth and it.scenario != "jitter"
        if smooth:
            try:
                ss, S, ws = replay(it.log, it.system_config, stations=stations, filt=True, filter_settings=settings,
                                   imu=True, smooth=True)
            except ValueError as exc:
                ss, S, ws = None, None, str(exc)
        g = _groups(J)
        okJ, okF = g["ok"], F["status"] == "ok"
        tj, pj, tf, pf = J["t"][okJ], J["p"][okJ], F["t"][okF], F["p"][okF]
        span = sj["stream_time_s"]
        on, off = fw["markers"] if fw["markers"] else (tj[0] if len(tj) else 0.0, tj[-1] if len(tj) else 1.0)
        f = sf.get("filter") or {}
        row.update(stream_s=round(span, 2), joint_good=sj["good"], joint_good_per_s=round(sj["good"] / span, 1),
                   joint_by_status=sj["by_status"], joint_max_sigma_position=sj.get("max_sigma_position_m"),
                   joint_windows_by_stations_used={str(k): int((J["used"] == k).sum()) for k in np.unique(J["used"])},
                   joint_ok_with_one_station=int(g["ok_one_station"].sum()),
                   filter_ok_outputs=len(tf), filter_by_status={k: int((F["status"] == k).sum())
                                                               for k in np.unique(F["status"])},
                   filter_inits=(f.get("counters") or {}).get("inits"),
                   filter_coverage_100ms=round(coverage(tf, on, off), 4),
                   joint_coverage_100ms=round(coverage(tj, on, off), 4),
                   filter_cpu_s=f.get("filter_cpu_seconds"), replay_wall_s=round(wf, 1),
                   filter_real_time_x=round(span / f["filter_cpu_seconds"], 1) if f.get("filter_cpu_seconds") else None,
                   filter_angle_noise_rad=f.get("angle_noise_rad"))
        cb = fw["crossing_beam"]
        if it.scenario == "jitter":
            row.update(joint_jitter_mm=mm(jitter(pj)), filter_jitter_mm=mm(jitter(pf)),
                       joint_imprecise_jitter_mm=mm(jitter(J["p"][g["imprecise"]])),
                       joint_ok_predicted_sigma_mm=mm(np.sqrt(np.nanmean(J["sigma"][okJ] ** 2))) if okJ.any() else None,
                       joint_imprecise_predicted_sigma_mm=mm(np.sqrt(np.nanmean(J["sigma"][g["imprecise"]] ** 2)))
                       if g["imprecise"].any() else None)
            if cb is not None:
                row["fw_crossing_beam_jitter_mm"] = mm(jitter(cb[1]))
                row["fw_crossing_beam_source"] = "lhCrossingBeam events"
            else:
                _, pcb = firmware_crossing_beam(it.log, it.system_config)
                row["fw_crossing_beam_jitter_mm"] = mm(jitter(pcb))
                row["fw_crossing_beam_source"] = "the firmware's method on our decode (no lhCrossingBeam events)"
            if fw["ekf"] is not None and it.mode == "kalman":
                row["fw_ekf_jitter_mm"] = mm(jitter(fw["ekf"][1]))
        elif it.mocap is not None and fw["markers"]:
            row["filter_interval_causes"] = interval_causes(F, on, off)
            mc = np.load(it.mocap)
            series = {"joint": (tj, pj, None), "filter": (tf, pf, None)}
            if cb is not None:
                series["fw_crossing_beam"] = (cb[0], cb[1], cb[2] < 0.1)
            if fw["ekf"] is not None and it.mode == "kalman":  # the crossing-beam sets do not fly on the EKF
                series["fw_ekf"] = (fw["ekf"][0], fw["ekf"][1], _valid_ekf(fw["ekf"][0], fw["angle_t"]))
            for name, (t, p, valid) in series.items():
                if len(t) < 10:
                    continue
                al = align_to_mocap(t, p, mc, on, off, valid=valid)
                if al.get("status") != "ok":
                    row[f"{name}_alignment"] = al.get("message")
                    continue
                row[f"{name}_rms_mm"] = mm(al["rms_m"])
                row[f"{name}_median_mm"] = mm(al["median_m"])
                row[f"{name}_max_mm"] = mm(al["max_m"])
                row[f"{name}_samples"] = al["samples"]
                if name == "joint":
                    # item 2: every joint pose judged in the ok poses' alignment, by status and stations used
                    e = errors_by_alignment(al, mc, on, off, tj, pj, J["t"], J["p"])
                    row["joint_errors_by_group"] = {k: _err_stats(e[m], J["sigma"][m]) for k, m in g.items()}
                if name == "filter":
                    e = errors_by_alignment(al, mc, on, off, tf, pf, tf, pf)
                    sg = F["sigma"][okF]
                    k = np.isfinite(e) & np.isfinite(sg)
                    # the filter's 1-sigma is per axis: |e|^2 / sum sigma_i^2 averages 1 when consistent
                    row["filter_error_over_sigma_rms"] = round(float(np.sqrt(np.mean((e[k] / sg[k]) ** 2))), 2)
                    row["filter_ok_errors_by_interval_stations"] = ok_errors_by_interval_stations(F, e, on, off)
        if not a.no_imu:
            row.update(imu_metrics(si, I, wi, it, fw, span))
        if smooth:
            row.update(imu_metrics(ss, S, ws, it, fw, span, prefix="smooth_"))
        res["logs"][it.name] = row
        print(it.name, json.dumps(row), flush=True)
        (out / "results.json").write_text(json.dumps(res, indent=2, default=float) + "\n")
    print("wrote", out / "results.json", write_table(res, out))


if __name__ == "__main__":
    main()
