"""Sweep-by-sweep tracking: PnP (re-)initialisation, the EKF, a static detector, per-sweep output.

:class:`SweepTracker` consumes decoded sweeps — any objects with ``t`` (s, sync time), ``station``
(index), ``axis`` (0/1), ``angles`` ((n,) rad, NaN = not hit) and ``kind`` ("lh1"/"lh2"), e.g.
:class:`layoutkit.live.frames.SweepMeasurement` — in time order and returns one
:class:`FilterOutput` per sweep once the filter is initialised.

Life cycle (docs/filter.md):

1. *init*: per station the latest angle of every sensor on each axis is kept; the sensors with
   both angles younger than ``init_window_s`` form a frame (with heavy dropout one X/Y pair rarely
   has 4 lit sensors, a few consecutive sweeps do). With >= 4 of them
   :func:`layoutkit.pnp.solve_pnp` solves it (angles of a calibrated station first undistorted,
   LH2 plane angles converted to LH1 angles — for the start only). A
   pose with status ok (or "ambiguous": the two planar solutions are used in turn, the wrong one
   is rejected by the innovations) and an RMS residual below ``init_max_residual_sigma`` sigma starts the
   filter at the sweep's time with the PnP covariance (the sandwich ``A^-1 J^T R J A^-1`` of Chen
   eq. 18) times ``init_inflation``, plus the motion the velocity prior allows over the age of the
   oldest angle used (``(init_sigma_rate · age)²``, ``(init_sigma_speed · age)²``), and zero velocities.
2. *tracking*: every sweep predicts to its sync time and updates with its lit angles
   (:meth:`ErrorStateEKF.update_sweep`). Status "ok" while the 1-sigma pose is within the limits
   of :class:`EkfConfig`, fewer than two consecutive sweeps were rejected and ``confirm_sweeps``
   sweeps were accepted since the start, else "uncertain".
3. *lost*: ``lost_after`` consecutive rejected sweeps (the innovations say the state is wrong),
   a pose sigma beyond ``lost_factor`` times the limits, or time running backwards → status
   "lost" and back to 1 (the outputs keep coming, with status "lost", until a frame re-initialises).

Static detector (``zupt``): consecutive sweeps of the same station and axis differ by ``d`` on the
sensors lit in both; at rest ``d ~ N(0, 2 sigma² C)`` with ``C`` the correlation of Chen eq. (19), so
``T = d^T C^-1 d / (2 sigma²)`` is chi²(m). When the sum of ``T`` over the last ``zupt_window`` pairs is
below the chi² quantile ``1 - zupt_p`` the body is taken as static: no process noise and a
zero-velocity update per sweep.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from ..lighthouse import Station, to_sweep_angles
from ..units import RAD2DEG
from .ekf import EkfConfig, ErrorStateEKF, SweepUpdate, chi2_quantile
from .so3 import quat_to_rotvec

__all__ = ["FilterOutput", "TrackerCounters", "SweepTracker", "STATUSES", "pnp_pose_covariance"]

#: Output statuses: "ok" = tracking within the configured sigma limits.
STATUSES = ("ok", "uncertain", "lost")


@dataclass(frozen=True)
class FilterOutput:
    """The filter state after one sweep.

    t : s (the sweep's sync time); station, axis : of the sweep; status : one of :data:`STATUSES`;
    quaternion : (4,) ``[x, y, z, w]`` body-to-world attitude (``rotvec`` (3,) rad its rotation
    vector); translation : (3,) m — body position in the world (stations') frame;
    state_cov : (d, d) error-state covariance; ``pose_cov`` (6, 6) its ``(dphi rad, dp m)`` block,
    ``cov_rot_deg`` (3,) deg and ``cov_pos_m`` (3,) m the 1-sigma per world axis;
    used, rejected : angles of this sweep used / dropped by the gate; sweep_rejected : the sweep
    failed the NIS gate; nis, dof : its NIS and degrees of freedom; static : the static detector's
    verdict; event : "init" on the sweep that (re-)initialised the filter, else "";
    correction : (6,) pose correction applied by this sweep's update and prior_sigma : (6,) the
    pose 1-sigma before it (None without update).
    """

    t: float
    station: int
    axis: int
    status: str
    quaternion: np.ndarray
    translation: np.ndarray
    state_cov: np.ndarray
    used: int = 0
    rejected: int = 0
    sweep_rejected: bool = False
    nis: float = float("nan")
    dof: int = 0
    static: bool = False
    event: str = ""
    correction: np.ndarray | None = None
    prior_sigma: np.ndarray | None = None

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def rotvec(self) -> np.ndarray:
        """(3,) rad rotation vector of the attitude."""
        return quat_to_rotvec(self.quaternion)

    @property
    def pose_cov(self) -> np.ndarray:
        """(6, 6) covariance of ``(dphi rad, dp m)`` (from the full error-state covariance)."""
        i = np.r_[0:3, 6:9]
        return self.state_cov[np.ix_(i, i)]

    @property
    def cov_rot_deg(self) -> np.ndarray:
        """(3,) deg, 1-sigma attitude error per world axis."""
        return np.sqrt(np.diagonal(self.state_cov)[0:3]) * RAD2DEG

    @property
    def cov_pos_m(self) -> np.ndarray:
        """(3,) m, 1-sigma position error per world axis."""
        return np.sqrt(np.diagonal(self.state_cov)[6:9])

    def record(self) -> dict:
        """The JSON-lines object (``--filter ekf --json-lines``)."""
        return {"t": self.t, "status": self.status,
                "rotvec": [float(v) for v in self.rotvec], "translation": [float(v) for v in self.translation],
                "cov_rot_deg": [float(v) for v in self.cov_rot_deg], "cov_pos_m": [float(v) for v in self.cov_pos_m],
                "station": self.station, "axis": self.axis, "used": self.used, "rejected": self.rejected,
                "nis": None if not math.isfinite(self.nis) else self.nis, "dof": self.dof,
                "static": self.static, "event": self.event}


@dataclass
class TrackerCounters:
    """Running counts (sweeps and angles)."""

    sweeps: int = 0
    outputs: int = 0
    ok: int = 0
    inits: int = 0
    losts: int = 0
    angles_used: int = 0
    angles_rejected: int = 0
    sweeps_rejected: int = 0
    zupts: int = 0
    pnp_tries: int = 0

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def pnp_pose_covariance(jac, sigma: float, rho: float) -> np.ndarray:
    """Covariance (6, 6) of an unweighted least-squares pose from one frame (Chen eq. 18).

    jac : (m, 2, 6) per-sensor Jacobian of one station's X/Y angles, world perturbation;
    ``H = A^-1 J^T R J A^-1`` with ``A = J^T J`` and R of Chen eq. (19), times sigma².
    """
    from ..noise import angle_correlation

    J = np.asarray(jac, float).reshape(-1, 6)
    A = J.T @ J
    Ai = np.linalg.inv(A)
    M = J.T @ angle_correlation(J.shape[0] // 2, rho) @ J
    H = Ai @ M @ Ai * sigma ** 2
    return 0.5 * (H + H.T)


class SweepTracker:
    """Sweeps in, :class:`FilterOutput` out (see the module docstring).

    points_body : (n, 3) m; stations : list of :class:`Station` in the world frame (default one LH1
    station at the origin); config : :class:`EkfConfig`; model : optional forward model;
    init_max_residual_sigma : PnP starts whose RMS angle residual exceeds this many sigma are refused;
    init_window_s : s, oldest angle used for a PnP start (a failed start with the same lit set is
    retried after half of it, with fresh angles); confirm_sweeps : after a (re-)start the
    status stays "uncertain" until this many sweeps were accepted (a PnP start from a wrong basin
    or from mixed data is not reported as ok).
    """

    def __init__(self, points_body, stations=None, config: EkfConfig | None = None, model=None,
                 init_max_residual_sigma: float = 8.0, init_window_s: float = 0.1, confirm_sweeps: int = 4):
        self.config = config or EkfConfig()
        self.points_body = np.ascontiguousarray(points_body, float)
        self.n = self.points_body.shape[0]
        self.stations = list(stations) if stations else [Station()]
        self.ekf = ErrorStateEKF(self.points_body, self.stations, self.config, model)
        self.init_max_residual_sigma = float(init_max_residual_sigma)
        self.init_window_s = float(init_window_s)
        self.init_retry_s = 0.5 * float(init_window_s)
        self.confirm_sweeps = int(confirm_sweeps)
        self._confirm = 0
        self._ambiguous = 0
        self.counters = TrackerCounters()
        self._recent: dict = {}  # station -> (angles (n, 2), times (n, 2)) latest per sensor and axis
        self._tried: dict = {}  # station -> lit set of the last failed PnP start
        self._bad_run = 0
        self._lost = False
        self._last_same: dict = {}
        W = self.config.zupt_window
        self._static_T = deque(maxlen=W)
        self._static_m = deque(maxlen=W)
        self._static_q: dict = {}
        self.static = False

    # --------------------------------------------------------------------------- helpers
    def _station(self, s: int) -> Station:
        if not 0 <= s < len(self.stations):
            raise ValueError(f"sweep station {s}: the set-up has {len(self.stations)} station(s)")
        return self.stations[s]

    def _hit_offsets(self, st: Station, kind: str, ang: np.ndarray):
        if not self.config.hit_timing:
            return None
        omega = 2.0 * math.pi * st.rotor_rpm / 60.0
        return (ang + (math.pi if kind == "lh2" else 0.0)) / omega

    def _remember(self, s: int, axis: int, t: float, ang: np.ndarray) -> None:
        rec = self._recent.get(s)
        if rec is None:
            rec = (np.full((self.n, 2), np.nan), np.full((self.n, 2), -np.inf))
            self._recent[s] = rec
        hit = np.isfinite(ang)
        rec[0][hit, axis] = ang[hit]
        rec[1][hit, axis] = t

    def _try_init(self, s: int, t: float, st: Station) -> bool:
        """PnP on the recent angles of station ``s`` (see the module docstring); True when started."""
        from ..pnp import solve_pnp
        from ..status import AMBIGUOUS as STATUS_AMBIGUOUS

        rec = self._recent.get(s)
        if rec is None:
            return False
        ang, times = rec
        lit = np.all(times >= t - self.init_window_s, -1)
        if lit.sum() < 4:
            return False
        key = lit.tobytes()
        prev = self._tried.get(s)
        if prev is not None and prev[0] == key and t - prev[1] < self.init_retry_s:
            return False  # the same lit set failed moments ago: wait for new sensors or fresh angles
        self._tried[s] = (key, t)
        ang = ang.copy()
        # the start only (ideal angles); the updates go through the forward model
        ang[lit] = to_sweep_angles(ang[lit], st.kind, st.calibration)
        self.counters.pnp_tries += 1
        a = np.where(lit[:, None], ang, np.pi / 2)
        sol = solve_pnp(self.points_body, a[None], lit[None])
        Rs, ts, res = sol.rotation[0], sol.translation[0], sol.residual_rms[0]
        if sol.status[0] == STATUS_AMBIGUOUS and sol.alt_rotation is not None:
            # two poses fit equally well: start from each in turn; the innovations reject the wrong one
            self._ambiguous += 1
            if self._ambiguous % 2 == 0:
                Rs, ts, res = sol.alt_rotation[0], sol.alt_translation[0], sol.alt_residual_rms[0]
        elif not sol.success[0]:
            return False
        if not res <= self.init_max_residual_sigma * self.config.sigma_theta:
            return False
        R = st.rotation @ Rs
        p = st.rotation @ ts + st.translation
        Jm = self.ekf.model.jacobian(self.points_body[lit], R, p, st)
        c = self.config
        try:
            cov = pnp_pose_covariance(Jm, c.sigma_theta, c.rho) * c.init_inflation
        except np.linalg.LinAlgError:
            return False
        if not np.all(np.isfinite(cov)):
            return False
        age = t - float(times[lit].min())
        cov[0:3, 0:3] += np.eye(3) * (c.init_sigma_rate * age) ** 2
        cov[3:6, 3:6] += np.eye(3) * (c.init_sigma_speed * age) ** 2
        self.ekf.initialize(t, R, p, cov)
        self._confirm = self.confirm_sweeps
        self._lost = False
        self._bad_run = 0
        self._tried.clear()
        self.counters.inits += 1
        return True

    def _static_test(self, key, t, ang) -> None:
        c = self.config
        prev = self._last_same.get(key)
        self._last_same[key] = (t, ang)
        if prev is None:
            return
        d = ang - prev[1]
        d = d[np.isfinite(d)]
        m = d.size
        if m == 0:
            return
        rho = c.rho
        s = d.sum()
        T = (float(d @ d) - rho / (1.0 - rho + m * rho) * s * s) / ((1.0 - rho) * 2.0 * c.sigma_theta ** 2)
        self._static_T.append(T)
        self._static_m.append(m)
        if len(self._static_T) < c.zupt_window:
            self.static = False
            return
        dof = int(sum(self._static_m))
        q = self._static_q.get(dof)
        if q is None:
            q = chi2_quantile(1.0 - c.zupt_p, dof)
            self._static_q[dof] = q
        self.static = sum(self._static_T) <= q

    # --------------------------------------------------------------------------- main
    def push(self, sweep) -> FilterOutput | None:
        """Process one sweep; returns the filter state after it (None before the first init)."""
        c = self.config
        self.counters.sweeps += 1
        s = int(sweep.station)
        st = self._station(s)
        axis = int(sweep.axis)
        t = float(sweep.t)
        kind = getattr(sweep, "kind", st.kind) or st.kind
        ang = np.asarray(sweep.angles, float)
        if ang.shape != (self.n,):
            raise ValueError(f"sweep angles: expected shape ({self.n},), got {ang.shape}")
        ekf = self.ekf
        if ekf.initialized and t < ekf.t:  # time ran backwards (device reset): start over
            self._declare_lost()
            ekf.initialized = False
            self._recent.clear()
            self._last_same.clear()
            self._static_T.clear()
            self._static_m.clear()
        if c.zupt:
            self._static_test((s, axis), t, ang)
        event = ""
        if not ekf.initialized or self._lost:
            self._remember(s, axis, t, ang)
            if self._try_init(s, t, st):
                event = "init"
                self._recent.clear()
            elif not ekf.initialized:
                return None
        else:
            self._recent.clear()
        upd = None
        if event != "init":
            ekf.predict(t, process_noise=not (c.zupt and self.static))
            if not self._lost:
                idx = np.flatnonzero(np.isfinite(ang))
                if idx.size:
                    a = ang[idx]
                    upd = ekf.update_sweep(s, axis, idx, a, self._hit_offsets(st, kind, a))
                    self._account(upd)
                if c.zupt and self.static:
                    ekf.zero_velocity_update()
                    self.counters.zupts += 1
        return self._output(t, s, axis, upd, event)

    def _account(self, upd: SweepUpdate) -> None:
        cnt = self.counters
        cnt.angles_used += upd.used
        cnt.angles_rejected += upd.rejected
        if upd.sweep_rejected:
            cnt.sweeps_rejected += 1
            self._bad_run += 1
            if self._bad_run >= self.config.lost_after:
                self._declare_lost()
        elif upd.used:
            self._bad_run = 0
            self._confirm -= 1

    def _declare_lost(self) -> None:
        if not self._lost:
            self._lost = True
            self.counters.losts += 1
        self._bad_run = 0

    def _output(self, t, s, axis, upd: SweepUpdate | None, event: str) -> FilterOutput:
        c = self.config
        ekf = self.ekf
        P = ekf.P  # never modified in place by the filter: safe to hand out
        d = np.diagonal(P)
        big = max(math.sqrt(max(d[0], d[1], d[2])) * RAD2DEG / c.max_sigma_rot_deg,
                  math.sqrt(max(d[6], d[7], d[8])) / c.max_sigma_pos_m)
        if big > c.lost_factor and not self._lost:
            self._declare_lost()
        if self._lost:
            status = "lost"
        else:  # two consecutive rejected sweeps: the data no longer support the state
            status = "ok" if big <= 1.0 and self._bad_run < 2 and self._confirm <= 0 else "uncertain"
        cnt = self.counters
        cnt.outputs += 1
        cnt.ok += status == "ok"
        if upd is None:
            return FilterOutput(t, s, axis, status, ekf.q, ekf.p, P, static=self.static, event=event)
        return FilterOutput(t, s, axis, status, ekf.q, ekf.p, P, upd.used, upd.rejected, upd.sweep_rejected,
                            upd.nis, upd.dof, self.static, event, upd.correction, upd.prior_sigma)
