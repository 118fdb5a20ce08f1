"""The fused DOP kernel (layoutkit.dop_batch) against the batched matrix implementation pose_dop.

Proof kind: independent reference — pose_dop forms J, A = J^T J, inverts with LAPACK and builds
H = A^-1 J^T R J A^-1 (itself checked by finite differences in test_dop.py); the kernel never forms
J or H. Degenerate inputs are checked against their known status.
"""
import numpy as np
import pytest

from layoutkit.dop import pose_dop
from layoutkit.dop_batch import batch_dop
from layoutkit.geometry import random_rotations
from layoutkit.lighthouse import Station


@pytest.fixture(scope="module")
def poses():
    rng = np.random.default_rng(3)
    n = 400
    R = random_rotations(n, rng)
    t = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(1, 3, n)])
    pts = rng.uniform(-0.1, 0.1, (12, 3))
    return pts, R, t, rng


@pytest.mark.parametrize("rho", [0.0, 0.5, 0.8717])
def test_matches_pose_dop_one_station(poses, rho):
    pts, R, t, rng = poses
    vis = rng.random((len(R), 12)) < 0.7
    a = pose_dop(pts, R, t, rho=rho, visible=vis)
    b = batch_dop(pts, R, t, rho=rho, visible=vis, chunk=97)  # odd chunk: chunk borders
    np.testing.assert_array_equal(a.status, b.status)
    np.testing.assert_array_equal(a.n_visible, b.n_visible)
    ok = a.status == 0
    assert ok.sum() > 300
    np.testing.assert_allclose(b.adop[ok], a.adop[ok], rtol=1e-9)
    np.testing.assert_allclose(b.pdop[ok], a.pdop[ok], rtol=1e-9)
    assert np.all(np.isinf(b.adop[~ok]))


def test_matches_pose_dop_rotated_stations(poses):
    pts, R, t, rng = poses
    st = [Station(rotation=random_rotations(1, rng)[0], translation=np.array([0.3, 0.1, -0.2]), id="A"),
          Station(rotation=random_rotations(1, rng)[0], translation=np.array([-1.0, 0.0, 0.0]), id="B")]
    vis = rng.random((len(R), 2, 12)) < 0.5
    a = pose_dop(pts, R, t, rho=0.8717, visible=vis, stations=st)
    b = batch_dop(pts, R, t, rho=0.8717, visible=vis, stations=st)
    np.testing.assert_array_equal(a.status, b.status)
    ok = a.status == 0
    np.testing.assert_allclose(b.adop[ok], a.adop[ok], rtol=1e-9)
    np.testing.assert_allclose(b.pdop[ok], a.pdop[ok], rtol=1e-9)


def test_degenerate_statuses():
    """Fewer than 3 lit pairs -> status 1; three collinear sensors seen by one station -> status 2
    (a rotation about their line is unobservable), as in pose_dop."""
    R = np.eye(3)[None].repeat(2, 0)
    t = np.array([[0.0, 0.0, 2.0], [0.1, 0.0, 2.0]])
    pts = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]])
    vis = np.array([[1, 1, 0, 0], [1, 1, 1, 0]], bool)
    b = batch_dop(pts, R, t, visible=vis)
    a = pose_dop(pts, R, t, visible=vis)
    assert b.status.tolist() == [1, 2] == a.status.tolist()
    assert np.all(np.isinf(b.adop))


def test_bad_input_names_field():
    with pytest.raises(ValueError, match="visible"):
        batch_dop(np.zeros((3, 3)), np.eye(3)[None], np.zeros((1, 3)), visible=np.ones((2, 3), bool))
    with pytest.raises(ValueError, match="rho"):
        batch_dop(np.zeros((3, 3)), np.eye(3)[None], np.zeros((1, 3)), rho=1.0)
