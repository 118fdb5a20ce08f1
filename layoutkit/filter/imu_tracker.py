"""Sweep-by-sweep tracking with an IMU: the IMU-aided error-state filter (:class:`layoutkit.filter.imu.ImuEskf`)
driven by the gyro and accelerometer, corrected by every decoded sweep, started and restarted from the
lighthouse-only tracker (:class:`layoutkit.filter.tracker.SweepTracker`, whose start is the joint solve of
two stations); same :class:`~layoutkit.filter.tracker.FilterOutput` per sweep as the lighthouse-only filter.

Life cycle (docs/filter.md, "IMU-aided"):

1. *start*: the sweeps go to a fresh lighthouse-only :class:`SweepTracker` until its status is "ok"
   (two stations' joint start, confirmed by accepted sweeps, 1-sigma within its limits); the IMU filter
   starts from that pose, velocity and covariance (attitude error turned from the tracker's world
   frame into the IMU filter's local one). Gravity (world) at the first start: the accelerometer's
   mean over ±``rest_window_s`` turned into the world when the body is at rest there (specific
   force within ``rest_acc_tol`` of 1 g, rate below ``rest_rate``), else ``(0, 0, -g)``; biases start
   at 0 with the config's prior.
2. *tracking*: each sweep propagates the IMU (samples linearly interpolated between their times,
   each interval integrated at its midpoint) to the sweep's mean hit time (LH2: ``(alpha + pi -/+
   pi/3) / omega`` after the rotor zero) and updates with its lit angles through the station's
   calibrated forward model; the chi² gate (``gate_p``) rejects a sweep whose NIS is too large. The
   angle noise is ``sigma_theta * sqrt(scale)`` with ``scale`` estimated from the innovations
   (exponential average of ``(y^T y / m - mean diag(H P H^T)) / sigma_theta²``, each sweep's estimate
   limited to 1/4..4 times the current scale, the scale to ``[1, EkfConfig.noise_scale_max]``; a
   covariance-matching estimate, Mehra 1972): the light's model error (station
   geometry, calibration) is larger than the paper's sigma and the data say by how much. While the
   IMU says the body is at rest (:func:`rest_flags`: rate and specific force steady over 0.2 s) each
   sweep is followed by a zero-velocity update (1-sigma ``zupt_sigma``).
3. *status*: "ok" when ``confirm_sweeps`` sweeps were accepted since the start and no station axis that
   sent sweeps since then has had all of them refused, fewer than two in a
   row were rejected (overall and of each station), fewer than half of the last ``health_window`` sweeps were rejected (the gate is
   not starving the filter), and the 1-sigma attitude / position / speed are within the lighthouse-only
   filter's limits (:class:`EkfConfig` ``max_sigma_rot_deg``, ``max_sigma_pos_m``, ``max_sigma_speed``
   and, with two stations or more, the position root trace within the best single station's
   ``PDOP_1 sigma_theta``: ``ok_beats_one_station``); else "uncertain".
4. *lost*: ``lost_after`` sweeps rejected in a row (overall or of one station), or a position 1-sigma
   beyond ``lost_factor`` times its limit → "lost" for that sweep, and a soft restart: the state kept
   with its position / velocity / attitude 1-sigma reset to ``soft_restart_sigma`` (the gates then
   take the next sweeps; biases and gravity kept), or back to 1 (``soft_restart_sigma=None``, or the
   previous soft restart less than ``soft_restart_every_s`` ago).
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from ..geometry import rotvec_to_matrix
from ..lighthouse import hit_offset
from ..units import RAD2DEG, STANDARD_GRAVITY
from .ekf import EkfConfig, chi2_quantile, single_station_sigma
from .imu import ImuEskf, ImuFilterConfig
from .so3 import quat_to_matrix
from .tracker import FilterOutput, SweepTracker

__all__ = ["ImuTrackerConfig", "ImuCounters", "ImuSweepTracker", "sigma_why"]


@dataclass(frozen=True)
class ImuTrackerConfig:
    """The IMU side's tuning (SI). imu : :class:`ImuFilterConfig` (noise densities, bias walks, priors,
    gate ``gate_p`` per sweep and per angle, 1e-6: on the hand-moved logs 1e-3 restarts 15-32
    times per log for the same errors; its ``sigma_theta`` is replaced by the session's); imu_position : (3,) m, the IMU in the body
    (layout) frame (the adaptive angle-noise scale is capped at the lighthouse filter's
    ``EkfConfig.noise_scale_max``); noise_alpha : its averaging weight per sweep; health_window : sweeps over which the rejected share
    is judged; confirm_sweeps : accepted sweeps after a start before "ok"; rest_window_s, rest_acc_tol
    (fraction of 1 g), rest_rate (rad/s): the rest test for gravity at the first start; max_imu_gap_s :
    a sweep further than this from the IMU samples is propagated with the saturated (loose)
    accelerometer noise; imu_delay_s : s, how much later than the motion the IMU samples are
    stamped (their low-pass filters and the logging: they are moved earlier by it); reorder_s : s, a
    sweep whose hit time is at most this much before the filter's is applied at its own time (first
    order: the pose moved back with the velocity, acceleration and rate, its position covariance grown by
    the velocity's share and the acceleration's), an older one is dropped; lighthouse_beside :
    run the lighthouse-only tracker on every sweep (a hard restart starts from its current state at
    once) rather than only while the IMU filter waits for a start (with soft restarts it is not
    needed: off); zupt_window_s, zupt_rate (rad/s),
    zupt_acc (m/s²): the IMU's rest test (:func:`rest_flags`), zupt_sigma (m/s): 1-sigma of the
    zero-velocity update applied at every sweep while the IMU is at rest; gravity_from_start : the
    accelerometer at rest at the first start gives gravity (else the world's -z);
    soft_restart_sigma : (m, m/s, rad) when lost, keep the state with its position, velocity and
    attitude 1-sigma reset to these (the next sweeps pin it again), None = wait for the lighthouse
    tracker to start it afresh — also when the previous soft restart is less than
    ``soft_restart_every_s`` s old."""

    imu: ImuFilterConfig = ImuFilterConfig()
    imu_position: tuple = (0.0, 0.0, 0.0)
    noise_alpha: float = 0.02
    health_window: int = 20
    confirm_sweeps: int = 4
    rest_window_s: float = 0.1
    rest_acc_tol: float = 0.03
    rest_rate: float = 0.1
    max_imu_gap_s: float = 0.1
    imu_delay_s: float = 0.0
    reorder_s: float = 0.05
    lighthouse_beside: bool = False
    zupt_window_s: float = 0.2
    gravity_from_start: bool = True
    soft_restart_sigma: tuple | None = (0.05, 0.5, 0.05)
    soft_restart_every_s: float = 1.0
    zupt_rate: float = 0.02
    zupt_acc: float = 0.05
    zupt_sigma: float = 1e-3
    acc_noise_per_acc: float = 0.0


@dataclass
class ImuCounters:
    """Running counts of the IMU-aided tracker (mutable, owned by one tracker)."""

    sweeps: int = 0
    outputs: int = 0
    ok: int = 0
    inits: int = 0
    restarts: int = 0
    losts: int = 0
    accepted: int = 0
    rejected: int = 0
    too_few_lit: int = 0
    waiting: int = 0
    sweeps_late: int = 0
    imu_gap_sweeps: int = 0
    sweeps_reordered: int = 0
    angles_dropped: int = 0
    angles_used: int = 0
    zupts: int = 0
    nis_sum: float = 0.0
    dof_sum: int = 0

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        d["mean_nis_per_dof"] = self.nis_sum / self.dof_sum if self.dof_sum else None
        # the lighthouse-only tracker's names of the same counts (summaries print them)
        d["angles_rejected"] = self.angles_dropped
        d["sweeps_rejected"] = self.rejected
        return d


def sigma_why(d, config: EkfConfig, n_stations: int, one_station_limit) -> str:
    """Why a pose with the body covariance diagonal ``d (12,)`` (``(dphi world rad, dw, dp m, dv m/s)``,
    variances) is not ok by its sigma ("" when it is): the speed 1-sigma above ``max_sigma_speed``,
    the attitude / position 1-sigma above ``max_sigma_rot_deg`` / ``max_sigma_pos_m``, or (with
    ``ok_beats_one_station`` and two stations or more) the position root trace above the best single
    station's ``one_station_limit()`` (m; called only when the other limits pass). The one rule of the
    causal filter's statuses and of the smoothed ones."""
    c = config
    big_pos = math.sqrt(max(d[6], d[7], d[8])) / c.max_sigma_pos_m
    big_rot = math.sqrt(max(d[0], d[1], d[2])) * RAD2DEG / c.max_sigma_rot_deg
    if not math.sqrt(max(d[9], d[10], d[11])) <= c.max_sigma_speed:
        return "velocity unknown"
    if max(big_rot, big_pos) > 1.0:
        return "sigma above the filter's limits"
    if c.ok_beats_one_station and n_stations >= 2 and math.sqrt(d[6] + d[7] + d[8]) > one_station_limit():
        return "position sigma above one station's"
    return ""


def rest_flags(t, gyro, acc, window_s: float, max_rate: float, max_acc: float) -> np.ndarray:
    """(N,) bool: the IMU at rest at sample k — over the ``window_s`` s up to it every sample's rate is
    below ``max_rate`` rad/s and its specific force within ``max_acc`` m/s² of the window's mean (a
    resting accelerometer reads a constant; its noise on the Crazyflie is ~0.012 m/s², its gyro's
    ~0.003 rad/s), the window full (90 % of ``window_s``). A constant acceleration without turning
    over the whole window would pass: hand and flight motion do not hold one. t (N,) s, gyro, acc
    (N, 3)."""
    t = np.asarray(t, float)
    n = t.size
    rate_ok = np.linalg.norm(gyro, axis=1) <= max_rate
    out = np.zeros(n, bool)
    j = 0
    for k in range(n):
        while t[k] - t[j] > window_s:
            j += 1
        if k - j < 3 or t[k] - t[j] < 0.9 * window_s or not rate_ok[j:k + 1].all():
            continue
        a = acc[j:k + 1]
        out[k] = bool(np.all(np.abs(a - a.mean(0)) <= max_acc))
    return out


class ImuSweepTracker:
    """Sweeps in (``t``, ``station``, ``axis``, ``angles (n,)`` rad NaN = not hit, ``kind``), one
    :class:`FilterOutput` out per sweep once a start was attempted (see the module docstring).

    points_body : (n, 3) m; stations : list of :class:`~layoutkit.lighthouse.Station` (world);
    config : the lighthouse-only :class:`EkfConfig` (its sigma_theta / rho, limits, ``lost_after``;
    the starts' tracker uses it as it is); imu_t (N,) s, gyro (N, 3) rad/s, acc (N, 3) m/s² (IMU
    frame, the sweeps' clock); imu_config : :class:`ImuTrackerConfig`.
    """

    def __init__(self, points_body, stations, config: EkfConfig, imu_t, gyro, acc,
                 imu_config: ImuTrackerConfig | None = None):
        self.config = config
        self.ic = imu_config or ImuTrackerConfig()
        self.points_body = np.ascontiguousarray(points_body, float)
        self.n = len(self.points_body)
        self.stations = list(stations)
        self.p_ib = np.asarray(self.ic.imu_position, float)
        self.points_imu = self.points_body - self.p_ib
        from dataclasses import replace

        self.fc = replace(self.ic.imu, sigma_theta=config.sigma_theta)
        self.imu_t = np.asarray(imu_t, float) - self.ic.imu_delay_s
        self.gyro = np.ascontiguousarray(gyro, float)
        self.acc = np.ascontiguousarray(acc, float)
        if self.imu_t.size < 2:
            raise ValueError("IMU-aided filter: fewer than two IMU samples")
        self.rest = rest_flags(self.imu_t, self.gyro, self.acc, self.ic.zupt_window_s, self.ic.zupt_rate,
                               self.ic.zupt_acc)
        self.counters = ImuCounters()
        self.eskf: ImuEskf | None = None
        self.why = "waiting for a start"  # why the latest output is not ok ("" when it is)
        self.ekf = None  # (the lighthouse-only tracker's estimator attribute; summaries read it)
        self.starter: SweepTracker | None = None
        self.g = None
        self.gravity = {}
        self.noise_scale = 1.0
        self.t = -math.inf
        self._bad_run = 0
        self._bad_by_station = {}
        self._confirm = 0
        # since the latest (re)start: the (station, axis) whose sweeps were accepted, and those that sent
        # sweeps none of which was accepted yet (a start is confirmed only when the second set is empty)
        self._beams_ok, self._beams_refused = set(), set()
        self._recent = deque(maxlen=self.ic.health_window)
        self._one = (-math.inf, math.inf)
        self._keep_bias = None
        self._started_once = False
        self.static = False
        self._jac = None  # the compiled station Jacobians of the lighthouse tracker's estimator
        self._soft_at = -math.inf  # time of the latest soft restart
        # the smoother's recorder (:class:`layoutkit.filter.smoother.SmoothedImuTracker`), None = causal only;
        # it reads the states and never changes them (the causal outputs stay the same with or without it)
        self.recorder = None
        self._Fc = np.eye(15)  # the error transition accumulated since the recorder's latest step
        fc = self.fc
        self._qg, self._qba, self._qbg = fc.gyro_noise ** 2, fc.acc_bias_walk ** 2, fc.gyro_bias_walk ** 2
        self._q1 = chi2_quantile(1.0 - fc.gate_p, 1)
        self._qm = np.array([np.inf] + [chi2_quantile(1.0 - fc.gate_p, k) for k in range(1, self.n + 1)])
        self._out = np.zeros(6)
        self._par = []
        for st in self.stations:  # per station: pose, kind, calibration per axis, gib argument
            cal = getattr(st, "calibration", None) if config.model == "station" else None
            cp = np.zeros((2, 7)) if cal is None else np.ascontiguousarray(cal.params, float)[:, :7]
            self._par.append((np.ascontiguousarray(st.rotation, float), np.ascontiguousarray(st.translation, float),
                              st.kind == "lh2", cp, bool(cal is not None and cal.gib_argument == "corrected")))

    # ------------------------------------------------------------------ IMU
    def _sample(self, t: float):
        """(gyro, acc) (3,) linearly interpolated at ``t`` (held beyond the ends):
        :func:`layoutkit.filter._imu_numba.sample_at`, the propagation's own interpolation."""
        from . import _imu_numba as K

        w, f = np.empty(3), np.empty(3)
        K.sample_at(self.imu_t, self.gyro, self.acc, t, w, f)
        return w, f

    def _propagate(self, t: float) -> None:
        """Integrate the IMU from the filter's time to ``t`` (each stretch between sample times at its
        midpoint's interpolated sample: :func:`layoutkit.filter._imu_numba.propagate_span`); with the
        smoother's recorder, its poses inside gaps between sweeps on the way."""
        if t <= self.t:
            return
        T = self.imu_t
        gap = t < T[0] - self.ic.max_imu_gap_s or t > T[-1] + self.ic.max_imu_gap_s
        if gap:
            self.counters.imu_gap_sweeps += 1
        from . import _imu_numba as K

        e, rec, fc = self.eskf, self.recorder, self.fc
        a = self.t
        while True:
            a = K.propagate_span(e.R, e.p, e.v, e.ba, e.bg, e.g, e.P, T, self.gyro, self.acc, a, t, gap,
                                 fc.saturated_acc_noise ** 2, fc.acc_noise, self.ic.acc_noise_per_acc, self._qg,
                                 self._qba, self._qbg, self._Fc, rec is not None,
                                 math.inf if rec is None else rec.gap_from(), 0.0 if rec is None else rec.sc.gap_dt_s)
            if a >= t:
                break
            # a pose inside a gap between sweeps (at an IMU sample's time): a step without update
            rec.gap_step(a, self)
            self._Fc = np.eye(15)
        self.t = t

    # ------------------------------------------------------------------ start
    def _gravity(self, t: float, R) -> np.ndarray:
        m = np.abs(self.imu_t - t) <= self.ic.rest_window_s
        if not self.ic.gravity_from_start:
            self.gravity = {"from": "world -z", "t": t, "angle_to_minus_z_deg": 0.0}
            return np.array([0.0, 0.0, -STANDARD_GRAVITY])
        if m.sum() >= 3:
            f = self.acc[m]
            mag = np.linalg.norm(f, axis=1)
            rate = np.linalg.norm(self.gyro[m], axis=1)
            if np.all(np.abs(mag - STANDARD_GRAVITY) <= self.ic.rest_acc_tol * STANDARD_GRAVITY) \
                    and np.all(rate <= self.ic.rest_rate):
                g = -(R @ f.mean(0))
                g = g / np.linalg.norm(g) * STANDARD_GRAVITY
                ang = math.degrees(math.acos(min(1.0, max(-1.0, -g[2] / STANDARD_GRAVITY))))
                self.gravity = {"from": "accelerometer at rest at the start", "t": t, "angle_to_minus_z_deg": ang,
                                "samples": int(m.sum())}
                return g
        self.gravity = {"from": "world -z (the body was moving at the start)", "t": t,
                        "angle_to_minus_z_deg": 0.0}
        return np.array([0.0, 0.0, -STANDARD_GRAVITY])

    def _start_from(self, o: FilterOutput, velocity) -> None:
        """Start the IMU filter from the lighthouse tracker's ok output ``o``."""
        Rb = quat_to_matrix(o.quaternion)
        p_body = np.asarray(o.translation, float)
        if self.g is None:
            self.g = self._gravity(o.t, Rb)
        R = Rb  # IMU frame = body frame axes (the Crazyflie's IMU is in its body frame)
        p = p_body + Rb @ self.p_ib
        f = ImuEskf(R, p, self.g, self.fc, v=velocity)
        C = np.asarray(o.state_cov, float)
        # tracker error state (dphi world, dw, dp, dv): dtheta_local = R^T dphi
        A = np.zeros((9, 12))
        A[0:3, 6:9] = np.eye(3)
        A[3:6, 9:12] = np.eye(3)
        A[6:9, 0:3] = R.T
        f.P[0:9, 0:9] = A @ C @ A.T
        if self._keep_bias is not None:
            f.ba, f.bg, f.P[9:15, 9:15] = self._keep_bias
        for k in ("R", "p", "v", "ba", "bg", "P", "g"):
            setattr(f, k, np.ascontiguousarray(getattr(f, k), float).copy())
        self.eskf = f
        self.t = float(o.t)
        self._reset_health()
        self._one = (-math.inf, math.inf)
        self.counters.inits += 1
        if self._started_once:
            self.counters.restarts += 1
        self._started_once = True

    def _can_start(self, o: FilterOutput) -> bool:
        """The lighthouse tracker's output ``o`` starts the IMU filter: ok, or its (re)start itself when
        that was solved from two stations or more (its position 1-sigma within the best single
        station's, :meth:`_one_station_limit`); the IMU filter then confirms it with its own sweeps."""
        if len(self.stations) < 2 or getattr(self.starter.ekf, "v", None) is None:
            return False
        if o.ok:
            return True
        if o.event != "init":
            return False
        d = np.diagonal(o.state_cov)
        R = quat_to_matrix(o.quaternion)
        self._one = (-math.inf, math.inf)
        return math.sqrt(d[6] + d[7] + d[8]) <= self._one_station_limit(o.t, R, np.asarray(o.translation, float))

    def _lose(self) -> None:
        f = self.eskf
        self._keep_bias = (f.ba.copy(), f.bg.copy(), f.P[9:15, 9:15].copy())
        self.counters.losts += 1
        if self.ic.soft_restart_sigma is None or self.t - self._soft_at < self.ic.soft_restart_every_s:
            # (a soft restart that did not hold for soft_restart_every_s: start afresh from the
            # lighthouse tracker instead — the state itself is wrong)
            self.eskf = None
            return
        self._soft_at = self.t
        # soft restart: the state kept, its position / velocity / attitude declared unknown to the
        # given 1-sigma (the gates then take the next sweeps; "ok" returns only once they pin it)
        sp, sv, sr = self.ic.soft_restart_sigma
        P = f.P
        P[0:9, :] = 0.0
        P[:, 0:9] = 0.0
        P[0:3, 0:3] = np.eye(3) * sp ** 2
        P[3:6, 3:6] = np.eye(3) * sv ** 2
        P[6:9, 6:9] = np.eye(3) * sr ** 2
        self._reset_health()
        self.counters.restarts += 1

    # ------------------------------------------------------------------ update
    def _update(self, s: int, axis: int, z: np.ndarray, idx: np.ndarray) -> dict:
        """One sweep's update (:func:`layoutkit.filter._imu_numba.update`); the angle-noise scale follows
        the innovations of the accepted sweeps afterwards."""
        from . import _imu_numba as K

        f = self.eskf
        Rs, ts, lh2, cal, corr = self._par[s]
        s2 = self.fc.sigma_theta ** 2
        out = self._out
        K.update(f.R, f.p, f.v, f.ba, f.bg, f.P, self.points_imu, idx, z, Rs, ts, lh2, axis, cal[axis], corr,
                 s2 * self.noise_scale, self._q1, self._qm, out)
        acc = bool(out[0])
        m = int(out[2])
        res = {"accepted": acc, "nis": float(out[1]), "m": m, "dropped": int(out[5])}
        if acc:
            # one sweep moves the scale by at most a factor 4 of its share (a heavy-tailed estimate:
            # one odd sweep must not make the filter ignore the light)
            cap = self.config.noise_scale_max
            est = min(max((out[3] - out[4]) / s2, 0.25 * self.noise_scale), 4.0 * self.noise_scale)
            a = self.ic.noise_alpha
            self.noise_scale = min(max((1 - a) * self.noise_scale + a * est, 1.0), cap)
        return res

    # ------------------------------------------------------------------ main
    def push(self, sweep) -> FilterOutput | None:
        """Process one sweep (see the module docstring); None while nothing was started and the
        lighthouse tracker has no output yet, and for a sweep too old to apply."""
        c = self.config
        self.counters.sweeps += 1
        s = int(sweep.station)
        if not 0 <= s < len(self.stations):
            raise ValueError(f"sweep station {s}: the set-up has {len(self.stations)} station(s)")
        ang = np.asarray(sweep.angles, float)
        if ang.shape != (self.n,):
            raise ValueError(f"sweep angles: expected shape ({self.n},), got {ang.shape}")
        if self.starter is None:
            self.starter = SweepTracker(self.points_body, self.stations, c)
        # the lighthouse-only tracker runs beside (continuous: a restart needs no new start of its own)
        o = self.starter.push(sweep) if self.ic.lighthouse_beside or self.eskf is None else None
        if self.eskf is None:
            if o is None:
                return None
            self.counters.waiting += 1
            if self._can_start(o):
                self._jac = getattr(self.starter.ekf, "station_jacobians", None)
                self._start_from(o, np.asarray(self.starter.ekf.v, float).copy())
                if not self.ic.lighthouse_beside:
                    self.starter = None
                return self._output(float(sweep.t), s, int(sweep.axis), None, "init")
            status = "lost" if self._started_once else ("uncertain" if o.status == "ok" else o.status)
            self.why = "waiting for a start"
            self.counters.outputs += 1
            return FilterOutput(o.t, o.station, o.axis, status, o.quaternion, o.translation, o.state_cov, o.used,
                                o.rejected, o.sweep_rejected, o.nis, o.dof, o.static, o.event)
        st = self.stations[s]
        axis = int(sweep.axis)
        t = float(sweep.t)
        idx = np.flatnonzero(np.isfinite(ang))
        kind = getattr(sweep, "kind", None) or st.kind
        th = t + (hit_offset(st, kind, float(np.mean(ang[idx])), axis) if idx.size else 0.0)  # mean hit time
        if th < self.t - self.ic.reorder_s:
            self.counters.sweeps_late += 1
            return None
        self._propagate(th)
        if self.recorder is not None:
            self.recorder.predicted(self.eskf)
        upd = None
        if idx.size >= self.fc.min_sensors:
            late = self.t - th
            if late > 0.0:
                # a sweep the decoder emitted after later ones (the stations' sweeps interleave): its
                # angles are predicted at the pose moved back to its hit time with the current velocity
                # and rate, the correction applied, the pose moved forward again (first order in late)
                self.counters.sweeps_reordered += 1
                f = self.eskf
                w, fs = self._sample(th)
                dR = rotvec_to_matrix((np.asarray(w) - f.bg) * late)
                # the pose moved back is uncertain by the velocity's share and the acceleration the
                # constant-velocity step leaves out (before the gates judge the sweep)
                ad = f.R @ (np.asarray(fs) - f.ba) + f.g
                f.P[0:3, 0:3] += f.P[3:6, 3:6] * late * late + np.eye(3) * (0.5 * (ad @ ad) ** 0.5 * late * late) ** 2
                if self.recorder is not None:  # (the inflation is part of this step's prediction)
                    self.recorder.predicted_cov(f.P)
                f.p -= f.v * late - 0.5 * ad * late * late
                f.R[:, :] = f.R @ dR.T
                upd = self._update(s, axis, ang[idx], idx)
                f.p += f.v * late - 0.5 * ad * late * late
                f.R[:, :] = f.R @ dR
            else:
                upd = self._update(s, axis, ang[idx], idx)
            if math.isfinite(upd["nis"]):
                self.counters.nis_sum += upd["nis"]
                self.counters.dof_sum += upd["m"]
            self.counters.angles_dropped += upd["dropped"]
            self._recent.append(upd["accepted"])
            if upd["accepted"]:
                self.counters.accepted += 1
                self.counters.angles_used += upd["m"]
                self._bad_run = 0
                self._bad_by_station[s] = 0
                self._confirm -= 1
                self._beams_ok.add((s, axis))
                self._beams_refused.discard((s, axis))
            else:
                self.counters.rejected += 1
                self._bad_run += 1
                self._bad_by_station[s] = self._bad_by_station.get(s, 0) + 1
                if (s, axis) not in self._beams_ok:
                    self._beams_refused.add((s, axis))
        elif idx.size:
            self.counters.too_few_lit += 1
        j = int(np.searchsorted(self.imu_t, self.t, side="right")) - 1
        self.static = bool(0 <= j < self.imu_t.size - 1 and self.rest[j])
        if self.static:
            from . import _imu_numba as K

            f = self.eskf
            K.zero_velocity(f.R, f.p, f.v, f.ba, f.bg, f.P, self.ic.zupt_sigma ** 2)
            self.counters.zupts += 1
        return self._output(self.t, s, axis, upd, "")  # the state's time: the sweep's mean hit time

    def one_station_sigma(self, R, p) -> float:
        """m, the best single station's position 1-sigma at the body pose ``R (3, 3)``, ``p (3,)`` m (world)
        (:func:`layoutkit.filter.ekf.single_station_sigma`, with the lighthouse tracker's compiled station
        Jacobians when it had them); the causal filter's limit and the smoother's."""
        jac = self._jac
        return single_station_sigma(self.points_body, R, p, self.stations, self.config.rho, self.config.sigma_theta,
                                    None if jac is None else jac(R, p))

    def _one_station_limit(self, t: float, R, p) -> float:
        """:meth:`one_station_sigma`, re-evaluated after 0.1 s of stream time or a (re)start."""
        t0, lim = self._one
        if abs(t - t0) <= 0.1:
            return lim
        if self.starter is not None:
            self._jac = getattr(self.starter.ekf, "station_jacobians", None)
        lim = self.one_station_sigma(R, p)
        self._one = (t, lim)
        return lim

    def state_cov(self) -> np.ndarray:
        """(12, 12) covariance in the lighthouse filter's layout ``(dphi world, dw, dp, dv)`` (``dw``:
        the gyro bias's, turned into the world) of the body pose
        (:func:`layoutkit.filter._imu_numba.body_cov`)."""
        from . import _imu_numba as K

        out = np.empty((12, 12))
        K.body_cov(self.eskf.R, self.eskf.P, self.p_ib, out)
        return out

    def _output(self, t, s, axis, upd, event) -> FilterOutput:
        c = self.config
        f = self.eskf
        P = self.state_cov()
        d = P.diagonal()
        p_body = f.p - f.R @ self.p_ib
        big_pos = math.sqrt(max(d[6], d[7], d[8])) / c.max_sigma_pos_m
        # one station's sweeps refused again and again while the other's are taken: the state is wrong
        # for that station (the lighthouse-only tracker's rule too)
        bad = self._worst_run()
        lost = bad >= c.lost_after or big_pos > c.lost_factor
        health = ""
        if lost:
            status = "lost"
            self.why = "lost"
        else:
            health = self._health()
            why = health or sigma_why(d, c, len(self.stations),
                                      lambda: self._one_station_limit(t, f.R, p_body))
            self.why = why
            status = "uncertain" if why else "ok"
        cnt = self.counters
        cnt.outputs += 1
        cnt.ok += status == "ok"
        from . import _imu_numba as K

        q = np.empty(4)
        K.matrix_to_quat(f.R, q)
        if upd is None:
            o = FilterOutput(t, s, axis, status, q, p_body, P, static=self.static, event=event)
        else:
            acc = bool(upd["accepted"])
            o = FilterOutput(t, s, axis, status, q, p_body, P, upd["m"] if acc else 0, 0 if acc else upd["m"],
                             not acc, upd["nis"], upd["m"], self.static, event)
        if self.recorder is not None:
            self.recorder.step(o, health, lost, self)
            self._Fc = np.eye(15)
        if lost:
            self._lose()
        return o

    def _reset_health(self) -> None:
        """A (re)start: no rejections counted, ``confirm_sweeps`` accepted sweeps and every station axis
        that sends sweeps to be confirmed again."""
        self._bad_run = 0
        self._bad_by_station = {}
        self._confirm = self.ic.confirm_sweeps
        self._beams_ok, self._beams_refused = set(), set()
        self._recent.clear()

    def _worst_run(self) -> int:
        """The longest current run of rejected sweeps, overall or of one station."""
        return max(self._bad_run, max(self._bad_by_station.values(), default=0))

    def _health(self) -> str:
        """Why the filter's state is not to be trusted now, its sigma aside ("" when it is): a start not
        yet confirmed (fewer than ``confirm_sweeps`` sweeps accepted, or a station's axis that has sent
        sweeps since the (re)start without one accepted: after a soft restart the state can settle where
        one station's faulty angles put it, consistent with the other station's and with one axis of the
        faulty one, the other axis refused every time), sweeps rejected in a row (overall or of one
        station), the gate starving.""" 
        bad = self._worst_run()
        starving = len(self._recent) >= self._recent.maxlen // 2 and \
            sum(1 for x in self._recent if not x) > len(self._recent) // 2
        return ("confirming a start" if self._confirm > 0 or self._beams_refused else "sweeps rejected" if bad >= 2 else
                "gate starving" if starving else "")
