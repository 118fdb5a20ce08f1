"""Tests of the rectangle-face attitude solvers (Zhai et al. 2014) and camera conventions."""
import numpy as np
import pytest

import layoutkit
from layoutkit.camera import (
    BOX_FACES,
    RECTANGLE_SOLVERS,
    box_attitude,
    euler_zyx,
    euler_zyx_to_matrix,
    frame_rotation,
    label_symmetries,
    order_corners,
    rectangle_attitude,
    rectangle_corners,
    resolve_labelling,
    solve_rectangle,
    zhai_depth_ratios,
)
from layoutkit.camera.conventions import (
    pixels_to_paper_uv,
    pose_cv_to_paper,
    pose_paper_to_cv,
    project_paper,
)
from layoutkit.geometry import attitude_error, random_rotations

F_PX = 8e-3 / 3.75e-6


def _visible_poses(rng, n, H=2.0, L=3.0, W=1.5, dist=(5.0, 40.0), max_tilt_deg=75.0):
    """Random poses whose observed face (x_t = H/2) is in front of the camera and facing it."""
    Rs, Ts = [], []
    while len(Rs) < n:
        R = random_rotations(1, rng)[0]
        T = np.array([-rng.uniform(*dist), rng.uniform(-2, 2), rng.uniform(-2, 2)])
        Pc = rectangle_corners(H, L, W) @ R.T + T
        view = -Pc.mean(0) / np.linalg.norm(Pc.mean(0))
        if np.all(Pc[:, 0] < -0.5) and R[:, 0] @ view > np.cos(np.radians(max_tilt_deg)):
            Rs.append(R)
            Ts.append(T)
    return np.array(Rs), np.array(Ts), rectangle_corners(H, L, W)


def _project(R, T, P, f=F_PX):
    return project_paper(np.einsum("...ij,nj->...ni", R, P) + T[..., None, :], f)


def test_public_names_resolve_lazily():
    """The package-level names are the camera room's functions (API contract)."""
    assert layoutkit.rectangle_attitude is rectangle_attitude
    assert layoutkit.euler_zyx is euler_zyx


def test_noise_free_attitude_exact_on_random_visible_poses(rng):
    """Closed form: exact corners of random visible poses give back the generating R to 1e-9."""
    R, T, P = _visible_poses(rng, 200)
    R_est = rectangle_attitude(_project(R, T, P), F_PX)
    assert attitude_error(R_est, R).max() < 1e-9
    # proper rotations
    np.testing.assert_allclose(np.linalg.det(R_est), 1.0, atol=1e-12)


def test_depth_ratios_match_true_depths_and_eq10_erratum(rng):
    """a, b (eqs. 8, 9) equal the true depth ratios; x4c/x1c = a + b - 1 (design §7 erratum of eq. 10)."""
    R, T, P = _visible_poses(rng, 50)
    Pc = np.einsum("tij,nj->tni", R, P) + T[:, None, :]
    a, b, c = zhai_depth_ratios(_project(R, T, P))
    x = Pc[..., 0]
    np.testing.assert_allclose(a, x[:, 1] / x[:, 0], rtol=1e-10)
    np.testing.assert_allclose(b, x[:, 2] / x[:, 0], rtol=1e-10)
    np.testing.assert_allclose(c, x[:, 3] / x[:, 0], rtol=1e-10)


def test_batch_equals_per_item(rng):
    """Batched (T, 4, 2) and nested (2, T/2, 4, 2) calls equal item-by-item calls, noisy corners."""
    R, T, P = _visible_poses(rng, 20)
    uv = _project(R, T, P) + rng.normal(0, 0.5, (20, 4, 2))
    batch = rectangle_attitude(uv, F_PX)
    single = np.array([rectangle_attitude(q, F_PX) for q in uv])
    np.testing.assert_array_equal(batch, single)
    np.testing.assert_array_equal(rectangle_attitude(uv.reshape(2, 10, 4, 2), F_PX).reshape(20, 3, 3), batch)


def test_noisy_corners_still_give_proper_rotations(rng):
    """With noise eqs. (15)-(16) are not orthogonal; the result is projected onto SO(3)."""
    R, T, P = _visible_poses(rng, 100)
    uv = _project(R, T, P) + rng.normal(0, 2.0, (100, 4, 2))
    Re = rectangle_attitude(uv, F_PX)
    np.testing.assert_allclose(Re @ np.swapaxes(Re, -1, -2), np.broadcast_to(np.eye(3), Re.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(Re), 1.0, atol=1e-12)


@pytest.mark.parametrize("method", sorted(RECTANGLE_SOLVERS))
def test_registry_methods_exact_without_noise(rng, method):
    """Every registered solver recovers the generating rotation from exact corners."""
    R, T, P = _visible_poses(rng, 30, L=3.0, W=1.5)
    opts = {"aspect_ratio": 2.0, "reference": R} if method == "ippe" else {}
    sol = solve_rectangle(_project(R, T, P), F_PX, method=method, **opts)
    assert sol.success.all(), sol.status
    tol = 1e-6 if method == "ippe" else 1e-9  # OpenCV IPPE refines in float64 to ~1e-8
    assert attitude_error(sol.rotation, R).max() < tol


def test_zhai_equals_homography_under_noise(rng):
    """Two independent derivations (depth ratios vs DLT homography) agree on noisy corners."""
    R, T, P = _visible_poses(rng, 50)
    uv = _project(R, T, P) + rng.normal(0, 0.3, (50, 4, 2))
    a = solve_rectangle(uv, F_PX, "zhai").rotation
    b = solve_rectangle(uv, F_PX, "homography").rotation
    assert attitude_error(a, b).max() < 1e-7


def test_mirrored_labelling_is_reported(rng):
    """Swapping P2 and P3 (mirror) turns the face normal away: status 'mirrored', not success."""
    R, T, P = _visible_poses(rng, 10)
    uv = _project(R, T, P)[:, [0, 2, 1, 3]]
    sol = solve_rectangle(uv, F_PX)
    assert not sol.success.any()
    assert set(sol.status) == {"mirrored"}


def test_180_degree_relabelling_and_resolution(rng):
    """P1<->P4, P2<->P3 is also an exact solution, R @ Rx(180°); resolve_labelling restores R."""
    R, T, P = _visible_poses(rng, 40, L=2.0, W=2.0)
    uv = _project(R, T, P)
    R180 = rectangle_attitude(uv[:, [3, 2, 1, 0]], F_PX)
    np.testing.assert_allclose(R180, R @ frame_rotation("x", np.pi), atol=1e-9)
    assert attitude_error(resolve_labelling(R180, R, n_fold=2), R).max() < 1e-9
    # a cyclic shift by one corner (P1 -> P2 -> P4 -> P3) is a 90° turn about x_t for a square
    R90 = rectangle_attitude(uv[:, [2, 0, 3, 1]], F_PX)
    S = label_symmetries(4)
    d = [attitude_error(R90, R @ s).max() for s in S]
    assert min(d) < 1e-9 and np.argmin(d) in (1, 3)
    assert attitude_error(resolve_labelling(R90, R, n_fold=4), R).max() < 1e-9


def test_order_corners_recovers_labels_from_any_permutation(rng):
    """order_corners(shuffled) equals the true order up to the documented cyclic labelling shift."""
    R, T, P = _visible_poses(rng, 30, max_tilt_deg=50)
    uv = _project(R, T, P)
    for i in range(30):
        perm = rng.permutation(4)
        got = order_corners(uv[i, perm])
        R_got = rectangle_attitude(got, F_PX)
        assert attitude_error(resolve_labelling(R_got, R[i]), R[i]) < 1e-9
        assert solve_rectangle(got, F_PX).status == "ok"


def test_euler_round_trip_and_paper_formulas(rng):
    """euler_zyx inverts Rx(θ3)Ry(θ2)Rz(θ1); θ's equal Zhai's closed forms; gimbal-lock branch."""
    th = np.stack([rng.uniform(-np.pi, np.pi, 500), rng.uniform(-1.5, 1.5, 500), rng.uniform(-np.pi, np.pi, 500)])
    R = euler_zyx_to_matrix(*th)
    got = np.array(euler_zyx(R))
    np.testing.assert_allclose(got, th, atol=1e-12)
    # the paper's formula with plain arctan, where the angles are in (-90°, 90°)
    small = np.all(np.abs(th) < 1.5, axis=0)
    np.testing.assert_allclose(np.arctan(R[small, 0, 1] / R[small, 0, 0]), th[0, small], atol=1e-12)
    np.testing.assert_allclose(np.arctan(R[small, 1, 2] / R[small, 2, 2]), th[2, small], atol=1e-12)
    # frame rotations are transposes of scipy's active rotations
    from scipy.spatial.transform import Rotation
    np.testing.assert_allclose(frame_rotation("y", 0.3), Rotation.from_euler("y", 0.3).as_matrix().T, atol=1e-15)
    # gimbal lock: θ2 = ±90°, θ3 = 0 and R reproduced
    for t2 in (np.pi / 2, -np.pi / 2):
        Rg = euler_zyx_to_matrix(0.7, t2, 0.0)
        t1g, t2g, t3g = euler_zyx(Rg)
        assert t3g == 0.0 and abs(t2g - t2) < 1e-6
        np.testing.assert_allclose(euler_zyx_to_matrix(t1g, t2g, t3g), Rg, atol=1e-12)


def test_conventions_round_trip_and_projection(rng):
    """Paper <-> OpenCV poses: same image points through cv2.projectPoints and Zhai eq. (3)."""
    import cv2

    R, T, P = _visible_poses(rng, 5)
    K = np.array([[F_PX, 0, 640.3], [0, F_PX, 480.2], [0, 0, 1]])
    for i in range(5):
        Rc, tc = pose_paper_to_cv(R[i], T[i])
        assert np.isclose(np.linalg.det(Rc), 1.0)
        px = cv2.projectPoints(P, cv2.Rodrigues(Rc)[0], tc, K, None)[0][:, 0]
        uv = pixels_to_paper_uv(px, (640.3, 480.2))
        np.testing.assert_allclose(uv, _project(R[i], T[i], P), atol=1e-8)
        R2, T2 = pose_cv_to_paper(Rc, tc)
        np.testing.assert_allclose(R2, R[i], atol=1e-15)
        np.testing.assert_allclose(T2, T[i], atol=1e-12)


def test_box_attitude_averages_faces(rng):
    """Two faces of a box seen at once: each face alone and the averaged box attitude are exact."""
    R_box = euler_zyx_to_matrix(0.4, -0.3, 0.2)
    R_box = frame_rotation("z", 0.5) @ frame_rotation("y", -0.4)  # sees +x and +y faces
    T = np.array([-20.0, 0.0, 0.0])
    faces = {}
    for name in ("+x", "+y"):
        Fm = BOX_FACES[name]
        Pf = rectangle_corners(2.0, 2.0, 2.0) @ Fm.T  # the face's corners in the box frame
        faces[name] = _project(R_box, T, Pf)
    sol = box_attitude(faces, F_PX)
    assert sol.success and attitude_error(sol.rotation, R_box) < 1e-9
    noisy = {k: v + rng.normal(0, 0.2, v.shape) for k, v in faces.items()}
    single = [attitude_error(solve_rectangle(v, F_PX).rotation @ BOX_FACES[k].T, R_box) for k, v in noisy.items()]
    both = attitude_error(box_attitude(noisy, F_PX).rotation, R_box)
    assert both <= max(single) + 1e-12


@pytest.mark.parametrize(
    "args, message",
    [
        ((np.zeros((4, 3)), 1.0), "corners_uv: expected shape (..., 4, 2), got (4, 3)"),
        ((np.ones((4, 2)), -1.0), "focal_length: expected a positive finite number, got -1.0"),
        ((np.full((4, 2), np.nan), 1.0), "corners_uv: 8 non-finite value(s) (NaN or inf)"),
    ],
)
def test_bad_input_messages(args, message):
    """Bad input raises ValueError with the exact message."""
    with pytest.raises(ValueError) as e:
        rectangle_attitude(*args)
    assert str(e.value) == message


def test_degenerate_quadrilateral_is_a_status():
    """Collinear corners: NaN rotation and status 'degenerate', no exception."""
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.0]])
    sol = solve_rectangle(uv, 100.0)
    assert not sol.success and sol.status == "degenerate"
    assert np.all(np.isnan(rectangle_attitude(uv, 100.0)))
    with pytest.raises(ValueError, match="method: expected one of"):
        solve_rectangle(uv, 100.0, method="nope")
