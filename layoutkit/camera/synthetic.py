"""Synthetic pinhole camera: off-screen pyvista renders of any mesh with exact intrinsics (design §8).

Poses are in OpenCV's camera convention, ``p_cv = R @ p_body + t`` (x right, y down, z forward),
so a render can be checked against ``cv2.projectPoints`` directly; use
:func:`layoutkit.camera.conventions.pose_paper_to_cv` for poses in Zhai's convention.

How the VTK camera is made a pinhole with intrinsics ``K = [[f, 0, cx], [0, f, cy], [0, 0, 1]]``
(square pixels, pixel centres at integer coordinates, rows from the top):

* position ``C = -R^T t``, focal point ``C + R[2]``, view-up ``-R[1]`` (all in the body frame);
* view angle = the **vertical** field of view ``2 atan(H / (2 f))``;
* principal point through the window centre (VTK moves the optical axis to minus the window
  centre in normalised device coordinates): ``wcx = 1 - 2 (cx + 0.5) / W``,
  ``wcy = 2 (cy + 0.5) / H - 1`` (measured: the sign is easy to get wrong);
* anti-aliasing off, so a pixel is lit iff its centre sees the surface. Optional supersampling
  (render ``k`` times larger with the scaled intrinsics, then area-average) gives
  pixel-coverage edges, i.e. sub-pixel edge information like a real sensor.

**Lens distortion** (``PinholeCamera.distortion``, OpenCV's vector k1 k2 p1 p2 [k3 ...]): the scene
is rendered by the ideal pinhole on a canvas large enough to hold the undistorted position of
every output pixel (a barrel lens, k1 < 0, sees further out than its pinhole), at ``k``× the
resolution; each output sub-pixel (distorted image, ``k``× grid) takes the canvas value at its
undistorted position (``cv2.undistortPoints``, computed once per camera; ``cv2.remap``, bilinear),
then the ``k``× image is area-averaged. So the image is what the real lens would record, and
:meth:`PinholeCamera.project` (``cv2.projectPoints`` with the distortion) says where a body point
lands in it (tested: lit area and centroid against the distorted polygon).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._validate import as_array

__all__ = ["PinholeCamera", "SyntheticCamera", "render_mesh"]


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole intrinsics in pixels: ``width``, ``height``, focal length ``f`` (px), ``cx``, ``cy``.

    ``cx``/``cy`` default (None) to the image centre ``((W - 1)/2, (H - 1)/2)``. ``distortion``:
    OpenCV's distortion vector (empty = an ideal pinhole), applied by :meth:`project` and by
    :class:`SyntheticCamera` renders.
    """

    width: int
    height: int
    f: float
    cx: float | None = None
    cy: float | None = None
    distortion: tuple = ()

    @classmethod
    def from_sensor(cls, focal_length_m: float, pixel_pitch_m: float, width: int, height: int):
        """Intrinsics from a lens focal length and a pixel pitch (both m), principal point centred."""
        return cls(int(width), int(height), focal_length_m / pixel_pitch_m)

    @property
    def principal_point(self) -> np.ndarray:
        cx = (self.width - 1) / 2 if self.cx is None else self.cx
        cy = (self.height - 1) / 2 if self.cy is None else self.cy
        return np.array([cx, cy], float)

    @property
    def K(self) -> np.ndarray:
        """3 × 3 OpenCV camera matrix."""
        cx, cy = self.principal_point
        return np.array([[self.f, 0.0, cx], [0.0, self.f, cy], [0.0, 0.0, 1.0]])

    def scaled(self, k: int) -> "PinholeCamera":
        """Intrinsics of the same camera sampled ``k`` times finer (for supersampling)."""
        cx, cy = self.principal_point
        return PinholeCamera(self.width * k, self.height * k, self.f * k, k * (cx + 0.5) - 0.5, k * (cy + 0.5) - 0.5,
                             self.distortion)

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(np.asarray(self.distortion, float) != 0))

    def project(self, rotation, translation, points) -> np.ndarray:
        """Pixels ``(..., n, 2)`` of body points ``(..., n, 3)`` under an OpenCV pose (with the
        lens distortion, if any: OpenCV's model, as ``cv2.projectPoints``)."""
        R = as_array(rotation, "rotation", (..., 3, 3))
        p = np.einsum("...ij,...nj->...ni", R, np.asarray(points, float)) + np.asarray(translation, float)[..., None, :]
        cx, cy = self.principal_point
        ideal = np.stack([self.f * p[..., 0] / p[..., 2] + cx, self.f * p[..., 1] / p[..., 2] + cy], -1)
        if not self.has_distortion:
            return ideal
        from .lens import distort_pixels

        return distort_pixels(ideal, self.K, np.asarray(self.distortion, float))


class SyntheticCamera:
    """Reusable off-screen renderer of one mesh (keeps a pyvista plotter open between frames).

    Parameters
    ----------
    mesh : trimesh.Trimesh or pyvista.DataSet, body frame (m).
    camera : PinholeCamera.
    face_colors : (n_faces, 3) uint8/float RGB per face, optional (default light grey).
    lighting : "headlight" (light at the camera), "sun" (directional light from ``sun_direction``
        in the body frame, plus a dim ambient term) or "flat" (no shading: colours as given).
    supersample : int ≥ 1; render k× larger and area-average (sub-pixel edges).
    background : RGB of empty space (default black).

    Use as a context manager or call :meth:`close`.
    """

    def __init__(self, mesh, camera: PinholeCamera, face_colors=None, lighting: str = "headlight",
                 sun_direction=(1.0, 0.3, 0.5), supersample: int = 1, background=(0, 0, 0)):
        import pyvista as pv

        if lighting not in ("headlight", "sun", "flat"):
            raise ValueError(f"lighting: expected 'headlight', 'sun' or 'flat', got {lighting!r}")
        if int(supersample) < 1:
            raise ValueError(f"supersample: expected an integer >= 1, got {supersample!r}")
        self.camera = camera
        self.k = int(supersample)
        self._remap = None
        if camera.has_distortion:
            canvas, self._remap = _distortion_canvas(camera, self.k)
            self._cam_hi = canvas.scaled(self.k)
        else:
            self._cam_hi = camera.scaled(self.k)
        self._background = background
        if not isinstance(mesh, pv.DataSet):
            mesh = pv.wrap(mesh)
        mesh = mesh.copy()
        from ..render import offscreen_backend

        offscreen_backend()  # pick EGL/OSMesa before the first render window (no display here)
        pl = pv.Plotter(off_screen=True, window_size=(self._cam_hi.width, self._cam_hi.height),
                        lighting="none")
        pl.disable_anti_aliasing()
        pl.set_background(background)
        kw = dict(smooth_shading=False, show_edges=False)
        if face_colors is not None:
            fc = np.asarray(face_colors)
            if fc.shape != (mesh.n_cells, 3):
                raise ValueError(f"face_colors: expected shape ({mesh.n_cells}, 3), got {fc.shape}")
            if fc.dtype.kind == "f":
                fc = np.clip(fc * 255 if fc.max() <= 1.0 else fc, 0, 255)
            mesh.cell_data["rgb"] = fc.astype(np.uint8)
            kw.update(scalars="rgb", rgb=True)
        else:
            kw.update(color=(200, 200, 200))
        if lighting == "flat":
            kw.update(lighting=False)
        else:
            kw.update(ambient=0.15, diffuse=0.85, specular=0.0)
        pl.add_mesh(mesh, **kw)
        if lighting == "headlight":
            pl.add_light(pv.Light(light_type="headlight"))
        elif lighting == "sun":
            d = np.asarray(sun_direction, float)
            d = d / np.linalg.norm(d)
            pl.add_light(pv.Light(position=tuple(d * 1e3), focal_point=(0, 0, 0), light_type="scene light",
                                  positional=False))
        self._pl = pl
        self._bounds_radius = float(np.linalg.norm(np.ptp(np.asarray(mesh.bounds).reshape(3, 2), axis=1))) + 1e-9
        self._center = np.asarray(mesh.center, float)

    def render(self, rotation, translation, *, blur_sigma_px: float = 0.0, noise_sigma: float = 0.0,
               rng: np.random.Generator | None = None, gray: bool = True) -> np.ndarray:
        """Image of the mesh under the OpenCV pose ``p_cv = R p_body + t``.

        Returns ``(H, W)`` uint8 (``gray=True``, ITU-R 601 luma) or ``(H, W, 3)`` uint8. Optional
        Gaussian blur (sigma in output pixels, an optics PSF) and additive Gaussian intensity noise
        (sigma in grey levels, drawn from ``rng``).
        """
        import cv2

        R = as_array(rotation, "rotation", (3, 3))
        t = as_array(translation, "translation", (3,))
        cam = self._cam_hi
        C = -R.T @ t
        vc = self._pl.camera
        vc.position = tuple(C)
        vc.focal_point = tuple(C + R[2])
        vc.up = tuple(-R[1])
        vc.view_angle = float(np.degrees(2 * np.arctan(cam.height / (2 * cam.f))))
        cx, cy = cam.principal_point
        # VTK shifts the projection centre to -WindowCenter in normalised device coordinates
        vc.SetWindowCenter(1 - 2 * (cx + 0.5) / cam.width, 2 * (cy + 0.5) / cam.height - 1)
        depth = float(np.dot(R[2], self._center - C))
        near = max(depth - self._bounds_radius, 1e-3 * max(depth, 1e-3))
        vc.clipping_range = (near, depth + self._bounds_radius)
        self._pl.render()
        img = np.asarray(self._pl.screenshot(return_img=True))[..., :3]
        if self._remap is not None:
            bg = tuple(float(v) for v in np.asarray(self._background, float).ravel()[:3])
            img = cv2.remap(np.ascontiguousarray(img), self._remap[0], self._remap[1], cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=bg)
        if self.k > 1:
            img = cv2.resize(img, (self.camera.width, self.camera.height), interpolation=cv2.INTER_AREA)
        img = img.astype(np.float32)
        if gray:
            img = img @ np.array([0.299, 0.587, 0.114], np.float32)
        if blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
        if noise_sigma > 0:
            if rng is None:
                raise ValueError("rng: a numpy Generator is required when noise_sigma > 0")
            img = img + rng.normal(0.0, noise_sigma, img.shape).astype(np.float32)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)

    def close(self) -> None:
        self._pl.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _distortion_canvas(camera: PinholeCamera, k: int, max_growth: float = 4.0):
    """The ideal pinhole canvas that covers every output pixel of a distorted camera, and the
    remap tables ``(map_x, map_y)`` (float32, ``(k H, k W)``) from the ``k``× output grid into
    the ``k``× canvas (module docstring)."""
    from .lens import undistort_pixels

    from scipy.interpolate import RectBivariateSpline

    W, H = camera.width, camera.height
    # exact undistortion on the whole-pixel grid (one pixel beyond the image), bicubic spline to
    # the k-times finer grid: the map is smooth, the spline adds < 1e-5 px (tested) for 1/k² the cost
    cx_, cy_ = np.arange(-2, W + 2, dtype=float), np.arange(-2, H + 2, dtype=float)
    gx, gy = np.meshgrid(cx_, cy_)
    coarse = undistort_pixels(np.stack([gx, gy], -1), camera.K, np.asarray(camera.distortion, float), camera.f)
    if not np.all(np.isfinite(coarse)):
        raise ValueError("distortion: the lens model does not map every pixel to a finite ray")
    xs = (np.arange(k * W) + 0.5) / k - 0.5
    ys = (np.arange(k * H) + 0.5) / k - 0.5
    ideal = np.stack([RectBivariateSpline(cy_, cx_, coarse[..., i])(ys, xs) for i in range(2)], -1)
    if not np.all(np.isfinite(ideal)):
        raise ValueError("distortion: the lens model does not map every pixel to a finite ray")
    lo = np.floor(ideal.reshape(-1, 2).min(0)) - 1
    hi = np.ceil(ideal.reshape(-1, 2).max(0)) + 1
    Wc, Hc = int(hi[0] - lo[0]) + 1, int(hi[1] - lo[1]) + 1
    if Wc > max_growth * W or Hc > max_growth * H:
        raise ValueError(f"distortion: the undistorted field of view needs a {Wc} x {Hc} px canvas "
                         f"(> {max_growth:g}x the {W} x {H} image); not a lens this renderer can model")
    cx, cy = camera.principal_point
    canvas = PinholeCamera(Wc, Hc, camera.f, cx - lo[0], cy - lo[1])
    hx = k * (ideal[..., 0] - lo[0] + 0.5) - 0.5
    hy = k * (ideal[..., 1] - lo[1] + 0.5) - 0.5
    return canvas, (hx.astype(np.float32), hy.astype(np.float32))


def render_mesh(mesh, camera: PinholeCamera, rotation, translation, **kwargs) -> np.ndarray:
    """One-shot render (see :class:`SyntheticCamera`; render keywords: blur_sigma_px, noise_sigma, rng, gray)."""
    rkw = {k: kwargs.pop(k) for k in ("blur_sigma_px", "noise_sigma", "rng", "gray") if k in kwargs}
    with SyntheticCamera(mesh, camera, **kwargs) as sc:
        return sc.render(rotation, translation, **rkw)
