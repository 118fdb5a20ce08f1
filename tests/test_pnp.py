"""Tests of the batched PnP solver (layoutkit.pnp, its LH1 fast path layoutkit.pnp_lh1).

Kinds of proof used: exact recovery of known poses from noise-free synthetic angles (closed form),
first-order optimality of the returned estimate (gradient of the angle cost by the independent
``dop.angle_jacobian``), Monte-Carlo error against the Cramér–Rao bound of ``dop.pose_dop`` with a
tolerance from the sample's own standard error, OpenCV (SQPNP, IPPE) on the same frames, and
exact messages for bad input.
"""
import numpy as np
import pytest

from layoutkit.dop import angle_jacobian, pose_dop
from layoutkit.geometry import attitude_error, random_rotations, transform_points
from layoutkit.lighthouse import in_field_of_view, sweep_angles
from layoutkit.noise import sample_angle_noise
from layoutkit.units import SIGMA_THETA_PAPER
from layoutkit import pnp_lh1
from layoutkit.pnp import (PNP_SOLVERS, STATUS_DEGENERATE, STATUS_INVALID_ANGLE, STATUS_NO_START, STATUS_OK,
                           STATUS_TOO_FEW, PnPResult,
                           solve_pnp)
from layoutkit.shapes import chen_target

LAYOUT = chen_target()[1]
P12 = LAYOUT.positions
TOP = [0, 1, 2, 3]          # coplanar (top face)
CHAMFERS = [4, 5, 6, 7]     # coplanar (one height)
SUBSETS = {
    "top4_coplanar": TOP,
    "chamfer4_coplanar": CHAMFERS,
    "mixed4": [0, 1, 4, 8],
    "mixed5": [0, 1, 2, 3, 4],
    "mixed6": [0, 4, 5, 8, 9, 1],
    "eight": [0, 1, 2, 3, 4, 5, 8, 9],
    "all12": list(range(12)),
}


def poses(F, points, rng, dmin=1.0, dmax=3.0):
    """Uniform random attitudes; translations 1-3 m with every point in the 120° field of view."""
    R = random_rotations(F, rng)
    t = np.empty((F, 3))
    todo = np.arange(F)
    while todo.size:
        v = rng.standard_normal((todo.size, 3))
        v *= (rng.uniform(dmin, dmax, todo.size) / np.linalg.norm(v, axis=1))[:, None]
        ok = np.all(in_field_of_view(transform_points(R[todo], v, points)), axis=1)
        t[todo[ok]] = v[ok]
        todo = todo[~ok]
    return R, t


def angles_of(points, R, t):
    return sweep_angles(transform_points(R, t, points))


def errors(res, R, t):
    return attitude_error(res.rotation, R), np.linalg.norm(res.translation - t, axis=1)


@pytest.mark.parametrize("method", sorted(PNP_SOLVERS))
@pytest.mark.parametrize("name", sorted(SUBSETS))
def test_noise_free_recovery_chen_subsets(name, method, rng):
    """Closed form: noise-free angles of a known pose give that pose back (coplanar and not, n = 4..12)."""
    P = P12[SUBSETS[name]]
    R, t = poses(300, P, rng)
    res = solve_pnp(P, angles_of(P, R, t), method=method, sigma=0.0)  # noise-free: nothing ties
    e_rot, e_t = errors(res, R, t)
    assert res.success.all(), res.message
    assert e_rot.max() < 1e-9 and e_t.max() < 1e-9
    assert np.all(res.residual_rms < 1e-11)


@pytest.mark.parametrize("n", [4, 5, 7, 12])
@pytest.mark.parametrize("planar", [False, True])
def test_noise_free_recovery_random_bodies(n, planar, rng):
    """Closed form, per-frame bodies (F, n, 3): random 10 cm point clouds, flat or not."""
    F = 200
    P = rng.uniform(-0.05, 0.05, (F, n, 3))
    if planar:  # random plane through the origin
        P[..., 2] = 0.0
        P = np.einsum("fij,fnj->fni", random_rotations(F, rng), P)
    R = random_rotations(F, rng)
    t = np.stack([rng.uniform(-0.5, 0.5, F), rng.uniform(-0.5, 0.5, F), rng.uniform(1.0, 3.0, F)], -1)
    res = solve_pnp(P, sweep_angles(transform_points(R, t, P)), sigma=0.0)  # noise-free: nothing ties
    e_rot, e_t = errors(res, R, t)
    assert res.success.all(), res.message
    assert e_rot.max() < 1e-9 and e_t.max() < 1e-9


def test_visibility_mask_and_nan(rng):
    """A mask and NaN angles select the same sensors; unlit sensors' garbage angles are ignored."""
    R, t = poses(100, P12, rng)
    ang = angles_of(P12, R, t)
    vis = np.zeros((100, 12), bool)
    for f in range(100):
        vis[f, rng.choice(12, rng.integers(4, 13), replace=False)] = True
    garbage = np.where(vis[..., None], ang, rng.uniform(0.5, 2.5, ang.shape))
    a = solve_pnp(P12, garbage, vis)
    b = solve_pnp(P12, np.where(vis[..., None], ang, np.nan))
    for res in (a, b):
        e_rot, e_t = errors(res, R, t)
        assert res.success.all(), res.message
        assert e_rot.max() < 1e-9 and e_t.max() < 1e-9
    np.testing.assert_allclose(a.rotation, b.rotation, atol=1e-12)


def test_batch_equals_per_item_and_chunking(rng):
    """Batch == per-item == any chunk size (frames are independent)."""
    R, t = poses(40, P12, rng)
    ang = angles_of(P12, R, t) + sample_angle_noise((40, 12), SIGMA_THETA_PAPER, 0.0, rng)
    vis = rng.random((40, 12)) < 0.7
    batch = solve_pnp(P12, ang, vis)
    chunked = solve_pnp(P12, ang, vis, chunk_size=7)
    items = [solve_pnp(P12, ang[f], vis[f][None]) for f in range(40)]
    for field in ("rotation", "translation", "residual_rms"):
        one = np.concatenate([getattr(r, field) for r in items])
        np.testing.assert_allclose(getattr(batch, field), one, atol=1e-12, equal_nan=True)
        np.testing.assert_allclose(getattr(chunked, field), one, atol=1e-12, equal_nan=True)
    np.testing.assert_array_equal(batch.status, np.concatenate([r.status for r in items]))


def test_single_frame_shapes(rng):
    """(n, 2) angles give a batch of one with a leading F axis."""
    R, t = poses(1, P12, rng)
    res = solve_pnp(P12, angles_of(P12, R, t)[0])
    assert isinstance(res, PnPResult)
    assert res.rotation.shape == (1, 3, 3) and res.translation.shape == (1, 3)
    assert res.success.shape == res.status.shape == res.residual_rms.shape == res.iterations.shape == (1,)
    assert res.message == "ok (1 frame(s))"


def test_previous_frame_start(rng):
    """Tracking: starting from the previous solution (or a good guess) gives the same estimate;
    a wrong start (attitude flipped by 180°) falls back to the cold start. "Same" is to 1e-8 rad / m,
    the convergence tolerance (1e-5 of the ~1e-3 rad noise-driven spread of the estimate)."""
    R, t = poses(200, P12, rng)
    ang = angles_of(P12, R, t) + sample_angle_noise((200, 12), SIGMA_THETA_PAPER, 0.0, rng)
    cold = solve_pnp(P12, ang)
    warm = solve_pnp(P12, ang, initial=(cold.rotation, cold.translation))
    np.testing.assert_allclose(warm.rotation, cold.rotation, atol=1e-8)
    np.testing.assert_allclose(warm.translation, cold.translation, atol=1e-8)
    near = solve_pnp(P12, ang, initial=(R, t + 0.01))
    np.testing.assert_allclose(near.rotation, cold.rotation, atol=1e-8)
    flip = np.diag([-1.0, -1.0, 1.0])
    bad = solve_pnp(P12, ang, initial=(flip @ R, -t))
    assert bad.success.all()
    np.testing.assert_allclose(bad.rotation, cold.rotation, atol=1e-8)


def test_estimate_is_a_minimum_of_the_angle_cost(rng):
    """Maximum likelihood: at the estimate the gradient J^T r of the angle cost vanishes (J from the
    independent dop.angle_jacobian), and the cost is not above the cost at the true pose."""
    R, t = poses(300, P12, rng)
    ang = angles_of(P12, R, t) + sample_angle_noise((300, 12), SIGMA_THETA_PAPER, 0.0, rng)
    res = solve_pnp(P12, ang)
    p = transform_points(res.rotation, res.translation, P12)
    J = angle_jacobian(p, p - res.translation[:, None, :]).reshape(300, 24, 6)
    r = (ang - sweep_angles(p)).reshape(300, 24)
    grad = np.einsum("fki,fk->fi", J, r)
    scale = np.linalg.norm(J, axis=1) * np.linalg.norm(r, axis=1)[:, None]
    assert np.max(np.abs(grad) / scale) < 1e-3
    cost_est = np.sum(r * r, axis=1)
    cost_true = np.sum((ang - angles_of(P12, R, t)).reshape(300, 24) ** 2, axis=1)
    assert np.all(cost_est <= cost_true * (1 + 1e-9))
    np.testing.assert_allclose(res.residual_rms, np.sqrt(cost_est / 24), rtol=1e-6)


def test_monte_carlo_error_matches_cramer_rao(rng):
    """Monte-Carlo vs predicted covariance: over 4000 noisy frames (rho = 0) the mean squared
    attitude / position error equals sigma² trace(H) of pose_dop (Chen eq. 18) within 4 standard
    errors of the sample mean (the standard error is estimated from the same sample, ~1.3%)."""
    F = 4000
    R, t = poses(F, P12, rng)
    ang = angles_of(P12, R, t) + sample_angle_noise((F, 12), SIGMA_THETA_PAPER, 0.0, rng)
    res = solve_pnp(P12, ang)
    assert res.success.all()
    e_rot, e_t = errors(res, R, t)
    H = pose_dop(P12, R, t).cov * SIGMA_THETA_PAPER ** 2
    for err, var in ((e_rot, np.trace(H[:, :3, :3], axis1=1, axis2=2)),
                     (e_t, np.trace(H[:, 3:, 3:], axis1=1, axis2=2))):
        z = err ** 2 / var  # mean 1 for an efficient estimator
        se = z.std(ddof=1) / np.sqrt(F)
        assert abs(z.mean() - 1.0) < 4 * se, (z.mean(), se)


def test_degenerate_inputs_give_status(rng):
    """Fewer than 4 lit sensors, NaN angles and collinear sensors give a status, not an exception."""
    R, t = poses(6, P12, rng)
    ang = angles_of(P12, R, t)
    vis = np.ones((6, 12), bool)
    vis[0, 3:] = False                      # 3 lit
    ang[1, 2:] = np.nan                     # 2 finite
    ang[2] = np.nan                         # nothing
    vis[3, :] = False
    ang[4, :, 0] = np.inf                   # non-finite
    res = solve_pnp(P12, ang, vis)
    np.testing.assert_array_equal(res.status, [STATUS_NO_START] + [STATUS_TOO_FEW] * 3 + [STATUS_INVALID_ANGLE, STATUS_OK])
    assert not res.success[:5].any() and res.success[5]
    assert np.isnan(res.rotation[:5]).all() and np.isnan(res.residual_rms[:5]).all()
    assert "3 too few angles" in res.message and "1 invalid angle" in res.message and "1 no start" in res.message
    # collinear body points (a rod), 5 sensors
    rod = np.outer(np.linspace(-0.05, 0.05, 5), [1.0, 0.5, 0.2])
    Rr, tr = poses(3, rod, rng)
    res = solve_pnp(rod, angles_of(rod, Rr, tr))
    np.testing.assert_array_equal(res.status, [STATUS_DEGENERATE] * 3)


def test_bad_shapes_exact_messages():
    """Shape errors name the expected and the actual shapes."""
    ang = np.full((5, 12, 2), 1.5)
    with pytest.raises(ValueError) as e:
        solve_pnp(P12, np.full((5, 12, 3), 1.5))
    assert str(e.value) == "angles: expected shape (..., *, 2), got (5, 12, 3)"
    with pytest.raises(ValueError) as e:
        solve_pnp(P12[:11], ang)
    assert str(e.value) == "points_body: expected shape (12, 3) or (5, 12, 3), got (11, 3)"
    with pytest.raises(ValueError) as e:
        solve_pnp(np.zeros((4, 12, 3)), ang)
    assert str(e.value) == "points_body: expected shape (12, 3) or (5, 12, 3), got (4, 12, 3)"
    with pytest.raises(ValueError) as e:
        solve_pnp(P12, ang, np.ones((5, 11), bool))
    assert str(e.value) == "visible: expected shape (5, 12) per sensor or (5, 12, 2) per angle, got (5, 11)"
    with pytest.raises(ValueError) as e:
        solve_pnp(P12, ang, initial=(np.eye(3), np.zeros(3)))
    assert str(e.value) == "initial: expected shapes (5, 3, 3) and (5, 3), got (3, 3) and (3,)"
    with pytest.raises(ValueError) as e:
        solve_pnp(P12, ang, method="nope")
    assert str(e.value) == "method: expected one of ['lm', 'lm-numpy'], got 'nope'"


def test_normal_equations_match_dop_angle_jacobian(rng):
    """The unrolled normal equations equal J^T J and J^T r built from dop.angle_jacobian."""
    R, t = poses(30, P12, rng)
    ang = angles_of(P12, R, t) + 1e-3 * rng.standard_normal((30, 12, 2))
    vis = rng.random((30, 12)) < 0.8
    fr = pnp_lh1._Frames(P12, ang, vis)
    ev = pnp_lh1._eval(fr, R.reshape(30, 9).T.copy(), t.T.copy())
    A, g = pnp_lh1._normal_equations(fr, ev)
    p = transform_points(R, t, P12)
    J = (angle_jacobian(p, p - t[:, None, :]) * vis[..., None, None]).reshape(30, 24, 6)
    r = ((ang - sweep_angles(p)) * vis[..., None]).reshape(30, 24)
    A_ref = np.einsum("fki,fkj->fij", J, J)
    iu = np.triu_indices(6)
    A_got = np.stack([A[i][j] for i, j in zip(*iu)], -1)
    np.testing.assert_allclose(A_got, A_ref[:, iu[0], iu[1]], rtol=1e-12, atol=1e-12 * np.abs(A_ref).max())
    np.testing.assert_allclose(np.stack(g, -1), np.einsum("fki,fk->fi", J, r), rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(ev["cost"], np.sum(r * r, axis=1), rtol=1e-9)


@pytest.mark.parametrize("name", ["all12", "mixed6", "eight"])
def test_agrees_with_opencv_sqpnp_noise_free(name, rng):
    """Independent reference: OpenCV SQPNP on the same noise-free frames (normalised coordinates,
    K = I) finds the same poses."""
    cv2 = pytest.importorskip("cv2")
    P = P12[SUBSETS[name]]
    R, t = poses(50, P, rng)
    ang = angles_of(P, R, t)
    res = solve_pnp(P, ang)
    uv = np.cos(ang) / np.sin(ang)
    for f in range(50):
        ok, rvec, tvec = cv2.solvePnP(P, uv[f], np.eye(3), None, flags=cv2.SOLVEPNP_SQPNP)
        assert ok
        Rc = cv2.Rodrigues(rvec)[0]
        assert attitude_error(res.rotation[f], Rc) < 1e-7
        np.testing.assert_allclose(res.translation[f], tvec[:, 0], atol=1e-7)


def test_agrees_with_opencv_ippe_coplanar_noise_free(rng):
    """Independent reference for the planar branch: OpenCV IPPE on 4 coplanar sensors."""
    cv2 = pytest.importorskip("cv2")
    P = P12[TOP]
    R, t = poses(50, P, rng)
    ang = angles_of(P, R, t)
    res = solve_pnp(P, ang)
    uv = np.cos(ang) / np.sin(ang)
    for f in range(50):
        ok, rvec, tvec = cv2.solvePnP(P, uv[f], np.eye(3), None, flags=cv2.SOLVEPNP_IPPE)
        assert ok
        assert attitude_error(res.rotation[f], cv2.Rodrigues(rvec)[0]) < 1e-7
        np.testing.assert_allclose(res.translation[f], tvec[:, 0], atol=1e-7)


def test_no_gross_failures_n12_with_paper_noise(rng):
    """Robustness (reduced version of the 180k-frame benchmark): no frame off by > 1 deg."""
    R, t = poses(5000, P12, rng)
    ang = angles_of(P12, R, t) + sample_angle_noise((5000, 12), SIGMA_THETA_PAPER, 0.8717, rng)
    res = solve_pnp(P12, ang)
    assert res.success.all()
    assert np.rad2deg(attitude_error(res.rotation, R)).max() < 1.0


def test_unobservable_range_and_non_rotation_start(rng):
    """All sensors on one ray (equal angles) has no finite pose → degenerate status; a start that
    is not a rotation (scaled identity) is projected onto SO(3) and still converges."""
    res = solve_pnp(P12, np.full((1, 12, 2), 1.5))
    np.testing.assert_array_equal(res.status, [STATUS_DEGENERATE])
    R, t = poses(5, P12, rng)
    ang = angles_of(P12, R, t)
    res = solve_pnp(P12, ang, initial=(2.0 * R, t))
    assert res.success.all()
    assert attitude_error(res.rotation, R).max() < 1e-9
    assert solve_pnp(P12, np.zeros((0, 12, 2))).message == "no frames"


@pytest.mark.parametrize("qmax", [5e-3, 4e-2, 0.5])
def test_angle_residual_series_matches_arctan2(qmax, rng):
    """The small-argument series of the residual equals numpy's arctan2 to 1e-17 in every tier
    (short series, long series, exact fallback), including negative denominators."""
    den = rng.uniform(0.5, 2.0, 2000)
    num = rng.uniform(-qmax, qmax, 2000) * den
    np.testing.assert_allclose(pnp_lh1._atan_ratio(num, den), np.arctan2(num, den), rtol=0, atol=1e-17)
    den[0] = -1.0
    np.testing.assert_allclose(pnp_lh1._atan_ratio(num, den), np.arctan2(num, den), rtol=0, atol=1e-17)
