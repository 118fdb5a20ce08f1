"""Rotation helpers against scipy and closed forms."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from layoutkit.geometry import (
    attitude_error, look_at_rotation, matrix_to_rotvec, nearest_rotation, random_rotations,
    right_jacobian_so3, rotvec_to_matrix, skew, transform_points,
)


def test_rotvec_round_trip_batched(rng):
    rv = rng.normal(size=(4, 5, 3))
    rv *= (rng.uniform(0, 3, (4, 5)) / np.linalg.norm(rv, axis=-1))[..., None]
    R = rotvec_to_matrix(rv)
    assert R.shape == (4, 5, 3, 3)
    np.testing.assert_allclose(R[1, 2], Rotation.from_rotvec(rv[1, 2]).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(matrix_to_rotvec(R), rv, atol=1e-10)


def test_skew_is_cross_product(rng):
    a, b = rng.normal(size=(2, 6, 3))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", skew(a), b), np.cross(a, b), atol=1e-14)


def test_right_jacobian_finite_difference(rng):
    """R(phi + d) ≈ R(phi) exp(J_r(phi) d) (Chen eq. 9)."""
    phi = rng.normal(size=3)
    Jr = right_jacobian_so3(phi)
    h = 1e-6
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        D = rotvec_to_matrix(phi).T @ rotvec_to_matrix(phi + d)
        np.testing.assert_allclose(matrix_to_rotvec(D) / h, Jr[:, k], atol=1e-6)
    np.testing.assert_allclose(right_jacobian_so3(np.zeros(3)), np.eye(3))


def test_attitude_error_and_nearest_rotation(rng):
    R = random_rotations(3, rng)
    d = rotvec_to_matrix(np.array([[0.01, 0, 0], [0, 0.02, 0], [0, 0, 0.03]]))
    np.testing.assert_allclose(attitude_error(d @ R, R), [0.01, 0.02, 0.03], atol=1e-12)
    noisy = R + 1e-3 * rng.normal(size=R.shape)
    Q = nearest_rotation(noisy)
    np.testing.assert_allclose(Q @ np.swapaxes(Q, -1, -2), np.broadcast_to(np.eye(3), Q.shape), atol=1e-12)
    assert np.all(np.linalg.det(Q) > 0)
    assert np.all(attitude_error(Q, R) < 3e-3)


def test_transform_and_look_at(rng):
    R = random_rotations(2, rng)
    t = rng.normal(size=(2, 3))
    P = rng.normal(size=(2, 4, 3))
    np.testing.assert_allclose(transform_points(R, t, P)[1], P[1] @ R[1].T + t[1])
    d = rng.normal(size=3)
    L = look_at_rotation(d)
    np.testing.assert_allclose(L[2], d / np.linalg.norm(d))
    np.testing.assert_allclose(L @ L.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(L) == pytest.approx(1.0)


def test_ensure_rotation_projects_only_what_is_not_a_rotation():
    """Proper rotations pass bit for bit; a scaled matrix, a reflection and a NaN-free shear are each
    replaced by the SVD-nearest proper rotation (closed form: the polar factor), per matrix."""
    from layoutkit.geometry import ensure_rotation, nearest_rotation, random_rotations

    R = random_rotations(5, np.random.default_rng(3))
    bad = R.copy()
    bad[1] *= 1.001                                 # scaled: M M^T - I ~ 2e-3
    bad[2] = -bad[2]                                # a reflection: orthogonal, det -1
    bad[3] = bad[3] + 1e-6 * np.triu(np.ones((3, 3)))
    out = ensure_rotation(bad)
    for i in (0, 4):
        assert np.array_equal(out[i], R[i])
    assert np.allclose(out[1], R[1], atol=1e-12)    # the polar factor of s R is R
    for i in (1, 2, 3):
        assert np.allclose(out[i] @ out[i].T, np.eye(3), atol=1e-12) and np.linalg.det(out[i]) > 0
        assert np.allclose(out[i], nearest_rotation(bad[i]), atol=1e-15)
    assert np.array_equal(ensure_rotation(R), R) and ensure_rotation(R) is not R
    assert ensure_rotation(R[0]).shape == (3, 3)
