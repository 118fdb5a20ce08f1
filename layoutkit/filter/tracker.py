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
   a pose sigma beyond ``lost_factor`` times the limits, or time running backwards for
   ``lost_after`` sweeps in a row (a device reset; one late sweep is dropped) → status
   "lost" and back to 1 (the outputs keep coming, with status "lost", until a frame re-initialises).

Static detector (``zupt``; always on in the adaptive mode, where it holds the bank in its quietest
model at rest, :meth:`layoutkit.filter.imm.ImmFilter.hold_static`, with the robust rule of
:meth:`SweepTracker._static_test`): consecutive sweeps of the same station and axis differ by ``d`` on the
sensors lit in both; at rest ``d ~ N(0, 2 sigma² C)`` with ``C`` the correlation of Chen eq. (19), so
``T = d^T C^-1 d / (2 sigma²)`` is chi²(m). When the sum of ``T`` over the last ``zupt_window`` pairs is
below the chi² quantile ``1 - zupt_p`` the body is taken as static: no process noise and a
zero-velocity update per sweep.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from statistics import median

import numpy as np

from ..lighthouse import Station, hit_offset, to_sweep_angles
from ..units import RAD2DEG
from .ekf import POSE_IDX, EkfConfig, ErrorStateEKF, SweepUpdate, chi2_quantile, single_station_sigma, two_point_start
from .so3 import quat_to_matrix, quat_to_rotvec, rotvec_floats

__all__ = ["FilterOutput", "TrackerCounters", "SweepTracker", "STATUSES", "pnp_pose_covariance", "joint_pose_covariance"]

#: Output statuses: "ok" = tracking within the configured sigma limits.
STATUSES = ("ok", "uncertain", "lost")


@dataclass(frozen=True, slots=True)
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
    pose 1-sigma before it (None without update); smoothed : the pose and covariance are the offline
    smoother's (:mod:`layoutkit.filter.smoother`: the sweeps after ``t`` used too; the JSON line then
    carries ``"smoothed": true``).
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
    smoothed: bool = False

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
        return self.state_cov[np.ix_(POSE_IDX, POSE_IDX)]

    @property
    def cov_rot_deg(self) -> np.ndarray:
        """(3,) deg, 1-sigma attitude error per world axis."""
        return np.sqrt(np.diagonal(self.state_cov)[0:3]) * RAD2DEG

    @property
    def cov_pos_m(self) -> np.ndarray:
        """(3,) m, 1-sigma position error per world axis."""
        return np.sqrt(np.diagonal(self.state_cov)[6:9])

    def record(self) -> dict:
        """The JSON-lines object (``--filter ekf --json-lines``; the properties' values, without their arrays;
        written by :func:`layoutkit.filter.jsonline.json_line`, byte-identical to ``json.dumps`` of it)."""
        sd = np.sqrt(np.diagonal(self.state_cov)[POSE_IDX]).tolist()
        return {"t": self.t, "status": self.status,
                "rotvec": rotvec_floats(self.quaternion), "translation": np.asarray(self.translation, float).tolist(),
                "cov_rot_deg": [sd[0] * RAD2DEG, sd[1] * RAD2DEG, sd[2] * RAD2DEG], "cov_pos_m": sd[3:],
                "station": self.station, "axis": self.axis, "used": self.used, "rejected": self.rejected,
                "nis": None if not math.isfinite(self.nis) else self.nis, "dof": self.dof,
                "static": self.static, "event": self.event} | ({"smoothed": True} if self.smoothed else {})


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
    sweeps_late: int = 0

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def joint_pose_covariance(jacs, sigma: float, rho: float) -> np.ndarray:
    """Covariance (6, 6) of an unweighted least-squares pose over several stations: the sandwich
    ``A^-1 (sum_k J_k^T R_k J_k) A^-1``, ``A = sum_k J_k^T J_k``, each station's angles correlated as
    Chen eq. (19) within its own rotor only. jacs : per station (m_k, 2, 6), world perturbation."""
    from ..noise import angle_correlation

    A = np.zeros((6, 6))
    M = np.zeros((6, 6))
    for jac in jacs:
        J = np.asarray(jac, float).reshape(-1, 6)
        A += J.T @ J
        M += J.T @ angle_correlation(J.shape[0] // 2, rho) @ J
    Ai = np.linalg.inv(A)
    H = Ai @ M @ Ai * sigma ** 2
    return 0.5 * (H + H.T)


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
        if self.config.motion == "fixed" and (self.config.constant_acceleration or self.config.zupt or model is not None):
            self.ekf = ErrorStateEKF(self.points_body, self.stations, self.config, model)
        else:  # the compiled estimator: the adaptive bank, or one constant-velocity model
            from .imm import ImmFilter

            self.ekf = ImmFilter(self.points_body, self.stations, self.config)
        self.init_max_residual_sigma, self.init_window_s = float(init_max_residual_sigma), float(init_window_s)
        self.init_retry_s = 0.5 * float(init_window_s)
        self.reorder_s = 0.05  # s, sweeps older than the filter by at most this are applied late, not a reset
        # s, oldest angle of a multi-station start: about one rotation of every station (a moving body
        # has moved little since; the single-station start waits up to init_window_s for 4 sensors)
        self.joint_init_window_s = min(self.init_window_s, 0.025)
        self.confirm_sweeps = int(confirm_sweeps)
        self._confirm = self._ambiguous = 0
        self._amb = None  # (station, start R) of an ambiguous PnP start: not ok until told apart
        self.counters = TrackerCounters()
        self._recent: dict = {}  # station -> (angles (n, 2), times (n, 2)) latest per sensor and axis
        self._tried: dict = {}  # station -> lit set of the last failed PnP start
        self._waiting_since = None  # when the tracker began waiting for a start (several stations)
        self._first = None  # (t, mean angle time, R, p, cov) of a joint start's first solve
        self._bad_run = self._late_run = 0  # sweeps in a row: rejected; older than reorder_s
        self._bad_by_station: dict = {}
        self._lost = False
        self._last_same: dict = {}
        W = self.config.zupt_window
        self._static_T = deque(maxlen=W)
        self._static_m = deque(maxlen=W)
        self._static_per = deque(maxlen=min(W, 20))  # T / m of the latest pairs (the adaptive rule)
        self._static_q: dict = {}
        self.static = False
        # the adaptive bank takes the static detector's verdict (ImmFilter.hold_static) over the last
        # 20 pairs of sweeps (~0.1 s of two LH2 stations): a start settles at rest quickly
        self.static_window = min(self.config.zupt_window, 20)
        self._hold = hasattr(self.ekf, "hold_static") and self.config.motion == "adaptive"
        self._own_offsets = hasattr(self.ekf, "propagate")  # the compiled bank: hit times from its rotor rate
        self._one_station = (-math.inf, math.inf)  # (t evaluated, m): ok_beats_one_station's limit
        c = self.config  # per-sweep constants, looked up once (the adaptive static rule's 2 sigma², rho = 0)
        self._static_on, self._static_den = bool(c.zupt or self._hold), 1.0 * 2.0 * c.sigma_theta ** 2
        self._one_station_check = bool(c.ok_beats_one_station and len(self.stations) >= 2)

    # --------------------------------------------------------------------------- helpers
    def _station(self, s: int) -> Station:
        if not 0 <= s < len(self.stations):
            raise ValueError(f"sweep station {s}: the set-up has {len(self.stations)} station(s)")
        return self.stations[s]

    def _hit_offsets(self, st: Station, kind: str, ang: np.ndarray, axis: int = 0):
        """:func:`layoutkit.lighthouse.hit_offset` of each angle, or None when the config's ``hit_timing`` is
        off."""
        if not self.config.hit_timing:
            return None
        return hit_offset(st, kind, ang, axis)

    def _remember(self, s: int, axis: int, t: float, ang: np.ndarray) -> None:
        rec = self._recent.get(s)
        if rec is None:
            rec = (np.full((self.n, 2), np.nan), np.full((self.n, 2), -np.inf))
            self._recent[s] = rec
        hit = np.isfinite(ang)
        rec[0][hit, axis] = ang[hit]
        rec[1][hit, axis] = t

    def _try_joint_init(self, t: float) -> bool:
        """A start from every station's recent angles at once (:func:`layoutkit.joint.solve_joint`
        through each station's forward model): with two or more stations a small body's range is
        fixed by the stations' baseline, where one station alone leaves it centimetres uncertain
        (and the other stations' first sweeps would then be rejected). Needs >= 2 stations with
        >= 2 sensors lit on both axes and one with >= 4 (the solve's start); True when started."""
        from ..joint import solve_joint

        S = len(self.stations)
        ang = np.full((S, self.n, 2), np.nan)
        lits = np.zeros((S, self.n), bool)
        for k, rec in self._recent.items():
            if 0 <= k < S:
                lit = np.all(rec[1] >= t - self.joint_init_window_s, -1)
                ang[k][lit], lits[k] = rec[0][lit], lit
        per = lits.sum(1)
        if (per >= 2).sum() < 2 or per.max() < 4:
            return False
        first = self._first
        if first is not None and t - first[0] > self.init_window_s:
            first = self._first = None  # too old to difference with: start over
        if first is not None and t - first[0] < self.joint_init_window_s:
            return False  # the second solve uses fresh angles (no angle in both)
        key = lits.tobytes()
        prev = self._tried.get("joint")
        if prev is not None and prev[0] == key and t - prev[1] < self.init_retry_s:
            return False
        self.counters.pnp_tries += 1
        sol = solve_joint(self.points_body, ang[None], stations=self.stations)
        c = self.config
        if not sol.success[0] or not sol.residual_rms[0] <= self.init_max_residual_sigma * c.sigma_theta:
            self._tried["joint"] = (key, t)
            return False
        R, p = np.asarray(sol.rotation[0]), np.asarray(sol.translation[0])
        try:
            cov = joint_pose_covariance([self.ekf.model.jacobian(self.points_body[lits[k]], R, p, self.stations[k])
                                         for k in range(S) if lits[k].any()], c.sigma_theta, c.rho) * c.init_inflation
        except np.linalg.LinAlgError:
            cov = np.full((6, 6), np.nan)
        if not np.all(np.isfinite(cov)):
            self._tried["joint"] = (key, t)
            return False
        times = np.concatenate([self._hit_times(k, lits[k]) for k in range(S) if lits[k].any()])
        # the solve's time: the mean hit time of its angles; their spread says how much a motion blurs it
        tm, spread = float(times.mean()), float(times.std())
        noise = (float(sol.residual_rms[0]) / c.sigma_theta) ** 2
        if first is None:
            self._first = (t, tm, R, p, cov, spread)
            return False
        return self._start_two_point(first, (t, tm, R, p, cov, spread), noise)

    def _hit_times(self, k: int, lit) -> np.ndarray:
        """(2 m,) s, hit times of the remembered angles of station ``k``'s sensors ``lit`` (sweep
        time + :meth:`_hit_offsets`)."""
        ang, times = self._recent[k][0][lit], self._recent[k][1][lit]
        st = self.stations[k]
        out = times.copy()
        for axis in (0, 1):
            offs = self._hit_offsets(st, st.kind, ang[:, axis], axis)
            if offs is not None:
                out[:, axis] += offs
        return out.ravel()

    def _start_two_point(self, a, b, noise_scale) -> bool:
        """Start from two joint solves on disjoint angles (:func:`~layoutkit.filter.ekf.two_point_start`)
        at solve b's time; an implied speed beyond 3x the velocity prior keeps b as the first."""
        c = self.config
        _, ta, Ra, pa, Ca, sa = a
        t, tb, Rb, pb, Cb, sb = b
        st = two_point_start((ta, Ra, pa, Ca, sa), (tb, Rb, pb, Cb, sb), 3 * c.init_sigma_speed, 3 * c.init_sigma_rate)
        if st is None:
            self._first = b
            return False
        v, w, P = st
        self._start(tb, Rb, pb, P, 0.0, noise_scale, velocity=v, rate=w)
        return True

    def _start(self, t, R, p, cov, age, noise_scale=None, velocity=None, rate=None) -> None:
        """Initialise the filter at ``t``: ``cov`` (6, 6) pose covariance (velocity priors of the
        config, inflated by the motion they allow over ``age`` s), or (12, 12) the whole state's
        (with the given ``velocity``/``rate``)."""
        c = self.config
        if cov.shape == (6, 6):
            cov[0:3, 0:3] += np.eye(3) * (c.init_sigma_rate * age) ** 2
            cov[3:6, 3:6] += np.eye(3) * (c.init_sigma_speed * age) ** 2
        kw = {"noise_scale": noise_scale} if noise_scale is not None and hasattr(self.ekf, "hold_static") else {}
        self.ekf.initialize(t, R, p, cov, velocity=velocity, rate=rate, **kw)
        self._first = None
        self._one_station = (-math.inf, math.inf)
        self._amb = None
        self._waiting_since = None
        self._confirm = self.confirm_sweeps
        self._lost = False
        self._bad_run = 0
        self._bad_by_station.clear()
        self._tried.clear()
        self.counters.inits += 1

    def _try_init(self, s: int, t: float, st: Station) -> bool:
        """A start from all stations' recent angles (:meth:`_try_joint_init`), else PnP on the recent
        angles of station ``s`` (see the module docstring); True when started."""
        from ..pnp import solve_pnp
        from ..status import AMBIGUOUS as STATUS_AMBIGUOUS

        if len(self.stations) >= 2:
            if self._try_joint_init(t):
                return True
            if self._waiting_since is None:
                self._waiting_since = t
            if t - self._waiting_since < self.init_window_s:
                return False  # give the other stations one init window to be seen before starting from one
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
        self._start(t, R, p, cov, t - float(times[lit].min()))
        if sol.status[0] == STATUS_AMBIGUOUS and sol.alt_rotation is not None:
            self._amb = (s, R)
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
        fixed = c.motion == "fixed"
        if fixed:
            rho, s = c.rho, d.sum()
            T = (float(d @ d) - rho / (1.0 - rho + m * rho) * s * s) / ((1.0 - rho) * 2.0 * c.sigma_theta ** 2)
        else:  # adaptive: rho = 0 (a real rotor's correlation is not the paper's; 2 sigma² per difference holds)
            T = float(d @ d) / self._static_den  # the rho term is exactly +0 here
        self._static_T.append(T)
        self._static_m.append(m)
        (per := self._static_per).append(T / m)
        if not fixed and len(per) >= self.static_window:
            # robust form for the adaptive bank: at rest the median per-dof statistic of the window is
            # ~1 (up to 4 allows sigma_theta half the real noise), a single decoding glitch does not
            # move the median, and three consecutive large pairs (a motion starting) end rest at once
            # statistics.median: numpy's definition, without numpy's per-call overhead (every sweep)
            self.static = bool(median(per) <= 4.0 and not (per[-1] > 9.0 and per[-2] > 9.0 and per[-3] > 9.0))
            return
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
        """Process one sweep; returns the filter state after it (None before the first init and for
        a sweep more than ``reorder_s`` older than the filter: dropped, ``counters.sweeps_late``)."""
        c = self.config
        self.counters.sweeps += 1
        s, stations = int(sweep.station), self.stations
        st = stations[s] if 0 <= s < len(stations) else self._station(s)  # (_station raises)
        axis = int(sweep.axis)
        t = float(sweep.t)
        ang = np.asarray(sweep.angles, float)
        if ang.shape != (self.n,):
            raise ValueError(f"sweep angles: expected shape ({self.n},), got {ang.shape}")
        ekf, late = self.ekf, 0.0
        if ekf.initialized and t < ekf.t:
            if ekf.t - t <= self.reorder_s:
                # sweeps of different stations reach the decoder slightly out of time order (a rotation's
                # time is its zero, the sweep is complete only when the plane has passed): applied at the
                # filter's time with their hit times moved back
                late, t = t - ekf.t, ekf.t
            else:  # too old to apply (the decoder holds a lone light plane until the channel's next block,
                # up to ~1 s): dropped; lost_after such sweeps in a row are a device reset: start over
                self._late_run += 1
                if self._late_run < c.lost_after:
                    self.counters.sweeps_late += 1
                    return None
                self._late_run = 0
                self._declare_lost()
                ekf.initialized = False
                self._first = None
                for kept in (self._recent, self._last_same, self._static_T, self._static_m, self._static_per):
                    kept.clear()
        self._late_run = 0
        if self._static_on:
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
            if self._hold:
                ekf.hold_static(self.static)
            ekf.predict(t, process_noise=not (c.zupt and self.static))
            if not self._lost:
                idx = np.isfinite(ang).nonzero()[0]
                if idx.size:
                    a = ang[idx]
                    if self._own_offsets:  # the compiled bank ignores hit offsets (ImmFilter.update_sweep)
                        upd = ekf.update_sweep(s, axis, idx, a, None, late)
                    else:
                        offs = self._hit_offsets(st, getattr(sweep, "kind", st.kind) or st.kind, a, axis)
                        upd = ekf.update_sweep(s, axis, idx, a, (0.0 if offs is None else offs) + late if late else offs)
                    self._account(upd, s)
                    if self._amb is not None and upd.used >= 2 and not upd.sweep_rejected:
                        self._resolve_ambiguity(s)
                elif self._own_offsets:
                    ekf.propagate()
                if c.zupt and self.static:
                    ekf.zero_velocity_update()
                    self.counters.zupts += 1
        return self._output(t, s, axis, upd, event)

    def _account(self, upd: SweepUpdate, s: int = 0) -> None:
        """Counters; lost after ``lost_after`` rejected sweeps in a row, overall or of one station
        (a state that one station's sweeps keep refusing is wrong although the other station's
        interleaved sweeps agree with it — e.g. the mirrored pose of a planar one-station start)."""
        cnt = self.counters
        cnt.angles_used += upd.used
        cnt.angles_rejected += upd.rejected
        if upd.sweep_rejected:
            cnt.sweeps_rejected += 1
            self._bad_run += 1
            self._bad_by_station[s] = self._bad_by_station.get(s, 0) + 1
            if max(self._bad_run, self._bad_by_station[s]) >= self.config.lost_after:
                self._declare_lost()
        elif upd.used:
            self._bad_run = 0
            self._bad_by_station[s] = 0
            self._confirm -= 1

    def _resolve_ambiguity(self, s: int) -> None:
        """An ambiguous start is settled by a sweep of another station accepted, or by the body
        turning more than 20 deg from the start pose with its sweeps accepted (the two planar poses
        mirror about the line of sight: a turn makes their angles differ, the gates reject the
        wrong one)."""
        s0, R0 = self._amb
        if s != s0:
            self._amb = None
            return
        dR = quat_to_matrix(self.ekf.q) @ R0.T
        if math.degrees(math.acos(min(max((np.trace(dR) - 1.0) / 2.0, -1.0), 1.0))) > 20.0:
            self._amb = None

    def _declare_lost(self) -> None:
        if not self._lost:
            self._lost = True
            self.counters.losts += 1
        self._bad_run = 0
        self._bad_by_station.clear()

    def _one_station_limit(self, t: float) -> float:
        """m, ``PDOP_1 · sigma_theta`` of the best single station at the filter's pose, every sensor lit
        (:attr:`EkfConfig.ok_beats_one_station`); re-evaluated after 0.1 s of stream time or a (re)start."""
        t0, lim = self._one_station
        if abs(t - t0) <= 0.1:
            return lim
        R, jac = quat_to_matrix(self.ekf.q), getattr(self.ekf, "station_jacobians", None)
        lim = single_station_sigma(self.points_body, R, self.ekf.p, self.stations, self.config.rho,
                                   self.config.sigma_theta, None if jac is None else jac(R, self.ekf.p))
        self._one_station = (t, lim)
        return lim

    def _output(self, t, s, axis, upd: SweepUpdate | None, event: str) -> FilterOutput:
        c = self.config
        ekf = self.ekf
        P = ekf.P  # never modified in place by the filter: safe to hand out
        d = P.diagonal().tolist()
        big_pos = math.sqrt(max(d[6], d[7], d[8])) / c.max_sigma_pos_m
        big = max(math.sqrt(max(d[0], d[1], d[2])) * RAD2DEG / c.max_sigma_rot_deg, big_pos)
        # lost when the position is beyond recovery; an attitude the sweeps leave unobserved about one
        # axis (2-3 sensors lit) is uncertain, not lost (the innovations say when the state is wrong)
        if big_pos > c.lost_factor and not self._lost:
            self._declare_lost()
        if self._lost:
            status = "lost"
        else:  # two consecutive rejected sweeps: the data no longer support the state
            # ok also needs the velocity known (a start's 3 m/s prior lets the pose swing for a few sweeps)
            slow_known = math.sqrt(max(d[9], d[10], d[11])) <= c.max_sigma_speed
            status = "ok" if big <= 1.0 and slow_known and self._bad_run < 2 and self._confirm <= 0 else "uncertain"
            if status == "ok" and self._amb is not None:
                status = "uncertain"  # a planar two-fold start not yet told apart
            if status == "ok" and self._one_station_check and math.sqrt(d[6] + d[7] + d[8]) > self._one_station_limit(t):
                status = "uncertain"
        cnt = self.counters
        cnt.outputs += 1
        cnt.ok += status == "ok"
        if upd is None:
            return FilterOutput(t, s, axis, status, ekf.q, ekf.p, P, static=self.static, event=event)
        return FilterOutput(t, s, axis, status, ekf.q, ekf.p, P, upd.used, upd.rejected, upd.sweep_rejected,
                            upd.nis, upd.dof, self.static, event, upd.correction, upd.prior_sigma)
