"""The compiled joint solve (layoutkit.joint_numba, ``solve_joint(method="lm")``, the default)
against the numpy reference (``method="lm-numpy"``, layoutkit.joint._lm) on the same frames.

Proof kind: an independent implementation of the same model and steps — scalar per-frame
derivatives of every station's calibrated forward model (LH1 sweeps, LH2 light planes, both gib
arguments) vs the vectorised forward-mode ones of layoutkit.lighthouse — must give the same status
in every frame and the same pose to rounding: two calibrated LH2 stations and a 4-sensor deck, LH1
stations with a 10-sensor body, ideal stations, motion compensation with one time per station and
one per station and axis, single-axis gaps, too few and low-redundancy windows, given starts.
"""
import numpy as np
import pytest

from layoutkit.geometry import look_at_rotation, rotvec_to_matrix
from layoutkit.joint import JOINT_METHODS, solve_joint
from layoutkit.lighthouse import Station
from layoutkit.simulate import simulate_station_angles, stations_looking_at

from test_joint import DECK, random_calibration, two_stations


def _same(a, b, tol=1e-7):
    """Same statuses; same poses to 1e-7 (rad, m) — the LM (the shared core, layoutkit.lm_numba) stops
    when a step's predicted decrease is below 1e-8 of the cost, so two implementations whose sums round
    differently may stop one step apart, ~1e-9..1e-8 off, three orders below the poses' precision here
    (~1e-4)."""
    np.testing.assert_array_equal(a.status, b.status)
    fin = np.isfinite(a.translation[:, 0]) & (a.status != 3)
    np.testing.assert_array_equal(np.isfinite(a.translation[:, 0]), np.isfinite(b.translation[:, 0]))
    np.testing.assert_allclose(a.rotation[fin], b.rotation[fin], rtol=0, atol=tol)
    np.testing.assert_allclose(a.translation[fin], b.translation[fin], rtol=0, atol=tol)
    np.testing.assert_allclose(a.residual_rms[fin], b.residual_rms[fin], rtol=1e-6, atol=1e-15)
    # (iteration counts may differ: at the minimum a step that changes the cost only by rounding is
    # accepted by one implementation and rejected by the other, which then raises the damping to stop)


def _both(*args, **kw):
    return solve_joint(*args, method="lm", **kw), solve_joint(*args, method="lm-numpy", **kw)


def test_methods():
    assert JOINT_METHODS == ("lm", "lm-numpy")
    with pytest.raises(ValueError, match="method"):
        solve_joint(DECK, np.zeros((1, 4, 2)), stations=[Station()], method="x")


def test_deck_two_calibrated_lh2_stations(rng):
    """The Crazyflie case: 4 sensors, two calibrated LH2 stations (gib 'ideal' and 'corrected'),
    noisy angles, single-axis gaps and windows with too few angles."""
    sts = two_stations(rng)
    F = 300
    R = rotvec_to_matrix(rng.normal(0, 0.2, (F, 3))) @ look_at_rotation([0.0, 0.0, 1.0]).T
    t = rng.uniform(-0.3, 0.3, (F, 3))
    a = simulate_station_angles(DECK, R, t, sts, sigma=1e-4, rho=0.0, rng=rng)
    a[::7, 1] = np.nan                       # station 1 missing: one station's 8 angles
    a[3::11, :, 0, 1] = np.nan               # single-axis gap
    a[5::13, 0] = np.nan
    a[5::13, 1, 1:] = np.nan                 # 2 angles: too few
    x, y = _both(DECK, a, stations=sts)
    assert (x.status == 0).mean() > 0.8 and (x.status == 1).sum() > 0
    _same(x, y)


@pytest.mark.parametrize("gib", ["ideal", "corrected"])
def test_lh1_calibrated_and_ideal(rng, gib):
    P = rng.uniform(-0.06, 0.06, (10, 3))
    sts = stations_looking_at([[-2.0, -1.0, 2.0], [2.0, -1.2, 2.0]], (0, 0, 0), kind="lh1",
                              calibrations=[random_calibration(rng, "lh1", gib), random_calibration(rng, "lh1", gib)])
    F = 200
    R = rotvec_to_matrix(rng.normal(0, 0.3, (F, 3)))
    t = rng.uniform(-0.3, 0.3, (F, 3))
    a = simulate_station_angles(P, R, t, sts, sigma=5e-5, rho=0.0, rng=rng)
    _same(*_both(P, a, stations=sts))
    ideal = stations_looking_at([[-2.0, -1.0, 2.0], [2.0, -1.2, 2.0]], (0, 0, 0), kind="lh1")
    a = simulate_station_angles(P, R, t, ideal, sigma=5e-5, rho=0.0, rng=rng)
    vis = np.ones((F, 2, 10), bool)
    vis[:, :, 3:] = False
    vis[::2, 1] = False                      # 3 sensors at one station: low redundancy
    x, y = _both(P, a, vis, stations=ideal, initial=(R, t + 1e-3))
    assert (x.status == 11).sum() > 0 and (x.status == 0).sum() > 0
    _same(x, y)


@pytest.mark.parametrize("per_axis", [False, True])
def test_motion_compensation(rng, per_axis):
    sts = two_stations(rng, "lh1")
    P = rng.uniform(-0.05, 0.05, (10, 3))
    F = 100
    R = rotvec_to_matrix(rng.normal(0, 0.2, (F, 3)))
    t = rng.uniform(-0.2, 0.2, (F, 3))
    omega = np.tile([0.0, 0.3, np.radians(90)], (F, 1))
    v = np.tile([1.0, 0.0, 0.2], (F, 1))
    dt = np.tile([-0.008, 0.008], (F, 1))
    if per_axis:
        dt = np.stack([dt, dt + 0.004], -1)
    a = simulate_station_angles(P, R, t, sts, sigma=2e-5, rho=0.0, rng=rng, dt=dt if not per_axis else dt[..., 0],
                                velocity=(omega, v))
    x, y = _both(P, a, stations=sts, dt=dt, velocity=(omega, v))
    assert (x.status == 0).mean() > 0.9
    _same(x, y)
