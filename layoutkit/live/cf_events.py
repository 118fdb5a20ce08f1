"""Crazyflie sweep-angle events (``lhAngle`` / ``estSweepAngle`` of a microSD log) → :class:`AngleFrame` s.

The firmware logs one event per sensor and sweep, in its own angle convention
(:func:`layoutkit.importers.cfusdlog.sweep_events`); this module groups them into one frame per
station and rotation and converts the angles to ours, so that ``replay LOG --solve joint`` solves
them like the deck's bytes (:mod:`layoutkit.live.joint_stream`: the 20 ms window rule, residuals
through each station's calibrated forward model).

Grouping (per station, events in log order): a frame collects sweep-0 then sweep-1 angles; it is
closed by a repeated (sensor, sweep), by a sweep-0 angle after sweep-1 angles, or by an event more
than ``span`` after the frame's first (LH2 0.75 rotor period, LH1 25 ms: a station's X and Y
sweeps are at most 16.7 ms apart in A/B mode, its next X sweep 33 ms later).

Angles (the firmware's convention → ours, as the deck decoder :mod:`layoutkit.live.protocols.bitcraze`):
LH1 ``theta = pi/2 - angle`` per rotor (the raw, distorted angle: a station's calibration is
applied by the forward model :func:`layoutkit.lighthouse.measure`); LH2 the firmware's light-plane
angles are ours (plane 0: -30°, plane 1: +30°), kept as ``raw`` and converted to LH1-equivalent
angles with :func:`layoutkit.lighthouse.lh2_to_lh1_angles` for ``angles``.

Times: the events are stamped when the firmware has processed the sweep, not when the light
crossed the sensors. LH1: a sweep is processed at the next sync pulse, one LH1 frame
(``P/2`` = 8.33 ms at 3600 rpm) after its own sync, so the sweep's sync time is
``t_event - P/2``. LH2: a light plane is processed when its block of pulses closes, right after
the plane crossed the sensors, so the plane's crossing time is the event time; the rotor zero is
``t_event - (mean alpha + pi -/+ pi/3) / 2 pi * P`` (the inverse of
:class:`~layoutkit.live.pipeline.SweepPairer`'s ``t_axes``). When both planes carry one time (the
estimator's events are written together after the second plane), the second plane's time is used.
These are assumptions about the firmware's latency (< 1 ms on the deck): they shift the window
times, which the reference alignment absorbs, and the motion compensation's per-station times.
"""
from __future__ import annotations

import numpy as np

from ..lighthouse import LH1_ROTOR_RPM, lh2_to_lh1_angles
from .frames import DecodeStats
from .pipeline import AngleFrame

__all__ = ["event_frames", "EventFrameSource", "LH2_DEFAULT_PERIOD_S"]

#: a station period when nothing better is known (LH2 channel 0's rotor: 479500 ticks / 24 MHz)
LH2_DEFAULT_PERIOD_S = 479500 / 24e6
LH1_SPAN_S = 0.025


def _lh2_period(station: int, periods: dict) -> float:
    from .protocols.bitcraze import DECK_CLOCK_HZ, LH2_CYCLE_PERIODS

    if station in periods:
        return float(periods[station])
    if 0 <= station < len(LH2_CYCLE_PERIODS):
        return LH2_CYCLE_PERIODS[station] / DECK_CLOCK_HZ
    return LH2_DEFAULT_PERIOD_S


def event_frames(ev, kind: str, n_sensors: int = 4, *, periods: dict | None = None, stats: DecodeStats | None = None):
    """Sweep events → list of :class:`AngleFrame` (sorted by ``t``).

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
    order = np.argsort(t, kind="stable")
    open_: dict = {}
    out: list = []

    def close(s):
        fr = open_.pop(s, None)
        if fr is not None:
            f = _frame(s, fr, kind, n, periods)
            if f is None:
                stats.drop("sweep-angle events of a frame without any angle")
            else:
                stats.good += 1
                out.append(f)

    for k in order:
        s, i, w, a, tk = int(st[k]), int(se[k]), int(sw[k]), float(an[k]), float(t[k])
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
        fr = open_.get(s)
        span = 0.75 * _lh2_period(s, periods) if kind == "lh2" else LH1_SPAN_S
        if fr is not None and ((i, w) in fr["a"] or (w == 0 and fr["times"][1]) or tk - fr["t0"] > span):
            close(s)
            fr = None
        if fr is None:
            fr = open_[s] = {"t0": tk, "a": {}, "times": ([], [])}
        fr["a"][(i, w)] = a
        fr["times"][w].append(tk)
    for s in list(open_):
        close(s)
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
        tx = sync[0] if np.isfinite(sync[0]) else sync[1]
        ty = sync[1] if np.isfinite(sync[1]) else tx
        return AngleFrame(t=float(tx), station=int(s), angles=np.pi / 2 - raw, dt_y=float(ty - tx), kind="lh1",
                          raw=None, t_axes=(float(tx), float(ty)))
    P = _lh2_period(s, periods)
    with np.errstate(invalid="ignore"):
        mean = np.nanmean(raw, 0) if np.isfinite(raw).any() else np.zeros(2)
    mean = np.where(np.isfinite(mean), mean, 0.0)
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
