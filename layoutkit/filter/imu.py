"""IMU-aided error-state Kalman filter: gyro and accelerometer drive the pose, every lighthouse sweep
corrects it (issue 26 item 4).

Nominal state (Solà 2017, "Quaternion kinematics for the error-state Kalman filter", §5, with the
*local* attitude error of §5.3.3): the IMU frame's attitude ``R`` (IMU → world, ``p_world = R p_imu +
p``), position ``p`` (m, world), velocity ``v`` (m/s, world), accelerometer bias ``b_a`` (m/s²) and gyro
bias ``b_g`` (rad/s), both in the IMU frame; gravity ``g`` (m/s², world) is fixed at the start.
Error state ``dx = [dp, dv, dtheta, db_a, db_g]`` (15) with ``R_true = R exp([dtheta]x)``.

Propagation with a sample ``(f, w)`` (specific force m/s², angular rate rad/s, IMU frame) held for
``dt`` (Solà eqs. 260, 269-270):

    a = R (f - b_a) + g;   p += v dt + a dt²/2;   v += a dt;   R = R exp([(w - b_g) dt]x)
    F: dp' = dp + dv dt;  dv' = dv - R [f - b_a]x dtheta dt - R db_a dt;
       dtheta' = exp([(w - b_g) dt]x)^T dtheta - db_g dt;  biases constant
    Q: acc_noise² dt (dv), gyro_noise² dt (dtheta), acc_bias_walk² dt, gyro_bias_walk² dt

A sample whose accelerometer clipped (``saturated``) is propagated with ``saturated_acc_noise``
instead: the filter then leans on the light.

Update with one sweep of one station (the lit sensors' angles on that axis / LH2 plane, in the
station's convention, through its calibrated forward model :func:`layoutkit.lighthouse.measure_jacobian`):
``h_i = angle(R_s^T (R P_i + p - T_s))``, rows ``H_i = (d angle / d p_s) R_s^T [I, 0, -R [P_i]x, 0, 0]``,
noise ``sigma_theta² I``. The sweep is rejected when its NIS exceeds the chi²(m) quantile ``1 - gate_p``;
otherwise the Joseph-form update and the error injection (the reset Jacobian is taken as I).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import rotvec_to_matrix, skew
from ..lighthouse import measure_jacobian

__all__ = ["ImuFilterConfig", "ImuEskf", "run_imu_filter"]


@dataclass(frozen=True)
class ImuFilterConfig:
    """Tuning (SI units). gyro_noise rad/s/√Hz, acc_noise m/s²/√Hz: white sensor noise densities;
    gyro_bias_walk rad/s²/√Hz, acc_bias_walk m/s³/√Hz: bias random walks; saturated_acc_noise:
    density used for a clipped accelerometer sample; sigma_theta rad: 1-sigma angle error (noise and
    the station/layout model's own error); gate_p: false-rejection probability of the per-sweep
    chi² gate; init_sigma_*: prior 1-sigma at the start (rad, m, m/s, m/s², rad/s); min_sensors:
    fewest angles for an update."""

    gyro_noise: float = 0.005
    acc_noise: float = 0.1
    gyro_bias_walk: float = 1e-3
    acc_bias_walk: float = 0.01
    saturated_acc_noise: float = 30.0
    sigma_theta: float = 2e-4
    gate_p: float = 1e-6
    init_sigma_rot: float = 0.01
    init_sigma_pos: float = 0.01
    init_sigma_vel: float = 0.1
    init_sigma_acc_bias: float = 0.2
    init_sigma_gyro_bias: float = 0.02
    min_sensors: int = 2

    def __post_init__(self):
        for k in ("gyro_noise", "acc_noise", "gyro_bias_walk", "acc_bias_walk", "saturated_acc_noise",
                  "sigma_theta", "init_sigma_rot", "init_sigma_pos", "init_sigma_vel", "init_sigma_acc_bias",
                  "init_sigma_gyro_bias"):
            v = getattr(self, k)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"ImuFilterConfig.{k}: expected a positive number, got {v!r}")
        if not 0.0 < self.gate_p < 1.0:
            raise ValueError(f"ImuFilterConfig.gate_p: expected 0 < p < 1, got {self.gate_p!r}")


class ImuEskf:
    """The filter of the module docstring (one body; poses of the IMU frame in the world)."""

    def __init__(self, R, p, g, config: ImuFilterConfig, v=None):
        c = config
        self.c = c
        self.R = np.asarray(R, float).copy()
        self.p = np.asarray(p, float).copy()
        self.v = np.zeros(3) if v is None else np.asarray(v, float).copy()
        self.ba = np.zeros(3)
        self.bg = np.zeros(3)
        self.g = np.asarray(g, float)
        self.P = np.diag(np.repeat([c.init_sigma_pos, c.init_sigma_vel, c.init_sigma_rot, c.init_sigma_acc_bias,
                                    c.init_sigma_gyro_bias], 3) ** 2)

    def propagate(self, f, w, dt: float, saturated: bool = False) -> None:
        """Advance by ``dt`` s with specific force ``f`` (m/s²) and rate ``w`` (rad/s), IMU frame."""
        if dt <= 0:
            return
        c = self.c
        fa = np.asarray(f, float) - self.ba
        wg = np.asarray(w, float) - self.bg
        a = self.R @ fa + self.g
        E = rotvec_to_matrix(wg * dt)
        F = np.eye(15)
        F[0:3, 3:6] = np.eye(3) * dt
        F[3:6, 6:9] = -self.R @ skew(fa) * dt
        F[3:6, 9:12] = -self.R * dt
        F[6:9, 6:9] = E.T
        F[6:9, 12:15] = -np.eye(3) * dt
        qa = (c.saturated_acc_noise if saturated else c.acc_noise) ** 2 * dt
        Q = np.diag(np.concatenate([np.zeros(3), np.full(3, qa), np.full(3, c.gyro_noise ** 2 * dt),
                                    np.full(3, c.acc_bias_walk ** 2 * dt), np.full(3, c.gyro_bias_walk ** 2 * dt)]))
        self.p = self.p + self.v * dt + 0.5 * a * dt * dt
        self.v = self.v + a * dt
        self.R = self.R @ E
        self.P = F @ self.P @ F.T + Q

    def predict_angles(self, station, axis: int, points_imu, jacobian: bool = True):
        """Predicted angles ``(m,)`` of ``points_imu (m, 3)`` on ``axis`` of ``station`` and ``H (m, 15)``."""
        pw = points_imu @ self.R.T + self.p
        ps = (pw - station.translation) @ station.rotation
        a, dp, _ = measure_jacobian(ps[None], station.calibration, station.kind, jacobian=jacobian)
        h = a[0, :, axis]
        if not jacobian:
            return h, None
        dw = dp[0, :, axis] @ station.rotation.T                     # d angle / d p_world (m, 3)
        H = np.zeros((len(h), 15))
        H[:, 0:3] = dw
        H[:, 6:9] = -np.einsum("mi,ij,mjk->mk", dw, self.R, skew(points_imu))
        return h, H

    def update(self, station, axis: int, angles, points_imu) -> dict:
        """One sweep: ``angles (m,)`` rad (station convention) of the sensors at ``points_imu (m, 3)`` (IMU
        frame). Returns ``{"accepted", "nis", "m", "prior_rms", "posterior_rms"}`` (residual RMS, rad)."""
        from scipy.stats import chi2

        z = np.asarray(angles, float)
        m = z.size
        h, H = self.predict_angles(station, axis, points_imu)
        y = (z - h + np.pi) % (2 * np.pi) - np.pi
        out = {"accepted": False, "nis": float("nan"), "m": int(m), "prior_rms": float(np.sqrt(np.mean(y * y))),
               "posterior_rms": float("nan")}
        if m < self.c.min_sensors:
            return out
        S = H @ self.P @ H.T + self.c.sigma_theta ** 2 * np.eye(m)
        try:
            Si = np.linalg.inv(S)
        except np.linalg.LinAlgError:
            return out
        nis = float(y @ Si @ y)
        out["nis"] = nis
        if nis > chi2.ppf(1.0 - self.c.gate_p, m):
            return out
        K = self.P @ H.T @ Si
        dx = K @ y
        IKH = np.eye(15) - K @ H
        self.P = IKH @ self.P @ IKH.T + self.c.sigma_theta ** 2 * K @ K.T
        self.p = self.p + dx[0:3]
        self.v = self.v + dx[3:6]
        self.R = self.R @ rotvec_to_matrix(dx[6:9])
        self.ba = self.ba + dx[9:12]
        self.bg = self.bg + dx[12:15]
        h2, _ = self.predict_angles(station, axis, points_imu, jacobian=False)
        y2 = (z - h2 + np.pi) % (2 * np.pi) - np.pi
        out.update(accepted=True, posterior_rms=float(np.sqrt(np.mean(y2 * y2))))
        return out


def run_imu_filter(imu_t, acc, gyro, saturated, sweep_t, sweep_station, sweep_axis, sweep_angles, stations,
                   points_imu, init, config: ImuFilterConfig = ImuFilterConfig(), *, restarts=None,
                   max_rejected: int = 10, restart_sigma_vel: float = 2.0) -> dict:
    """Run :class:`ImuEskf` over time-ordered IMU samples and sweeps.

    imu_t (N,) s, acc (N, 3) m/s², gyro (N, 3) rad/s (IMU frame), saturated (N,) bool; sweep_t (K,) s,
    sweep_station (K,) station index, sweep_axis (K,) axis / plane, sweep_angles (K, n) rad in the
    station's convention (NaN = not hit); stations; points_imu (n, 3) m sensors in the IMU frame;
    init = ``(t0, R (3, 3), p (3,), g (3,))``: the start (IMU frame in the world) and gravity (world).
    Each sample is held until the next (zero-order hold); a sweep propagates to its time, records the
    prior pose and residual, then updates. Sweeps before ``t0`` are skipped.
    restarts : optional ``(t (W,), R (W, 3, 3), p (W, 3))`` poses of the IMU frame from the lighthouse
    alone (e.g. joint windows); after ``max_rejected`` sweeps rejected in a row the filter is lost and
    restarts from the first of them after that time (velocity 0 with 1-sigma ``restart_sigma_vel``,
    biases kept); the sweeps in between are flagged ``lost``.
    Returns per sweep: ``t``, ``accepted`` (bool), ``prior_rms``, ``posterior_rms`` (rad), ``nis``,
    ``rotation (K, 3, 3)`` / ``position (K, 3)`` / ``velocity (K, 3)`` (posterior; prior where rejected),
    and ``counts``.
    """
    t0, R0, p0, g = init
    f = ImuEskf(R0, p0, g, config)
    K = len(sweep_t)
    out = {"t": np.asarray(sweep_t, float), "accepted": np.zeros(K, bool), "prior_rms": np.full(K, np.nan),
           "posterior_rms": np.full(K, np.nan), "nis": np.full(K, np.nan), "rotation": np.full((K, 3, 3), np.nan),
           "position": np.full((K, 3), np.nan), "velocity": np.full((K, 3), np.nan)}
    out["lost"] = np.zeros(K, bool)
    imu_t = np.asarray(imu_t, float)
    j = int(np.searchsorted(imu_t, t0, side="right")) - 1      # the sample in force at t0
    bad_run, n_restart, lost_since = 0, 0, None
    t_now = float(t0)
    cur = (acc[max(j, 0)], gyro[max(j, 0)], bool(saturated[max(j, 0)]))
    for k in np.argsort(sweep_t, kind="stable"):
        tk = float(sweep_t[k])
        if tk < t0:
            continue
        while j + 1 < imu_t.size and imu_t[j + 1] <= tk:      # samples up to the sweep
            f.propagate(cur[0], cur[1], imu_t[j + 1] - t_now, cur[2])
            t_now = imu_t[j + 1]
            j += 1
            cur = (acc[j], gyro[j], bool(saturated[j]))
        f.propagate(cur[0], cur[1], tk - t_now, cur[2])
        t_now = tk
        if lost_since is not None and restarts is not None:    # lost: restart from the lighthouse alone
            q = int(np.searchsorted(restarts[0], lost_since))
            if q < len(restarts[0]) and restarts[0][q] <= tk:
                P_keep = f.P[9:15, 9:15].copy()
                f2 = ImuEskf(restarts[1][q], restarts[2][q], f.g, config)
                f2.ba, f2.bg = f.ba, f.bg
                f2.P[3:6, 3:6] = np.eye(3) * restart_sigma_vel ** 2
                f2.P[9:15, 9:15] = P_keep
                f, lost_since, bad_run = f2, None, 0
                n_restart += 1
        if lost_since is not None:
            out["lost"][k] = True
            continue
        lit = np.flatnonzero(np.isfinite(sweep_angles[k]))
        r = f.update(stations[int(sweep_station[k])], int(sweep_axis[k]), sweep_angles[k][lit], points_imu[lit])
        if np.isfinite(r["nis"]):
            bad_run = 0 if r["accepted"] else bad_run + 1
        if bad_run >= max_rejected and restarts is not None:
            lost_since = tk
        out["accepted"][k] = r["accepted"]
        out["prior_rms"][k], out["posterior_rms"][k], out["nis"][k] = r["prior_rms"], r["posterior_rms"], r["nis"]
        out["rotation"][k], out["position"][k], out["velocity"][k] = f.R, f.p, f.v
    out["counts"] = {"sweeps": int(K), "accepted": int(out["accepted"].sum()),
                     "rejected": int(np.sum(np.isfinite(out["nis"]) & ~out["accepted"])),
                     "lost": int(out["lost"].sum()), "restarts": int(n_restart)}
    return out
