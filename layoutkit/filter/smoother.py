"""Offline smoothing of the IMU-aided filter for replay (``layoutkit replay ... --filter ekf --smooth``).

Replaying a recorded file is offline: the best estimate at time t uses the sweeps after t too. The
smoother is a Rauch-Tung-Striebel pass (Rauch, Tung & Striebel 1965; for the error-state filter
Solà 2017 §7 conventions) over the states of :class:`layoutkit.filter.imu_tracker.ImuSweepTracker`,
run as a *fixed-lag smoother by blocks* so that memory stays bounded and the JSON lines still
stream:

- the causal filter runs as it does without smoothing (its arithmetic untouched); per step (every
  sweep's output, and every ``gap_dt_s`` s of IMU propagation without a sweep: a *gap pose*) the
  recorder keeps the filtered nominal state and error covariance, the predicted ones before the
  step's update and the error transition ``F`` from the previous step (``F = I`` for a step at the
  same time, e.g. a sweep applied late);
- once the buffered steps span ``2 lag_s`` s, the backward pass (:func:`rts_smooth`, compiled
  :func:`layoutkit.filter._imu_numba.rts_backward`) runs from the newest step back over the buffer;
  the steps older than the newest minus ``lag_s`` are emitted (each smoothed with at least ``lag_s``
  s of later sweeps) and dropped, the rest is kept; the outputs are therefore delayed by at most
  ``2 lag_s`` s of data;
- a restart (the filter lost: soft restart or a fresh start) breaks the chain: the steps up to it
  are smoothed and emitted as one segment, the next segment starts at the next step. The filter
  was lost because the sweeps refused its state, which was wrong before that verdict: the sweeps it
  accepted while it drifted (one station, fast motion) would pull the smoothed poses before them
  the wrong way (move/log00 at 81.2-81.5 s: a causal ok pose 8 mm from the motion capture smoothed
  to 29-112 mm with a 6-10 mm sigma). Such a chain is smoothed only up to its last causal ok output;
  the steps after it are emitted as the causal filter gave them (none ok);
- at the end of the stream (:meth:`SmoothedImuTracker.finish`) the rest is smoothed and emitted.

Statuses of smoothed outputs use the causal filter's rules unchanged: "lost" where the causal filter
was lost, "uncertain" where its health says so (a start not yet confirmed, sweeps rejected in a row,
the gate starving: :meth:`ImuSweepTracker._health`), else the same sigma limits
(:func:`layoutkit.filter.imu_tracker.sigma_why`: speed, attitude and position 1-sigma, and the
position root trace within the best single station's ``PDOP_1 sigma_theta`` at the smoothed pose) on
the *smoothed* covariance.

Memory: 15×15 matrices ×3 and two nominal states per step; ~6 kB per step, ~200 steps per second of a
two-station LH2 log: ``2 lag_s`` s of them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .imu_tracker import ImuSweepTracker, sigma_why
from .tracker import FilterOutput

__all__ = ["SmootherConfig", "SmootherCounters", "rts_smooth", "StepBuffer", "SmoothedImuTracker"]


@dataclass(frozen=True)
class SmootherConfig:
    """lag_s : s, the fixed lag (each output smoothed with at least this much later data; blocks of
    ``2 lag_s``); gap_dt_s : s, a gap pose every this much IMU propagation without a sweep (at the
    first IMU sample time at least ``gap_dt_s`` after the latest step)."""

    lag_s: float = 1.5
    gap_dt_s: float = 0.02

    def __post_init__(self):
        for k in ("lag_s", "gap_dt_s"):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"SmootherConfig.{k}: expected a positive number of seconds, got {v!r}")


@dataclass
class SmootherCounters:
    """Running counts of the smoother (mutable, owned by one :class:`SmoothedImuTracker`)."""

    steps: int = 0
    gap_poses: int = 0
    outputs: int = 0
    ok: int = 0
    gap_ok: int = 0
    segments: int = 0
    blocks: int = 0
    max_buffer: int = 0
    passthrough: int = 0
    unsmoothed_tail: int = 0

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def rts_smooth(Rf, xf, Pf, Rp, xp, Pp, F):
    """Smoothed states of one chain of ``K`` steps (no restart in between): returns ``(Rs (K, 3, 3),
    xs (K, 12) = [p m, v m/s, ba m/s², bg rad/s], Ps (K, 15, 15))``.

    Rf, xf, Pf : the filtered nominal states and error covariances (after each step's update); Rp, xp,
    Pp : the predicted ones (before it; step 0's unused); F (K, 15, 15) : the error transition from
    step k-1's filtered state to step k's prediction (step 0's unused). Error state ``[dp, dv,
    dtheta, dba, dbg]``, ``dtheta`` local (``R_true = R exp([dtheta]x)``). The backward pass of
    :func:`layoutkit.filter._imu_numba.rts_backward`."""
    from . import _imu_numba as K

    Rf, xf, Pf, Rp, xp, Pp, F = (np.ascontiguousarray(a, float) for a in (Rf, xf, Pf, Rp, xp, Pp, F))
    n = len(Rf)
    Rs, xs, Ps = np.empty_like(Rf), np.empty_like(xf), np.empty_like(Pf)
    if n:
        K.rts_backward(Rf, xf, Pf, Rp, xp, Pp, F, n, Rs, xs, Ps)
    return Rs, xs, Ps


class StepBuffer:
    """The recorded steps of one chain, in growable arrays (see :func:`rts_smooth` for the fields),
    and per step its time ``t`` (s) and what the output needs (``meta``)."""

    _FIELDS = (("Rf", (3, 3)), ("xf", (12,)), ("Pf", (15, 15)), ("Rp", (3, 3)), ("xp", (12,)), ("Pp", (15, 15)),
               ("F", (15, 15)))

    def __init__(self, capacity: int = 256):
        self.n = 0
        self.t = np.empty(capacity)
        for k, shp in self._FIELDS:
            setattr(self, k, np.empty((capacity, *shp)))
        self.meta = []

    def _grow(self) -> None:
        cap = 2 * len(self.t)
        self.t = np.resize(self.t, cap)
        for k, shp in self._FIELDS:
            a = getattr(self, k)
            b = np.empty((cap, *shp))
            b[:self.n] = a[:self.n]
            setattr(self, k, b)

    def append(self, t, e, pred, F, meta) -> None:
        """One step: time ``t``, the filter ``e``'s state now (filtered), ``pred = (R, x, P)`` before its
        update (None: the same as filtered), ``F``, ``meta``."""
        from . import _imu_numba as K

        if self.n == len(self.t):
            self._grow()
        i = self.n
        self.t[i] = t
        K.record_state(e.R, e.p, e.v, e.ba, e.bg, e.P, self.Rf[i], self.xf[i], self.Pf[i])
        if pred is None:
            self.Rp[i], self.xp[i], self.Pp[i] = self.Rf[i], self.xf[i], self.Pf[i]
        else:
            self.Rp[i], self.xp[i], self.Pp[i] = pred
        self.F[i] = F
        self.meta.append(meta)
        self.n += 1

    def smooth(self, n: int | None = None):
        """:func:`rts_smooth` over the first ``n`` buffered steps (default all)."""
        n = self.n if n is None else n
        return rts_smooth(*(getattr(self, k)[:n] for k, _ in self._FIELDS))

    def drop(self, k: int) -> None:
        """Forget the first ``k`` steps."""
        m = self.n - k
        self.t[:m] = self.t[k:self.n]
        for name, _ in self._FIELDS:
            a = getattr(self, name)
            a[:m] = a[k:self.n]
        del self.meta[:k]
        self.n = m


class SmoothedImuTracker:
    """The fixed-lag smoother of the module docstring around an :class:`ImuSweepTracker` ``tracker``
    (it becomes the tracker's recorder). :meth:`push` takes a sweep and returns the outputs that
    became final (smoothed :class:`FilterOutput` with ``smoothed=True``, in time order; the
    tracker's own outputs while it waits for a start pass through unchanged); :meth:`finish` the rest.
    Gap poses: ``station`` and ``axis`` -1, event "gap"."""

    def __init__(self, tracker: ImuSweepTracker, config: SmootherConfig | None = None):
        self.tracker = tracker
        self.sc = config or SmootherConfig()
        tracker.recorder = self
        self.buf = StepBuffer()
        self.counters = SmootherCounters()
        self._pred = None
        self._last_t = -math.inf
        self._stepped = False
        self._out = []
        self._one = (-math.inf, math.inf)
        self.last_causal = None  # the tracker's own (causal) output of the latest sweep

    # ------------------------------------------------------------------ recorder (called by the tracker)
    def gap_from(self) -> float:
        """s, the time the next pose inside a gap is counted from (``gap_dt_s`` after it): the latest
        step's; infinite while the buffer is empty."""
        return self._last_t if len(self.buf.meta) > 0 else math.inf

    def predicted(self, e) -> None:
        from . import _imu_numba as K

        R, x, P = np.empty((3, 3)), np.empty(12), np.empty((15, 15))
        K.record_state(e.R, e.p, e.v, e.ba, e.bg, e.P, R, x, P)
        self._pred = (R, x, P)

    def predicted_cov(self, P) -> None:
        R, x, _ = self._pred
        self._pred = (R, x, np.array(P, float))

    def _append(self, t, e, meta, F, pred) -> None:
        self.buf.append(t, e, pred, F, meta)
        self._last_t = t
        self.counters.steps += 1
        self.counters.max_buffer = max(self.counters.max_buffer, self.buf.n)

    def gap_step(self, t: float, trk: ImuSweepTracker) -> None:
        e = trk.eskf
        # a step without update: predicted = filtered
        self._append(t, e, ("gap", None, trk._health(), False, trk.static), trk._Fc, None)
        self.counters.gap_poses += 1

    def step(self, o: FilterOutput, health: str, lost: bool, trk: ImuSweepTracker) -> None:
        if o.event == "init" and self.buf.n:
            self._flush()
        self._append(o.t, trk.eskf, ("sweep", o, health, lost, o.static), trk._Fc,
                     None if o.event == "init" else self._pred)
        self._pred = None
        self._stepped = True
        if lost:  # the chain breaks here (soft restart or a fresh start follows)
            self._flush(lost=True)

    # ------------------------------------------------------------------ blocks
    def _emit(self, upto: int, smoothed) -> None:
        from . import _imu_numba as K

        trk = self.tracker
        c = trk.config
        Rs, xs, Ps = smoothed
        covs, qs, pbs = np.empty((upto, 12, 12)), np.empty((upto, 4)), np.empty((upto, 3))
        K.body_outputs(Rs, xs, Ps, upto, trk.p_ib, covs, qs, pbs)
        ns = len(trk.stations)
        for k in range(upto):
            kind, o, health, lost, static = self.buf.meta[k]
            R, cov, p_body = Rs[k], covs[k], pbs[k]
            if lost:
                status = "lost"
            elif health:
                status = "uncertain"
            else:
                d = cov.diagonal()
                t = float(self.buf.t[k])
                status = "uncertain" if sigma_why(d, c, ns, lambda: self._one_station_limit(t, R, p_body)) else "ok"
            if o is None:
                out = FilterOutput(float(self.buf.t[k]), -1, -1, status, qs[k], p_body, cov,
                                   static=static, event="gap", smoothed=True)
            else:
                out = FilterOutput(o.t, o.station, o.axis, status, qs[k], p_body, cov, o.used, o.rejected,
                                   o.sweep_rejected, o.nis, o.dof, static, o.event, smoothed=True)
            self.counters.outputs += 1
            self.counters.ok += status == "ok"
            self.counters.gap_ok += status == "ok" and o is None
            self._out.append(out)
        self.buf.drop(upto)

    def _flush(self, lost: bool = False) -> None:
        """Smooth the buffered chain and emit all of it (the end of the stream, a fresh start). A chain
        that ends lost (the sweeps refused the state: it was wrong before the verdict) is smoothed only
        up to its last causal ok output, backwards from there; its steps after that one are emitted as
        the causal filter gave them (none of them ok), its gap poses there dropped."""
        b = self.buf
        if not b.n:
            return
        self.counters.segments += 1
        if not lost:
            self._emit(b.n, b.smooth())
            return
        last_ok = max((k for k, m in enumerate(b.meta) if m[0] == "sweep" and m[1].status == "ok"), default=-1)
        if last_ok >= 0:
            self._emit(last_ok + 1, b.smooth(last_ok + 1))
        for kind, o, *_ in b.meta:
            if kind == "sweep":
                self._out.append(o)
                self.counters.unsmoothed_tail += 1
        b.drop(b.n)

    def _block(self) -> None:
        b = self.buf
        if b.n < 2 or b.t[b.n - 1] - b.t[0] < 2.0 * self.sc.lag_s:
            return
        upto = int(np.searchsorted(b.t[:b.n], b.t[b.n - 1] - self.sc.lag_s, side="right"))
        if upto:
            self._emit(upto, b.smooth())
            self.counters.blocks += 1

    def _one_station_limit(self, t: float, R, p) -> float:
        """The best single station's position 1-sigma at the smoothed pose (cached for 0.1 s, like the
        causal filter's own)."""
        t0, lim = self._one
        if abs(t - t0) <= 0.1:
            return lim
        lim = self.tracker.one_station_sigma(R, p)
        self._one = (t, lim)
        return lim

    # ------------------------------------------------------------------ stream
    def push(self, sweep) -> list:
        """One sweep through the tracker; the outputs that became final (maybe none)."""
        self._stepped = False
        o = self.last_causal = self.tracker.push(sweep)
        if o is not None and not self._stepped:  # waiting for a start: no state to smooth
            self._flush()
            self._out.append(o)
            self.counters.passthrough += 1
        self._block()
        out, self._out = self._out, []
        return out

    def finish(self) -> list:
        """The end of the stream: the rest smoothed and emitted."""
        self._flush()
        out, self._out = self._out, []
        return out
