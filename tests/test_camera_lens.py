"""Lens distortion everywhere a camera appears (issue 28 item 1): the camera model file, the lens
maps, the pixel-level face attitude and its predicted sigma, the synthetic camera with distortion.

Kinds of proof: round trips through OpenCV's own functions (``cv2.FileStorage``,
``cv2.projectPoints``), finite differences, Monte-Carlo scatter vs the predicted covariance,
renders checked against the analytic (distorted) polygon.
"""
from pathlib import Path

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from layoutkit.camera.conventions import PAPER_FROM_CV  # noqa: E402
from layoutkit.camera.face import face_attitude, pixels_to_ideal_uv  # noqa: E402
from layoutkit.camera.rectangle import resolve_labelling, solve_rectangle  # noqa: E402
from layoutkit.camera.lens import (distort_jacobian, distort_pixels, undistort_jacobian,  # noqa: E402
                                   undistort_pixels)
from layoutkit.geometry import attitude_error, matrix_to_rotvec, rotvec_to_matrix  # noqa: E402
from layoutkit.io.camera import (CameraMeta, CameraModel, read_camera_meta, read_camera_model,  # noqa: E402
                                 write_camera_meta, write_camera_model)

DATA = Path(__file__).parent / "data" / "camera"
K = np.array([[535.9, 0.0, 342.3], [0.0, 535.9, 235.6], [0.0, 0.0, 1.0]])
D = np.array([-0.266, -0.0386, 0.00178, -0.00028, 0.238])  # the OpenCV sample camera (k1 = -0.27)
FACE = np.array([[-0.1, -0.0625, 0.0], [0.1, -0.0625, 0.0], [0.1, 0.0625, 0.0], [-0.1, 0.0625, 0.0]])  # 1.6:1


def _project(R, t, pts, dist=D):
    return cv2.projectPoints(pts, cv2.Rodrigues(R)[0], t, K, dist)[0].reshape(-1, 2)


# ----------------------------------------------------------------------------- camera model file
def test_reads_opencv_sample_intrinsics():
    """The OpenCV calibration sample's file (``%YAML:1.0``, opencv-matrix nodes) reads as written there."""
    m = read_camera_model(DATA / "left_intrinsics.yml")
    assert m.image_size == (640, 480)
    np.testing.assert_allclose(m.matrix[0], [535.91573396163199, 0.0, 342.28315473308373])
    np.testing.assert_allclose(m.distortion, [-0.26637260909660682, -0.038588898922304653, 0.0017831947042852964,
                                              -0.00028122100441115472, 0.23839153080878486])
    assert m.rms_px == pytest.approx(0.39259098975581364)
    assert m.focal_length_px == pytest.approx(535.91573396163199)


@pytest.mark.parametrize("suffix", [".yml", ".xml", ".json"])
def test_camera_model_round_trip(tmp_path, suffix):
    """Write → read gives the same model for OpenCV YAML, XML and our JSON, rational model and the
    covariance included; the YAML/XML are readable by cv2.FileStorage itself (independent reader)."""
    rng = np.random.default_rng(1)
    A = rng.normal(size=(12, 12))
    cov = A @ A.T * 1e-4
    m = CameraModel(np.array([[800.5, 0.1, 320.2], [0.0, 801.5, 240.7], [0.0, 0.0, 1.0]]), rng.normal(0, 0.1, 8),
                    (640, 480), np.abs(rng.normal(size=18)), 0.321, "test", cov)
    p = write_camera_model(tmp_path / f"cam{suffix}", m)
    m2 = read_camera_model(p)
    np.testing.assert_array_equal(m2.matrix, m.matrix)
    np.testing.assert_array_equal(m2.distortion, m.distortion)
    np.testing.assert_allclose(m2.covariance, m.covariance)
    assert (m2.image_size, m2.rms_px) == ((640, 480), 0.321)
    if suffix != ".json":
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
        np.testing.assert_array_equal(fs.getNode("camera_matrix").mat(), m.matrix)
        np.testing.assert_array_equal(fs.getNode("distortion_coefficients").mat().ravel(), m.distortion)
        fs.release()
    assert not list(tmp_path.glob(".*"))  # the atomic write left no temporary file


def test_camera_model_bad_input_names_file_and_field(tmp_path):
    p = tmp_path / "bad.yml"
    p.write_text("%YAML:1.0\n---\nimage_width: 640\n")
    with pytest.raises(ValueError, match=r"bad.yml: camera matrix: none of the keys camera_matrix"):
        read_camera_model(p)
    p.write_text("%YAML:1.0\n---\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
                 "   data: [ 500., 0., 320., 0., 500., 240., 0., 0., 1. ]\n"
                 "distortion_coefficients: !!opencv-matrix\n   rows: 3\n   cols: 1\n   dt: d\n   data: [ 0.1, 0.2, 0.3 ]\n")
    with pytest.raises(ValueError, match=r"bad.yml: distortion: expected 4, 5, 8, 12, 14"):
        read_camera_model(p)
    j = tmp_path / "bad.json"
    j.write_text('{"format": "layoutkit-camera-model", "camera_matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "k1": 3}')
    with pytest.raises(ValueError, match=r"bad.json: unknown key\(s\) k1"):
        read_camera_model(j)
    j.write_text('{"format": "layoutkit-camera-model", "camera_matrix": [[-5, 0, 0], [0, 1, 0], [0, 0, 1]]}')
    with pytest.raises(ValueError, match=r"camera_matrix: expected \[\[fx, s, cx\]"):
        read_camera_model(j)
    (tmp_path / "x.txt").write_text("")
    with pytest.raises(ValueError, match="unknown camera model format '.txt'"):
        read_camera_model(tmp_path / "x.txt")
    g = tmp_path / "garbage.yml"
    g.write_text("{{{ not yaml")
    with pytest.raises(ValueError, match="garbage.yml: not an OpenCV YAML/XML file"):
        read_camera_model(g)


def test_ros_camera_info_yaml(tmp_path):
    """ROS camera_info YAML ({rows, cols, data} maps, no opencv-matrix tag) reads too."""
    p = tmp_path / "ros.yaml"
    p.write_text("%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
                 "  data: [500.0, 0.0, 320.0, 0.0, 501.0, 240.0, 0.0, 0.0, 1.0]\ndistortion_coefficients:\n"
                 "  rows: 1\n  cols: 5\n  data: [-0.1, 0.01, 0.0, 0.0, 0.0]\n")
    m = read_camera_model(p)
    assert m.fy == 501.0 and m.distortion[0] == -0.1


def test_capture_meta_records_the_camera_model(tmp_path):
    """camera.json (version 2) keeps the matrix, distortion and file; version 1 files still read."""
    m = read_camera_model(DATA / "left_intrinsics.yml")
    write_camera_meta(tmp_path, CameraMeta.from_model(m, source="0"))
    back = read_camera_meta(tmp_path).camera_model()
    np.testing.assert_array_equal(back.matrix, m.matrix)
    np.testing.assert_array_equal(back.distortion, m.distortion)
    assert back.source.endswith("left_intrinsics.yml")
    (tmp_path / "camera.json").write_text('{"format": "layoutkit-camera", "version": 1, "focal_length_px": 500.0,'
                                          ' "width": 640, "height": 480}')
    old = read_camera_meta(tmp_path).camera_model()
    assert old.focal_length_px == 500.0 and old.principal_point_px == (319.5, 239.5) and not old.has_distortion


# ----------------------------------------------------------------------------- lens maps
def test_undistort_inverts_opencv_projection():
    """undistort_pixels ∘ cv2.projectPoints = identity to 1e-8 px over the whole 640 × 480 image
    (OpenCV's default 5 iterations leave ~5 mpx at the corners; the explicit rule closes it)."""
    xs, ys = np.meshgrid(np.linspace(0, 639, 17), np.linspace(0, 479, 13))
    p = np.stack([xs.ravel(), ys.ravel()], -1)
    u = undistort_pixels(p, K, D)
    rays = np.column_stack([(u - K[:2, 2]) / K[0, 0], np.ones(len(u))])
    back = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, D)[0].reshape(-1, 2)
    assert np.abs(back - p).max() < 1e-8
    np.testing.assert_allclose(distort_pixels(u, K, D), p, atol=1e-8)
    # no distortion, fx = fy: the identity
    np.testing.assert_allclose(undistort_pixels(p, K, None), p, atol=1e-9)
    default = cv2.undistortPoints(p.reshape(-1, 1, 2), K, D, P=K).reshape(-1, 2)
    assert np.abs(default - u).max() > 1e-3  # why the stopping rule is set explicitly


def test_lens_jacobians_are_inverse_and_match_finite_differences():
    p = np.array([[20.0, 15.0], [600.0, 400.0], [342.0, 236.0]])
    A = undistort_jacobian(p, K, D)
    F = distort_jacobian(undistort_pixels(p, K, D), K, D)
    np.testing.assert_allclose(A @ F, np.broadcast_to(np.eye(2), (3, 2, 2)), atol=1e-6)
    h = 1e-2
    fd = np.stack([(undistort_pixels(p + [h, 0], K, D) - undistort_pixels(p - [h, 0], K, D)) / (2 * h),
                   (undistort_pixels(p + [0, h], K, D) - undistort_pixels(p - [0, h], K, D)) / (2 * h)], -1)
    np.testing.assert_allclose(A, fd, atol=1e-5)
    assert np.linalg.svd(A[0], compute_uv=False).min() > 1.1  # a barrel lens stretches noise at the corners


# ----------------------------------------------------------------------------- pixel attitude
def test_face_attitude_exact_through_the_lens():
    """Noise-free corners projected with distortion → the generating attitude (zhai, homography,
    ippe), and without undistortion it is degrees off (the reason for item 1)."""
    R = rotvec_to_matrix(np.radians([25, -20, 10]))
    t = np.array([0.17, 0.12, 0.55])
    px = _project(R, t, FACE)
    B = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])  # face frame in the board frame
    for method, ar in (("zhai", None), ("homography", None), ("ippe", 1.6)):
        fa = face_attitude(px[[3, 2, 0, 1]], K, D, method=method, aspect_ratio=ar, ordered=True)
        assert fa.success and fa.status == "ok"
        assert np.degrees(attitude_error(fa.rotation, PAPER_FROM_CV @ R @ B)) < 1e-6
        assert fa.aspect_ratio == pytest.approx(1.6, rel=1e-9)
        centre = PAPER_FROM_CV @ t / 0.125  # position / W, W = 0.125 m
        np.testing.assert_allclose(fa.position_over_width, centre, rtol=1e-9)
    raw = face_attitude(px[[3, 2, 0, 1]], K, None, method="zhai", ordered=True)
    assert np.degrees(attitude_error(raw.rotation, PAPER_FROM_CV @ R @ B)) > 2.0


@pytest.mark.parametrize("method,ar", [("zhai", None), ("ippe", 1.6)])
def test_monte_carlo_scatter_matches_predicted_sigma_with_distortion(method, ar):
    """Must-show (corner level): i.i.d. 0.3 px noise on corners of a distorted image near the image
    corner; the RMS attitude scatter of 1200 (zhai) / 700 (ippe) solves / predicted sigma in
    [0.9, 1.1]. Leaving the
    lens Jacobian out of the prediction puts the ratio outside that band (it matters)."""
    rng = np.random.default_rng(7)
    R = rotvec_to_matrix(np.radians([25, -20, 10]))
    t = np.array([0.2, 0.14, 0.5])
    px = _project(R, t, FACE)
    fa = face_attitude(px, K, D, method=method, aspect_ratio=ar, corner_sigma_px=0.3)
    noisy = fa.corners_px + rng.normal(0, 0.3, (1200, 4, 2))
    if method == "zhai":  # the same pipeline, batched: undistort, (u, v), Zhai
        _, uv, f = pixels_to_ideal_uv(noisy, K, D)
        Rs = resolve_labelling(solve_rectangle(uv, f).rotation, fa.rotation, 4)
    else:
        Rs = np.array([face_attitude(q, K, D, method=method, aspect_ratio=ar, ordered=True, reference=fa.rotation,
                                     predict=False).rotation for q in noisy[:700]])
    e = matrix_to_rotvec(Rs @ fa.rotation.T)
    obs = np.degrees(np.sqrt(np.mean(np.sum((e - e.mean(0)) ** 2, 1))))
    assert 0.9 <= obs / fa.sigma_deg <= 1.1
    ideal = undistort_pixels(px, K, D)
    no_lens = face_attitude(ideal, K, None, method=method, aspect_ratio=ar, corner_sigma_px=0.3)
    assert not 0.9 <= obs / no_lens.sigma_deg <= 1.1


def test_camera_covariance_share_matches_monte_carlo():
    """The calibration's share: drawing (fx, fy, cx, cy, k1..k3) from a covariance and solving
    with the drawn camera scatters the attitude as J_θ C J_θᵀ predicts (ratio in [0.9, 1.1])."""
    from layoutkit.camera.lens import model_from_parameters, model_parameter_vector

    rng = np.random.default_rng(3)
    R = rotvec_to_matrix(np.radians([25, -20, 10]))
    px = _project(R, np.array([0.2, 0.14, 0.5]), FACE)
    sd = np.array([0.9, 0.9, 1.0, 1.0, 0.01, 0.03, 2e-4, 2e-4, 0.05])
    corr = np.eye(9)
    corr[4, 5] = corr[5, 4] = -0.9
    C = corr * np.outer(sd, sd)
    fa = face_attitude(px, K, D, camera_cov=C)
    assert fa.sigma_camera_deg > 0 and not np.isfinite(fa.sigma_deg)  # no corner noise given
    v0 = model_parameter_vector(K, D)[:9]
    L = np.linalg.cholesky(C)
    e = []
    for _ in range(600):
        Ki, Di = model_from_parameters(np.concatenate([v0 + L @ rng.standard_normal(9), np.zeros(9)]), 5)
        e.append(matrix_to_rotvec(face_attitude(px, Ki, Di, reference=fa.rotation, predict=False).rotation
                                  @ fa.rotation.T))
    e = np.array(e)
    obs = np.degrees(np.sqrt(np.mean(np.sum((e - e.mean(0)) ** 2, 1))))
    assert 0.9 <= obs / fa.sigma_camera_deg <= 1.1


def test_face_attitude_statuses():
    fa = face_attitude(np.full((4, 2), np.nan), K, D)
    assert (fa.success, fa.status) == (False, "no_corners")
    line = np.array([[100.0, 100.0], [200.0, 100.0], [300.0, 100.0], [150.0, 300.0]])
    fa = face_attitude(line, K, D, ordered=True)
    assert not fa.success and fa.status in ("degenerate", "mirrored")
    # face-on: IPPE's two branches fit equally well → ambiguous, both returned
    R = np.eye(3)
    px = _project(R, np.array([0.0, 0.0, 1.0]), FACE, dist=None)
    fa = face_attitude(px, K, None, method="ippe", aspect_ratio=1.6)
    assert fa.status == "ambiguous" and fa.alternative is not None and "face-on" in fa.message
