"""Joint multi-station and calibrated solving (layoutkit.joint): Monte-Carlo RMS against the
DOP prediction of the same geometry (Chen eq. 24), exact recovery from noise-free calibrated and
moving data (closed-form truth), statuses on bad frames."""
import numpy as np
import pytest

from layoutkit.dop import pose_dop
from layoutkit.geometry import look_at_rotation, rotvec_to_matrix
from layoutkit.joint import model_angles_jacobian, solve_joint
from layoutkit.lighthouse import CALIBRATION_PARAMS, Calibration, Station, measure
from layoutkit.pnp import STATUS_OK, STATUS_TOO_FEW, solve_pnp
from layoutkit.simulate import simulate_station_angles, stations_looking_at

# 4 sensors, 3 x 1.5 cm, the Crazyflie Lighthouse deck's shape
DECK = np.array([[-0.015, 0.0075, 0.0], [-0.015, -0.0075, 0.0], [0.015, 0.0075, 0.0], [0.015, -0.0075, 0.0]])


def random_calibration(rng, kind, gib="ideal", scale=1.0):
    """Factory-magnitude parameters (phase ~0.05, tilt ~0.01, curve ~0.003, gib ~0.02 rad)."""
    mag = {"phase": 0.05, "tilt": 0.01, "curve": 0.003, "gib_phase": np.pi, "gib_mag": 0.02,
           "ogee_phase": np.pi, "ogee_mag": 0.02 if kind == "lh2" else 0.0}
    p = np.array([[rng.uniform(-1, 1) * mag[n] * (1 if n.endswith("phase") and n != "phase" else scale)
                   for n in CALIBRATION_PARAMS] for _ in range(2)])
    return Calibration(p, kind, gib)


def two_stations(rng, kind="lh2"):
    return stations_looking_at([[-2.0, -1.0, 2.0], [2.0, -1.2, 2.0]], (0, 0, 0), kind=kind,
                               calibrations=[random_calibration(rng, kind), random_calibration(rng, kind, "corrected")])


def _pos_rms(res, t):
    e = res.translation[res.success] - t[res.success]
    return float(np.sqrt(np.mean(np.sum(e * e, 1))))


def test_joint_deck_two_stations_follows_joint_dop(rng):
    """4-sensor deck, two calibrated LH2 stations ~3 m away: joint position RMS within 5 % of the joint
    PDOP·sigma; each station alone at its own prediction (8 %) — 3000 static frames, rho = 0."""
    sts = two_stations(rng)
    F, sigma = 3000, 1e-4
    R = np.tile(look_at_rotation([0.0, 0.0, 1.0]).T, (F, 1, 1))
    t = np.zeros((F, 3))
    a = simulate_station_angles(DECK, R, t, sts, sigma=sigma, rho=0.0, rng=rng)
    joint = solve_joint(DECK, a, stations=sts)
    assert joint.success.all()
    pred = pose_dop(DECK, R[0], t[0], stations=sts).pdop * sigma
    assert _pos_rms(joint, t) == pytest.approx(pred, rel=0.05)
    for k in range(2):
        one = solve_joint(DECK, a[:, k:k + 1], stations=[sts[k]])
        pk = pose_dop(DECK, R[0], t[0], stations=[sts[k]]).pdop * sigma
        assert one.success.mean() > 0.99
        assert _pos_rms(one, t) == pytest.approx(pk, rel=0.08)
        assert pk > 20 * pred          # the joint geometry is what makes a 3 cm deck usable


@pytest.mark.parametrize("kind", ["lh1", "lh2"])
def test_calibrated_solve_is_exact_and_uncalibrated_is_not(rng, kind):
    """Noise-free distorted angles: solve_pnp(calibration=...) returns the true pose to 1e-9 m; the same
    angles solved as if ideal are off by millimetres (the calibration matters)."""
    P = rng.uniform(-0.06, 0.06, (8, 3))
    cal = random_calibration(rng, kind)
    F = 50
    R = rotvec_to_matrix(rng.normal(0, 0.3, (F, 3)))
    t = np.column_stack([rng.uniform(-0.5, 0.5, F), rng.uniform(-0.5, 0.5, F), rng.uniform(1.5, 3.0, F)])
    pts = np.einsum("fij,nj->fni", R, P) + t[:, None]
    a = measure(pts, cal)
    r = solve_pnp(P, a, calibration=cal)
    assert np.all(r.status == STATUS_OK)
    np.testing.assert_allclose(r.translation, t, atol=1e-9)
    assert np.max(r.residual_rms) < 1e-10
    ideal = solve_joint(P, a[:, None], stations=[Station(kind=kind)])
    assert np.median(np.linalg.norm(ideal.translation - t, axis=1)) > 1e-3


def test_motion_compensation_recovers_moving_pose(rng):
    """A body spinning at 90 deg/s and moving 1 m/s, stations' sweeps 8 ms before/after the window time:
    with the constant-velocity model the window pose is exact; without it it is off by millimetres."""
    sts = two_stations(rng, "lh1")
    P = rng.uniform(-0.05, 0.05, (10, 3))
    F = 20
    R = rotvec_to_matrix(rng.normal(0, 0.2, (F, 3)))
    t = rng.uniform(-0.2, 0.2, (F, 3))
    omega = np.tile([0.0, 0.0, np.radians(90)], (F, 1))
    v = np.tile([1.0, 0.0, 0.0], (F, 1))
    dt = np.tile([-0.008, 0.008], (F, 1))
    a = simulate_station_angles(P, R, t, sts, sigma=0.0, rho=0.0, rng=rng, dt=dt, velocity=(omega, v))
    comp = solve_joint(P, a, stations=sts, dt=dt, velocity=(omega, v))
    np.testing.assert_allclose(comp.translation, t, atol=1e-8)
    plain = solve_joint(P, a, stations=sts)
    assert np.median(np.linalg.norm(plain.translation - t, axis=1)) > 1e-3


def test_bad_frames_get_statuses_not_exceptions(rng):
    """NaN, inf, too few angles: a status per frame, the good frames still solved."""
    sts = two_stations(rng)
    F = 6
    R = np.tile(look_at_rotation([0.0, 0.0, 1.0]).T, (F, 1, 1))
    t = np.zeros((F, 3))
    a = simulate_station_angles(DECK, R, t, sts, sigma=0.0, rho=0.0, rng=rng)
    a[0] = np.nan
    a[1, :, 1:] = np.nan                      # one sensor per station: 4 angles
    a[2, 0] = np.inf
    a[2, 1] = np.nan
    res = solve_joint(DECK, a, stations=sts)
    assert list(res.status[:3]) == [STATUS_TOO_FEW] * 3
    assert np.all(res.status[3:] == STATUS_OK)
    assert np.isnan(res.translation[0]).all()


def test_model_jacobian_matches_finite_differences(rng):
    """d angles / d (dphi, dt) of the multi-station calibrated model == central differences (1e-6 rel)."""
    sts = two_stations(rng)
    P = rng.uniform(-0.05, 0.05, (5, 3))
    R = rotvec_to_matrix(rng.normal(0, 0.3, (3, 3)))
    t = rng.uniform(-0.2, 0.2, (3, 3))
    _, J, _ = model_angles_jacobian(P, R, t, sts)
    h = 1e-6
    fd = np.zeros_like(J)
    for i in range(6):
        d = np.zeros(6)
        d[i] = h
        up = model_angles_jacobian(P, rotvec_to_matrix(d[:3]) @ R, t + d[3:], sts, jacobian=False)[0]
        dn = model_angles_jacobian(P, rotvec_to_matrix(-d[:3]) @ R, t - d[3:], sts, jacobian=False)[0]
        fd[..., i] = (up - dn) / (2 * h)
    np.testing.assert_allclose(J, fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())
