"""Crazyflie sweep-angle events (``lhAngle`` / ``estSweepAngle`` of a microSD log) → :class:`AngleFrame` s.

The firmware logs one event per sensor and sweep, in its own angle convention
(:func:`layoutkit.importers.cfusdlog.sweep_events`); this module groups them into one frame per
station and rotation and converts the angles to ours, so that ``replay LOG --solve joint`` solves
them like the deck's bytes (:mod:`layoutkit.live.joint_stream`: the 20 ms window rule, residuals
through each station's calibrated forward model).

How the firmware writes them (crazyflie-firmware e9ff096 ``lighthouse_core.c``; seen on every
public log): when a station's rotation (LH2) or X+Y sweep pair (LH1) completes, it logs, **sensor
by sensor**, the latest angles of **every** station it still holds — sensor 0 station 0 sweep 0,
sensor 0 station 0 sweep 1, sensor 0 station 1 sweep 0, ..., sensor 3 station 1 sweep 1 — one
*burst*. A station's angles are held until they are used: in crossing-beam mode (the estimator
takes both stations at once, when station 1 completes) station 0's angles are logged again, bit for
bit, in station 1's burst: 40-47 % of the events of the LH2 crossing-beam jitter logs (in Kalman
mode each station's angles are used at once and are never repeated; the 26-30 % of events there
that equal the previous value of their sensor are the deck at rest on the 6 MHz offset grid, real
measurements).

Grouping (:func:`angle_bursts`): a burst is a run of events in log order whose (sensor, station,
sweep) keys increase and that are less than 2 ms apart; a burst gives one frame per station in it.
Repeats (:func:`event_frames`): in a burst with several stations, a station whose angles equal,
every one, those of its previous frame is a repeat and is dropped (counted as "repeat of the
station's previous angles"); if every station of the burst repeats, the one whose previous frame is
oldest is kept (a burst always has one new station). A single-station burst is never a repeat.

Angles (the firmware's convention → ours, as the deck decoder :mod:`layoutkit.live.protocols.bitcraze`):
LH1 ``theta = pi/2 - angle`` per rotor (the raw, distorted angle: a station's calibration is
applied by the forward model :func:`layoutkit.lighthouse.measure`); LH2 the firmware's light-plane
angles are ours (plane 0: -30°, plane 1: +30°), kept as ``raw`` and converted to LH1-equivalent
angles with :func:`layoutkit.lighthouse.lh2_to_lh1_angles` for ``angles``.

Times: the events are stamped when the firmware has processed the sweep, not when the light
crossed the sensors. LH1: a sweep is processed at the next sync pulse, one LH1 frame
(``P/2`` = 8.33 ms at 3600 rpm) after its own sync, so the sweep's sync time is
``t_event - P/2``; a burst holds a station's X and Y angles, logged after its Y sweep, whose X
sweep was one frame earlier (``t_event - P``). LH2: a light plane is processed when its block of pulses closes, right after
the plane crossed the sensors, so the plane's crossing time is the event time; the rotor zero is
``t_event - (mean alpha + pi -/+ pi/3) / 2 pi * P`` (the inverse of
:class:`~layoutkit.live.pipeline.SweepPairer`'s ``t_axes``). When both planes carry one time (a
burst), the second plane's time is used.
These are assumptions about the firmware's latency (< 1 ms on the deck): they shift the window
times, which the reference alignment absorbs, and the motion compensation's per-station times.
"""
from __future__ import annotations

import numpy as np

from ..io.systemconfig import DECK_CLOCK_HZ, LH2_CYCLE_PERIODS
from ..lighthouse import LH1_ROTOR_RPM, lh2_to_lh1_angles
from .frames import DecodeStats
from .pipeline import AngleFrame

__all__ = ["event_frames", "angle_bursts", "EventFrameSource", "LH2_DEFAULT_PERIOD_S", "firmware_angle_check",
           "REPEAT_REASON"]

#: a station period when nothing better is known (LH2 channel 0's rotor: 479500 ticks / 24 MHz)
LH2_DEFAULT_PERIOD_S = 479500 / 24e6
LH1_SPAN_S = 0.025
#: events of one burst are logged within microseconds; bursts of two stations >= 4.5 ms apart
BURST_GAP_S = 2e-3
#: the drop reason of a station's angles logged again in another station's burst
REPEAT_REASON = "repeat of the station's previous angles (the firmware logs every station's latest angles)"


def _lh2_period(station: int, periods: dict) -> float:
    if station in periods:
        return float(periods[station])
    if 0 <= station < len(LH2_CYCLE_PERIODS):
        return LH2_CYCLE_PERIODS[station] / DECK_CLOCK_HZ
    return LH2_DEFAULT_PERIOD_S


def angle_bursts(ev) -> list:
    """Index arrays (log order) of the bursts of a :class:`~layoutkit.importers.cfusdlog.SweepEvents`:
    a burst continues while the (sensor, station, sweep) key increases and events are less than
    :data:`BURST_GAP_S` apart (module docstring)."""
    n = len(ev.t)
    if n == 0:
        return []
    key = (np.asarray(ev.sensor, np.int64) * 64 + np.asarray(ev.station, np.int64)) * 4 + np.asarray(ev.sweep, np.int64)
    t = np.asarray(ev.t, float)
    new = np.concatenate([[True], (np.diff(key) <= 0) | (np.diff(t) > BURST_GAP_S)])
    starts = np.flatnonzero(new)
    return np.split(np.arange(n), starts[1:])


def event_frames(ev, kind: str, n_sensors: int = 4, *, periods: dict | None = None, stats: DecodeStats | None = None):
    """Sweep events → list of :class:`AngleFrame` (sorted by ``t``): one frame per station and burst,
    repeats dropped (module docstring).

    ev : :class:`~layoutkit.importers.cfusdlog.SweepEvents`. kind : "lh1" or "lh2" (the system's
    base-station type). n_sensors : deck sensors (angles of sensors >= n are dropped). periods :
    station index → rotor period (s) (LH1 default 60 / 3600 rpm; LH2 the channel's
    ``LH2_CYCLE_PERIODS``). stats : counts frames (``good``) and what was dropped, by reason.
    """
    if kind not in ("lh1", "lh2"):
        raise ValueError(f"kind: expected 'lh1' or 'lh2', got {kind!r}")
    periods = dict(periods or {})
    stats = DecodeStats() if stats is None else stats
    n = int(n_sensors)
    t, st, se, sw, an = ev.t, ev.station, ev.sensor, ev.sweep, ev.angle
    last: dict = {}       # station -> (angles of its previous frame, burst number)
    out: list = []
    for b, idx in enumerate(angle_bursts(ev)):
        by_station: dict = {}
        for k in idx:
            s, i, w, a = int(st[k]), int(se[k]), int(sw[k]), float(an[k])
            if w not in (0, 1):
                stats.drop("sweep-angle event with a sweep id other than 0/1")
                continue
            if not 0 <= i < n:
                stats.drop("sweep-angle event of a sensor outside the layout")
                continue
            if not np.isfinite(a) or a == 0.0:
                # exactly 0 is the firmware's "no measurement" (its estimator skips such angles too)
                stats.drop("sweep angle missing (non-finite or exactly 0)")
                continue
            fr = by_station.setdefault(s, {"a": {}, "times": ([], [])})
            fr["a"][(i, w)] = a
            fr["times"][w].append(float(t[k]))
        if len(by_station) > 1:
            same = [s for s, fr in by_station.items() if s in last and last[s][0] == fr["a"]]
            if len(same) == len(by_station):
                same.remove(min(same, key=lambda s: last[s][1]))   # the burst's new station
            for s in same:
                stats.drop(REPEAT_REASON, len(by_station.pop(s)["a"]))
        for s, fr in sorted(by_station.items()):
            last[s] = (fr["a"], b)
            f = _frame(s, fr, kind, n, periods)
            if f is None:
                stats.drop("sweep-angle events of a frame without any angle")
            else:
                stats.good += 1
                out.append(f)
    out.sort(key=lambda f: f.t)
    return out


def _frame(s, fr, kind, n, periods):
    raw = np.full((n, 2), np.nan)
    for (i, w), a in fr["a"].items():
        raw[i, w] = a
    te = [float(np.median(x)) if x else np.nan for x in fr["times"]]
    if not np.isfinite(raw).any():
        return None
    if kind == "lh1":
        P = float(periods.get(s, 60.0 / LH1_ROTOR_RPM))
        sync = [x - P / 2 for x in te]
        if np.isfinite(te[0]) and np.isfinite(te[1]) and abs(te[1] - te[0]) < 1e-3:
            sync[0] = sync[1] - P / 2       # one burst after the Y sweep: its X sweep was one frame earlier
        tx = sync[0] if np.isfinite(sync[0]) else sync[1]
        ty = sync[1] if np.isfinite(sync[1]) else tx
        return AngleFrame(t=float(tx), station=int(s), angles=np.pi / 2 - raw, dt_y=float(ty - tx), kind="lh1",
                          raw=None, t_axes=(float(tx), float(ty)))
    P = _lh2_period(s, periods)
    cnt = np.isfinite(raw).sum(0)
    mean = np.where(cnt > 0, np.where(np.isfinite(raw), raw, 0.0).sum(0) / np.maximum(cnt, 1), 0.0)
    frac = (mean + np.pi + np.array([-np.pi / 3, np.pi / 3])) / (2 * np.pi) * P   # rotor zero → plane k
    zeros = [te[k] - frac[k] for k in (0, 1) if np.isfinite(te[k])]
    if len(zeros) == 2 and abs(te[1] - te[0]) < 1e-3:
        t0 = zeros[1]                       # both planes logged together, after the second one
    else:
        t0 = float(np.mean(zeros))
    return AngleFrame(t=float(t0), station=int(s), angles=lh2_to_lh1_angles(raw), kind="lh2", raw=raw,
                      t_axes=(float(t0 + frac[0]), float(t0 + frac[1])))


class EventFrameSource:
    """Stands in for a byte decoder in a :class:`~layoutkit.live.session.LiveSession` whose frames
    come from log events (``LiveSession.feed_frames``): its ``stats`` are the event grouping's;
    it decodes no bytes."""

    name = "cfusdlog-events"

    def __init__(self, stats: DecodeStats):
        self.stats = stats

    def feed(self, data) -> list:
        return []

    def flush(self) -> list:
        return []


def firmware_angle_check(log, *, pulse_processor: str = "firmware", n_sensors: int = 4, tol: float = 1e-6) -> dict:
    """Our LH2 light-plane angles from a log's ``lhUartFrame`` pulses vs the firmware's own ``lhAngle``
    events in the same log (the check of issue 25 item 1).

    log : path or :class:`~layoutkit.importers.cfusdlog.UsdLog`. pulse_processor : "firmware" (the
    firmware's decoding, expected equal to float32 rounding) or "phase" (ours,
    :mod:`layoutkit.live.protocols.bitcraze_lh2`). Each ``lhAngle`` frame (bursts, repeats dropped:
    :func:`event_frames`) is compared with the decoded rotations of its channel within 0.1 s
    (deck clock mapped to the log clock by :func:`~layoutkit.importers.cfusdlog.fit_deck_clock`); a
    frame *matches* when a rotation has all its angles within ``tol`` rad. Returns ``{"status",
    "message", "firmware_frames", "matched", "matched_share", "max_abs_diff_rad" (over matched
    frames), "rotations" (decoded), "rotations_per_s", "decode_dropped" (reasons), "clock"}``;
    status "no_data" when the log lacks either event type.
    """
    from ..importers.cfusdlog import UsdLog, fit_deck_clock, read_cfusdlog, sweep_events, uart_frames
    from .protocols.bitcraze_lh2 import PROCESSORS, plane_angles

    ul = log if isinstance(log, UsdLog) else read_cfusdlog(log)
    u = uart_frames(ul)
    ev = sweep_events(ul)
    if u is None or ev is None or ev.source != "lhAngle":
        return {"status": "no_data", "message": f"{ul.path}: needs lhUartFrame and lhAngle events "
                                                f"(found {sorted(k for k, v in ul.events.items() if len(v['t']))})"}
    if not np.any(u.channel >= 0):
        return {"status": "no_data", "message": f"{ul.path}: no lhUartFrame event carries an LH2 channel (an LH1 log)"}
    clock = fit_deck_clock(u.deck_s, u.t)
    stats = DecodeStats()
    proc = PROCESSORS[pulse_processor](n_sensors, stats)
    rots = []
    for s, tk, off, ch in zip(u.sensor.tolist(), u.ticks.tolist(), u.offset.tolist(), u.channel.tolist()):
        rots += proc.push(s, tk, off, None if ch < 0 else ch)
    rots += proc.flush()
    by_ch: dict = {}
    for r in rots:
        by_ch.setdefault(r.channel, []).append((float(clock.to_log(r.t0 / DECK_CLOCK_HZ)), plane_angles(r.offsets, r.channel)))
    fstats = DecodeStats()
    frames = [f for f in event_frames(ev, "lh2", n_sensors, stats=fstats)]
    matched, diffs = 0, []
    for f in frames:
        cand = by_ch.get(f.station, [])
        tt = np.array([c[0] for c in cand]) if cand else np.zeros(0)
        lo, hi = np.searchsorted(tt, f.t - 0.1), np.searchsorted(tt, f.t + 0.1)
        have = np.isfinite(f.raw)
        best = np.inf
        for k in range(lo, hi):
            a = cand[k][1]
            if np.all(np.isfinite(a[have])):
                best = min(best, float(np.max(np.abs(a[have] - f.raw[have]))))
        if best <= tol:
            matched += 1
            diffs.append(best)
    span = float(u.t[-1] - u.t[0]) if len(u.t) > 1 else float("nan")
    share = matched / len(frames) if frames else float("nan")
    return {"status": "ok", "pulse_processor": pulse_processor, "firmware_frames": len(frames), "matched": matched,
            "matched_share": share, "max_abs_diff_rad": float(max(diffs)) if diffs else None,
            "rotations": len(rots), "rotations_per_s": len(rots) / span if span > 0 else None,
            "decode_dropped": dict(stats.reasons), "repeats_dropped": int(fstats.reasons.get(REPEAT_REASON, 0)),
            "clock": clock.as_dict(),
            "message": f"{matched} of {len(frames)} lhAngle frames reproduced to {tol:g} rad "
                       f"(max |diff| {max(diffs) if diffs else float('nan'):.2e} rad) by the {pulse_processor} "
                       f"processor; {len(rots)} rotations decoded"}
