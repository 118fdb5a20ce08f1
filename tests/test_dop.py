"""ADOP/PDOP (Chen eqs. 18–22) against independent routes.

Proof kinds: finite-difference Jacobian through the paper's rotation-vector coordinates and J_r
(eq. 21) with the explicit 2n×2n correlation matrix of eq. (19); closed-form frame changes;
batch == per-item; Monte-Carlo of the linearised estimator against H σ².
"""
import numpy as np
import pytest

from layoutkit.dop import angle_jacobian, pose_dop, precision, pose_errors
from layoutkit.geometry import random_rotations, right_jacobian_so3, rotvec_to_matrix, skew
from layoutkit.lighthouse import Station, sweep_angles
from layoutkit.noise import angle_correlation, sample_angle_noise
from layoutkit.shapes import chen_target


def _random_case(rng, n=None):
    n = n or int(rng.integers(4, 13))
    P = rng.uniform(-0.07, 0.07, (n, 3))
    phi = rng.normal(size=3)
    phi *= rng.uniform(0.1, 3.0) / np.linalg.norm(phi)
    t = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(1.0, 3.0)])
    return P, phi, t


def _paper_route_dop(P, phi, t, rho, h=1e-6):
    """Chen's own route: psi = (phi, t) with R = R(phi); FD Jacobian of the angle vector
    ordered [th1x, th1y, th2x, ...] (eq. 14); H by eq. (18) with R_theta of eq. (19);
    ADOP with J_r (eq. 21–22)."""
    def angles(psi):
        R = rotvec_to_matrix(psi[:3])
        return sweep_angles(P @ R.T + psi[3:]).reshape(-1)

    psi0 = np.concatenate([phi, t])
    J = np.empty((2 * len(P), 6))
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        J[:, k] = (angles(psi0 + d) - angles(psi0 - d)) / (2 * h)
    Rth = angle_correlation(len(P), rho)
    G = np.linalg.inv(J.T @ J)
    H = G @ J.T @ Rth @ J @ G  # eq. (18)
    Jr = right_jacobian_so3(phi)
    adop = np.degrees(np.sqrt(np.trace(Jr @ H[:3, :3] @ Jr.T)))  # eq. (22)
    pdop = np.sqrt(np.trace(H[3:, 3:]))
    return adop, pdop


@pytest.mark.parametrize("rho", [0.0, 0.5, 0.8717])
def test_pose_dop_equals_paper_route_finite_differences(rng, rho):
    """pose_dop == FD implementation of eqs. (14), (18), (19), (21), (22) to 1e-6 relative."""
    for _ in range(20):
        P, phi, t = _random_case(rng)
        ref_a, ref_p = _paper_route_dop(P, phi, t, rho)
        r = pose_dop(P, rotvec_to_matrix(phi), t, rho=rho)
        assert r.success
        assert r.adop == pytest.approx(ref_a, rel=1e-6)
        assert r.pdop == pytest.approx(ref_p, rel=1e-6)


def test_analytic_jacobian_matches_finite_differences(rng):
    """angle_jacobian == central differences of sweep_angles under the left perturbation."""
    P, phi, t = _random_case(rng, 7)
    R = rotvec_to_matrix(phi)
    J = angle_jacobian(P @ R.T + t, P @ R.T)
    h = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        def ang(s):
            Rp = rotvec_to_matrix(s * d[:3]) @ R
            return sweep_angles(P @ Rp.T + t + s * d[3:])
        fd = (ang(1) - ang(-1)) / (2 * h)
        np.testing.assert_allclose(J[..., k], fd, rtol=1e-6, atol=1e-9)


def test_dop_invariant_to_body_rotation_and_origin_shift_closed_form(rng):
    """Re-expressing the same physical set-up in another body frame (P' = Q P + c):
    ADOP and H_rot unchanged; H transforms by the lever-arm map of the new origin."""
    P, phi, t = _random_case(rng, 9)
    R = rotvec_to_matrix(phi)
    Q = random_rotations(1, rng)[0]
    c = rng.normal(scale=0.1, size=3)
    P2 = P @ Q.T + c
    R2 = R @ Q.T
    t2 = t - R2 @ c
    np.testing.assert_allclose(P2 @ R2.T + t2, P @ R.T + t, atol=1e-12)
    a = pose_dop(P, R, t, rho=0.8717)
    b = pose_dop(P2, R2, t2, rho=0.8717)
    assert b.adop == pytest.approx(a.adop, rel=1e-9)
    # new origin is the old body point P0 = -Q^T c: dt' = dt - [R P0]x dphi
    T = np.eye(6)
    T[3:, :3] = -skew(R @ (-Q.T @ c))
    np.testing.assert_allclose(b.cov, T @ a.cov @ T.T, rtol=1e-7, atol=1e-12 * np.abs(a.cov).max())
    # pure rotation of the body frame (c = 0) leaves PDOP unchanged too
    c0 = pose_dop(P @ Q.T, R2, t, rho=0.8717)
    assert c0.pdop == pytest.approx(a.pdop, rel=1e-9)


def test_batch_equals_per_item(rng):
    """Batched poses and per-pose calls agree exactly, visibility masks included."""
    P = rng.uniform(-0.07, 0.07, (10, 3))
    R = random_rotations(25, rng)
    t = np.column_stack([rng.uniform(-1, 1, 25), rng.uniform(-1, 1, 25), rng.uniform(1, 3, 25)])
    vis = rng.random((25, 10)) < 0.7
    vis[:, :4] = True
    batch = pose_dop(P, R, t, rho=0.8717, visible=vis)
    for i in range(25):
        one = pose_dop(P[vis[i]], R[i], t[i], rho=0.8717)
        assert batch.adop[i] == pytest.approx(float(one.adop), rel=1e-10)
        assert batch.pdop[i] == pytest.approx(float(one.pdop), rel=1e-10)


def test_station_in_world_equals_station_frame(rng):
    """A station with a world pose gives the same DOP as the pose expressed in its own frame
    (trace invariance under the world→station rotation of dt)."""
    P = rng.uniform(-0.07, 0.07, (8, 3))
    Rs = random_rotations(1, rng)[0]
    st = Station("B", Rs, np.array([1.0, -2.0, 0.5]))
    Rb = random_rotations(1, rng)[0]
    # body 2 m along the station boresight, expressed in the world
    tb = Rs @ np.array([0.1, -0.2, 2.0]) + st.translation
    w = pose_dop(P, Rb, tb, rho=0.6, stations=[st])
    R_loc, t_loc = st.world_to_station(Rb, tb)
    s = pose_dop(P, R_loc, t_loc, rho=0.6)
    assert float(w.adop) == pytest.approx(float(s.adop), rel=1e-9)
    assert float(w.pdop) == pytest.approx(float(s.pdop), rel=1e-9)


def test_two_stations_correlate_only_within_a_rotor(rng):
    """Two stations: H from the closed form equals eq. (18) with a block-diagonal R_theta
    (eq. 19 within each station, zero across stations), built explicitly."""
    P = rng.uniform(-0.07, 0.07, (6, 3))
    st = [Station("A"), Station("B", rotvec_to_matrix([0, 0.4, 0]), np.array([-0.8, 0, 0.2]))]
    Rb = random_rotations(1, rng)[0]
    tb = np.array([0.0, 0.1, 2.0])
    rho = 0.8717
    res = pose_dop(P, Rb, tb, rho=rho, stations=st)
    Js = []
    for s in st:
        Rl, tl = s.world_to_station(Rb, tb)
        Js.append(angle_jacobian(P @ Rl.T + tl, P @ Rb.T, s.rotation).reshape(-1, 6))
    J = np.vstack(Js)
    Rth = np.zeros((24, 24))
    Rth[:12, :12] = angle_correlation(6, rho)
    Rth[12:, 12:] = angle_correlation(6, rho)
    G = np.linalg.inv(J.T @ J)
    np.testing.assert_allclose(res.cov, G @ J.T @ Rth @ J @ G, rtol=1e-9)


def test_monte_carlo_linearised_estimator_matches_H(rng):
    """Sampled correlated noise through the least-squares map (eq. 16) has covariance H σ²."""
    mesh, lay = chen_target()
    R = rotvec_to_matrix([0.3, -0.2, 0.1])
    t = np.array([0.2, -0.1, 2.0])
    P = lay.positions
    J = angle_jacobian(P @ R.T + t, P @ R.T).reshape(-1, 6)
    sigma, rho = 4e-5, 0.8717
    e = sample_angle_noise((40000, P.shape[0]), sigma, rho, rng).reshape(40000, -1)
    dpsi = e @ (np.linalg.pinv(J)).T
    emp = np.cov(dpsi.T)
    H = pose_dop(P, R, t, rho=rho).cov * sigma**2
    # diagonal variances within 4 standard errors of the sample variance (sqrt(2/N))
    np.testing.assert_allclose(np.diag(emp), np.diag(H), rtol=4 * np.sqrt(2 / 40000))


def test_degenerate_geometry_is_a_status_not_an_exception():
    """Collinear sensors: singular J^T J → status 2, inf DOP; < 3 lit → status 1."""
    P = np.column_stack([np.linspace(-0.05, 0.05, 6), np.zeros(6), np.zeros(6)])
    r = pose_dop(P, np.eye(3), [0, 0, 2.0])
    assert not r.success and r.status == 2 and np.isinf(r.adop)
    P2 = np.random.default_rng(0).uniform(-0.05, 0.05, (5, 3))
    vis = np.array([True, True, False, False, False])
    r2 = pose_dop(P2, np.eye(3), [0, 0, 2.0], visible=vis)
    assert r2.status == 1 and "fewer than 3" in r2.message


def test_bad_shapes_name_expected_and_actual():
    with pytest.raises(ValueError, match=r"rotation: expected shape \(\.\.\., 3, 3\), got \(3, 2\)"):
        pose_dop(np.zeros((4, 3)), np.zeros((3, 2)), np.zeros(3))
    with pytest.raises(ValueError, match="translation: 1 non-finite value"):
        pose_dop(np.ones((4, 3)), np.eye(3), [0, np.nan, 2])


def test_precision_and_errors_closed_form(rng):
    """eq. (23): rotations spread by known small angles about a mean; eq. (25) per frame."""
    R0 = random_rotations(1, rng)[0]
    ang = np.deg2rad(0.1)
    axes = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]], float)
    Rs = rotvec_to_matrix(axes * ang) @ R0
    ts = np.array([[0.001, 0, 2], [-0.001, 0, 2], [0, 0.002, 2], [0, -0.002, 2]])
    s_rot, s_t = precision(Rs, ts)
    assert s_rot == pytest.approx(ang, rel=1e-6)
    assert s_t == pytest.approx(np.sqrt((2 * 1e-6 + 2 * 4e-6) / 4), rel=1e-9)
    e_rot, e_t = pose_errors(Rs, ts, np.broadcast_to(R0, Rs.shape), np.array([0, 0, 2.0]))
    np.testing.assert_allclose(e_rot, ang, rtol=1e-9)


def test_predicted_precision_is_eq24_and_matches_monte_carlo():
    """Chen eq. (24) in one place: sqrt(mean(ADOP²)) sigma over poses; against a Monte-Carlo of the
    linearised model (pose noise drawn with covariance sigma² H) at two poses, within 5 %."""
    from layoutkit.dop import predicted_precision
    from layoutkit.shapes import chen_target

    lay = chen_target()[1]
    R = np.stack([rotvec_to_matrix([np.pi, 0, 0]), rotvec_to_matrix([np.pi - 0.3, 0.2, 0])])
    t = np.array([[0.0, 0.1, 2.0], [0.2, 0.0, 2.5]])
    d = pose_dop(lay.positions, R, t, rho=0.5)
    sigma = 4e-5
    pr, pt = predicted_precision(d.adop, d.pdop, sigma)
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.multivariate_normal(np.zeros(6), sigma**2 * d.cov[k], 20000) for k in range(2)])
    mc_rot = np.degrees(np.sqrt(np.mean(np.sum(x[:, :3] ** 2, 1))))
    mc_t = np.sqrt(np.mean(np.sum(x[:, 3:] ** 2, 1)))
    assert abs(pr / mc_rot - 1) < 0.05 and abs(pt / mc_t - 1) < 0.05


def test_gross_failure_rule():
    """One rule: failed solve, attitude error > 1 deg (NaN counts), or body behind the station."""
    from layoutkit.dop import gross_failures

    e = np.radians([0.5, 1.5, 0.1, np.nan, 0.2])
    ok = np.array([True, True, False, True, True])
    tr = np.array([[0, 0, 2.0]] * 4 + [[0, 0, -1.0]])
    np.testing.assert_array_equal(gross_failures(e, success=ok, translation=tr), [False, True, True, True, True])
    np.testing.assert_array_equal(gross_failures(e[:2]), [False, True])
