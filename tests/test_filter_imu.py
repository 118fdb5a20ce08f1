"""The IMU-aided error-state filter (layoutkit.filter.imu). Proof by simulation against an analytic
trajectory: gyro and specific force computed in closed form from the motion, sweeps from the forward
model at their own times. The filter's pose follows the truth to a fraction of a millimetre at
1.3 m/s, and the pose it predicts for each sweep before seeing it (IMU + earlier sweeps) fits that
sweep's angles at the noise, where the previous pose held still misses them by the motion."""
import numpy as np
import pytest

from _calib_sim import STATION_POSITIONS, sphere_layout
from layoutkit.filter.imu import ImuFilterConfig, run_imu_filter
from layoutkit.geometry import rotvec_to_matrix
from layoutkit.lighthouse import measure
from layoutkit.simulate import stations_looking_at

G = np.array([0.0, 0.0, -9.80665])
A, F = 0.1, 2.0                       # 0.1 m at 2 Hz: up to 1.26 m/s, 15.8 m/s²
TH, F2 = 0.3, 1.0                     # +-0.3 rad about a tilted axis at 1 Hz
U = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])


def truth(t):
    w = 2 * np.pi * F
    p = np.array([0.0, 0.0, A * np.sin(w * t)])
    v = np.array([0.0, 0.0, A * w * np.cos(w * t)])
    a = np.array([0.0, 0.0, -A * w * w * np.sin(w * t)])
    w2 = 2 * np.pi * F2
    th, thd = TH * np.sin(w2 * t), TH * w2 * np.cos(w2 * t)
    R = rotvec_to_matrix(th * U)
    return R, p, v, a, R.T @ (thd * U)          # body rate = R^T omega_world (fixed axis)


def simulate(rng, sigma=2e-5, gyro_noise=0.002, acc_noise=0.02, duration=2.0):
    st = stations_looking_at(STATION_POSITIONS, (0, 0, 0), kind="lh1")
    P, _ = sphere_layout(rng, 16)
    ti = np.arange(0.0, duration, 1e-3)
    acc, gyro = [], []
    for t in ti:
        R, p, v, a, wb = truth(t)
        acc.append(R.T @ (a - G) + rng.normal(0, acc_noise, 3))
        gyro.append(wb + rng.normal(0, gyro_noise, 3))
    # sweeps: station 0 x, station 1 x, station 0 y, station 1 y, every 1/120 s
    ts = np.arange(0.01, duration - 0.01, 1 / 120)
    s_st = np.arange(ts.size) % 2
    s_ax = (np.arange(ts.size) // 2) % 2
    ang = np.full((ts.size, P.shape[0]), np.nan)
    for k, t in enumerate(ts):
        R, p, *_ = truth(t)
        s = st[s_st[k]]
        ps = (P @ R.T + p - s.translation) @ s.rotation
        a = measure(ps[None], None, "lh1")[0, :, s_ax[k]]
        ang[k] = a + rng.normal(0, sigma, a.shape)
    return st, P, ti, np.array(acc), np.array(gyro), ts, s_st, s_ax, ang


def test_imu_filter_follows_fast_motion(rng):
    st, P, ti, acc, gyro, ts, s_st, s_ax, ang = simulate(rng)
    R0, p0, *_ = truth(0.0)
    cfg = ImuFilterConfig(gyro_noise=0.002, acc_noise=0.02, sigma_theta=2e-5, init_sigma_rot=1e-3,
                          init_sigma_pos=1e-3, init_sigma_vel=0.5, init_sigma_acc_bias=0.05, init_sigma_gyro_bias=0.01)
    out = run_imu_filter(ti, acc, gyro, np.zeros(ti.size, bool), ts, s_st, s_ax, ang, st, P,
                         (0.0, R0 @ rotvec_to_matrix([1e-3, 0, 0]), p0 + 1e-3, G), cfg)
    late = ts > 0.5                                             # after the velocity has converged
    err = np.array([np.linalg.norm(out["position"][k] - truth(t)[1]) for k, t in enumerate(ts)])
    speed = np.array([np.linalg.norm(truth(t)[2]) for t in ts])
    assert out["accepted"][late].mean() > 0.97
    assert np.sqrt(np.mean(err[late] ** 2)) < 3e-4
    fast = late & (speed > 1.0)
    assert fast.sum() > 20
    # before its own update, each sweep is predicted at the noise level from the IMU and earlier sweeps
    assert np.median(out["prior_rms"][fast]) < 2.0 * 2e-5
    # ... while the pose of the previous sweep, held still, misses it by the motion (1/120 s at > 1 m/s)
    held = []
    for k in np.flatnonzero(fast):
        s = st[s_st[k]]
        lit = np.isfinite(ang[k])
        ps = (P[lit] @ out["rotation"][k - 1].T + out["position"][k - 1] - s.translation) @ s.rotation
        held.append(np.sqrt(np.mean((ang[k][lit] - measure(ps[None], None, "lh1")[0, :, s_ax[k]]) ** 2)))
    assert np.median(held) > 10 * np.median(out["prior_rms"][fast])


def test_imu_filter_config_is_validated():
    with pytest.raises(ValueError, match="gyro_noise"):
        ImuFilterConfig(gyro_noise=-1.0)


def test_compiled_propagation_span_is_the_midpoint_rule_and_stops_for_gap_poses(rng):
    """layoutkit.filter._imu_numba.propagate_span (the IMU integration between two sweeps, one compiled
    call) against an independent loop: the stretches between sample times, each propagated with the
    samples interpolated at its midpoint (np.interp) and the motion-dependent accelerometer noise; with
    ``record`` it stops at the first sample time ``gap_dt`` after ``gap_from`` with the stretches'
    transitions multiplied up."""
    from layoutkit.filter import _imu_numba as K

    T = np.cumsum(rng.uniform(0.005, 0.015, 40))
    gyro, acc = rng.normal(0, 1.0, (40, 3)), rng.normal([0, 0, 9.8], 2.0, (40, 3))
    g = np.array([0.0, 0.0, -9.80665])
    R0, p0, v0 = rotvec_to_matrix(rng.normal(0, 1, 3)), rng.normal(0, 1, 3), rng.normal(0, 1, 3)
    ba0, bg0 = rng.normal(0, 0.05, 3), rng.normal(0, 0.01, 3)
    P0 = np.eye(15) * 1e-4
    q = (0.02, 0.05, 1e-4, 1e-6, 1e-8)  # acc_noise, acc_noise_per_acc, qg, qba, qbg

    def state():
        return [np.array(x, float) for x in (R0, p0, v0, ba0, bg0)] + [g.copy(), P0.copy()]

    def reference(a, t, stop=np.inf):
        R, p, v, ba, bg, gg, P = state()
        Fc = np.eye(15)
        edges = [a] + [x for x in T if a < x < t] + [t]
        for lo, hi in zip(edges[:-1], edges[1:]):
            m = 0.5 * (lo + hi)
            w = np.array([np.interp(m, T, gyro[:, i]) for i in range(3)])
            f = np.array([np.interp(m, T, acc[:, i]) for i in range(3)])
            qa = (q[0] + q[1] * np.linalg.norm(R @ (f - ba) + gg)) ** 2
            K.transition(R, ba, bg, f, w, hi - lo, Fc)
            K.propagate(R, p, v, ba, bg, gg, P, f, w, hi - lo, qa, *q[2:])
            if hi < t and hi - stop >= 0.03:
                return hi, (R, p, v, P, Fc)
        return t, (R, p, v, P, Fc)

    a, t = T[3] + 0.002, T[30] - 0.001
    for stop in (np.inf, a + 0.01):
        R, p, v, ba, bg, gg, P = state()
        Fc = np.eye(15)
        got = K.propagate_span(R, p, v, ba, bg, gg, P, T, gyro, acc, a, t, False, 900.0, q[0], q[1], *q[2:], Fc,
                               np.isfinite(stop), stop, 0.03)
        want, (Rr, pr, vr, Pr, Fr) = reference(a, t, stop)
        assert got == want and (got < t) == np.isfinite(stop)
        for x, y in ((R, Rr), (p, pr), (v, vr), (P, Pr)):
            np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-15)
        if np.isfinite(stop):
            np.testing.assert_allclose(Fc, Fr, rtol=1e-12, atol=1e-15)
