"""Camera conventions: Zhai et al. (2014) ↔ OpenCV (design §7).

**Paper camera frame** (Zhai Fig. 1): x along the optical axis pointing *away* from the scene
(points in front have ``x < 0``), y along the image u axis, z along the image v axis;
``u = -f y / x``, ``v = -f z / x`` (Zhai eq. 3), (u, v) centred on the principal point, same units
as ``f``.

**OpenCV camera frame**: x right, y down, z forward; pixels ``x_pix = fx X/Z + cx``,
``y_pix = fy Y/Z + cy`` (pixel centres at integer coordinates).

To keep both frames right-handed, layoutkit fixes the paper's image axes as
``u = x_pix - cx`` (to the right) and ``v = cy - y_pix`` (**up**). Then

    p_paper = M @ p_cv,   M = [[0, 0, -1], [1, 0, 0], [0, -1, 0]]   (det M = +1)

and a pose ``p_cv = R_cv p_t + t_cv`` becomes ``R_ct = M R_cv``, ``T_ct = M t_cv``
(the target frame is unchanged). In pixels with ``fx = fy = f`` the paper's (u, v) are just
the pixel offsets from the principal point with v flipped.
"""
from __future__ import annotations

import numpy as np

from .._validate import as_array

__all__ = [
    "PAPER_FROM_CV",
    "pose_cv_to_paper",
    "pose_paper_to_cv",
    "pixels_to_paper_uv",
    "paper_uv_to_pixels",
    "project_paper",
]

#: Rotation taking OpenCV camera coordinates to the paper's camera coordinates.
PAPER_FROM_CV = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def pose_cv_to_paper(rotation_cv, translation_cv=None):
    """OpenCV pose ``(R_cv (..., 3, 3), t_cv (..., 3))`` → paper ``(R_ct, T_ct)``.

    If ``translation_cv`` is None only the rotation is converted and returned.
    """
    R = as_array(rotation_cv, "rotation_cv", (..., 3, 3))
    Rp = PAPER_FROM_CV @ R
    if translation_cv is None:
        return Rp
    t = as_array(translation_cv, "translation_cv", (..., 3))
    return Rp, t @ PAPER_FROM_CV.T


def pose_paper_to_cv(rotation_ct, translation_ct=None):
    """Paper pose ``(R_ct, T_ct)`` → OpenCV ``(R_cv, t_cv)`` (inverse of :func:`pose_cv_to_paper`)."""
    R = as_array(rotation_ct, "rotation_ct", (..., 3, 3))
    Rc = PAPER_FROM_CV.T @ R
    if translation_ct is None:
        return Rc
    t = as_array(translation_ct, "translation_ct", (..., 3))
    return Rc, t @ PAPER_FROM_CV


def pixels_to_paper_uv(pixels, principal_point) -> np.ndarray:
    """Pixel coordinates ``(..., 2)`` (x right, y down) → paper ``(u, v)`` in pixels (v up)."""
    p = as_array(pixels, "pixels", (..., 2))
    c = np.asarray(principal_point, dtype=float)
    return np.stack([p[..., 0] - c[0], c[1] - p[..., 1]], -1)


def paper_uv_to_pixels(uv, principal_point) -> np.ndarray:
    """Paper ``(u, v)`` in pixels ``(..., 2)`` → pixel coordinates (x right, y down)."""
    q = as_array(uv, "uv", (..., 2))
    c = np.asarray(principal_point, dtype=float)
    return np.stack([q[..., 0] + c[0], c[1] - q[..., 1]], -1)


def project_paper(points_c, focal_length) -> np.ndarray:
    """Zhai eq. (3): camera-frame points ``(..., 3)`` (paper frame) → ``(u, v)`` ``(..., 2)``."""
    p = as_array(points_c, "points_c", (..., 3))
    return np.stack([-focal_length * p[..., 1] / p[..., 0], -focal_length * p[..., 2] / p[..., 0]], -1)
