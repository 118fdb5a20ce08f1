"""Lens distortion: OpenCV's camera model between observed (distorted) pixels and the ideal pinhole.

A camera is OpenCV's matrix ``K`` and distortion vector ``dist`` (k1 k2 p1 p2 [k3 [k4 k5 k6
[s1..s4 [tx ty]]]]; :class:`layoutkit.io.camera.CameraModel` reads and writes them). The rectangle
solvers (:mod:`layoutkit.camera.rectangle`) need an **ideal camera**: square pixels, no distortion,
focal length ``f`` and principal point ``(cx, cy)``. Here ``f = (fx + fy) / 2`` and ``(cx, cy)``
are K's (:func:`ideal_camera`), so a camera without distortion and with ``fx = fy`` maps every pixel
to itself.

- :func:`undistort_pixels`: observed → ideal pixels, ``cv2.undistortPoints`` with ``P = K_ideal``
  and an explicit stopping rule (OpenCV's default of 5 iterations leaves 5 mpx at the corners
  of a k1 = -0.27 lens: measured; with ``(COUNT + EPS, 100, 1e-10)`` the round trip through
  ``cv2.projectPoints`` closes to 1e-10 px, 0.4 s per 3e5 points here);
- :func:`distort_pixels`: ideal → observed pixels (``cv2.projectPoints`` of the rays);
- :func:`undistort_jacobian`: ``d ideal / d observed (..., 2, 2)``, the inverse of the forward
  map's Jacobian (central differences through :func:`distort_pixels`): how pixel noise of the
  detected corners scales into the ideal image (Σ_ideal = A Σ Aᵀ per corner);
- :func:`model_parameter_vector` / :func:`model_from_parameters`: the model as the 18-vector of
  OpenCV's ``stdDeviationsIntrinsics`` order, for propagating calibration uncertainty.

Frames: pixels ``(x right, y down)``, pixel centres at integer coordinates, arrays ``(..., 2)``.
"""
from __future__ import annotations

import numpy as np

from .._validate import as_array

__all__ = ["ideal_camera", "undistort_pixels", "distort_pixels", "undistort_jacobian", "distort_jacobian",
           "model_parameter_vector", "model_from_parameters", "UNDISTORT_CRITERIA"]

#: ``cv2.undistortPoints`` stopping rule (type = COUNT + EPS = 3, at most 100 iterations, 1e-10 px).
UNDISTORT_CRITERIA = (3, 100, 1e-10)


def _km(K, dist):
    Km = as_array(K, "camera_matrix", (3, 3)).astype(float)
    D = np.asarray(dist if dist is not None else [], float).ravel()
    return Km, D


def ideal_camera(K) -> tuple[float, float, float]:
    """``(f, cx, cy)`` px of the ideal square-pixel camera for OpenCV matrix ``K (3, 3)``."""
    Km = as_array(K, "camera_matrix", (3, 3))
    return 0.5 * float(Km[0, 0] + Km[1, 1]), float(Km[0, 2]), float(Km[1, 2])


def _ideal_matrix(K, f=None):
    f0, cx, cy = ideal_camera(K)
    f = f0 if f is None else float(f)
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


def undistort_pixels(pixels, K, dist, f: float | None = None) -> np.ndarray:
    """Observed pixels ``(..., 2)`` → ideal pixels ``(..., 2)`` (focal ``f``, default :func:`ideal_camera`).

    NaN rows stay NaN. Without distortion and with ``fx = fy = f`` (and no skew) this is the identity.
    """
    import cv2

    p = as_array(pixels, "pixels", (..., 2)).astype(float)
    Km, D = _km(K, dist)
    P = _ideal_matrix(Km, f)
    return _finite_rows(p, lambda xy: cv2.undistortPoints(xy.reshape(-1, 1, 2), Km, D if D.size else None, None,
                                                          None, P, UNDISTORT_CRITERIA))


def distort_pixels(ideal_px, K, dist, f: float | None = None) -> np.ndarray:
    """Ideal pixels ``(..., 2)`` (focal ``f``, default :func:`ideal_camera`) → observed pixels ``(..., 2)``."""
    import cv2

    q = as_array(ideal_px, "ideal_px", (..., 2)).astype(float)
    Km, D = _km(K, dist)
    P = _ideal_matrix(Km, f)
    return _finite_rows(q, lambda xy: cv2.projectPoints(np.column_stack([(xy - P[:2, 2]) / P[0, 0], np.ones(len(xy))]),
                                                        np.zeros(3), np.zeros(3), Km, D if D.size else None)[0])


def _finite_rows(points, fn) -> np.ndarray:
    """``fn`` applied to the finite points of ``points (..., 2)`` (as an ``(m, 2)`` array; it returns m
    points in any shape OpenCV gives); NaN where a coordinate is not finite. Returns ``(..., 2)``."""
    flat = points.reshape(-1, 2)
    out = np.full_like(flat, np.nan)
    ok = np.all(np.isfinite(flat), axis=1)
    if ok.any():
        out[ok] = np.asarray(fn(flat[ok])).reshape(-1, 2)
    return out.reshape(points.shape)


def undistort_jacobian(pixels, K, dist, f: float | None = None, step_px: float = 1e-3) -> np.ndarray:
    """``A = d ideal / d observed`` ``(..., 2, 2)`` at observed ``pixels (..., 2)``.

    Computed as the inverse of the forward (distortion) Jacobian at the undistorted point, by
    central differences of :func:`distort_pixels` (a closed-form map, so no iteration noise).
    """
    p = as_array(pixels, "pixels", (..., 2)).astype(float)
    u = undistort_pixels(p, K, dist, f)
    e = np.eye(2) * step_px
    cols = [(distort_pixels(u + e[k], K, dist, f) - distort_pixels(u - e[k], K, dist, f)) / (2 * step_px)
            for k in range(2)]
    Jf = np.stack(cols, -1)  # d observed / d ideal
    with np.errstate(invalid="ignore"):
        return np.linalg.inv(np.where(np.isfinite(Jf), Jf, np.nan))


def model_parameter_vector(K, dist) -> np.ndarray:
    """``(18,)`` fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6, s1..s4, tx, ty (OpenCV's order)."""
    Km, D = _km(K, dist)
    v = np.zeros(18)
    v[:4] = Km[0, 0], Km[1, 1], Km[0, 2], Km[1, 2]
    order = [4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17]  # dist index i -> vector index 4 + i
    for i, d in enumerate(D):
        v[order[i]] = d
    return v


def model_from_parameters(v, n_dist: int, skew: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`model_parameter_vector`: ``(K (3, 3), dist (n_dist,))``."""
    v = np.asarray(v, float)
    K = np.array([[v[0], skew, v[2]], [0.0, v[1], v[3]], [0.0, 0.0, 1.0]])
    return K, v[4:4 + n_dist].copy()


def distort_jacobian(ideal_px, K, dist, f: float | None = None, step_px: float = 1e-3) -> np.ndarray:
    """``F = d observed / d ideal`` ``(..., 2, 2)`` at ideal pixels (central differences of
    :func:`distort_pixels`); ``Σ_observed = F Σ_ideal Fᵀ`` per point."""
    q = as_array(ideal_px, "ideal_px", (..., 2)).astype(float)
    e = np.eye(2) * step_px
    cols = [(distort_pixels(q + e[k], K, dist, f) - distort_pixels(q - e[k], K, dist, f)) / (2 * step_px)
            for k in range(2)]
    return np.stack(cols, -1)
