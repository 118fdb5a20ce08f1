"""Precision vs accuracy from the angles alone (layoutkit.workflows.accuracy) and motion in the joint
solve (layoutkit.workflows.joint_solve). Proof by simulation with known truth: sensor errors we put in
come back as per-sensor offsets of the right size and the lit-set spread appears only with them;
a moving body's windows fit to the noise only with the motion model, and a body at rest is not touched."""
import numpy as np
import pytest

from _calib_sim import STATION_POSITIONS, sphere_layout
from layoutkit.geometry import random_rotations, rotvec_to_matrix
from layoutkit.joint import solve_joint
from layoutkit.simulate import simulate_station_angles, stations_looking_at
from layoutkit.workflows.accuracy import precision_accuracy

SIGMA = 2e-5


def _static(rng, offsets_rms, windows=300, n=24):
    st = stations_looking_at(STATION_POSITIONS, (0, 0, 0), kind="lh1")
    P, N = sphere_layout(rng, n)
    R = np.repeat(random_rotations(1, rng), windows, 0)
    t = np.zeros((windows, 3))
    off = rng.normal(0, offsets_rms / np.sqrt(3), P.shape) if offsets_rms else np.zeros_like(P)
    a = simulate_station_angles(P + off, R, t, st, sigma=SIGMA, rho=0.0, rng=rng)
    nw = N @ R[0].T
    for s, s_ in enumerate(st):
        d = s_.translation - P @ R[0].T
        a[:, s][:, ~(np.sum(nw * d, -1) > 0.2)] = np.nan
    # each window loses one of a few sensors (a handful of lit sets, as a real device shows)
    drop = rng.integers(0, 4, windows)
    a[np.arange(windows), :, drop] = np.nan
    return st, P, off, a


def _pa(st, P, a):
    r = solve_joint(P, a, stations=st)
    return precision_accuracy(P, st, r.rotation, r.translation, a, ok=r.success, sigma=SIGMA)


def test_exact_layout_gives_noise_level_offsets_and_no_lit_set_spread(rng):
    st, P, _, a = _static(rng, 0.0)
    pa = _pa(st, P, a)
    assert pa["at_rest"]
    assert pa["sensor_offsets"]["median_mm"] < 0.02
    ratio = pa["scatter_all_windows"]["position_sd_mm"] / pa["precision_within_lit_set"]["position_sd_mm"]
    assert ratio < 1.5 and "the scatter is the noise" in pa["message"]
    # within one lit set the scatter is the DOP prediction (Chen eq. 24)
    w = pa["precision_within_lit_set"]
    assert 0.6 < w["position_sd_mm"] / w["predicted_position_sd_mm"] < 1.5


def test_sensor_errors_come_back_as_offsets_and_as_lit_set_spread(rng):
    """0.5 mm RMS sensor errors (0.29 mm per coordinate): the per-sensor offsets explaining the
    residuals have the size of the errors' part the pose cannot absorb, point the same way, and the
    scatter over all windows exceeds the within-lit-set scatter by the systematic part."""
    st, P, off, a = _static(rng, 0.5e-3)
    pa = _pa(st, P, a)
    est = np.array([pa["sensor_offsets"]["per_sensor_mm"][str(i)] for i in range(len(P))
                    if str(i) in pa["sensor_offsets"]["per_sensor_mm"]]) * 1e-3
    have = [i for i in range(len(P)) if str(i) in pa["sensor_offsets"]["per_sensor_mm"]]
    true = off[have]
    # the part a rigid motion of the whole body cannot explain (the pose took the rest)
    A = np.concatenate([np.tile(np.eye(3), (len(have), 1)),
                        np.concatenate([-np.cross(np.eye(3)[None], P[have][:, None]).reshape(-1, 3)])], 1)
    rigid = A @ np.linalg.lstsq(A, true.ravel(), rcond=None)[0]
    shape = true.ravel() - rigid
    assert 0.4 < np.median(np.linalg.norm(est, axis=1)) / np.median(np.linalg.norm(shape.reshape(-1, 3), axis=1)) < 2.5
    assert np.corrcoef(est.ravel(), shape)[0, 1] > 0.5
    ratio = pa["scatter_all_windows"]["position_sd_mm"] / pa["precision_within_lit_set"]["position_sd_mm"]
    _, P0, _, a0 = _static(rng, 0.0)
    pa0 = _pa(st, P0, a0)
    ratio0 = pa0["scatter_all_windows"]["position_sd_mm"] / pa0["precision_within_lit_set"]["position_sd_mm"]
    assert ratio > 1.1 and ratio > ratio0 + 0.1


def _moving_frames(rng, speed, rate, windows=60, n=24):
    """Rows 8 ms apart per station (station 0 then 1), the body moving at constant velocity."""
    from layoutkit.workflows.joint_solve import StationFrames

    st = stations_looking_at(STATION_POSITIONS, (0, 0, 0), kind="lh1")
    P, N = sphere_layout(rng, n)
    R0 = random_rotations(1, rng)[0]
    v = np.array([speed, 0.0, 0.0])
    w = np.array([0.0, 0.0, rate])
    ts, rows_st, ang = [], [], []
    for k in range(windows):
        for s in range(2):
            tt = 0.02 * k + 0.008 * s
            R = rotvec_to_matrix(w * tt) @ R0
            t = v * (tt - 0.6)
            a = simulate_station_angles(P, R[None], t[None], [st[s]], sigma=SIGMA, rho=0.0, rng=rng)[0, 0]
            d = st[s].translation - (P @ R.T + t)
            a[~(np.sum((N @ R.T) * d, -1) > 0.2)] = np.nan
            ts.append(tt); rows_st.append(str(s)); ang.append(a)
    return st, P, StationFrames(np.array(ts), np.array(rows_st), np.array(ang))


@pytest.mark.parametrize("speed,rate", [(1.0, 0.0), (0.0, 2.0)])
def test_motion_compensation_fits_a_moving_body_to_the_noise(rng, speed, rate):
    """1 m/s (or 2 rad/s) with the two stations' rows 8 ms apart: the static model leaves residuals far
    above the noise; the motion model (solve --solve joint's default) brings them to it."""
    from layoutkit.layout import Layout
    from layoutkit.workflows.joint_solve import solve_joint_frames

    st, P, fr = _moving_frames(rng, speed, rate)
    lay = Layout(P, P / np.linalg.norm(P, axis=1, keepdims=True), tuple(str(i) for i in range(len(P))))
    _, r0, _, _ = solve_joint_frames(fr, lay, st, motion_compensation=False)
    _, r1, _, info = solve_joint_frames(fr, lay, st, motion_compensation=True, sigma=SIGMA)
    inner = slice(3, -3)
    assert np.nanmedian(r0.residual_rms[inner]) > 2 * SIGMA
    assert np.nanmedian(r1.residual_rms[inner]) < 1.2 * SIGMA
    assert info["compensated"][inner].all()


def test_motion_compensation_leaves_a_body_at_rest_alone(rng):
    from layoutkit.layout import Layout
    from layoutkit.workflows.joint_solve import solve_joint_frames

    st, P, fr = _moving_frames(rng, 0.0, 0.0)
    lay = Layout(P, P / np.linalg.norm(P, axis=1, keepdims=True), tuple(str(i) for i in range(len(P))))
    _, r0, _, _ = solve_joint_frames(fr, lay, st, motion_compensation=False)
    _, r1, _, info = solve_joint_frames(fr, lay, st, motion_compensation=True, sigma=SIGMA)
    assert info["compensated"].mean() < 0.1
    assert np.median(np.linalg.norm(r1.translation - r0.translation, axis=1)) < 1e-6
