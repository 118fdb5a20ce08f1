"""Lighthouse measurement model: closed forms of Chen eq. (1)–(2) and the LH2 plane geometry."""
import numpy as np
import pytest

from layoutkit.lighthouse import (
    Station, angles_to_normalized, angles_to_ticks, in_field_of_view, lh2_sweep_angles,
    normalized_to_angles, quantize_angles, sweep_angles, ticks_to_angles,
)


def test_sweep_angles_cotangent_closed_form(rng):
    """cot(theta_x) = x/z, cot(theta_y) = y/z (Chen eq. 2); 90° on boresight."""
    p = np.column_stack([rng.uniform(-2, 2, 100), rng.uniform(-2, 2, 100), rng.uniform(0.1, 3, 100)])
    th = sweep_angles(p)
    np.testing.assert_allclose(1 / np.tan(th[:, 0]), p[:, 0] / p[:, 2], rtol=1e-12)
    np.testing.assert_allclose(1 / np.tan(th[:, 1]), p[:, 1] / p[:, 2], rtol=1e-12)
    np.testing.assert_allclose(sweep_angles([[0, 0, 2.0]]), [[np.pi / 2, np.pi / 2]])
    np.testing.assert_allclose(normalized_to_angles(angles_to_normalized(th)), th, atol=1e-14)


def test_timing_round_trip_and_tick_size():
    """theta = omega (t_hit - t_sync) (eq. 1); one 50 MHz tick at 3600 rpm is 7.54e-6 rad (1.55")."""
    one = ticks_to_angles(1.0)
    assert one == pytest.approx(120 * np.pi / 50e6, rel=1e-12)
    assert np.degrees(one) * 3600 == pytest.approx(1.555, abs=0.001)
    th = np.linspace(0.5, 2.6, 11)
    np.testing.assert_allclose(ticks_to_angles(angles_to_ticks(th)), th, rtol=1e-14)
    q = quantize_angles(th)
    assert np.all(np.abs(q - th) <= one / 2 + 1e-15)
    np.testing.assert_allclose(angles_to_ticks(q), np.round(angles_to_ticks(q)), atol=1e-6)


def test_field_of_view_edges():
    """120° × 120°: theta in [30°, 150°] on both axes, z > 0."""
    z = 1.0
    x_edge = z / np.tan(np.radians(30))
    pts = np.array([[x_edge * 0.999, 0, z], [x_edge * 1.001, 0, z], [0, 0, -1.0], [0, -x_edge * 0.999, z]])
    np.testing.assert_array_equal(in_field_of_view(pts), [True, False, False, True])


def test_lh2_angle_puts_the_point_on_the_tilted_light_plane(rng):
    """Each LH2 angle alpha is the rotor angle at which the plane tilted by ∓30° contains the
    point: with Bitcraze axes (x fwd), normal Rz(alpha) (0, cos t, sin t) is orthogonal to p."""
    p = np.column_stack([rng.uniform(-1, 1, 50), rng.uniform(-1, 1, 50), rng.uniform(1, 3, 50)])
    a = lh2_sweep_angles(p)
    pb = np.column_stack([p[:, 2], p[:, 0], p[:, 1]])
    for k, t in enumerate((-np.pi / 6, np.pi / 6)):
        n = np.column_stack([-np.sin(a[:, k]) * np.cos(t), np.cos(a[:, k]) * np.cos(t), np.sin(t) * np.ones(50)])
        np.testing.assert_allclose(np.sum(n * pb, 1), 0, atol=1e-12)
    # both planes agree on the horizontal bearing when z_bc = 0 (the point is on the rotor's equator)
    a0 = lh2_sweep_angles([[0.3, 0.0, 2.0]])
    assert a0[0, 0] == pytest.approx(a0[0, 1])


def test_station_validation_messages():
    with pytest.raises(ValueError, match="Station.rotation: expected a proper rotation matrix"):
        Station("A", np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match=r"Station.translation: expected shape \(3\), got \(2,\)"):
        Station("A", np.eye(3), [0.0, 1.0])
    with pytest.raises(ValueError, match="Station.kind: expected 'lh1' or 'lh2', got 'lh3'"):
        Station("A", kind="lh3")
