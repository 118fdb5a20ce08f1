"""Predicted error of a rectangle attitude solve: corner noise propagated through the solver.

For independent corner noise of ``sigma_px`` on each image coordinate, the attitude error
``dphi`` (``R_est = exp([dphi]x) R``) of a solve has covariance ``C = sigma_px^2 J J^T`` to first
order, ``J = d dphi / d corners (3 x 8)``. ``J`` is taken by central differences through the
solver itself (the chosen branch and labelling held fixed by passing the solution as the
reference), so the prediction is exactly the solver's own linearisation — for the size-free
Zhai solve, the homography, or IPPE. Near face-on the linearisation breaks down (the tilt sign
is nearly unobservable and the error is not Gaussian): callers flag those frames by
:func:`face_tilt`.

The corner noise itself is estimated from IPPE's reprojection residuals (a known aspect ratio
leaves 8 - 6 = 2 degrees of freedom per frame): with OpenCV's RMS over the 4 corners,
``E[rms^2] = sigma^2 / 4``, so :func:`corner_sigma_from_reprojection` returns
``sqrt(4 mean(rms^2))`` (checked by Monte-Carlo in the tests).
"""
from __future__ import annotations

import numpy as np

from ..geometry import matrix_to_rotvec
from .rectangle import resolve_labelling, solve_rectangle

__all__ = ["attitude_jacobian_corners", "rectangle_attitude_covariance", "corner_sigma_from_reprojection",
           "face_tilt"]


def attitude_jacobian_corners(corners_uv, focal_length, rotation, method: str = "zhai", step_px: float = 1e-3,
                              n_fold: int = 4, **options) -> np.ndarray:
    """``J (3, 8)``: attitude error (rad) per corner coordinate (px), P1..P4 (u, v) order.

    rotation : (3, 3) the solution at ``corners_uv (4, 2)``; NaN ``J`` when a perturbed solve fails.
    """
    c = np.asarray(corners_uv, float)
    R = np.asarray(rotation, float)
    pert = np.zeros((16, 4, 2))
    for k in range(8):
        pert[2 * k].flat[k] = step_px
        pert[2 * k + 1].flat[k] = -step_px
    cs = c[None] + pert
    opts = dict(options)
    if method == "ippe":
        opts["reference"] = R
        sols = [solve_rectangle(q, focal_length, method=method, **opts) for q in cs]
        Rs = np.stack([s.rotation for s in sols])
        ok = np.array([bool(s.success) for s in sols])
    else:
        s = solve_rectangle(cs, focal_length, method=method, **opts)
        Rs, ok = s.rotation, np.asarray(s.success)
    if not ok.all():
        return np.full((3, 8), np.nan)
    Rs = np.stack([resolve_labelling(Ri, R, n_fold) for Ri in Rs])
    d = matrix_to_rotvec(Rs @ R.T)  # (16, 3)
    return ((d[0::2] - d[1::2]) / (2 * step_px)).T


def rectangle_attitude_covariance(corners_uv, focal_length, rotation, sigma_px: float, method: str = "zhai",
                                  **options) -> np.ndarray:
    """Predicted attitude covariance ``(3, 3)`` rad² of one solve (module docstring)."""
    J = attitude_jacobian_corners(corners_uv, focal_length, rotation, method=method, **options)
    return float(sigma_px) ** 2 * (J @ J.T)


def corner_sigma_from_reprojection(rms_px) -> float:
    """Per-coordinate corner noise (px) from IPPE RMS reprojection errors ``(F,)`` of many frames."""
    r = np.asarray(rms_px, float)
    r = r[np.isfinite(r)]
    if r.size == 0:
        return float("nan")
    return float(np.sqrt(4.0 * np.mean(r ** 2)))


def face_tilt(rotation, corners_uv, focal_length) -> np.ndarray:
    """Angle (rad) between the face normal and the line of sight to the face centre, ``(...)``.

    rotation : (..., 3, 3) R_ct (paper frame: the face normal is ``R[:, :, 0]``, the camera looks
    along -x). 0 = face-on, where the tilt sign is nearly unobservable.
    """
    R = np.asarray(rotation, float)
    c = np.asarray(corners_uv, float).mean(axis=-2)
    d = np.stack([-np.ones(c.shape[:-1]), c[..., 0] / focal_length, c[..., 1] / focal_length], -1)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    n = R[..., :, 0]
    return np.arccos(np.clip(np.abs(np.sum(n * d, -1)), 0.0, 1.0))
