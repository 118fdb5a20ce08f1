"""Rotations, rigid transforms and small SE(3) helpers (design §2).

Convention: a pose (R, t) maps body points into the lighthouse (or camera)
frame, ``p_lh = R @ p_body + t``; R is an active rotation as in
:class:`scipy.spatial.transform.Rotation`. Attitude errors are left
perturbations: ``R_est = exp([dphi]x) R_true``.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ._validate import as_array

__all__ = [
    "skew",
    "rotvec_to_matrix",
    "matrix_to_rotvec",
    "transform_points",
    "attitude_error",
    "random_rotations",
    "nearest_rotation",
    "ensure_rotation",
    "right_jacobian_so3",
    "look_at_rotation",
]


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[v]x`` of ``v : (..., 3)`` → ``(..., 3, 3)``."""
    v = np.asarray(v, dtype=float)
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack(
        [np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2
    )


def rotvec_to_matrix(rotvec) -> np.ndarray:
    """Rotation vectors ``(..., 3)`` rad → rotation matrices ``(..., 3, 3)`` (scipy convention)."""
    rv = as_array(rotvec, "rotvec", (..., 3))
    out = Rotation.from_rotvec(rv.reshape(-1, 3)).as_matrix()
    return out.reshape(rv.shape[:-1] + (3, 3))


def matrix_to_rotvec(rotation, *, assume_valid: bool = False) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` → rotation vectors ``(..., 3)`` rad, norm in [0, pi].

    assume_valid : the matrices are proper rotations to rounding (products of rotations inside a
    solver): scipy skips its orthonormalisation, half the time of a call; a matrix that is not a
    rotation then gives a meaningless vector. Default: any matrix, projected to the nearest rotation.
    """
    R = as_array(rotation, "rotation", (..., 3, 3))
    out = Rotation.from_matrix(R.reshape(-1, 3, 3), assume_valid=assume_valid).as_rotvec()
    return out.reshape(R.shape[:-2] + (3,))


def transform_points(rotation, translation, points) -> np.ndarray:
    """``p_out = R @ p + t`` for rotation ``(..., 3, 3)``, translation ``(..., 3)``, points ``(..., n, 3)``."""
    R = np.asarray(rotation, dtype=float)
    t = np.asarray(translation, dtype=float)
    p = np.asarray(points, dtype=float)
    return np.einsum("...ij,...nj->...ni", R, p) + t[..., None, :]


def attitude_error(rotation_est, rotation_ref) -> np.ndarray:
    """Rotation-vector norm (rad) of ``R_est R_ref^T`` — Chen eq. (23)/(25) attitude error."""
    Re = as_array(rotation_est, "rotation_est", (..., 3, 3))
    Rr = as_array(rotation_ref, "rotation_ref", (..., 3, 3))
    D = Re @ np.swapaxes(Rr, -1, -2)
    # atan2(|sin|, cos) is accurate at small and large angles (arccos of the trace is not)
    # and, unlike scipy's from_matrix, never raises on a matrix that is not a rotation.
    s = 0.5 * np.stack([D[..., 2, 1] - D[..., 1, 2], D[..., 0, 2] - D[..., 2, 0], D[..., 1, 0] - D[..., 0, 1]], -1)
    c = 0.5 * (np.trace(D, axis1=-2, axis2=-1) - 1.0)
    return np.arctan2(np.linalg.norm(s, axis=-1), c)


def random_rotations(n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` rotations ``(n, 3, 3)`` uniform on SO(3), drawn from ``rng``."""
    return Rotation.random(n, random_state=rng).as_matrix()


def nearest_rotation(M) -> np.ndarray:
    """Nearest proper rotation (Frobenius) to ``M : (..., 3, 3)`` via SVD."""
    M = as_array(M, "M", (..., 3, 3))
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.ones(M.shape[:-1])
    D[..., -1] = d
    return (U * D[..., None, :]) @ Vt


def ensure_rotation(M, tol: float = 1e-9) -> np.ndarray:
    """``M (..., 3, 3)`` with every matrix that is not a proper rotation to ``tol`` (``|M M^T - I|`` max,
    a non-positive determinant, or a non-finite entry) replaced by its :func:`nearest_rotation`; proper
    ones are returned untouched (a copy). The one place that decides "a rotation to rounding" for
    starts and inputs given by callers (PnP's initial poses, the rotation-pair fit)."""
    R = np.array(as_array(M, "M", (..., 3, 3)), float)
    flat = R.reshape(-1, 3, 3)
    with np.errstate(invalid="ignore"):
        err = np.abs(flat @ np.swapaxes(flat, -1, -2) - np.eye(3)).max((1, 2))
        off = ~(err <= tol) | ~(np.linalg.det(flat) > 0)
    if off.any():
        flat[off] = nearest_rotation(flat[off])
    return R


def right_jacobian_so3(rotvec) -> np.ndarray:
    """Right Jacobian ``J_r(phi)`` of SO(3), ``(..., 3)`` → ``(..., 3, 3)`` (Chen eq. 9).

    ``R(phi + dphi) ≈ R(phi) exp(J_r(phi) dphi)`` for scipy's ``R(phi)``.
    """
    phi = as_array(rotvec, "rotvec", (..., 3))
    th = np.linalg.norm(phi, axis=-1)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    e = phi / ths[..., None]
    s = np.where(small, 1.0, np.sin(ths) / ths)
    c = np.where(small, 0.0, (np.cos(ths) - 1.0) / ths)
    eye = np.broadcast_to(np.eye(3), phi.shape[:-1] + (3, 3))
    eet = e[..., :, None] * e[..., None, :]
    return s[..., None, None] * eye + (1 - s)[..., None, None] * eet + c[..., None, None] * skew(e)


def look_at_rotation(direction, up_hint=(0.0, 1.0, 0.0)) -> np.ndarray:
    """Rotation ``(..., 3, 3)`` whose third row is the unit ``direction (..., 3)``.

    Used to build a frame with z along a given direction (a station boresight);
    rows are the frame's axes expressed in the parent frame.
    """
    d = as_array(direction, "direction", (..., 3))
    z = d / np.linalg.norm(d, axis=-1, keepdims=True)
    up = np.broadcast_to(np.asarray(up_hint, float), z.shape)
    alt = np.broadcast_to(np.array([1.0, 0.0, 0.0]), z.shape)
    para = np.abs(np.sum(up * z, -1, keepdims=True)) > 0.99
    up = np.where(para, alt, up)
    x = np.cross(up, z)
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    y = np.cross(z, x)
    return np.stack([x, y, z], -2)
