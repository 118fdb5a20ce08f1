"""The tracking filter's fast, adaptive estimator: an interacting-multiple-model (IMM) bank of
constant-velocity error-state EKFs, compiled with numba.

Why several models: a deck at rest and a deck swung by hand or flown need process noises ~10⁹
apart (a white-acceleration PSD of ~1e-6 m²/s³ holds a resting deck to its noise floor; a hand
swing at 2–4 m/s with tens of m/s² needs ~1e2). One fixed value either starves the gates in motion
(the innovations of a too-stiff model exceed them: ~90 % of the angles rejected on the Crazyflie
move logs) or lets a resting pose wander. The IMM (Blom & Bar-Shalom 1988; Bar-Shalom, Li &
Kirubarajan 2001, §11.6) runs ``r`` models whose PSDs span that range, mixes them before every
sweep with the mode transition matrix, updates each with the sweep and re-weights them by their
likelihoods — the process noise follows the motion, nothing is tuned per log. The output is the
probability-weighted mixture (state and covariance with its spread term).

Each model is exactly :class:`layoutkit.filter.ekf.ErrorStateEKF` with the constant-velocity model
(the same state, error state, left attitude perturbation, Chen eq. 19 correlation, first-order
sub-sweep motion, chi² gates); with one model (``EkfConfig.motion == "fixed"``) this class is that
filter compiled (``tests/test_filter_imm.py`` checks both against each other on the same sweeps).
Gates: an angle is kept when it passes the per-angle gate in at least one model; a sweep is
rejected only when every model's NIS refuses it — the most agile model decides what counts as an
outlier, so a fast motion never starves the gates while a reflection no model can explain is still
dropped.

Hit times: LH1 angle ``theta`` is hit ``theta / omega`` after the sync; LH2 plane ``k`` angle ``alpha``
``(alpha + pi -/+ pi/3) / omega`` after the rotor zero (the decoder's ``a0 = off0 2 pi / P - pi + pi/3``,
``a1 = off1 2 pi / P - pi - pi/3``; the pipeline's ``AngleFrame.t_axes``).
"""
from __future__ import annotations

import math

import numpy as np

from ..rotations import matrix_to_quaternion
from .ekf import EkfConfig, PoseStateView, SweepUpdate, start_covariance, chi2_quantile
from .models import FORWARD_MODELS

__all__ = ["ImmFilter"]


def _kernels():
    from . import _kernels_numba  # compiled on first use (cached on disk)

    return _kernels_numba


class ImmFilter(PoseStateView):
    """The IMM bank (module docstring) behind :class:`layoutkit.filter.tracker.SweepTracker`, with
    :class:`~layoutkit.filter.ekf.ErrorStateEKF`'s interface (``initialize``, ``predict``,
    ``update_sweep``, ``q``/``w``/``p``/``v``/``P`` of the combined state, ``pose_sigma``).

    points_body : (n, 3) m; stations : list of :class:`~layoutkit.lighthouse.Station` (world poses,
    kinds, calibrations); config : :class:`EkfConfig` — ``motion`` "adaptive" (the bank of
    ``imm_psd_rot`` / ``imm_psd_pos``, per-sweep mode stay probability ``imm_stay``) or "fixed" (one
    model with ``psd_rot`` / ``psd_pos``); ``model`` "station" (each station's calibration) or "plain".
    """

    def __init__(self, points_body, stations, config: EkfConfig | None = None):
        c = self.config = config or EkfConfig()
        if c.constant_acceleration:
            raise ValueError("ImmFilter: constant-velocity models only (use ErrorStateEKF for constant_acceleration)")
        self._k = K = _kernels()
        self.points_body = np.ascontiguousarray(points_body, float)
        self.stations = list(stations)
        self.model = FORWARD_MODELS[c.model]
        self.dim = 12
        if c.motion == "adaptive":
            qr, qp = np.asarray(c.imm_psd_rot, float), np.asarray(c.imm_psd_pos, float)
        else:
            qr, qp = np.array([c.psd_rot]), np.array([c.psd_pos])
        r = len(qr)
        self.Pi = np.full((r, r), (1.0 - c.imm_stay) / max(r - 1, 1))
        np.fill_diagonal(self.Pi, c.imm_stay if r > 1 else 1.0)
        self.M = np.column_stack([np.full(r, 1.0 / r), qr, qp])   # mu, psd_rot, psd_pos per model
        self.X = np.tile([0.0, 0.0, 0.0, 1.0] + [0.0] * 9, (r, 1))   # q, w, p, v per model
        self.Pm = np.tile(np.eye(12), (r, 1, 1))
        self._out = np.zeros(K.OUT_SIZE)
        self._out[K.OUT_STATE + 3] = 1.0
        self._out[K.OUT_P:K.OUT_P + 144] = np.eye(12).ravel()
        self.initialized = False
        self.t = float("nan")
        self._t_model = float("nan")
        # per station: the parameter vector of the compiled step (calibration, pose, kind, rotor rate)
        self._par = []
        for st in self.stations:
            cal = getattr(st, "calibration", None) if c.model == "station" else None
            par = np.zeros((2, K.PAR_SIZE))
            for axis in (0, 1):
                v = par[axis]
                v[K.PAR_SIGMA2], v[K.PAR_RHO] = c.sigma_theta ** 2, c.update_rho
                v[K.PAR_Q1] = chi2_quantile(1.0 - c.gate_angle_p, 1)
                v[K.PAR_OMEGA] = 2.0 * math.pi * st.rotor_rpm / 60.0 if c.hit_timing else math.inf
                v[K.PAR_LH2] = float(st.kind == "lh2")
                v[K.PAR_AXIS] = axis
                v[K.PAR_CORRECTED] = float(cal is not None and cal.gib_argument == "corrected")
                v[K.PAR_MIX] = 1.0
                v[K.PAR_HIT_NOISE] = float(c.hit_time_noise)
                if cal is not None:
                    v[K.PAR_CAL:K.PAR_CAL + 7] = cal.params[axis]
                v[K.PAR_RS:K.PAR_RS + 9] = np.asarray(st.rotation, float).ravel()
                v[K.PAR_TS:K.PAR_TS + 3] = np.asarray(st.translation, float)
            self._par.append(par)
        n = self.points_body.shape[0]
        self._qm = np.array([np.inf] + [chi2_quantile(1.0 - c.gate_sweep_p, k) for k in range(1, n + 1)])
        # the bank's quietest model (the PSD columns of M never change)
        self._quiet = int(np.argmin(self.M[:, 1] + self.M[:, 2]))
        self._frozen = False  # mirrors PAR_FREEZE of every parameter vector (hold_static)
        self.noise_scale = 1.0
        self._adapt = c.motion == "adaptive" and c.noise_scale_max > 1.0 and c.noise_scale_rate > 0.0
        # per-sweep constants (read once per sweep: looked up here, not through config / the kernel module)
        self._sigma2 = c.sigma_theta ** 2
        self._rate, self._scale_max = c.noise_scale_rate, c.noise_scale_max
        self._sl_q = slice(K.OUT_STATE, K.OUT_STATE + 4)
        self._sl_p = slice(K.OUT_STATE + 7, K.OUT_STATE + 10)
        self._sl_P = slice(K.OUT_P, K.OUT_P + 144)
        self._sl_sig = slice(K.OUT_SIG, K.OUT_SIG + 6)
        self._i_dt = K.PAR_SWEEP_DT
        self._step = K.imm_step
        self._view()

    def _view(self) -> None:
        """The combined state as arrays (views of the last output vector; a new vector per sweep):
        ``q``, ``p``, ``P`` here (read every sweep), ``w``, ``v`` when asked for."""
        o = self._out
        self.q = o[self._sl_q]
        self.p = o[self._sl_p]
        self.P = o[self._sl_P].reshape(12, 12)

    @property
    def w(self) -> np.ndarray:
        """(3,) rad/s, the combined angular rate (a view of the last output vector)."""
        return self._out[self._k.OUT_STATE + 4:self._k.OUT_STATE + 7]

    @property
    def v(self) -> np.ndarray:
        """(3,) m/s, the combined velocity (a view of the last output vector)."""
        return self._out[self._k.OUT_STATE + 10:self._k.OUT_STATE + 13]

    # ----------------------------------------------------------------------------- state (rotation,
    # rotvec, pose_sigma, pose_covariance, sigma_deg_m of the combined state: PoseStateView)

    def initialize(self, t: float, rotation, position, pose_cov, velocity=None, rate=None,
                   noise_scale: float | None = None) -> None:
        """(Re)start every model at time ``t`` with the pose, its covariance ``pose_cov`` (6, 6)
        (dphi, dp), zero (or the given) velocities with the configured prior sigmas — or, with
        ``pose_cov`` (12, 12), the whole state's covariance (dphi, w, dp, v); equal mode
        probabilities. noise_scale : the angle-noise scale to start from (adaptive mode; e.g. the
        start solve's residual in sigma, squared: the model errors it saw)."""
        P = start_covariance(self.config, pose_cov, 12)
        x = np.concatenate([matrix_to_quaternion(rotation), np.zeros(3) if rate is None else rate,
                            np.asarray(position, float), np.zeros(3) if velocity is None else velocity])
        self.X[:] = x
        self.Pm[:] = P
        self.M[:, 0] = 1.0 / len(self.M)
        out = np.zeros(self._k.OUT_SIZE)
        out[self._k.OUT_STATE:self._k.OUT_STATE + 13] = x
        out[self._k.OUT_P:self._k.OUT_P + 144] = P.ravel()
        self._out = out
        self._view()
        self.t = self._t_model = float(t)
        self.initialized = True
        if self._adapt and noise_scale is not None and math.isfinite(noise_scale):
            self._set_noise(max(self.noise_scale, min(max(noise_scale, 1.0), self.config.noise_scale_max)))

    def predict(self, t: float, process_noise: bool = True) -> None:
        """Move the filter's time to ``t`` (the models are propagated with the next update, after
        the mixing step). ValueError when time runs backwards."""
        if t < self.t:
            raise ValueError(f"predict: time ran backwards ({t} < {self.t})")
        self.t = float(t)

    def update_sweep(self, station: int, axis: int, sensors, angles, hit_offsets=None,
                     sweep_offset: float = 0.0) -> SweepUpdate:
        """One sweep at the filter's time (after :meth:`predict`): mix, predict every model, gate,
        update, re-weight, combine (:func:`layoutkit.filter._kernels_numba.imm_step`). ``hit_offsets``
        is ignored (the kernel derives each angle's hit time from the station's rotor rate);
        ``sweep_offset`` (s, <= 0): the sweep's time minus the filter's (a sweep slightly out of order)."""
        o = self._sweep(station, axis, np.asarray(sensors, np.int64), np.asarray(angles, float), sweep_offset)
        sig0 = o[self._sl_sig]  # the pose 1-sigma before the step (the kernel's)
        used, rejected, swr, nis = o[:4].tolist()
        used, rejected = int(used), int(rejected)
        if self._adapt:
            self._match_noise(used or len(sensors), nis, swr)
        if swr or used == 0:
            return SweepUpdate(0, rejected, True, nis, 0, np.zeros(6), sig0)
        return SweepUpdate(used, rejected, False, nis, used, o[4:10], sig0)

    def _match_noise(self, dof: int, nis: float, rejected: bool) -> None:
        """The angle-noise scale follows the innovations (EkfConfig ``noise_scale_*``): a sweep whose
        every angle the gates refused counts with the cap (evidence the noise is too small)."""
        r = 10.0 if (rejected and not math.isfinite(nis)) else min(nis / max(dof, 1), 10.0) if math.isfinite(nis) else None
        if r is None:
            return
        self._set_noise(min(max(self.noise_scale * (1.0 + self._rate * (r - 1.0)), 1.0), self._scale_max))

    def _set_noise(self, s: float) -> None:
        if s != self.noise_scale:
            self.noise_scale = s
            v = s * self._sigma2
            i = self._k.PAR_SIGMA2
            for par in self._par:
                par[0, i] = par[1, i] = v

    def _sweep(self, station, axis, idx, z, sweep_offset=0.0):
        """mix + predict to ``self.t`` + update with ``z`` (idx int64, z float arrays) + combine, in one
        compiled call."""
        par = self._par[station][axis]
        par[0] = self._t_model
        par[1] = self.t
        par[self._i_dt] = sweep_offset
        out = self._out.copy()
        self._step(self.X, self.Pm, self.M, self.Pi, self.points_body, idx, z, par, self._qm, out)
        self._out = out
        self._view()
        self._t_model = self.t
        return out

    def zero_velocity_update(self) -> None:  # the bank's low-noise model is the static case
        raise ValueError("ImmFilter: no zero-velocity updates (the static case is the bank's quietest model)")

    def hold_static(self, static: bool) -> None:
        """The static detector's verdict (:class:`~layoutkit.filter.tracker.SweepTracker`): at rest
        the bank is held in its quietest model (probability 1, not re-weighted by the sweeps — a
        set-up's model errors would otherwise look like motion to the agile models and pull the pose
        sweep by sweep); in motion the likelihoods decide again."""
        was = self._frozen
        if static == was and not static:
            return  # in motion and staying so: nothing to change (called every sweep)
        if static != was:
            self._frozen = static = bool(static)
            for par in self._par:
                par[:, self._k.PAR_FREEZE] = float(static)
        if static and len(self.M) > 1:
            if not was:  # entering rest: every model continues from the bank's output (no jump)
                K = self._k
                self.X[:] = self._out[K.OUT_STATE:K.OUT_STATE + 13]
                self.Pm[:] = self._out[K.OUT_P:K.OUT_P + 144].reshape(12, 12)
            self.M[:, 0] = 0.0
            self.M[self._quiet, 0] = 1.0

    def station_jacobians(self, rotation, position) -> np.ndarray:
        """(S, n, 2, 6) d angle / d (left world rotation rad, world position m) of every sensor, axis
        and station at the body pose ``rotation (3, 3)``, ``position (3,)`` m — the compiled forward
        model of the updates (:func:`layoutkit.filter._kernels_numba.sweep_rows`), the rows of
        :func:`layoutkit.dop.pose_dop`'s Jacobian."""
        K = self._k
        n = self.points_body.shape[0]
        idx = np.arange(n, dtype=np.int64)
        R, p = np.ascontiguousarray(rotation, float), np.ascontiguousarray(position, float)
        out, z, rows = np.empty((len(self._par), n, 2, 6)), np.empty(n), np.empty((n, 6))
        for s, par in enumerate(self._par):
            for axis in (0, 1):
                v = par[axis]
                K.sweep_rows(self.points_body, idx, R, p, v[K.PAR_RS:K.PAR_RS + 9].reshape(3, 3).copy(),
                             v[K.PAR_TS:K.PAR_TS + 3].copy(), v[K.PAR_LH2] > 0.5, axis, v[K.PAR_CAL:K.PAR_CAL + 7].copy(),
                             v[K.PAR_CORRECTED] > 0.5, z, rows)
                out[s, :, axis] = rows
        return out

    def propagate(self) -> None:
        """Bring the models to the filter's time without a measurement (mix + predict)."""
        if self.t > self._t_model:
            self._sweep(0, 0, np.zeros(0, np.int64), np.zeros(0))

    @property
    def mode_probabilities(self) -> np.ndarray:
        """(r,) the models' current probabilities (order of ``imm_psd_*``)."""
        return self.M[:, 0].copy()
