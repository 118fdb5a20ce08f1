"""Unit quaternions for the filter's attitude (scipy order ``[x, y, z, w]``), single poses.

Attitude convention (design §2): ``p_world = R p_body + t``; the filter's attitude error is the
left perturbation in the world frame, ``R = exp([dphi]x) R_hat`` (as :mod:`layoutkit.dop`). These
helpers work on one quaternion ``(4,)`` at a time with plain floats — the filter's per-sweep hot
path, where numpy's per-call overhead on tiny arrays dominates.
"""
from __future__ import annotations

import math

import numpy as np

from ..rotations import matrix_to_quaternion

__all__ = ["quat_from_rotvec", "quat_mul", "quat_to_matrix", "quat_from_matrix", "quat_to_rotvec", "rotvec_floats"]


def quat_from_rotvec(phi) -> np.ndarray:
    """Rotation vector (3,) rad → unit quaternion ``[x, y, z, w]`` (series below 1e-6 rad)."""
    x, y, z = np.asarray(phi, float).tolist()
    th = math.sqrt(x * x + y * y + z * z)
    if th < 1e-6:
        s = 0.5 - th * th / 48.0
        c = 1.0 - th * th / 8.0
    else:
        s = math.sin(0.5 * th) / th
        c = math.cos(0.5 * th)
    return np.array([s * x, s * y, s * z, c])


def quat_mul(a, b) -> np.ndarray:
    """Hamilton product ``a ⊗ b`` (rotation b first, then a), normalised."""
    ax, ay, az, aw = np.asarray(a, float).tolist()
    bx, by, bz, bw = np.asarray(b, float).tolist()
    x = aw * bx + ax * bw + ay * bz - az * by
    y = aw * by - ax * bz + ay * bw + az * bx
    z = aw * bz + ax * by - ay * bx + az * bw
    w = aw * bw - ax * bx - ay * by - az * bz
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if w < 0:
        n = -n  # keep w >= 0 (one of the two signs, so rotvecs stay in [0, pi])
    return np.array([x / n, y / n, z / n, w / n])


def quat_to_matrix(q) -> np.ndarray:
    """Unit quaternion ``[x, y, z, w]`` → rotation matrix (3, 3): the closed form of
    :func:`layoutkit.rotations.quaternion_to_matrix` on plain floats (the per-sweep hot path;
    tests/test_filter.py checks that both agree)."""
    x, y, z, w = np.asarray(q, float).tolist()
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    return np.array([[1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)],
                     [2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)],
                     [2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)]])


def quat_from_matrix(R) -> np.ndarray:
    """Rotation matrix (3, 3) → unit quaternion ``[x, y, z, w]`` with w >= 0
    (:func:`layoutkit.rotations.matrix_to_quaternion`, the owner of quaternion orders)."""
    return matrix_to_quaternion(R)


def quat_to_rotvec(q) -> np.ndarray:
    """Unit quaternion ``[x, y, z, w]`` (w >= 0) → rotation vector (3,) rad, norm in [0, pi]."""
    return np.array(rotvec_floats(q))


def rotvec_floats(q) -> list:
    """:func:`quat_to_rotvec` as a list of 3 floats (the per-sweep JSON line: no array round trip)."""
    x, y, z, w = np.asarray(q, float).tolist()
    s = math.sqrt(x * x + y * y + z * z)
    if s < 1e-12:
        k = 2.0 / w if w != 0 else 0.0
    else:
        k = 2.0 * math.atan2(s, w) / s
    return [k * x, k * y, k * z]
