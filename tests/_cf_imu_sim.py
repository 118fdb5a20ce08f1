"""Simulated Crazyflie log with the IMU: a Lighthouse deck moved in front of two calibrated LH2 stations,
its deck pulses as the real logs hold them (:func:`cf_helpers.simulate_lh2_log`: no channel on a block's
first pulse, the sync offset on one pulse, the log clock at -1.1 % and the UART queue) and the
Crazyflie's ``fixedFrequency`` sensor events in the real logs' conventions: ~100 Hz, ``gyro.x/y/z`` in
deg/s and ``acc.x/y/z`` in g (specific force, +1 g on z at rest level), body frame x forward, y left,
z up, stamped :data:`layoutkit.importers.cfusdlog.IMU_DELAY_S` after the motion they measure.
Our own bytes: nothing of the public dataset."""
from __future__ import annotations

import numpy as np

from layoutkit.geometry import matrix_to_rotvec, rotvec_to_matrix
from layoutkit.importers.cfusdlog import IMU_DELAY_S
from layoutkit.io.systemconfig import LH2_CYCLE_PERIODS
from layoutkit.lighthouse import measure_jacobian
from layoutkit.units import STANDARD_GRAVITY

IMU_VARS = [("gyro.x", "f"), ("gyro.y", "f"), ("gyro.z", "f"), ("acc.x", "f"), ("acc.y", "f"), ("acc.z", "f")]


def hand_motion(t_start: float, rest_s: float = 0.6):
    """Pose ``(R (K, 3, 3), c (K, 3))`` at log times ``tau (K,)``: at rest for ``rest_s`` after
    ``t_start``, then a smooth hand-like motion (±0.2 m, up to ~0.5 m/s, turning up to ~1 rad/s)."""
    from _cf_joint_sim import TARGET

    def motion(tau):
        tau = np.atleast_1d(np.asarray(tau, float))
        u = np.maximum(tau - t_start - rest_s, 0.0)
        s = 1.0 - np.exp(-(u / 0.4) ** 2)
        c = TARGET + s[:, None] * np.column_stack([0.2 * np.sin(2.0 * u), 0.15 * (1 - np.cos(1.5 * u)),
                                                   0.06 * np.sin(2.5 * u)])
        rv = np.array([0.05, -0.03, 0.4]) + s[:, None] * np.column_stack(
            [0.15 * np.sin(1.3 * u), 0.12 * np.sin(1.7 * u), 0.5 * np.sin(0.9 * u)])
        return rotvec_to_matrix(rv), c
    return motion


def imu_events(motion, t0: float, t1: float, rate_hz: float = 101.2):
    """``fixedFrequency`` rows over log times [t0, t1): (event times, rows gyro deg/s + acc g) and the
    true (tau, gyro rad/s, acc m/s²) they were made from. Central differences (h = 1 ms)."""
    tau = np.arange(t0, t1, 1.0 / rate_hz)
    h = 1e-3
    Rm, cm = motion(tau - h)
    R0, c0 = motion(tau)
    Rp, cp = motion(tau + h)
    w = matrix_to_rotvec(np.swapaxes(Rm, -1, -2) @ Rp) / (2 * h)           # body rate, rad/s
    a = (cp - 2 * c0 + cm) / h ** 2                                         # world acceleration
    g = np.array([0.0, 0.0, -STANDARD_GRAVITY])
    f = np.einsum("kji,kj->ki", R0, a - g)                                  # specific force, body
    rows = [tuple(np.degrees(w[k])) + tuple(f[k] / STANDARD_GRAVITY) for k in range(len(tau))]
    return tau + IMU_DELAY_S, rows, (tau, w, f)


def plane_angles(motion, stations, cals, positions, log_offset_s, log_rate, duration, rng, sigma=4e-5):
    """Per channel: the rotations' rotor zeros (deck ticks) and each sensor's measured plane angles at
    its own hit time (fixed point of hit time ↔ angle), through the station's calibrated model."""
    alpha, t0 = {}, {}
    for ch, st in enumerate(stations):
        P = LH2_CYCLE_PERIODS[ch]
        n = int(duration * 24e6 / P)
        starts = 2_000_000 + ch * 77_777 + P * np.arange(n, dtype=np.int64)
        A = np.zeros((n, len(positions), 2))
        for k, shift in ((0, -np.pi / 3), (1, np.pi / 3)):
            a = np.zeros((n, len(positions)))
            for _ in range(3):
                ticks = starts[:, None] + (a + np.pi + shift) * P / (2 * np.pi)
                tau = log_offset_s + log_rate * ticks / 24e6
                R, c = motion(tau.ravel())
                pw = np.einsum("kij,kj->ki", R, np.tile(positions, (n, 1))) + c
                ps = (pw - st.translation) @ st.rotation
                a = measure_jacobian(ps, cals[ch], "lh2", jacobian=False)[0][:, k].reshape(n, -1)
            A[:, :, k] = a + rng.normal(0, sigma, a.shape)
        alpha[ch], t0[ch] = A, starts
    return alpha, t0
