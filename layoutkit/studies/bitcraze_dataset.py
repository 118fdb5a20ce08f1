"""The public Crazyflie Lighthouse dataset (bitcraze/positioning_dataset), with the dataset's own metrics,
for the firmware's estimates in the logs and for ours, side by side (issue 25 item 7).

``layoutkit study bitcraze-dataset --data DIR [--out OUT] [--json]``; DIR holds the dataset's
sets ``<lh1|lh2>_<crossingBeam|kalman>_<jitter|move|flight...>/`` with ``logNN`` (cfusdlog),
``mocapNN.npy`` (motion capture: ``t`` ms, ``x, y, z`` m, NaN rows while the markers are hidden) and
``system-config.yaml``. The dataset has no licence: nothing of it is copied; results only.

Methods, per log:

- ``fw_crossing_beam``: the firmware's crossing-beam positions (``lhCrossingBeam`` events, crossing-beam
  logs); ``fw_ekf``: the firmware's Kalman state estimate (``stateEstimate.x/y/z`` of
  ``fixedFrequency``, 100 Hz);
- ``ours_joint``, ``ours_per_station`` (one stream per station, in the world frame) and ``ours_filter``
  (``--filter ekf``): :func:`layoutkit.workflows.live.replay_capture` on the log itself (the same
  workflow as ``layoutkit replay LOG --system-config YAML --stations STATIONS``, so the replay's
  improvements show up here), "ok" poses only;
- station set-ups: the logs whose ``system-config.yaml`` is the same file (same kind, same bytes) are
  one set-up; its static (jitter) logs refine the stations once (``replay STATIC0 --refine-stations
  --refine-from STATIC1 ...``, :func:`refine_setup`: poses only, bundle-adjusted on the windows at
  rest) and, when the refinement is applied, every log of the set-up is replayed with those stations
  (the system config's calibration kept); ``ours_joint_config`` is the joint solve on the system
  config's own stations, for comparison. The moving logs are not used by the refinement: their error
  vs motion capture is a held-out check of it.

Metrics (the dataset's README and scripts ``compute_jitter.py``, ``temporal_alignment.py``,
``rigid_transform.py``, read to follow them):

- **jitter** = ``sqrt(mean |p_i - p_{i-1}|^2)`` over consecutive positions (static sets; also the
  motion capture's own, its floor);
- **error vs motion capture** after temporal and rigid alignment (moving sets): the log time of the
  markers switched on / off (``activeMarkerModeChanged`` mode 1 / 0) maps to the first / last motion
  capture sample (offset and rate: the log clock runs ~1.1 % slow); both ends are then moved by
  -100..+95 ms in 5 ms steps (the dataset's search) and refined by 1 ms around the best, keeping the
  pair with the least mean error after the rigid alignment: Arun's least squares (rotation by
  :meth:`scipy.spatial.transform.Rotation.align_vectors`, translation from the centroids) of the
  estimates onto the motion capture interpolated at their times (only between two samples < 20 ms
  apart). Reported: mean / RMS / max Euclidean error of the aligned positions (the alignment's own
  residuals), the offsets and rate found, the rigid transform's rotation angle, the samples used.
  As the dataset: crossing-beam positions with ``delta >= 0.1`` m (the two stations' rays far
  apart) are left out of the alignment; Kalman estimates are used only where the ``lhAngle`` events
  have no gap > 0.25 s (nor 1 s after one);
- **coverage** = the share of the log's 100 ms intervals (markers on → off) with an estimate, and
  estimates per second.

Length (~900 lines): one study — discovery, the set-ups' station refinement, the dataset's metrics and
alignment, the tasks and its table and figures — read together, as ``studies/chen2024.py``.

Logs run as tasks on the executor (:func:`layoutkit.parallel.open_executor`), one per log and
method; each task streams its replay's JSON lines and keeps only the ok positions. Figures: the
error over time and its CDF per method (moving sets), the positions' scatter (static sets).
"""
from __future__ import annotations

import io
import json
import re
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["METHODS", "LogItem", "discover", "usable_logs", "setups", "refine_setup", "read_mocap", "jitter", "coverage",
           "align_to_mocap", "firmware_series", "replay_positions", "evaluate_log", "run_study", "write_outputs",
           "DECK_LAYOUT"]

DECK_LAYOUT = Path(__file__).resolve().parents[2] / "models" / "crazyflie_lighthouse_deck.layout.json"
#: our methods (replays) and the firmware's
METHODS = ("fw_crossing_beam", "fw_ekf", "ours_per_station", "ours_joint", "ours_joint_config", "ours_filter")
#: the replay tasks of a log: "joint-config" (the system config's stations) runs only where a set-up's
#: refinement was applied (elsewhere it is "joint")
TASKS = ("decode", "per-station", "joint", "joint-config", "filter")
_SET = re.compile(r"^(lh1|lh2)_(crossingBeam|kalman)_(jitter|move|flight)\d*$")
_MOCAP_MAX_GAP_S = 0.02


@dataclass(frozen=True)
class LogItem:
    """One log of the dataset. set : folder name; kind : "lh1"/"lh2"; mode : "crossingBeam"/"kalman";
    scenario : "jitter"/"move"/"flight"; log, mocap (None: none), system_config : paths."""

    set: str
    kind: str
    mode: str
    scenario: str
    log: str
    mocap: str | None
    system_config: str

    @property
    def name(self) -> str:
        return f"{self.set}/{Path(self.log).name}"


def discover(data_dir) -> tuple[list, list]:
    """The usable logs under ``data_dir`` and what could not be used, with why: ``(items, skipped)``,
    skipped = list of ``{"file" (relative to data_dir), "reason"}`` (a set whose name is not a Lighthouse set, without a
    system config, a log without its motion capture file, a motion capture file without its log)."""
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise ValueError(f"{data_dir}: no such folder (--data: the dataset's data/ folder)")
    items, skipped = [], []
    for d in sorted(p for p in data_dir.iterdir() if p.is_dir()):
        m = _SET.match(d.name)
        logs = sorted(p for p in d.iterdir() if re.fullmatch(r"log\d+", p.name))
        mocaps = sorted(p for p in d.iterdir() if re.fullmatch(r"mocap\d+\.npy", p.name))
        if m is None:
            skipped.append({"file": d.name, "reason": "not a Lighthouse set (<lh1|lh2>_<crossingBeam|kalman>_"
                                                      "<jitter|move|flight>): e.g. the flow-deck sets"})
            continue
        yml = d / "system-config.yaml"
        if not yml.is_file():
            skipped.append({"file": d.name, "reason": "no system-config.yaml (station poses and calibration)"})
            continue
        if not logs:
            skipped.append({"file": d.name, "reason": "no logNN file"})
        for p in mocaps:
            if not (d / p.name.replace("mocap", "log").removesuffix(".npy")).is_file():
                skipped.append({"file": f"{d.name}/{p.name}", "reason": "no log with its number (the log was not published)"})
        for lg in logs:
            mc = d / (lg.name.replace("log", "mocap") + ".npy")
            if not mc.is_file():
                skipped.append({"file": f"{d.name}/{lg.name}", "reason": "no motion capture file with its number: firmware "
                                                          "and our jitter only"})
            items.append(LogItem(d.name, m.group(1), m.group(2), m.group(3), str(lg),
                                 str(mc) if mc.is_file() else None, str(yml)))
    return items, skipped


def usable_logs(data_dir) -> tuple[list, list]:
    """:func:`discover`, and ValueError naming the folder and what was skipped when no log is usable."""
    items, skipped = discover(data_dir)
    if not items:
        raise ValueError(f"{data_dir}: no usable Lighthouse log (skipped: "
                         f"{'; '.join(s['file'] + ': ' + s['reason'] for s in skipped) or 'nothing found'})")
    return items, skipped


def setups(items) -> dict:
    """The station set-ups of ``items``: logs of the same kind whose system config is the same file
    content. Returns ``{key: {"kind", "system_config" (the first set's path), "sets", "logs" (names),
    "static" (the static logs' paths, in order)}}``, key ``<kind>_<md5 of the YAML, 8 hex>``."""
    import hashlib

    out: dict = {}
    digests: dict = {}
    for it in items:
        if it.system_config not in digests:
            digests[it.system_config] = hashlib.md5(Path(it.system_config).read_bytes()).hexdigest()[:8]
        key = f"{it.kind}_{digests[it.system_config]}"
        g = out.setdefault(key, {"kind": it.kind, "system_config": it.system_config, "sets": [], "logs": [],
                                 "static": []})
        if it.set not in g["sets"]:
            g["sets"].append(it.set)
        g["logs"].append(it.name)
        if it.scenario == "jitter":
            g["static"].append(it.log)
    return out


def _setup_key(groups: dict, item: "LogItem") -> str:
    return next(k for k, g in groups.items() if item.name in g["logs"])


def _no_refinement(logs, why: str) -> dict:
    return {"status": "no_data", "applied": False, "stations_file": None, "logs": [str(x) for x in logs], "report": {},
            "seconds": 0.0, "message": f"{why}: the system config's stations are used"}


def refine_setup(static_logs, system_config, stations_out, layout=DECK_LAYOUT) -> dict:
    """The stations of one set-up refined once from its static logs: ``replay STATIC0 --system-config
    YAML --solve joint --refine-stations --refine-from STATIC1 ...`` (poses only,
    :func:`layoutkit.live.refine.refine_stations`). Writes ``stations_out`` (stations JSON) when the
    refinement is applied. Returns ``{"status", "applied", "stations_file" (or None), "logs" (the
    static logs used), "report" (the refinement's, without per-parameter detail), "seconds",
    "message"}``; a replay that fails is ``status "failed"`` with its message, never an exception."""
    import contextlib
    import tempfile

    from ..io.stations import read_stations, write_stations
    from ..live.pipeline import LiveConfig
    from ..workflows.live import replay_capture

    t0 = time.perf_counter()
    static_logs = [str(x) for x in static_logs]
    out = _no_refinement(static_logs, "no static log in this set-up")
    if not static_logs:
        return out
    with tempfile.TemporaryDirectory() as tmp, contextlib.redirect_stderr(io.StringIO()):
        try:
            summary = replay_capture(static_logs[0], str(layout), system_config=system_config, solve="joint",
                                     options=LiveConfig(), json_out=_PoseLines(), report_dir=tmp,
                                     refine_stations=True, refine_from=static_logs[1:])
        except ValueError as exc:
            return dict(out, status="failed", message=str(exc), seconds=time.perf_counter() - t0)
        rep = dict(summary.get("station_refinement") or {})
        f = rep.pop("file", None)
        if rep.get("applied") and f:
            write_stations(stations_out, read_stations(f))
            out["stations_file"] = str(stations_out)
    for st in rep.get("stations") or ():
        st.pop("calibration_fitted", None)
    out.update(status=rep.get("status") or "failed", applied=bool(rep.get("applied") and out["stations_file"]),
               report=rep, message=rep.get("message", ""), seconds=time.perf_counter() - t0)
    return out


# ----------------------------------------------------------------------------------- metrics
def jitter(p) -> float:
    """The dataset's jitter: ``sqrt(mean |p_i - p_{i-1}|^2)`` (m) over consecutive rows of ``p`` (N, 3);
    NaN rows are left out first (as its script does for the motion capture); NaN for < 2 rows."""
    p = np.asarray(p, float)
    p = p[np.all(np.isfinite(p), 1)]
    if len(p) < 2:
        return float("nan")
    return float(np.sqrt(np.mean(np.sum(np.diff(p, axis=0) ** 2, 1))))


def coverage(t, t_start: float, t_end: float, interval: float = 0.1) -> float:
    """Share of the intervals of ``interval`` s in ``[t_start, t_end)`` holding at least one of ``t``."""
    n = int(np.floor((t_end - t_start) / interval))
    if n <= 0:
        return float("nan")
    k = np.floor((np.asarray(t, float) - t_start) / interval).astype(np.int64)
    k = k[(k >= 0) & (k < n)]
    return float(np.unique(k).size / n)


def _mocap_at(tm, pm, t):
    """Motion capture positions (M, 3) interpolated at ``t`` (s, mocap clock); NaN unless two valid
    samples < 20 ms apart bracket the time."""
    ok = np.all(np.isfinite(pm), 1)
    tm, pm = tm[ok], pm[ok]
    out = np.full((len(t), 3), np.nan)
    if len(tm) < 2:
        return out
    j = np.searchsorted(tm, t)
    inside = (j > 0) & (j < len(tm))
    jj = np.clip(j, 1, len(tm) - 1)
    gap = tm[jj] - tm[jj - 1]
    use = inside & (gap <= _MOCAP_MAX_GAP_S)
    w = ((t - tm[jj - 1]) / np.where(gap > 0, gap, 1.0))[:, None]
    out[use] = (pm[jj - 1] + w * (pm[jj] - pm[jj - 1]))[use]
    return out


def _arun(a, b):
    """Rotation R and translation t minimising sum |R a_i + t - b_i|^2 (Arun et al. 1987)."""
    from scipy.spatial.transform import Rotation

    ca, cb = a.mean(0), b.mean(0)
    rot, _ = Rotation.align_vectors(b - cb, a - ca)
    R = rot.as_matrix()
    return R, cb - R @ ca


def align_to_mocap(t, p, mocap, marker_on: float, marker_off: float, valid=None) -> dict:
    """Temporal (offset + rate) and rigid alignment of estimates onto the motion capture (module
    docstring). t : (N,) s log clock; p : (N, 3) m; mocap : (M, 4) t ms, x, y, z m; marker_on / off :
    log times of the markers switched on / off; valid : (N,) bool used for the alignment (default
    all). Returns ``{"status", "message", "samples", "mean_m", "rms_m", "max_m", "start_ms",
    "end_ms", "rate", "rotation_deg", "translation_m", "t" (s since markers on, log clock), "error" (m)}``
    — the errors of the aligned estimates at every time the motion capture covers."""
    t = np.asarray(t, float)
    p = np.asarray(p, float)
    valid = np.ones(len(t), bool) if valid is None else np.asarray(valid, bool)
    mocap = np.asarray(mocap, float)
    tm = (mocap[:, 0] - mocap[0, 0]) / 1000.0
    pm = mocap[:, 1:4]
    dur_m = tm[-1]

    def fit(ds, de):
        t0, t1 = marker_on + ds / 1000.0, marker_off + de / 1000.0
        scale = dur_m / (t1 - t0)
        ts = (t - t0) * scale
        q = _mocap_at(tm, pm, ts)
        use = valid & np.all(np.isfinite(q), 1) & (t >= t0) & (t <= t1)
        if use.sum() < 4:
            return np.inf, None
        R, tr = _arun(p[use], q[use])
        e = np.linalg.norm(p[use] @ R.T + tr - q[use], axis=1)
        return float(e.mean()), (t0, t1, scale, R, tr, ts, q, use)

    # the dataset's 5 ms grid over -100..+95 ms at both ends, searched coarse to fine (20 ms grid, then
    # 5 ms around the best, then 1 ms) on at most 3000 evenly spread estimates; the final fit on all
    full = (t, p, valid)
    if len(t) > 3000:
        k = np.linspace(0, len(t) - 1, 3000).astype(int)
        t, p, valid = t[k], p[k], valid[k]
    best = (np.inf, 0.0, 0.0)
    for span, step in ((None, 20), (3, 5), (4, 1)):
        if span is None:
            cs = ce = np.arange(-100, 100, step)
        else:
            cs, ce = best[1] + step * np.arange(-span, span + 1), best[2] + step * np.arange(-span, span + 1)
        for ds in cs[(cs >= -100) & (cs <= 100)]:
            for de in ce[(ce >= -100) & (ce <= 100)]:
                m, _ = fit(ds, de)
                if m < best[0]:
                    best = (m, float(ds), float(de))
    if not np.isfinite(best[0]):
        return {"status": "no_data", "message": "fewer than 4 estimates overlap the motion capture", "samples": 0}
    t, p, valid = full
    best = (best[0], None, best[1], best[2])
    _, (t0, t1, scale, R, tr, ts, q, use) = fit(best[2], best[3])
    have = np.all(np.isfinite(q), 1) & (t >= t0) & (t <= t1)
    err = np.linalg.norm(p[have] @ R.T + tr - q[have], axis=1)
    e_used = np.linalg.norm(p[use] @ R.T + tr - q[use], axis=1)
    ang = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
    return {"status": "ok", "message": "", "samples": int(use.sum()), "mean_m": float(e_used.mean()),
            "rms_m": float(np.sqrt(np.mean(e_used ** 2))), "max_m": float(e_used.max()),
            "median_m": float(np.median(e_used)), "start_ms": float(best[2]), "end_ms": float(best[3]),
            "rate": float(scale), "rotation_deg": ang, "translation_m": [float(v) for v in tr],
            "t": (t[have] - t0).tolist(), "error": err.tolist(), "used": use[have].tolist()}


# ----------------------------------------------------------------------------------- sources
def firmware_series(log) -> dict:
    """The firmware's own estimates and the log's markers: ``{"crossing_beam": (t, p, delta) | None,
    "ekf": (t, p) | None, "markers": (on, off) | None, "angle_t": lhAngle times, "valid_ekf": (K,) bool
    (the dataset's rule: no lhAngle gap > 0.25 s, nor 1 s after one)}``."""
    from ..importers.cfusdlog import read_cfusdlog

    ul = read_cfusdlog(log)
    ev = ul.events
    out = {"crossing_beam": None, "ekf": None, "markers": None, "angle_t": None}
    cb = ev.get("lhCrossingBeam")
    if cb is not None and len(cb["t"]):
        out["crossing_beam"] = (cb["t"], np.column_stack([cb["x"], cb["y"], cb["z"]]).astype(float),
                                np.asarray(cb.get("delta", np.zeros(len(cb["t"]))), float))
    ff = ev.get("fixedFrequency")
    if ff is not None and len(ff["t"]) and "stateEstimate.x" in ff:
        out["ekf"] = (ff["t"], np.column_stack([ff["stateEstimate.x"], ff["stateEstimate.y"],
                                                ff["stateEstimate.z"]]).astype(float))
    mk = ev.get("activeMarkerModeChanged")
    if mk is not None and len(mk["t"]) >= 2:
        on = mk["t"][np.asarray(mk["mode"]) == 1]
        off = mk["t"][np.asarray(mk["mode"]) == 0]
        if len(on) and len(off) and off[-1] > on[0]:
            out["markers"] = (float(on[0]), float(off[-1]))
    la = ev.get("lhAngle")
    if la is not None and len(la["t"]):
        out["angle_t"] = np.asarray(la["t"], float)
    return out


def _valid_ekf(t, angle_t) -> np.ndarray:
    """The dataset's rule for Kalman estimates: not within a gap of the lhAngle events > 0.25 s nor
    in the 1 s after it."""
    ok = np.ones(len(t), bool)
    if angle_t is None or len(angle_t) < 2:
        return ok
    k = np.flatnonzero(np.diff(angle_t) > 0.25)
    for i in k:
        ok &= ~((t >= angle_t[i]) & (t <= angle_t[i + 1] + 1.0))
    return ok


#: statuses whose poses a replay task keeps: ok, and high_residual (a solved pose whose residual says the
#: station geometry disagrees; the diagnostic row only)
_KEEP = ("ok", "high_residual")


class _PoseLines(io.TextIOBase):
    """A text sink for ``replay_capture(json_out=...)``: parses every JSON line as it comes and keeps
    the time, position, station, station count and ok flag of the poses whose status is in
    :data:`_KEEP` (memory: 7 numbers per pose)."""

    def __init__(self):
        self._buf = ""
        self.t, self.p, self.station, self.n_stations, self.ok = [], [], [], [], []
        self.lines = 0
        self.statuses: dict = {}

    def writable(self) -> bool:
        return True

    def write(self, s: str) -> int:
        self._buf += s
        *lines, self._buf = self._buf.split("\n")
        for ln in lines:
            if not ln.startswith("{"):
                continue
            d = json.loads(ln)
            self.lines += 1
            st = d.get("status")
            self.statuses[st] = self.statuses.get(st, 0) + 1
            tr = d.get("translation")
            if st in _KEEP and tr is not None and all(v is not None for v in tr):
                self.ok.append(st == "ok")
                self.t.append(float(d["t"]))
                self.p.append([float(v) for v in tr])
                self.station.append(str(d.get("station")))
                self.n_stations.append(int(d.get("n_stations") or 1))
        return len(s)


def replay_positions(log, system_config, method: str, layout=DECK_LAYOUT, stations=None) -> dict:
    """Our ok positions of one log by ``method`` ("per-station", "joint", "filter"): the replay
    workflow on the log itself (:func:`layoutkit.workflows.live.replay_capture`, streamed);
    stations : a stations JSON used instead of the system config's poses (its calibration kept).
    Returns ``{"t" (N,), "p" (N, 3), "station" (N,) str, "lines", "statuses", "seconds" (wall),
    "decoder" (the summary's decode counts), "message"}``."""
    import contextlib

    from ..filter import EkfConfig
    from ..live.pipeline import LiveConfig
    from ..workflows.live import replay_capture

    cfg = LiveConfig()
    solve = "joint" if method in ("joint", "filter") else "per-station"
    if method == "filter":
        from dataclasses import replace

        cfg = replace(cfg, filter=EkfConfig(sigma_theta=cfg.sigma_theta, rho=cfg.rho))
    sink = _PoseLines()
    t0 = time.perf_counter()
    msg = ""
    summary = {}
    with contextlib.redirect_stderr(io.StringIO()):
        try:
            summary = replay_capture(log, str(layout), system_config=system_config, solve=solve, options=cfg,
                                     json_out=sink, stations=stations)
        except ValueError as exc:
            msg = str(exc)
    dec = (summary or {}).get("decoder") or (summary or {}).get("decode") or {}
    return {"t": np.asarray(sink.t, float), "p": np.asarray(sink.p, float).reshape(-1, 3),
            "station": np.asarray(sink.station, str), "n_stations": np.asarray(sink.n_stations, int),
            "ok": np.asarray(sink.ok, bool),
            "lines": sink.lines, "statuses": sink.statuses,
            "seconds": time.perf_counter() - t0, "message": msg,
            "decoder": {k: dec.get(k) for k in ("good", "dropped", "reasons") if k in dec}}


def decode_check(log) -> dict:
    """Our LH2 angles vs the firmware's ``lhAngle`` in the log, for both pulse processors
    (:func:`layoutkit.live.cf_events.firmware_angle_check`): frames reproduced, max difference,
    rotations/s, the deck clock fit. ``{"status": "no_data", ...}`` for a log without both event types."""
    from ..live.cf_events import firmware_angle_check

    out = {}
    for proc in ("firmware", "phase"):
        try:
            r = firmware_angle_check(log, pulse_processor=proc)
        except ValueError as exc:
            return {"status": "no_data", "message": str(exc)}
        if r["status"] != "ok":
            return r
        out[proc] = {k: r[k] for k in ("firmware_frames", "matched", "matched_share", "max_abs_diff_rad", "rotations",
                                       "rotations_per_s", "repeats_dropped")}
        out["clock"] = r["clock"]
    return {"status": "ok", **out}


def evaluate_log(item: LogItem, method: str, stations=None) -> dict:
    """One task: our replay of ``item`` by ``method`` (see :func:`replay_positions`; "joint-config":
    the joint solve on the system config's stations, ``stations`` ignored), as plain arrays; method
    "decode": :func:`decode_check` instead."""
    t0 = time.perf_counter()
    if method == "decode":
        check = decode_check(item.log) if item.kind == "lh2" else {"status": "no_data", "message": "an LH1 log"}
        return {"log": item.name, "method": method, "check": check, "t": np.zeros(0),
                "seconds": time.perf_counter() - t0}
    if method == "joint-config":
        r = replay_positions(item.log, item.system_config, "joint")
    else:
        r = replay_positions(item.log, item.system_config, method, stations=stations)
    r["log"] = item.name
    r["method"] = method
    return r


# ----------------------------------------------------------------------------------- the study
def _streams(item: LogItem, fw: dict, ours: dict) -> dict:
    """Method → list of (label, t, p, valid) streams of one log."""
    out = {}
    if fw["crossing_beam"] is not None and item.mode == "crossingBeam":
        t, p, delta = fw["crossing_beam"]
        out["fw_crossing_beam"] = [("fw_crossing_beam", np.asarray(t, float), p, delta < 0.1)]
    if fw["ekf"] is not None and item.mode == "kalman":     # as the dataset: the EKF of the Kalman logs
        t, p = fw["ekf"]
        keep = np.any(p != 0, 1)      # the estimate is 0 until the estimator runs
        t, p = np.asarray(t, float)[keep], p[keep]
        out["fw_ekf"] = [("fw_ekf", t, p, _valid_ekf(t, fw["angle_t"]))]
    for method, r in ours.items():
        if method == "decode":
            continue
        key = f"ours_{method.replace('-', '_')}"
        ok = r["ok"]
        if method == "per-station":
            out[key] = [(f"{key}_{s}", r["t"][ok & (r["station"] == s)], r["p"][ok & (r["station"] == s)],
                         np.ones(int((ok & (r["station"] == s)).sum()), bool))
                        for s in sorted(set(r["station"][ok].tolist()))]
        else:
            out[key] = [(key, r["t"][ok], r["p"][ok], np.ones(int(ok.sum()), bool))]
        if method == "joint":
            # diagnostic: every window both stations saw, ok or high_residual (the solve's residual says
            # the system config's two station poses disagree at the deck; the firmware's crossing beam
            # reports the same as its delta): what decoding + joint solving give before the statuses
            # and the station geometry are settled (issue 25 items 2, 3)
            two = r["n_stations"] >= 2
            out["ours_joint_two_stations"] = [("ours_joint_two_stations", r["t"][two], r["p"][two],
                                               np.ones(int(two.sum()), bool))]
    return out


def _log_metrics(item: LogItem, fw: dict, ours: dict, mocap) -> dict:
    res = {"log": item.name, "set": item.set, "scenario": item.scenario, "methods": {}}
    if "decode" in ours:
        res["decode"] = ours["decode"].get("check") or {"status": "failed", "message": ours["decode"].get("message")}
    mk = fw["markers"]
    if mk is None:
        res["note"] = "no activeMarkerModeChanged on/off events: no temporal alignment, no coverage"
    if mocap is not None:
        res["mocap_jitter_m"] = jitter(mocap[:, 1:4])
        res["mocap_nan_share"] = float(np.mean(~np.all(np.isfinite(mocap[:, 1:4]), 1)))
    for method, streams in _streams(item, fw, ours).items():
        for label, t, p, valid in streams:
            span = (mk[0], mk[1]) if mk is not None else ((t.min(), t.max()) if len(t) else (0.0, 0.0))
            inside = (t >= span[0]) & (t <= span[1])
            m = {"method": method, "estimates": int(inside.sum()),
                 "per_s": float(inside.sum() / (span[1] - span[0])) if span[1] > span[0] else float("nan"),
                 "coverage_100ms": coverage(t, span[0], span[1]) if mk is not None else None,
                 "jitter_m": jitter(p[inside])}
            if method.startswith("ours"):
                r = ours["joint" if method == "ours_joint_two_stations" else method[5:].replace("_", "-")]
                m.update(replay_seconds=r["seconds"], statuses=r["statuses"], message=r["message"] or None)
            if item.scenario != "jitter" and mocap is not None and mk is not None and inside.sum() >= 4:
                a = align_to_mocap(t, p, mocap, mk[0], mk[1], valid)
                m["alignment"] = a
            res["methods"][label] = m
    return res


def run_study(data_dir, *, executor=None, progress=None, methods=TASKS, refine: bool = True, work_dir=None) -> dict:
    """Every usable log of ``data_dir``: the stations refined once per set-up from its static logs
    (:func:`refine_setup`, when ``refine``), then our replays as executor tasks (with the refined
    stations where applied), the firmware's estimates and the metrics here. work_dir : where the
    refined stations files go (``stations/<set-up>.json``; default a temporary folder). Returns
    ``{"logs": [per-log metrics], "skipped": [...], "sets": {set: summary}, "setups": {key: set-up and its
    refinement}}``."""
    import contextlib
    import tempfile

    from ..parallel import SYNCHRONOUS, open_executor

    items, skipped = usable_logs(data_dir)
    groups = setups(items)
    with contextlib.ExitStack() as stack:
        ex = executor if executor is not None else stack.enter_context(open_executor(SYNCHRONOUS))
        work = Path(work_dir) if work_dir is not None else Path(stack.enter_context(tempfile.TemporaryDirectory()))
        (work / "stations").mkdir(parents=True, exist_ok=True)
        # 1. one refinement per set-up (its static logs), beside the decoding checks
        first = {ex.submit(refine_setup, g["static"], g["system_config"], work / "stations" / f"{key}.json",
                           key=f"refine:{key}"): ("refine", key)
                 for key, g in groups.items() if refine and g["static"]}
        if "decode" in methods:
            first.update({ex.submit(evaluate_log, it, "decode", key=f"{it.name}:decode"): ("decode", k)
                          for k, it in enumerate(items)})
        ours: dict = {k: {} for k in range(len(items))}
        for g in groups.values():
            g["refinement"] = _no_refinement(g["static"], "no static log in this set-up" if refine else "not asked")
        for h, ok, value in ex.completed(list(first)):
            what, k = first[h]
            if what == "refine":
                groups[k]["refinement"] = value if ok else dict(
                    _no_refinement(groups[k]["static"], f"task failed: {value!r}"), status="failed")
                if progress is not None:
                    r = groups[k]["refinement"]
                    progress(f"set-up {k}: stations refinement {r['status']}"
                             f"{' (applied)' if r['applied'] else ''} in {r['seconds']:.1f} s")
                continue
            if not ok:
                value = {"check": {"status": "failed", "message": f"task failed: {value!r}"}, "t": np.zeros(0),
                         "seconds": float("nan")}
            ours[k]["decode"] = value
            if progress is not None:
                progress(f"{items[k].name} decode: {value.get('check', {}).get('status', 'failed')} "
                         f"in {value['seconds']:.1f} s")
        # 2. the replays, with the set-up's stations
        handles = {}
        for k, it in enumerate(items):
            ref = groups[_setup_key(groups, it)]["refinement"]
            st = ref["stations_file"] if ref.get("applied") else None
            for m in methods:
                if m == "decode" or (m == "joint-config" and st is None):
                    continue
                handles[ex.submit(evaluate_log, it, m, st, key=f"{it.name}:{m}")] = (k, m)
        for h, ok, value in ex.completed(list(handles)):
            k, m = handles[h]
            if not ok:
                value = {"t": np.zeros(0), "p": np.zeros((0, 3)), "station": np.zeros(0, str),
                         "n_stations": np.zeros(0, int), "ok": np.zeros(0, bool), "lines": 0,
                         "statuses": {}, "seconds": float("nan"), "message": f"task failed: {value!r}"}
            ours[k][m] = value
            if progress is not None:
                progress(f"{items[k].name} {m}: {len(value['t'])} poses in {value['seconds']:.1f} s")
    logs = []
    for k, it in enumerate(items):
        try:
            fw = firmware_series(it.log)
        except ValueError as exc:          # not a log, damaged header: named, the study goes on
            skipped.append({"file": it.name, "reason": str(exc)})
            continue
        mocap = None
        if it.mocap:
            try:
                mocap = read_mocap(it.mocap)
            except ValueError as exc:
                skipped.append({"file": f"{it.set}/{Path(it.mocap).name}", "reason": f"{exc}: firmware and our jitter only"})
        logs.append(_log_metrics(it, fw, ours[k], mocap))
    if not logs:
        raise ValueError(f"{data_dir}: no log could be read ({'; '.join(s['file'] + ': ' + s['reason'] for s in skipped)})")
    names = {it.log: it.name for it in items}
    for g in groups.values():
        g["logs_used"] = [lg["log"] for lg in logs if lg["log"] in g["logs"]]
        g["static"] = [names.get(x, x) for x in g["static"]]
        g["system_config"] = str(Path(g["system_config"]).relative_to(Path(data_dir))) if Path(
            g["system_config"]).is_relative_to(Path(data_dir)) else g["system_config"]
        g["refinement"]["logs"] = [names.get(x, x) for x in g["refinement"].get("logs") or ()]
        rep = g["refinement"].get("report") or {}
        if "refined_from" in rep:
            rep["refined_from"] = [names.get(x, x) for x in rep["refined_from"]]
    return {"logs": logs, "skipped": skipped, "sets": _set_summaries(logs), "setups": groups}


def read_mocap(path) -> np.ndarray:
    """A dataset motion capture file: ``.npy`` (M, 4) ``t`` ms, ``x, y, z`` m (NaN rows allowed);
    ValueError naming the file for anything else."""
    try:
        a = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise ValueError(f"{path}: not a NumPy .npy array ({type(exc).__name__}: {exc})") from None
    if a.ndim != 2 or a.shape[1] < 4 or a.shape[0] < 2 or not np.issubdtype(a.dtype, np.number):
        raise ValueError(f"{path}: expected an (M, 4) array of t ms, x, y, z, got shape {a.shape} {a.dtype}")
    a = np.asarray(a[:, :4], float)
    if not np.all(np.isfinite(a[:, 0])) or np.any(np.diff(a[:, 0]) <= 0):
        raise ValueError(f"{path}: the time column (ms) is not finite and increasing")
    return a


def _set_summaries(logs) -> dict:
    """Per set and method: logs, estimates/s, coverage, jitter (median over logs) or error vs motion
    capture (RMS over every aligned sample of the set's logs, and the median of the per-log RMS)."""
    out: dict = {}
    for lg in logs:
        s = out.setdefault(lg["set"], {"scenario": lg["scenario"], "logs": 0, "methods": {},
                                        "mocap_jitter_m": []})
        s["logs"] += 1
        if "mocap_jitter_m" in lg:
            s["mocap_jitter_m"].append(lg["mocap_jitter_m"])
        for label, m in lg["methods"].items():
            d = s["methods"].setdefault(label, {"logs": 0, "per_s": [], "coverage": [], "jitter": [], "rms": [],
                                                "errors": [], "per_log": {}})
            d["logs"] += 1
            a = m.get("alignment") or {}
            d["per_log"][lg["log"]] = {"per_s": m["per_s"], "jitter_m": m["jitter_m"],
                                       "rms_m": a.get("rms_m") if a.get("status") == "ok" else None}
            d["per_s"].append(m["per_s"])
            if m["coverage_100ms"] is not None:
                d["coverage"].append(m["coverage_100ms"])
            d["jitter"].append(m["jitter_m"])
            a = m.get("alignment")
            if a and a.get("status") == "ok":
                d["rms"].append(a["rms_m"])
                d["errors"] += [e for e, u in zip(a["error"], a["used"]) if u]
    for s in out.values():
        s["mocap_jitter_m"] = float(np.median(s["mocap_jitter_m"])) if s["mocap_jitter_m"] else None
        for label, d in s["methods"].items():
            e = np.asarray(d.pop("errors"), float)

            def med(v):
                v = np.asarray(v, float)
                v = v[np.isfinite(v)]
                return float(np.median(v)) if v.size else None
            s["methods"][label] = {
                "logs": d["logs"], "per_s_median": med(d["per_s"]), "coverage_median": med(d["coverage"]),
                "coverage_min": float(np.nanmin(d["coverage"])) if d["coverage"] else None,
                "jitter_median_m": med(d["jitter"]), "jitter_per_log_m": [float(v) for v in d["jitter"]],
                "error_rms_m": float(np.sqrt(np.mean(e ** 2))) if e.size else None,
                "error_mean_m": float(e.mean()) if e.size else None,
                "error_rms_per_log_median_m": med(d["rms"]), "error_rms_per_log_m": [float(v) for v in d["rms"]],
                "aligned_samples": int(e.size), "per_log": d["per_log"]}
    return out


# ----------------------------------------------------------------------------------- outputs
_LABELS = {"fw_crossing_beam": "firmware crossing beam", "fw_ekf": "firmware EKF", "ours_joint": "ours joint",
           "ours_joint_two_stations": "ours joint, every two-station window incl. high_residual (diagnostic, not ok)",
           "ours_filter": "ours filter (EKF)", "ours_joint_config": "ours joint, system config stations (not refined)"}


def _label(k: str) -> str:
    if k.startswith("ours_per_station_"):
        return f"ours per-station (station {k.rsplit('_', 1)[1]})"
    return _LABELS.get(k, k)


def _mm(v) -> str:
    return "–" if v is None or not np.isfinite(v) else f"{1e3 * v:.2f}"


def _table(res) -> str:
    lines = ["# Crazyflie Lighthouse dataset: firmware vs layoutkit", "",
             "Generated by `layoutkit study bitcraze-dataset --data DIR` (layoutkit/studies/bitcraze_dataset.py). "
             "Jitter = RMS of consecutive position differences (static sets); error = Euclidean error vs motion "
             "capture after temporal (offset + rate) and rigid (Arun) alignment, RMS over every aligned sample "
             "of the set (moving sets; per-log RMS median in brackets). Coverage = share of the 100 ms "
             "intervals between markers on and off with an ok estimate (median over the logs, minimum). "
             "Ours: \"ok\" poses of `layoutkit replay LOG --system-config YAML --stations STATIONS` as of this run, "
             "STATIONS = the set-up's stations refined once from its static logs (section \"Station set-ups\"; "
             "the system config's calibration kept) wherever that refinement was applied, for every log of the "
             "set-up; \"ours joint, system config stations\" = the same joint solve on the system config's own "
             "station poses. The moving logs take no part in the refinement.", ""]
    for name, s in sorted(res["sets"].items()):
        static = s["scenario"] == "jitter"
        floor = f"; the motion capture's own jitter {_mm(s['mocap_jitter_m'])} mm" if static and s["mocap_jitter_m"] else ""
        lines += [f"## {name} ({s['logs']} log(s){floor})", ""]
        names = sorted({lg for m in s["methods"].values() for lg in m["per_log"]})
        if static:
            lines += ["| method | logs | estimates/s | coverage (min) | jitter median mm | jitter mm (estimates/s) per log: "
                      + ", ".join(n.rsplit("/", 1)[-1] for n in names) + " |", "|---|---|---|---|---|---|"]
        else:
            lines += ["| method | logs | estimates/s | coverage (min) | error RMS mm (per-log median) | error mean mm "
                      "| aligned samples |", "|---|---|---|---|---|---|---|"]
        for label, m in sorted(s["methods"].items(), key=lambda kv: (not kv[0].startswith("fw"), kv[0])):
            cov = ("–" if m["coverage_median"] is None else
                   f"{100 * m['coverage_median']:.0f} % ({100 * m['coverage_min']:.0f} %)")
            per = "–" if m["per_s_median"] is None else f"{m['per_s_median']:.1f}"
            if static:
                pl = ", ".join("–" if n not in m["per_log"] else
                               f"{_mm(m['per_log'][n]['jitter_m'])} ({m['per_log'][n]['per_s']:.1f})" for n in names)
                lines.append(f"| {_label(label)} | {m['logs']} | {per} | {cov} | {_mm(m['jitter_median_m'])} | {pl} |")
            else:
                lines.append(f"| {_label(label)} | {m['logs']} | {per} | {cov} | {_mm(m['error_rms_m'])} "
                             f"({_mm(m['error_rms_per_log_median_m'])}) | {_mm(m['error_mean_m'])} | "
                             f"{m['aligned_samples']} |")
        lines.append("")
        for label, m in sorted(s["methods"].items()):
            if not m["per_s_median"]:
                why = (" (the filter takes the deck's sweeps; an LH1 log gives frames of the firmware's angles, "
                       "which it does not take)" if label == "ours_filter" and name.startswith("lh1") else "")
                lines.append(f"- {_label(label)}: no estimate in most logs of this set{why}.")
        if any(not m["per_s_median"] for m in s["methods"].values()):
            lines.append("")
    lines += _alignment_table(res)
    lines += _setups_table(res)
    dec = [(lg["log"], lg["decode"]) for lg in res["logs"] if (lg.get("decode") or {}).get("status") == "ok"]
    if dec:
        lines += ["## Decoding check: our angles vs the firmware's lhAngle in the same log", "",
                  "The deck pulses (`lhUartFrame`) decoded by the firmware's pulse processor (crazyflie-firmware "
                  "e9ff096, `pulse_processor=\"firmware\"`) and by ours (`\"phase\"`, the default); a firmware "
                  "frame (an lhAngle burst's new station) is reproduced when a rotation of its channel has all its "
                  "angles within 1e-6 rad. Clock: the deck-to-log rate fitted on the log.", "",
                  "| log | lhAngle frames | reproduced (firmware / phase) | max abs diff rad | rotations/s firmware | "
                  "rotations/s phase | repeats dropped (events) | clock rate ppm |", "|---|---|---|---|---|---|---|---|"]
        for name, d in dec:
            f, h = d["firmware"], d["phase"]
            mx = "–" if f["max_abs_diff_rad"] is None else f"{f['max_abs_diff_rad']:.1e}"
            lines.append(f"| {name} | {f['firmware_frames']} | {f['matched']} / {h['matched']} | {mx} | "
                         f"{f['rotations_per_s']:.1f} | {h['rotations_per_s']:.1f} | {f['repeats_dropped']} | "
                         f"{d['clock']['rate_ppm']:+.0f} |")
        lines.append("")
    if res["skipped"]:
        lines += ["## Not used", ""] + [f"- `{s['file']}`: {s['reason']}" for s in res["skipped"]] + [""]
    return "\n".join(lines)


def _alignment_table(res) -> list:
    """Per moving log and method: the alignment found and its residuals."""
    rows = []
    for lg in res["logs"]:
        for label, m in sorted((lg.get("methods") or {}).items(), key=lambda kv: (not kv[0].startswith("fw"), kv[0])):
            a = m.get("alignment") or {}
            if a.get("status") != "ok":
                continue
            rows.append(f"| {lg['log']} | {_label(label)} | {a['samples']} | {_mm(a['rms_m'])} | {_mm(a['mean_m'])} | "
                        f"{_mm(a['median_m'])} | {_mm(a['max_m'])} | {a['start_ms']:+.0f} / {a['end_ms']:+.0f} | "
                        f"{(a['rate'] - 1) * 1e6:+.0f} | {a['rotation_deg']:.2f} |")
    if not rows:
        return []
    return ["## Per moving log: the alignment and its residuals", "",
            "Each method aligned on its own (temporal: the markers' on / off times moved by the offsets found; rate "
            "= motion capture seconds per log second; rigid: Arun's rotation and translation); residuals = the "
            "Euclidean errors of the aligned estimates used.", "",
            "| log | method | samples | RMS mm | mean mm | median mm | max mm | start / end offset ms | rate - 1 ppm "
            "| rotation deg |", "|---|---|---|---|---|---|---|---|---|---|", *rows, ""]


def _setups_table(res) -> list:
    """The station set-ups and their refinement."""
    ups = res.get("setups") or {}
    if not ups:
        return []
    lines = ["## Station set-ups", "",
             "Logs whose system-config.yaml is the same file are one set-up. Its static logs refine the stations once "
             "(`layoutkit replay STATIC0 --system-config YAML --solve joint --refine-stations --refine-from STATIC1 "
             "... --report R` → R/stations_refined.json: poses only, the first station held as the world frame); "
             "when applied, every log of the set-up is replayed with `--stations` those.", "",
             "| set-up | sets | static logs used | status | applied | residual scale before → after (sigma) | "
             "stations moved mm / rotated deg | seconds |", "|---|---|---|---|---|---|---|---|"]
    notes = []
    for key, g in sorted(ups.items()):
        r = g.get("refinement") or {}
        rep = r.get("report") or {}
        b, a = rep.get("residual_scale_before"), rep.get("residual_scale_after")
        scale = "–" if b is None or a is None else f"{b:.2f} → {a:.2f}"
        moved = "; ".join(f"{st['id']}: {1e3 * st['moved_norm_m']:.1f} / {st['rotated_deg']:.2f}"
                          for st in rep.get("stations") or ()) or "–"
        sec = r.get("seconds")
        lines.append(f"| {key} | {', '.join(g['sets'])} | {len(r.get('logs') or ())} | {r.get('status', '–')} | "
                     f"{'yes' if r.get('applied') else 'no'} | {scale} | {moved} | "
                     f"{'–' if sec is None or not np.isfinite(sec) else f'{sec:.0f}'} |")
        if r.get("message"):
            notes.append(f"- {key}: {r['message']}")
    return lines + [""] + notes + ([""] if notes else [])


def _figures(res, out: Path) -> list:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter

    from ..io.figures import save_figure

    paths = []
    by_set: dict = {}
    for lg in res["logs"]:
        by_set.setdefault(lg["set"], []).append(lg)
    for name, logs in sorted(by_set.items()):
        if logs[0]["scenario"] == "jitter":
            continue
        labels = sorted({k for lg in logs for k, m in lg["methods"].items() if (m.get("alignment") or {}).get("status") == "ok"},
                        key=lambda k: (not k.startswith("fw"), k))
        if not labels:
            continue
        fig, ax = plt.subplots(len(labels), 1, figsize=(9, 1.6 * len(labels) + 1), sharex=True, squeeze=False)
        for i, k in enumerate(labels):
            off = 0.0
            for lg in logs:
                a = (lg["methods"].get(k) or {}).get("alignment") or {}
                if a.get("status") == "ok":
                    ax[i, 0].plot(np.asarray(a["t"]) + off, 1e3 * np.asarray(a["error"]), ".", ms=1.5)
                    off += (a["t"][-1] if a["t"] else 0.0) + 5.0
            ax[i, 0].set_title(_label(k), fontsize=8)
            ax[i, 0].set_ylabel("error mm")
            ax[i, 0].set_yscale("log")
            ax[i, 0].yaxis.set_minor_formatter(NullFormatter())
        ax[-1, 0].set_xlabel("time since markers on, logs one after another (s)")
        fig.suptitle(f"{name}: error vs motion capture over time")
        fig.tight_layout(rect=(0, 0.03, 1, 1))
        paths.append(save_figure(fig, out / f"{name}_error_time.png",
                                 caption="Euclidean error of each method after temporal + rigid alignment to the motion capture (log scale)."))
        fig, ax = plt.subplots(figsize=(6.5, 4.5))
        for k in labels:
            e = np.concatenate([np.asarray(lg["methods"][k]["alignment"]["error"]) for lg in logs
                                if (lg["methods"].get(k) or {}).get("alignment", {}).get("status") == "ok"])
            e = np.sort(e) * 1e3
            ax.plot(e, np.arange(1, e.size + 1) / e.size, label=f"{_label(k)} (n={e.size})")
        ax.set_xscale("log")
        ax.set_xlabel("error vs motion capture (mm)")
        ax.set_ylabel("share of estimates")
        ax.set_title(f"{name}: error CDF per method")
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
        fig.tight_layout(rect=(0, 0.04, 1, 1))
        paths.append(save_figure(fig, out / f"{name}_error_cdf.png",
                                 caption="Cumulative share of estimates below each error, all logs of the set."))
    return paths


def write_outputs(res: dict, out_dir) -> dict:
    """``results.json`` (without the per-sample error series), ``table.md`` and the figures in
    ``out_dir``; returns the paths."""
    from ..io.atomic import atomic_write
    from ..io.jsonfile import to_jsonable

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    figs = _figures(res, out)
    slim = {"sets": res["sets"], "skipped": res["skipped"], "setups": res.get("setups") or {}, "logs": []}
    for lg in res["logs"]:
        d = dict(lg, methods={})
        for k, m in lg["methods"].items():
            m = dict(m)
            if "alignment" in m:
                m["alignment"] = {kk: vv for kk, vv in m["alignment"].items() if kk not in ("t", "error", "used")}
            d["methods"][k] = m
        slim["logs"].append(d)
    with atomic_write(out / "results.json", "w") as fh:
        json.dump(to_jsonable(slim), fh, indent=1)
    with atomic_write(out / "table.md", "w") as fh:
        fh.write(_table(res))
    return {"results": str(out / "results.json"), "table": str(out / "table.md"), "figures": [str(p) for p in figs]}
