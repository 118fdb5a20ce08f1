"""Error-state (multiplicative) extended Kalman filter on SE(3) for per-sweep lighthouse updates.

State (docs/filter.md): nominal attitude as a unit quaternion ``q`` (``R(q)`` maps body to world,
``p_world = R p_body + p``), angular velocity ``w`` (rad/s, world axes: ``R(t + dt) = exp([w dt]x) R``),
position ``p`` (m, world) and velocity ``v`` (m/s); with the constant-acceleration model also the
angular acceleration ``alpha`` (rad/s²) and the linear acceleration ``a`` (m/s²). The error state is
``dx = [dphi, dw, dp, dv (, dalpha, da)]`` with the attitude error a left perturbation in the world
frame, ``R = exp([dphi]x) R(q)`` (Solà 2017, "Quaternion kinematics for the error-state Kalman
filter", §7 with the global-error variant of §7.3; Markley 2003 for the multiplicative update).

Motion model: constant velocity driven by white angular and linear acceleration of power spectral
densities ``psd_rot`` (rad²/s³) and ``psd_pos`` (m²/s³); the discrete process noise per axis is
``q [[dt³/3, dt²/2], [dt²/2, dt]]`` (Bar-Shalom, Li & Kirubarajan 2001, §6.2.2 eq. 6.2.2-12). With
``constant_acceleration`` the driving noise is white jerk of PSDs ``psd_jerk_rot`` (rad²/s⁵) and
``psd_jerk_pos`` (m²/s⁵) (ibid. §6.2.3 eq. 6.2.3-8).

Measurement: one rotor sweep of one station — the ``m`` angles of the lit sensors on that axis,
each at its own hit time ``t_sweep + delta_i`` — batched in a single update with the same-rotor
correlation of Chen eq. (19): ``R_meas = sigma² ((1 - rho) I + rho 1 1^T)``. The prediction of
angle ``i`` is the forward model at the pose moved to its hit time with the current velocity,
``h_i(exp([w delta_i]x) R, p + v delta_i) ≈ h_i(R, p) + J_rot,i w delta_i + J_pos,i v delta_i`` (first
order in the sub-sweep motion), so the row of ``H`` is ``[J_rot, delta J_rot, J_pos, delta J_pos]``;
with ``EkfConfig.hit_time_noise`` the motion the white acceleration adds over ``delta``
(constant-velocity model, process noise on) is in the innovation covariance, ``S = H P H^T + R_meas +
C(delta) * (psd_rot J_rot J_rot^T + psd_pos J_pos J_pos^T)`` (:func:`hit_time_covariance`; an LH2
plane is hit up to ~20 ms after its rotor's zero).
Gates: an angle whose normalised innovation squared ``y_i² / S_ii`` exceeds the chi²(1) quantile
``1 - gate_angle_p`` is dropped; then the sweep is rejected when its NIS ``y^T S^-1 y`` exceeds the
chi²(m) quantile ``1 - gate_sweep_p``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..lighthouse import Station
from ..noise import angle_correlation
from ..units import RAD2DEG, RHO_PAPER, SIGMA_THETA_PAPER
from .models import FORWARD_MODELS, ForwardModel
from .so3 import quat_from_matrix, quat_from_rotvec, quat_mul, quat_to_matrix, quat_to_rotvec

__all__ = ["EkfConfig", "SweepUpdate", "ErrorStateEKF", "chi2_quantile", "hit_time_covariance", "POSE_IDX"]

_TWO_PI = 2.0 * math.pi

#: indices of the pose ``(dphi rad, dp m)`` in the error state ``[dphi, dw, dp, dv, ...]`` (read-only)
POSE_IDX = np.r_[0:3, 6:9]
POSE_IDX.flags.writeable = False


@dataclass(frozen=True)
class EkfConfig:
    """Tuning of the filter (SI units throughout).

    motion : "adaptive" (default) — an interacting-multiple-model bank of constant-velocity filters
        whose PSDs span a resting to a swung / flying body (``imm_psd_rot``, ``imm_psd_pos``; per-sweep
        mode stay probability ``imm_stay``): the process noise follows the motion
        (:class:`layoutkit.filter.imm.ImmFilter`, compiled); "fixed" — one model with ``psd_rot`` /
        ``psd_pos`` (compiled; with ``constant_acceleration`` or ``zupt`` this numpy class).
    noise_scale_max, noise_scale_rate : adaptive mode: the angle noise variance is ``s sigma_theta²``
        with ``s`` in ``[1, noise_scale_max]`` matched to the innovations (``s <- s (1 + rate
        (NIS/dof - 1))``, each sweep's ratio capped at 10): a real station's model errors (calibration,
        sensor positions: 2-6 sigma at the deck on the Bitcraze logs) count as noise instead of
        starving the gates; ``noise_scale_max = 1`` keeps ``sigma_theta``.
    adaptive_rho : adaptive mode: the same-rotor angle correlation the bank's updates and gates
        assume (:attr:`update_rho`); None (default) = ``rho``. A real deck's angles are far less
        correlated than the paper's rotor (consecutive sweeps of the Bitcraze static LH2 logs:
        0.1-0.6, not 0.87 — the static detector's reason for rho = 0), and with 0.87 a difference
        between a sweep's angles counts ~8x in the NIS: on the hand-moved logs the noise scale sits
        at its cap. ``adaptive_rho = 0`` (with ``hit_time_noise``) brings it to 1-3 at rest, keeps
        ~5x more angles and loses track less often there, but moves the share of ok 100 ms
        intervals by -2..+3 points per log (studies/bitcraze_live, ``--filter-set``) and costs
        most ok outputs on data with the paper's correlation: not the default. ``rho`` itself
        always sets the one-station limit of ``ok_beats_one_station`` (the session's sigma/rho)
        and the starts' covariances.
    psd_rot : rad²/s³, PSD of the white angular acceleration (constant-velocity model, "fixed").
    psd_pos : m²/s³, PSD of the white linear acceleration ("fixed").
    constant_acceleration : add angular and linear acceleration states, driven by white jerk of
        PSDs ``psd_jerk_rot`` (rad²/s⁵) and ``psd_jerk_pos`` (m²/s⁵).
    sigma_theta : rad, 1-sigma angle noise; rho : same-rotor correlation (Chen eq. 19).
    gate_angle_p, gate_sweep_p : false-rejection probabilities of the per-angle and per-sweep
        chi² gates.
    hit_timing : model each angle at its own hit time (sync + angle / rotor rate); False = all
        angles of a sweep at the sync time (the simulator's model).
    hit_time_noise : the innovation covariance also holds the white acceleration of the motion
        model between the state time and the angles' hit times (:func:`hit_time_covariance`;
        constant velocity only): the prediction to the hit times (LH2: up to ~20 ms after the
        rotor's zero) is first order in the velocity, and without the term a fast-moving filter
        claims too small a 1-sigma (simulated 2.5 m/s swing: ok outputs up to 5.7 of their own
        1-sigma off, 3.2 with it; tests/test_filter_imm.py). On the Bitcraze hand-moved logs it
        keeps ~5x more angles, restarts less, and moves the ok share by -1.5..+2 points.
    init_sigma_rate : rad/s, init_sigma_speed : m/s — prior 1-sigma of the velocities at
        (re-)initialisation (they start at zero; the defaults admit a hand-swung or flying body:
        the first sweeps then determine the velocity); init_inflation : factor on the PnP pose
        covariance.
    max_sigma_rot_deg, max_sigma_pos_m : status "ok" only while every 1-sigma attitude component
        (deg) and position component (m) is below these, and every velocity component below
        ``max_sigma_speed`` (m/s: a filter that does not know its velocity is not tracking); a
        position above ``lost_factor`` times its limit counts as lost (an attitude left unobserved
        about one axis stays "uncertain").
    ok_beats_one_station : with two or more stations, "ok" also needs the position 1-sigma (root
        trace, m) below what the best single station would give at the filter's pose with every
        sensor lit (``PDOP_1 · sigma_theta``, Chen eq. 24; re-evaluated every 0.1 s of stream) —
        the joint windows' rule (``layoutkit.live.joint_stream.auto_sigma_limit``): a small deck's
        filter that knows its position no better than one station is not ok.
    lost_after : consecutive rejected sweeps after which the filter counts as lost (re-initialise).
    zupt : static detector + zero-velocity updates; zupt_window : sweeps per static test;
        zupt_p : false-alarm probability of the motion test; zupt_sigma_rate (rad/s),
        zupt_sigma_speed (m/s) : 1-sigma of the zero-velocity pseudo-measurement.
    model : key of :data:`layoutkit.filter.models.FORWARD_MODELS`.
    """

    psd_rot: float = 1e-6
    psd_pos: float = 1e-6
    motion: str = "adaptive"
    imm_psd_rot: tuple = (1e-6, 1e-3, 1.0, 1e3)
    imm_psd_pos: tuple = (1e-6, 1e-3, 1.0, 1e3)
    imm_stay: float = 0.999
    noise_scale_max: float = 100.0
    noise_scale_rate: float = 0.01
    adaptive_rho: float | None = None
    constant_acceleration: bool = False
    psd_jerk_rot: float = 1e-6
    psd_jerk_pos: float = 1e-6
    sigma_theta: float = SIGMA_THETA_PAPER
    rho: float = RHO_PAPER
    gate_angle_p: float = 1e-4
    gate_sweep_p: float = 1e-4
    hit_timing: bool = True
    hit_time_noise: bool = True
    init_sigma_rate: float = 6.0
    init_sigma_speed: float = 3.0
    init_inflation: float = 4.0
    max_sigma_rot_deg: float = 5.0
    max_sigma_speed: float = 1.0
    ok_beats_one_station: bool = True
    max_sigma_pos_m: float = 0.02
    lost_factor: float = 10.0
    lost_after: int = 6
    zupt: bool = False
    zupt_window: int = 60
    zupt_p: float = 0.01
    zupt_sigma_rate: float = 1e-7
    zupt_sigma_speed: float = 1e-7
    model: str = "station"

    def __post_init__(self):
        for name in ("psd_rot", "psd_pos", "psd_jerk_rot", "psd_jerk_pos"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name}: expected a PSD >= 0, got {v}")
        for name in ("sigma_theta", "init_sigma_rate", "init_sigma_speed", "init_inflation",
                     "max_sigma_rot_deg", "max_sigma_pos_m", "max_sigma_speed", "zupt_sigma_rate", "zupt_sigma_speed"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name}: expected a positive value, got {v}")
        if not 0.0 <= self.rho < 1.0:
            raise ValueError(f"rho: expected a value in [0, 1), got {self.rho}")
        if self.adaptive_rho is not None and not 0.0 <= self.adaptive_rho < 1.0:
            raise ValueError(f"adaptive_rho: expected None or a value in [0, 1), got {self.adaptive_rho}")
        for name in ("gate_angle_p", "gate_sweep_p", "zupt_p"):
            v = getattr(self, name)
            if not 0.0 < v < 1.0:
                raise ValueError(f"{name}: expected a probability in (0, 1), got {v}")
        if self.lost_after < 1 or self.zupt_window < 2 or self.lost_factor < 1:
            raise ValueError("lost_after >= 1, zupt_window >= 2 and lost_factor >= 1 expected")
        if self.motion not in ("adaptive", "fixed"):
            raise ValueError(f"motion: expected 'adaptive' or 'fixed', got {self.motion!r}")
        if self.motion == "adaptive" and (self.constant_acceleration or self.zupt):
            raise ValueError("constant_acceleration and zupt need motion 'fixed' (the adaptive bank is constant "
                             "velocity; its quietest model is the static case)")
        qr, qp = tuple(self.imm_psd_rot), tuple(self.imm_psd_pos)
        if not (len(qr) == len(qp) >= 1 and all(math.isfinite(v) and v >= 0 for v in qr + qp)):
            raise ValueError(f"imm_psd_rot, imm_psd_pos: expected equally long lists of PSDs >= 0, got {qr}, {qp}")
        object.__setattr__(self, "imm_psd_rot", qr)
        object.__setattr__(self, "imm_psd_pos", qp)
        if not (math.isfinite(self.noise_scale_max) and self.noise_scale_max >= 1.0
                and 0.0 <= self.noise_scale_rate < 1.0):
            raise ValueError("noise_scale_max >= 1 and noise_scale_rate in [0, 1) expected")
        if not 0.0 < self.imm_stay <= 1.0:
            raise ValueError(f"imm_stay: expected a probability in (0, 1], got {self.imm_stay}")
        if self.model not in FORWARD_MODELS:
            raise ValueError(f"model: expected one of {sorted(FORWARD_MODELS)}, got {self.model!r}")

    @property
    def update_rho(self) -> float:
        """The same-rotor correlation of the sweep updates: ``adaptive_rho`` in the adaptive mode
        (when set), else ``rho``."""
        return self.rho if self.motion == "fixed" or self.adaptive_rho is None else self.adaptive_rho

    @property
    def dim(self) -> int:
        """Error-state dimension: 12 (constant velocity) or 18 (constant acceleration)."""
        return 18 if self.constant_acceleration else 12


@dataclass(frozen=True, slots=True)
class SweepUpdate:
    """Outcome of one sweep update.

    used, rejected : angles used / dropped by the per-angle gate; sweep_rejected : the whole sweep
    failed the NIS gate (nothing applied); nis : normalised innovation squared of the used angles
    (NaN when none), dof : its degrees of freedom (= used); correction : (6,) applied pose
    correction ``(dphi rad, dp m)``; prior_sigma : (6,) 1-sigma of the pose before the update.
    """

    used: int
    rejected: int
    sweep_rejected: bool
    nis: float
    dof: int
    correction: np.ndarray
    prior_sigma: np.ndarray


def chi2_quantile(p: float, dof: int) -> float:
    """The ``p`` quantile of chi² with ``dof`` degrees of freedom (scipy)."""
    from scipy.stats import chi2

    return float(chi2.ppf(p, dof))


def start_covariance(config: EkfConfig, cov, dim: int) -> np.ndarray:
    """(dim, dim) start covariance of the error state ``(dphi, w, dp, v, ...)``: ``cov`` (6, 6) of
    ``(dphi, dp)`` with the config's velocity priors (``init_sigma_rate``, ``init_sigma_speed``), or
    ``cov`` (12, 12) of ``(dphi, w, dp, v)`` as given (e.g. a two-point start)."""
    cov = np.asarray(cov, float)
    P = np.zeros((dim, dim))
    if cov.shape == (12, 12):
        P[:12, :12] = 0.5 * (cov + cov.T)
        return P
    if cov.shape != (6, 6):
        raise ValueError(f"start covariance: expected (6, 6) or (12, 12), got {cov.shape}")
    P[np.ix_(POSE_IDX, POSE_IDX)] = cov
    P[3:6, 3:6] = np.eye(3) * config.init_sigma_rate ** 2
    P[9:12, 9:12] = np.eye(3) * config.init_sigma_speed ** 2
    return P


def hit_time_covariance(offsets) -> np.ndarray:
    """(m, m) s³, covariance factor of the motion a white acceleration of unit PSD adds between the
    state time and the hit times ``offsets`` (m,) s: ``x(d) = int_0^d (d - s) a(s) ds`` has
    ``Cov(x(da), x(db)) = lo² hi / 2 - lo³ / 6``, ``lo = min(|da|, |db|)``, ``hi = max`` (``d³ / 3``
    on the diagonal, the position term of Bar-Shalom, Li & Kirubarajan 2001 eq. 6.2.2-12), 0 for
    offsets on opposite sides of the state time. A sweep's angles are predicted at their hit times
    to first order in the velocity (LH2: 0-20 ms after the rotor's zero); the innovation covariance
    adds ``C * (psd_rot J_rot J_rot^T + psd_pos J_pos J_pos^T)`` so that a moving body's
    acceleration over those milliseconds is not taken for angle noise (the compiled
    :func:`layoutkit.filter._kernels_numba.hit_time_noise` is the same formula per pair)."""
    d = np.asarray(offsets, float)
    a, b = np.abs(d)[:, None], np.abs(d)[None, :]
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    return np.where(d[:, None] * d[None, :] > 0.0, lo * lo * hi / 2.0 - lo ** 3 / 6.0, 0.0)


def single_station_sigma(points_body, rotation, translation, stations, rho: float, sigma_theta: float,
                         jacobians=None) -> float:
    """m, the best single station's predicted 1-sigma position (root trace, ``PDOP_1 · sigma_theta``,
    Chen eq. 24) at the pose ``rotation (3, 3)``, ``translation (3,)`` m (world) with every sensor
    of ``points_body (n, 3)`` lit; inf when no station sees the layout. jacobians : optional (S, n,
    2, 6) every station's angle Jacobian at that pose (``ImmFilter.station_jacobians``, compiled),
    else :func:`layoutkit.dop.pose_dop` computes them."""
    from ..dop import dop_from_jacobian, pose_dop

    if jacobians is not None:
        d = np.asarray(dop_from_jacobian(np.asarray(jacobians, float)[:, None], rho=rho).pdop, float)
        d = d[np.isfinite(d)]
        return float(d.min()) * sigma_theta if d.size else math.inf

    S, n = len(stations), len(points_body)
    vis = np.zeros((S, S, n), bool)
    for k in range(S):
        vis[k, k] = True
    d = np.asarray(pose_dop(points_body, np.broadcast_to(rotation, (S, 3, 3)), np.broadcast_to(translation, (S, 3)),
                            rho=rho, visible=vis, stations=stations).pdop, float)
    d = d[np.isfinite(d)]
    return float(d.min()) * sigma_theta if d.size else math.inf


def two_point_start(a, b, max_speed: float, max_rate: float):
    """Velocity, rate and start covariance from two pose solves on disjoint angles (two-point
    differencing, Bar-Shalom, Li & Kirubarajan 2001 §5.5.3). ``a``, ``b`` = ``(t s, R (3, 3), p (3,)
    m, C (6, 6) of (dphi, dp), s)`` with ``s`` the standard deviation (s) of the solve's angles' hit
    times. Velocity ``(p_b - p_a) / dt`` and rate ``log(R_b R_a^T) / dt`` (world frame); each solve's
    covariance is widened by the motion over its hit-time spread (``(|v| s)²``, ``(|w| s)²``: a
    solve of a moving body mixes poses), then the state ``(dphi, w, dp, v)`` at b has covariance
    ``C_b`` (pose), ``(C_a + C_b) / dt²`` (velocities) and ``C_b / dt`` between them. Returns
    ``(v (3,), w (3,), P (12, 12))``, or None when ``dt <= 0`` or the implied speed or rate exceeds
    ``max_speed`` m/s / ``max_rate`` rad/s (a wrong solve)."""
    from scipy.spatial.transform import Rotation

    ta, Ra, pa, Ca, sa = a
    tb, Rb, pb, Cb, sb = b
    dt = tb - ta
    if not dt > 0:
        return None
    v = (np.asarray(pb, float) - pa) / dt
    w = Rotation.from_matrix(Rb @ np.asarray(Ra).T).as_rotvec() / dt
    if not (np.linalg.norm(v) <= max_speed and np.linalg.norm(w) <= max_rate):
        return None
    blur = np.r_[np.full(3, float(np.linalg.norm(w)) ** 2), np.full(3, float(np.linalg.norm(v)) ** 2)]
    Ca, Cb = Ca + np.diag(blur * sa ** 2), Cb + np.diag(blur * sb ** 2)
    P = np.zeros((12, 12))
    ip, iv = POSE_IDX, np.r_[3:6, 9:12]
    P[np.ix_(ip, ip)] = Cb
    P[np.ix_(iv, iv)] = (Ca + Cb) / dt ** 2
    P[np.ix_(ip, iv)] = Cb / dt
    P[np.ix_(iv, ip)] = Cb / dt
    return v, w, P


class PoseStateView:
    """The pose read-outs shared by :class:`ErrorStateEKF` and :class:`~layoutkit.filter.imm.ImmFilter`:
    a nominal attitude ``q`` (x, y, z, w) and an error-state covariance ``P`` with the attitude error
    at rows 0:3 and the position at 6:9."""

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) body-to-world rotation."""
        return quat_to_matrix(self.q)

    @property
    def rotvec(self) -> np.ndarray:
        """(3,) rad rotation vector of the attitude."""
        return quat_to_rotvec(self.q)

    def pose_sigma(self) -> np.ndarray:
        """(6,) 1-sigma of ``(dphi rad, dp m)`` (world axes)."""
        return np.sqrt(np.maximum(np.diagonal(self.P)[POSE_IDX], 0.0))

    def pose_covariance(self) -> np.ndarray:
        """(6, 6) covariance of ``(dphi rad, dp m)``."""
        return self.P[POSE_IDX][:, POSE_IDX]

    def sigma_deg_m(self):
        """1-sigma attitude (3,) deg and position (3,) m (the ``cov_rot_deg`` / ``cov_pos_m`` fields)."""
        s = self.pose_sigma()
        return s[:3] * RAD2DEG, s[3:]


class ErrorStateEKF(PoseStateView):
    """The filter state and its two operations, :meth:`predict` and :meth:`update_sweep`.

    points_body : (n, 3) m sensor positions; stations : list of :class:`Station` (world poses);
    config : :class:`EkfConfig`; model : a :class:`~layoutkit.filter.models.ForwardModel`
    (default ``FORWARD_MODELS[config.model]``). Not initialised until :meth:`initialize`.
    """

    def __init__(self, points_body, stations, config: EkfConfig | None = None, model: ForwardModel | None = None):
        self.config = config or EkfConfig()
        self.points_body = np.ascontiguousarray(points_body, float)
        self.stations = list(stations)
        self.model = model if model is not None else FORWARD_MODELS[self.config.model]
        self._noise_on = True  # the last predict carried process noise (also over the hit-time offsets)
        self._both = getattr(self.model, "angles_and_jacobian", None)
        self._rows = getattr(self.model, "sweep_rows", None)
        d = self.config.dim
        self.dim = d
        self.initialized = False
        self.t = float("nan")
        self.q = np.array([0.0, 0.0, 0.0, 1.0])
        self.w = np.zeros(3)
        self.p = np.zeros(3)
        self.v = np.zeros(3)
        self.alpha = np.zeros(3)
        self.a = np.zeros(3)
        self.P = np.eye(d)
        self._corr: dict = {}
        self._q1 = chi2_quantile(1.0 - self.config.gate_angle_p, 1)
        self._qm: dict = {}
        self._eye = np.eye(d)
        # constant-velocity process noise: Q = Q3 dt³/3 + Q2 dt²/2 + Q1 dt (per-axis blocks of psd)
        q3, q2, q1 = np.zeros((d, d)), np.zeros((d, d)), np.zeros((d, d))
        for q, i0, i1 in ((self.config.psd_rot, 0, 3), (self.config.psd_pos, 6, 9)):
            for k in range(3):
                q3[i0 + k, i0 + k] = q
                q2[i0 + k, i1 + k] = q2[i1 + k, i0 + k] = q
                q1[i1 + k, i1 + k] = q
        self._q_cv = (q3, q2, q1)
        # entries of F equal to dt (and dt²/2 with the CA model): attitude/rate, position/velocity, ...
        pairs = [(k, 3 + k) for k in range(3)] + [(6 + k, 9 + k) for k in range(3)]
        hpairs = []
        if self.config.constant_acceleration:
            pairs += [(3 + k, 12 + k) for k in range(3)] + [(9 + k, 15 + k) for k in range(3)]
            hpairs = [(k, 12 + k) for k in range(3)] + [(6 + k, 15 + k) for k in range(3)]
        self._dt_idx = tuple(np.array(pairs).T)
        self._h_idx = tuple(np.array(hpairs).T) if hpairs else None

    # ----------------------------------------------------------------------------- state (rotation,
    # rotvec, pose_sigma, pose_covariance, sigma_deg_m: PoseStateView)
    def initialize(self, t: float, rotation, position, pose_cov, velocity=None, rate=None) -> None:
        """Start (or restart) at time ``t`` s with pose ``(rotation (3, 3), position (3,) m)`` of
        covariance ``pose_cov (6, 6)`` (dphi, dp) and zero (or the given) velocities with the
        configured prior sigmas — or, with ``pose_cov`` (12, 12), the covariance of ``(dphi, w, dp,
        v)`` (:func:`start_covariance`)."""
        c = self.config
        self.t = float(t)
        self.q = quat_from_matrix(rotation)
        self.p = np.array(position, float)
        self.w = np.zeros(3) if rate is None else np.array(rate, float)
        self.v = np.zeros(3) if velocity is None else np.array(velocity, float)
        self.alpha = np.zeros(3)
        self.a = np.zeros(3)
        P = start_covariance(c, pose_cov, self.dim)
        if c.constant_acceleration:
            P[12:15, 12:15] = np.eye(3) * (c.init_sigma_rate / 0.1) ** 2
            P[15:18, 15:18] = np.eye(3) * (c.init_sigma_speed / 0.1) ** 2
        self.P = P
        self.initialized = True

    # ----------------------------------------------------------------------------- predict
    def predict(self, t: float, process_noise: bool = True) -> None:
        """Propagate the state to time ``t`` s (t >= the current time; earlier is a ValueError).

        process_noise : False while the static detector says the body is at rest.
        """
        dt = float(t) - self.t
        if dt < 0:
            raise ValueError(f"predict: time ran backwards ({t} < {self.t})")
        self._noise_on = bool(process_noise)  # also the motion between the state time and the hit times
        if dt == 0:
            return
        c = self.config
        d = self.dim
        ca = c.constant_acceleration
        phi = self.w * dt + (0.5 * dt * dt) * self.alpha if ca else self.w * dt
        dq = quat_from_rotvec(phi)
        self.q = quat_mul(dq, self.q)
        Phi = quat_to_matrix(dq)
        F = self._eye.copy()
        F[0:3, 0:3] = Phi
        F[self._dt_idx] = dt
        if ca:
            h = 0.5 * dt * dt
            F[self._h_idx] = h
            self.p = self.p + self.v * dt + self.a * h
            self.v = self.v + self.a * dt
            self.w = self.w + self.alpha * dt
        else:
            self.p = self.p + self.v * dt
        P = F @ self.P @ F.T
        if process_noise:
            if ca:
                for q, (i0, i1, i2) in ((c.psd_jerk_rot, (0, 3, 12)), (c.psd_jerk_pos, (6, 9, 15))):
                    blk = q * np.array([[dt ** 5 / 20, dt ** 4 / 8, dt ** 3 / 6],
                                        [dt ** 4 / 8, dt ** 3 / 3, dt ** 2 / 2],
                                        [dt ** 3 / 6, dt ** 2 / 2, dt]])
                    idx = (i0, i1, i2)
                    for r in range(3):
                        for s in range(3):
                            P[idx[r]:idx[r] + 3, idx[s]:idx[s] + 3] += np.eye(3) * blk[r, s]
            else:
                P += self._q_cv[0] * (dt ** 3 / 3.0) + self._q_cv[1] * (dt ** 2 / 2.0) + self._q_cv[2] * dt
        self.P = P
        self.t = float(t)

    # ----------------------------------------------------------------------------- update
    def _correlation(self, m: int) -> np.ndarray:
        """(m, m) correlation of m angles of one sweep: the same-axis block of Chen eq. (19)."""
        C = self._corr.get(m)
        if C is None:
            C = angle_correlation(m, self.config.update_rho)[0::2, 0::2] * self.config.sigma_theta ** 2
            self._corr[m] = C
        return C

    def _sweep_quantile(self, m: int) -> float:
        v = self._qm.get(m)
        if v is None:
            v = chi2_quantile(1.0 - self.config.gate_sweep_p, m)
            self._qm[m] = v
        return v

    def predict_angles(self, station: int, idx=None) -> np.ndarray:
        """Predicted (k, 2) angles of sensors ``idx`` (default all) from ``station`` at the current state."""
        P = self.points_body if idx is None else self.points_body[idx]
        return self.model(P, self.rotation, self.p, self.stations[station])

    def update_sweep(self, station: int, axis: int, sensors, angles, hit_offsets=None) -> SweepUpdate:
        """One sweep update at the current time (call :meth:`predict` to the sweep time first).

        station : index into ``stations``; axis : 0 / 1 (LH1 X / Y, LH2 plane 0 / 1);
        sensors : (m,) int sensor indices; angles : (m,) rad measured; hit_offsets : (m,) s, hit
        time minus the state time (None: all zero).
        """
        c = self.config
        sensors = np.asarray(sensors, np.intp)
        z = np.asarray(angles, float)
        m = sensors.size
        sig0 = np.sqrt(np.diagonal(self.P)[POSE_IDX])
        if m == 0:
            return SweepUpdate(0, 0, False, float("nan"), 0, np.zeros(6), sig0)
        st = self.stations[station]
        R = quat_to_matrix(self.q)
        b = self.points_body[sensors]
        if self._rows is not None:
            zp, rows = self._rows(b, R, self.p, st, axis)
            Jr, Jt = rows[:, 0:3], rows[:, 3:6]
        else:
            if self._both is not None:
                ang, J = self._both(b, R, self.p, st)
            else:
                ang, J = self.model(b, R, self.p, st), self.model.jacobian(b, R, self.p, st)
            Jr, Jt, zp = J[:, axis, 0:3], J[:, axis, 3:6], ang[:, axis]
        H = np.zeros((m, self.dim))
        H[:, 0:3] = Jr
        H[:, 6:9] = Jt
        if hit_offsets is not None:
            dl = np.asarray(hit_offsets, float)
            zp = zp + dl * (Jr @ self.w + Jt @ self.v)
            H[:, 3:6] = Jr * dl[:, None]
            H[:, 9:12] = Jt * dl[:, None]
            if c.constant_acceleration:
                h2 = 0.5 * dl * dl
                zp = zp + h2 * (Jr @ self.alpha + Jt @ self.a)
                H[:, 12:15] = Jr * h2[:, None]
                H[:, 15:18] = Jt * h2[:, None]
        y = np.remainder(z - zp + math.pi, _TWO_PI) - math.pi
        HP = H @ self.P
        S = HP @ H.T + self._correlation(m)
        if hit_offsets is not None and c.hit_time_noise and not c.constant_acceleration \
                and self._noise_on:
            # the white acceleration between the state time and the hit times (hit_time_covariance)
            S = S + hit_time_covariance(dl) * (c.psd_rot * (Jr @ Jr.T) + c.psd_pos * (Jt @ Jt.T))
        keep = y * y <= self._q1 * np.diagonal(S)
        k = int(np.count_nonzero(keep))
        rejected = m - k
        if k == 0:
            return SweepUpdate(0, rejected, True, float("nan"), 0, np.zeros(6), sig0)
        if rejected:
            y, HP = y[keep], HP[keep]
            S = S[np.ix_(keep, keep)]
        try:
            X = np.linalg.solve(S, np.column_stack([y, HP]))
        except np.linalg.LinAlgError:
            return SweepUpdate(0, m, True, float("nan"), 0, np.zeros(6), sig0)
        nis = float(y @ X[:, 0])
        if not nis <= self._sweep_quantile(k):
            return SweepUpdate(0, rejected, True, nis, k, np.zeros(6), sig0)
        dx = HP.T @ X[:, 0]
        P = self.P - HP.T @ X[:, 1:]
        self.P = 0.5 * (P + P.T)
        self._inject(dx)
        return SweepUpdate(k, rejected, False, nis, k, np.concatenate([dx[0:3], dx[6:9]]), sig0)

    def zero_velocity_update(self) -> None:
        """Zero-velocity pseudo-measurement ``w = 0, v = 0`` (and accelerations 0 with the CA model)
        with 1-sigma ``zupt_sigma_rate`` / ``zupt_sigma_speed`` (static detector)."""
        c = self.config
        idx = [3, 4, 5, 9, 10, 11]
        r = [c.zupt_sigma_rate ** 2] * 3 + [c.zupt_sigma_speed ** 2] * 3
        z = np.concatenate([self.w, self.v])
        if c.constant_acceleration:
            idx += list(range(12, 18))
            r += [c.zupt_sigma_rate ** 2] * 3 + [c.zupt_sigma_speed ** 2] * 3
            z = np.concatenate([z, self.alpha, self.a])
        HP = self.P[idx]
        S = HP[:, idx] + np.diag(r)
        X = np.linalg.solve(S, np.column_stack([-z, HP]))
        dx = HP.T @ X[:, 0]
        P = self.P - HP.T @ X[:, 1:]
        self.P = 0.5 * (P + P.T)
        self._inject(dx)

    def _inject(self, dx) -> None:
        """Add the error-state estimate to the nominal state (multiplicative for the attitude) and
        reset the error to zero (the reset Jacobian ``I - [dphi/2]x`` is ~I for the tiny per-sweep
        corrections and is omitted, Solà 2017 §7.2)."""
        self.q = quat_mul(quat_from_rotvec(dx[0:3]), self.q)
        self.w = self.w + dx[3:6]
        self.p = self.p + dx[6:9]
        self.v = self.v + dx[9:12]
        if self.config.constant_acceleration:
            self.alpha = self.alpha + dx[12:15]
            self.a = self.a + dx[15:18]
