"""The live camera stream with a real lens (issue 28 item 5): ``--camera-model`` (matrix +
distortion) reaches the solver, the capture folder's camera.json records it, replay reads it back.

Kinds of proof: frames rendered through a known lens (the OpenCV sample camera, k1 = -0.27)
solved against the simulator's truth with and without the lens model; round trip of camera.json.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

pytest.importorskip("pyvista")
cv2 = pytest.importorskip("cv2")

from layoutkit.camera.rectangle import resolve_labelling  # noqa: E402
from layoutkit.geometry import attitude_error, rotvec_to_matrix  # noqa: E402
from layoutkit.io.camera import CameraModel, read_camera_meta, write_camera_model  # noqa: E402
from layoutkit.live.camera import CameraConfig, CameraReader, process_camera_folder  # noqa: E402
from layoutkit.live.camera_sim import bench_camera_for, render_camera_stream  # noqa: E402

D = (-0.266, -0.0386, 0.00178, -0.00028, 0.238)


@pytest.fixture(scope="module")
def lens_capture(tmp_path_factory):
    """Six frames of a slowly turning target seen off-centre through the sample lens."""
    R0 = rotvec_to_matrix([0.2, -0.1, 0.05])
    t0 = np.array([0.0, 0.0, 1.0])

    def traj(t):
        t = np.atleast_1d(t)
        R = np.stack([rotvec_to_matrix([0.0, 0.0, 0.02 * ti]) @ R0 for ti in t])
        return R, np.repeat(t0[None], len(t), 0)

    cam = bench_camera_for(R0, t0, focal_length_px=535.9, width=640, height=480, fps=2.0,
                           rng=np.random.default_rng(3), noise_grey=2.0)
    # aim 15 deg off the target so the face sits where the lens bends (towards the image corner)
    off = rotvec_to_matrix(np.radians([10.0, -15.0, 0.0]))
    c = -cam.R_cl.T @ cam.t_cl
    R_cl = off @ cam.R_cl
    cam = replace(cam, R_cl=R_cl, t_cl=-R_cl @ c, distortion=D, clock_offset_s=0.0, clock_drift=0.0, supersample=6)
    folder = tmp_path_factory.mktemp("lens") / "cam"
    render_camera_stream(cam, traj, 3.0, folder, seed=1)
    truth = [cam.X @ traj(k / cam.fps)[0][0] @ cam.R_bf for k in range(6)]
    return cam, folder, truth


def test_capture_records_the_lens(lens_capture):
    cam, folder, _ = lens_capture
    meta = read_camera_meta(folder)
    np.testing.assert_allclose(meta.distortion, D)
    model = meta.camera_model()
    assert model.has_distortion and model.focal_length_px == pytest.approx(535.9)


def test_replay_with_the_lens_model_matches_truth(lens_capture):
    """Solved with the recorded lens: every frame within 0.5 deg of the truth (IPPE, aspect known);
    the same frames solved as a pinhole are worse by more than 3x (median)."""
    cam, folder, truth = lens_capture
    meta = read_camera_meta(folder)
    with_lens, _ = process_camera_folder(folder, CameraConfig.from_model(meta.camera_model(), method="ippe",
                                                                         aspect_ratio=cam.aspect_ratio))
    pinhole, _ = process_camera_folder(folder, CameraConfig(cam.focal_length_px, None, "ippe", cam.aspect_ratio))

    def errs(frames):
        a = frames.arrays()
        assert (a["status"] == "ok").all(), a["status"]
        return np.degrees([attitude_error(resolve_labelling(R, T, 2), T) for R, T in zip(a["rotation"], truth)])

    e_lens, e_pin = errs(with_lens), errs(pinhole)
    assert e_lens.max() < 0.5
    assert np.median(e_pin) > 3 * np.median(e_lens)


def test_camera_reader_records_the_model_file(lens_capture, tmp_path):
    """live --camera-model: the recorded capture's camera.json keeps the matrix, the distortion and the file."""
    cam, folder, _ = lens_capture
    model_path = write_camera_model(tmp_path / "cam.yml", CameraModel(
        np.array([[535.9, 0.0, 319.5], [0.0, 535.9, 239.5], [0.0, 0.0, 1.0]]), np.array(D), (640, 480)))
    from layoutkit.io.camera import read_camera_model

    cfg = CameraConfig.from_model(read_camera_model(model_path), method="ippe", aspect_ratio=cam.aspect_ratio)
    rec = tmp_path / "rec.camera"
    reader = CameraReader(folder, cfg, record_dir=rec, clock=iter(np.arange(0, 100, 0.5)).__next__).start()
    reader.wait(120)
    reader.stop()
    meta = read_camera_meta(rec)
    np.testing.assert_allclose(meta.distortion, D)
    assert meta.camera_file == str(model_path) and reader.stats()["solved"] == 6


def test_cli_camera_config_from_model_and_folder(lens_capture, tmp_path):
    """The live/replay flags: --camera-model builds the lens config; a capture folder's recorded
    model is used when no flag is given; --camera-model with --focal-length-px is refused."""
    from layoutkit.cli.live import _camera_config

    cam, folder, _ = lens_capture
    cfg = _camera_config(str(folder), None, None, "ippe", None, None)
    assert cfg.camera_model is not None and cfg.camera_model.has_distortion
    p = write_camera_model(tmp_path / "c.json", CameraModel.pinhole(500.0, (320.0, 240.0), (640, 480), D))
    cfg = _camera_config(str(folder), None, None, "zhai", None, None, camera_model=str(p))
    assert cfg.focal_length_px == 500.0 and cfg.principal_point_px == (320.0, 240.0)
    with pytest.raises(SystemExit):
        _camera_config(str(folder), 500.0, None, "zhai", None, None, camera_model=str(p))
