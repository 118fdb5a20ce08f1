"""Bench camera simulator: the synthetic camera view of a simulated lighthouse session.

A rectangular face (``L x W`` m, a flat plate on the target) is rendered off-screen by the pyvista
pinhole camera of :mod:`layoutkit.camera.synthetic` along the same trajectory the lighthouse
simulator uses, as a camera capture folder (:mod:`layoutkit.io.camera`) — so a whole bench
session with both streams runs on this machine (serial bytes over a pty, camera frames from the
rendered folder).

Frames and conventions:

- the camera sits near station 0 (the world frame): OpenCV pose ``p_cv = R_cl p_lh + t_cl``;
- the face frame is the rectangle solver's target frame (normal ``x_t``, sides along ``y_t``
  (length L) and ``z_t`` (width W)); it sits on the body at ``p_body = R_bf p_face + c_bf``;
- so the solver's attitude is ``R_ct = X R_lh Y`` with ``X = PAPER_FROM_CV R_cl`` (camera ←
  lighthouse, what :func:`layoutkit.live.crosscheck.camera_crosscheck` estimates) and ``Y = R_bf``
  (body ← face);
- camera clock: ``t_cam = (1 + drift) t_device + offset`` (a host clock that runs fast by
  ``drift`` and started ``offset`` s apart).

Image noise (Gaussian grey levels) and blur make the detected corners noisy like a real sensor;
the truth is written to ``camera.json`` for the checks.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import matrix_to_rotvec, rotvec_to_matrix

__all__ = ["BenchCamera", "face_mesh", "bench_camera_for", "render_camera_stream"]


@dataclass(frozen=True)
class BenchCamera:
    """Set-up of the bench camera (all SI, see module docstring).

    width, height, focal_length_px : intrinsics (principal point at the image centre).
    R_cl (3, 3), t_cl (3,) m : camera (OpenCV) ← lighthouse/world. R_bf (3, 3), c_bf (3,) m : body ←
    face. length_m, width_m : the face's L and W. fps : frames per camera second.
    clock_offset_s, clock_drift : camera clock relation. noise_grey, blur_px, supersample : image model.
    distortion : OpenCV distortion vector of the lens (empty: a pinhole); the frames are rendered
    through it and ``camera.json`` records the camera model (matrix + distortion).
    """

    width: int
    height: int
    focal_length_px: float
    R_cl: np.ndarray
    t_cl: np.ndarray
    R_bf: np.ndarray
    c_bf: np.ndarray
    length_m: float = 0.10
    width_m: float = 0.07
    fps: float = 30.0
    clock_offset_s: float = 0.37
    clock_drift: float = 50e-6
    noise_grey: float = 4.0
    blur_px: float = 0.7
    supersample: int = 3
    distortion: tuple = ()

    @property
    def aspect_ratio(self) -> float:
        return self.length_m / self.width_m

    @property
    def X(self) -> np.ndarray:
        """Solver camera (paper frame) ← lighthouse rotation."""
        from ..camera.conventions import PAPER_FROM_CV

        return PAPER_FROM_CV @ self.R_cl

    def truth(self) -> dict:
        return {
            "clock_offset_s": self.clock_offset_s, "clock_drift": self.clock_drift,
            "camera_from_lighthouse_rotvec": matrix_to_rotvec(self.X).tolist(),
            "body_from_face_rotvec": matrix_to_rotvec(self.R_bf).tolist(),
            "camera_cv_from_lighthouse_rotvec": matrix_to_rotvec(self.R_cl).tolist(),
            "camera_cv_from_lighthouse_translation_m": np.asarray(self.t_cl).tolist(),
            "face_center_body_m": np.asarray(self.c_bf).tolist(),
            "face_length_m": self.length_m, "face_width_m": self.width_m, "fps": self.fps,
            "noise_grey": self.noise_grey, "blur_px": self.blur_px,
        }


def face_mesh(cam: BenchCamera):
    """The face as a two-triangle trimesh in the body frame (m)."""
    import trimesh

    L, W = cam.length_m, cam.width_m
    pf = np.array([[0.0, -L / 2, -W / 2], [0.0, L / 2, -W / 2], [0.0, -L / 2, W / 2], [0.0, L / 2, W / 2]])
    pb = pf @ np.asarray(cam.R_bf).T + np.asarray(cam.c_bf)
    faces = np.array([[0, 1, 3], [0, 3, 2]])
    return trimesh.Trimesh(pb, faces, process=False)


def bench_camera_for(rotation0, translation0, *, focal_length_px: float | None = None, width: int = 640,
                     height: int = 480, tilt_deg: float = 25.0, fps: float = 30.0, rng=None, **kw) -> BenchCamera:
    """A bench camera that sees the face at the trajectory's first pose ``(R0 body→world, t0 m)``.

    The camera sits 0.12 m beside the station, aimed at the target with a mounting error of up to
    1° per axis (to be estimated); the face normal points ``tilt_deg`` away from the line of sight (outside the
    face-on band); the focal length (default) makes the face ~1/5 of the image width.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    R0 = np.asarray(rotation0, float)
    t0 = np.asarray(translation0, float)
    # camera centre 0.12 m beside the station, optical axis at the target, plus a mounting error
    cam_c = np.array([0.12, -0.03, 0.0])
    z = t0 - cam_c
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    look = np.stack([x, np.cross(z, x), z])  # rows: camera axes in the world (x right, y down, z forward)
    R_cl = rotvec_to_matrix(np.deg2rad(rng.uniform(-1.0, 1.0, 3))) @ look
    t_cl = -R_cl @ cam_c
    to_cam = cam_c - t0
    dist = float(np.linalg.norm(to_cam))
    to_cam /= dist
    # face normal: the line of sight turned by tilt_deg about an axis perpendicular to it
    perp = np.cross(to_cam, [0.3, 1.0, 0.2])
    perp /= np.linalg.norm(perp)
    n_w = rotvec_to_matrix(perp * np.deg2rad(tilt_deg)) @ to_cam
    n_b = R0.T @ n_w
    e1 = np.cross(n_b, [0.0, 0.0, 1.0] if abs(n_b[2]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    R_bf = np.column_stack([n_b, e1, np.cross(n_b, e1)])
    L = kw.pop("length_m", 0.10)
    if focal_length_px is None:
        focal_length_px = float(np.round(0.2 * width * dist / L, 1))
    c_bf = 0.07 * n_b  # in front of the target's sensors
    return BenchCamera(int(width), int(height), float(focal_length_px), R_cl, t_cl, R_bf, c_bf, length_m=L,
                       fps=float(fps), **kw)


def render_camera_stream(cam: BenchCamera, trajectory, duration_s: float, out_dir, *, seed: int = 0,
                         t_start: float = 0.0, on_frame=None, run: dict | None = None) -> dict:
    """Render ``duration_s`` device seconds of the bench camera into a camera capture folder.

    trajectory : callable ``t_device (K,) -> (R (K, 3, 3) body→world, t (K, 3) m)``. Frame ``k`` is
    exposed at camera time ``t_cam0 + k / fps`` with ``t_cam0 = (1 + drift) t_start + offset``.
    run : the serial stream's tie (:class:`layoutkit.io.runtie.StreamTie` dict), recorded in
    ``camera.json`` as ``extra.run``. ``on_frame(k, n)`` is called after each frame (an exception
    it raises ends the rendering; the frames written so far stay). Returns a summary dict (frames,
    focal length, truth).
    """
    from ..camera.synthetic import PinholeCamera, SyntheticCamera
    from ..io.camera import CameraIndexWriter, CameraMeta

    rng = np.random.default_rng(seed)
    n = int(np.floor(duration_s * cam.fps))
    t_cam0 = (1.0 + cam.clock_drift) * t_start + cam.clock_offset_s
    t_cam = t_cam0 + np.arange(n) / cam.fps
    t_dev = (t_cam - cam.clock_offset_s) / (1.0 + cam.clock_drift)
    R, tr = trajectory(t_dev)
    pin = PinholeCamera(cam.width, cam.height, cam.focal_length_px, distortion=tuple(cam.distortion))
    if pin.has_distortion:  # the capture records the lens (camera.json version 2)
        from ..io.camera import CameraModel

        model = CameraModel(pin.K, np.asarray(cam.distortion, float), (cam.width, cam.height), source="fake-fpga")
        meta = CameraMeta.from_model(model, source="fake-fpga", clock="simulated", aspect_ratio=cam.aspect_ratio,
                                     truth=cam.truth(), extra={"run": run} if run else {})
    else:
        meta = CameraMeta(focal_length_px=cam.focal_length_px, principal_point_px=None, width=cam.width,
                          height=cam.height, source="fake-fpga", clock="simulated", aspect_ratio=cam.aspect_ratio,
                          truth=cam.truth(), extra={"run": run} if run else {})
    mesh = face_mesh(cam)
    with CameraIndexWriter(out_dir, meta) as wr, \
            SyntheticCamera(mesh, pin, lighting="flat", supersample=cam.supersample,
                            face_colors=np.full((2, 3), 220, np.uint8)) as sc:
        for k in range(n):
            Rk = cam.R_cl @ R[k]
            tk = cam.R_cl @ tr[k] + cam.t_cl
            img = sc.render(Rk, tk, blur_sigma_px=cam.blur_px, noise_sigma=cam.noise_grey, rng=rng)
            wr.add_image(img, float(t_cam[k]))
            if on_frame is not None:
                on_frame(k, n)
    return {"frames": n, "focal_length_px": cam.focal_length_px, "fps": cam.fps, "folder": str(out_dir),
            "aspect_ratio": cam.aspect_ratio, "truth": cam.truth()}
