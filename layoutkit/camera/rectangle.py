"""Attitude of a rectangular face from its four image corners (Zhai et al. 2014, design §7).

All functions work in the **paper's conventions** (see :mod:`layoutkit.camera.conventions`):
camera x along the optical axis pointing away from the scene, ``u = -f y/x``, ``v = -f z/x``;
the observed face is ``x_t = H/2`` of the target frame with corners

    P1 = (H/2, -L/2, -W/2), P2 = P1 + (0, L, 0), P3 = P1 + (0, 0, W), P4 = P1 + (0, L, W)

(Zhai eq. 2) and ``P_c = R_ct P_t + T_ct`` (eq. 1). Corners are passed as ``(..., 4, 2)`` arrays
in the order P1, P2, P3, P4 — *not* cyclic: going round the face is P1 → P2 → P4 → P3, which is
counter-clockwise in (u, v) (v up) when the face looks at the camera.

Labelling ambiguities (handled explicitly, never silently):

* **Which corner is P1.** A size-free solve cannot tell the four cyclic labellings apart; each
  shift by one corner turns the result by 90° about the face normal ``x_t`` (for a non-square
  rectangle the 90° shifts also swap L and W). The 180° shift (P1↔P4, P2↔P3) is the classic
  ambiguity of a rectangle: both labellings are exact solutions. :func:`label_symmetries` lists
  the rotations, :func:`resolve_labelling` picks the one nearest a reference (the previous frame,
  or a prior), which is how tracking keeps continuity.
* **Mirror labelling** (P2↔P3) makes the face normal point away from the camera; the solvers
  detect it and return ``status == "mirrored"``. :func:`order_corners` builds the non-mirrored
  order from any four corners.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np

from .._validate import as_array, check_finite
from ..geometry import nearest_rotation

__all__ = [
    "rectangle_corners",
    "zhai_depth_ratios",
    "rectangle_attitude",
    "frame_rotation",
    "euler_zyx",
    "euler_zyx_to_matrix",
    "RectangleSolution",
    "RectangleSolver",
    "RECTANGLE_SOLVERS",
    "solve_rectangle",
    "label_symmetries",
    "resolve_labelling",
    "order_corners",
    "BOX_FACES",
    "box_attitude",
]


# ----------------------------------------------------------------------------- geometry
def rectangle_corners(H: float, L: float, W: float) -> np.ndarray:
    """Target-frame corners ``(4, 3)`` (m) of the face ``x_t = H/2``, order P1..P4 (Zhai eq. 2)."""
    p1 = np.array([H / 2, -L / 2, -W / 2])
    return np.stack([p1, p1 + [0, L, 0], p1 + [0, 0, W], p1 + [0, L, W]])


def _corners(corners_uv, focal_length):
    c = as_array(corners_uv, "corners_uv", (..., 4, 2))
    check_finite(c, "corners_uv")
    f = float(focal_length)
    if not np.isfinite(f) or f <= 0:
        raise ValueError(f"focal_length: expected a positive finite number, got {focal_length!r}")
    return c, f


def zhai_depth_ratios(corners_uv) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth ratios ``a = x2c/x1c``, ``b = x3c/x1c``, ``c = x4c/x1c`` (each ``(...)``).

    ``a`` and ``b`` are Zhai eqs. (8), (9). Eq. (10) as printed is wrong (design §7 erratum);
    from eq. (7), ``x1c + x4c = x2c + x3c`` gives ``c = a + b - 1``. Degenerate quadrilaterals
    (three collinear corners) give non-finite values.
    """
    c = as_array(corners_uv, "corners_uv", (..., 4, 2))
    u1, u2, u3, u4 = np.moveaxis(c[..., 0], -1, 0)
    v1, v2, v3, v4 = np.moveaxis(c[..., 1], -1, 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        # Zhai eq. (8)
        a = ((u3 - u1) * (v3 - v4) - (u3 - u4) * (v3 - v1)) / ((u3 - u2) * (v3 - v4) - (u3 - u4) * (v3 - v2))
        # Zhai eq. (9)
        b = ((u2 - u1) * (v2 - v4) - (u2 - u4) * (v2 - v1)) / ((u2 - u3) * (v2 - v4) - (u2 - u4) * (v2 - v3))
    return a, b, a + b - 1.0  # erratum of eq. (10): from eq. (7)


def _zhai_columns(c, f):
    """Unnormalised-orthogonality columns r1, r2, r3 ``(..., 3)`` and the depth ratios."""
    a, b, _ = zhai_depth_ratios(c)
    u, v = c[..., 0], c[..., 1]
    # Zhai eqs. (11)-(12): left-hand sides, = L1 r2 and W1 r3 with L1, W1 < 0
    g2 = np.stack([a - 1.0, (u[..., 0] - u[..., 1] * a) / f, (v[..., 0] - v[..., 1] * a) / f], -1)
    g3 = np.stack([b - 1.0, (u[..., 0] - u[..., 2] * b) / f, (v[..., 0] - v[..., 2] * b) / f], -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        r2 = -g2 / np.linalg.norm(g2, axis=-1, keepdims=True)  # Zhai eq. (15)
        r3 = -g3 / np.linalg.norm(g3, axis=-1, keepdims=True)  # Zhai eq. (16)
    r1 = np.cross(r2, r3)  # Zhai eq. (17)
    return r1, r2, r3, a, b


def _project_to_rotation(r1, r2, r3):
    """Nearest proper rotation to ``[r1 r2 r3]`` (columns); NaN where the columns are not finite."""
    M = np.stack([r1, r2, r3], -1)
    ok = np.all(np.isfinite(M), axis=(-2, -1)) & (np.linalg.norm(r1, axis=-1) > 1e-12)
    Ms = np.where(ok[..., None, None], M, np.eye(3))
    R = nearest_rotation(Ms)
    return np.where(ok[..., None, None], R, np.nan), ok


def _facing(R, c, f):
    """True where the face normal ``r1`` points towards the camera (ray to P1 has x < 0)."""
    ray = np.stack([-np.ones(c.shape[:-2]), c[..., 0, 0] / f, c[..., 0, 1] / f], -1)  # ∝ P1c / |x1c|
    return np.einsum("...i,...i->...", R[..., :, 0], -ray) > 0


def rectangle_attitude(corners_uv, focal_length) -> np.ndarray:
    """Size-free attitude ``R_ct (..., 3, 3)`` of a rectangle from its image corners (Zhai 2014).

    Parameters
    ----------
    corners_uv : (..., 4, 2)
        Image corners P1, P2, P3, P4 (Zhai eq. 2 order) in the paper's (u, v), principal point at
        the origin, same unit as ``focal_length`` (pixels with a focal length in pixels, or metres
        on the sensor with f in metres).
    focal_length : float
        Focal length f, > 0.

    Returns
    -------
    (..., 3, 3) rotation, target → paper camera frame. With noise the columns of eqs. (15)-(17) are
    not orthonormal; the result is the nearest proper rotation (SVD), so it is always a rotation.
    Degenerate quadrilaterals (three collinear corners) give NaN. The size of the face is not
    needed; the mirror and 180° labelling ambiguities are discussed in the module docstring
    (:func:`solve_rectangle` reports them as a status).
    """
    c, f = _corners(corners_uv, focal_length)
    r1, r2, r3, _, _ = _zhai_columns(c, f)
    R, _ = _project_to_rotation(r1, r2, r3)
    return R


# ----------------------------------------------------------------------------- Euler angles
def frame_rotation(axis: str, angle) -> np.ndarray:
    """Frame-rotation matrix ``(..., 3, 3)`` about ``axis`` in 'xyz' (Zhai / design §7).

    ``Rz(θ) = [[c, s, 0], [-s, c, 0], [0, 0, 1]]``; Rx and Ry likewise (the transpose of scipy's
    active rotation by θ).
    """
    th = np.asarray(angle, dtype=float)
    c, s = np.cos(th), np.sin(th)
    o, z = np.ones_like(th), np.zeros_like(th)
    if axis == "x":
        rows = [[o, z, z], [z, c, s], [z, -s, c]]
    elif axis == "y":
        rows = [[c, z, -s], [z, o, z], [s, z, c]]
    elif axis == "z":
        rows = [[c, s, z], [-s, c, z], [z, z, o]]
    else:
        raise ValueError(f"axis: expected one of 'x', 'y', 'z', got {axis!r}")
    return np.stack([np.stack(r, -1) for r in rows], -2)


def euler_zyx_to_matrix(theta1, theta2, theta3) -> np.ndarray:
    """``R = Rx(θ3) Ry(θ2) Rz(θ1)`` ``(..., 3, 3)`` from angles in rad (Zhai §1, Z→Y→X)."""
    return frame_rotation("x", theta3) @ frame_rotation("y", theta2) @ frame_rotation("z", theta1)


def euler_zyx(R, gimbal_tol: float = 1e-12) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Euler angles ``(θ1, θ2, θ3)`` rad, each ``(...)``, with ``R = Rx(θ3) Ry(θ2) Rz(θ1)``.

    Zhai §1: ``θ2 = asin(-R13)``, ``θ1 = atan(R12/R11)``, ``θ3 = atan(R23/R33)``; at gimbal lock
    (``|R13| = 1`` within ``gimbal_tol``) ``θ1 = atan(-R21/R22)``, ``θ3 = 0``. ``arctan2`` is used
    instead of the paper's ``arctan`` so that θ1, θ3 cover (-π, π]; θ2 ∈ [-π/2, π/2].
    """
    R = as_array(R, "R", (..., 3, 3))
    s2 = np.clip(-R[..., 0, 2], -1.0, 1.0)
    th2 = np.arcsin(s2)
    lock = np.abs(s2) >= 1.0 - gimbal_tol
    th1 = np.where(lock, np.arctan2(-R[..., 1, 0], R[..., 1, 1]), np.arctan2(R[..., 0, 1], R[..., 0, 0]))
    th3 = np.where(lock, 0.0, np.arctan2(R[..., 1, 2], R[..., 2, 2]))
    return th1, th2, th3


# ----------------------------------------------------------------------------- labelling
def label_symmetries(n_fold: int = 4) -> np.ndarray:
    """Rotations ``(n_fold, 3, 3)`` about the face normal ``x_t`` that relabel the corners.

    ``n_fold = 4`` (square face, or unknown aspect ratio): 0°, 90°, 180°, 270°; ``n_fold = 2``
    (rectangle with known L ≠ W): 0°, 180°. If R solves one labelling, ``R @ S`` solves another.
    """
    if n_fold not in (1, 2, 4):
        raise ValueError(f"n_fold: expected 1, 2 or 4, got {n_fold!r}")
    angles = np.arange(n_fold) * (2 * np.pi / n_fold)
    return frame_rotation("x", angles)


def resolve_labelling(rotation, reference, n_fold: int = 4) -> np.ndarray:
    """Relabel ``rotation (..., 3, 3)`` to the symmetric solution nearest ``reference (..., 3, 3)``.

    Returns ``rotation @ S_k`` with ``S_k`` from :func:`label_symmetries` minimising the chordal
    distance to ``reference`` — temporal continuity for tracking (reference = previous estimate).
    """
    R = as_array(rotation, "rotation", (..., 3, 3))
    Ref = as_array(reference, "reference", (..., 3, 3))
    S = label_symmetries(n_fold)
    cand = R[..., None, :, :] @ S  # (..., k, 3, 3)
    score = np.einsum("...kij,...ij->...k", cand, Ref)  # trace(C^T Ref)
    k = np.argmax(score, axis=-1)
    return np.take_along_axis(cand, k[..., None, None, None], axis=-3)[..., 0, :, :]


def order_corners(quad_uv, first: int | None = None) -> np.ndarray:
    """Order four image corners ``(..., 4, 2)`` (any order) as P1, P2, P3, P4 (paper u, v; v up).

    The corners are sorted by angle around their centroid so that P1 → P2 → P4 → P3 runs
    counter-clockwise (face normal towards the camera, no mirror). ``P1`` is the corner with the
    smallest ``u + v`` (lower left) unless ``first`` (0..3, index into the counter-clockwise cycle
    starting at the lower-left corner) says otherwise; tracking should then fix the remaining 90°
    ambiguity with :func:`resolve_labelling`.
    """
    q = as_array(quad_uv, "quad_uv", (..., 4, 2))
    cen = q.mean(-2, keepdims=True)
    ang = np.arctan2(q[..., 1] - cen[..., 1], q[..., 0] - cen[..., 0])
    idx = np.argsort(ang, axis=-1)  # counter-clockwise
    cyc = np.take_along_axis(q, idx[..., None], axis=-2)
    start = np.argmin(cyc.sum(-1), axis=-1)
    if first is not None:
        start = (start + int(first)) % 4
    roll = (start[..., None] + np.arange(4)) % 4
    cyc = np.take_along_axis(cyc, roll[..., None], axis=-2)
    # cycle P1, P2, P4, P3 -> order P1, P2, P3, P4
    return cyc[..., [0, 1, 3, 2], :]


# ----------------------------------------------------------------------------- solver registry
@dataclass(frozen=True)
class RectangleSolution:
    """Result of a rectangle solve.

    rotation : (..., 3, 3) R_ct (paper conventions), NaN where not solved.
    success : (...) bool. status : (...) str array — "ok", "degenerate", "mirrored", "failed".
    alternative : (..., 3, 3) or None — the second (Necker-reversed) solution where a method has
        one (IPPE), else None. message : short human-readable summary.
    """

    rotation: np.ndarray
    success: np.ndarray
    status: np.ndarray
    alternative: np.ndarray | None = None
    message: str = ""
    extra: dict = field(default_factory=dict)


class RectangleSolver(Protocol):
    """``solver(corners_uv (..., 4, 2), focal_length, **options) -> RectangleSolution``."""

    def __call__(self, corners_uv, focal_length, **options) -> RectangleSolution: ...


def _finish(R, ok, c, f, alternative=None, extra=None) -> RectangleSolution:
    facing = _facing(np.where(ok[..., None, None], R, np.eye(3)), c, f)
    status = np.where(~ok, "degenerate", np.where(facing, "ok", "mirrored"))
    success = ok & facing
    n_bad = int(np.size(success) - np.count_nonzero(success))
    msg = "ok" if n_bad == 0 else f"{n_bad} of {np.size(success)} not solved (see status)"
    return RectangleSolution(R, success, status, alternative, msg, extra or {})


def _solve_zhai(corners_uv, focal_length) -> RectangleSolution:
    """Zhai eqs. (8), (9), (15)-(17), nearest rotation; size-free."""
    c, f = _corners(corners_uv, focal_length)
    r1, r2, r3, a, b = _zhai_columns(c, f)
    R, ok = _project_to_rotation(r1, r2, r3)
    ok &= (a > 0) & (b > 0)  # all corners in front of the camera
    return _finish(R, ok, c, f, extra={"a": a, "b": b})


def _solve_homography(corners_uv, focal_length) -> RectangleSolution:
    """Vanishing-point / homography method: DLT homography unit square → normalised image,
    columns h1, h2 normalised separately (size-free), nearest rotation."""
    c, f = _corners(corners_uv, focal_length)
    m = c / f
    plane = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])  # (y, z) of P1..P4 / (L, W)
    X, Y = plane[:, 0], plane[:, 1]
    x, y = m[..., 0], m[..., 1]
    z0 = np.zeros_like(x)
    o1 = np.ones_like(x)
    Xb, Yb = np.broadcast_to(X, x.shape), np.broadcast_to(Y, x.shape)
    rows_u = np.stack([Xb, Yb, o1, z0, z0, z0, -x * Xb, -x * Yb, -x], -1)
    rows_v = np.stack([z0, z0, z0, Xb, Yb, o1, -y * Xb, -y * Yb, -y], -1)
    A = np.concatenate([rows_u, rows_v], -2)  # (..., 8, 9)
    with np.errstate(invalid="ignore"):
        _, s, Vt = np.linalg.svd(A)
    Hm = Vt[..., -1, :].reshape(c.shape[:-2] + (3, 3))
    Hm = Hm * np.sign(Hm[..., 2, 2])[..., None, None]  # P1 in front: depth of P1 > 0
    # image homogeneous vector m ∝ q = (y_c, z_c, -x_c) = Q p_c
    Q = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])
    h1, h2 = Hm[..., :, 0], Hm[..., :, 1]
    r2 = h1 @ Q / np.linalg.norm(h1, axis=-1, keepdims=True)  # Q^T h1
    r3 = h2 @ Q / np.linalg.norm(h2, axis=-1, keepdims=True)
    r1 = np.cross(r2, r3)
    R, ok = _project_to_rotation(r1, r2, r3)
    ok &= s[..., -2] > 1e-12 * s[..., 0]  # rank-8 system
    return _finish(R, ok, c, f)


_NUDGE = np.array([[1.0, -1.0], [-1.0, 1.0], [1.0, 1.0], [-1.0, -1.0]])


def _solve_ippe(corners_uv, focal_length, aspect_ratio: float = 1.0, reference=None,
                ambiguity_ratio: float = 2.0) -> RectangleSolution:
    """OpenCV IPPE (``SOLVEPNP_IPPE``) on a rectangle of known aspect ratio ``L / W``.

    IPPE gives two poses (the plane's normal reflected about the line of sight). The one with the
    lower reprojection error is returned, except with a ``reference (..., 3, 3)`` (the previous or
    predicted attitude) when the two errors are within ``ambiguity_ratio`` of each other (the data
    cannot decide, e.g. near face-on): then the one nearer the reference (up to the corner-labelling
    symmetry) is taken. The other is ``alternative``; ``extra["reprojection_px"] (..., 2)`` holds the
    RMS reprojection errors (image units) of the returned and the alternative pose.
    """
    import cv2

    from .conventions import PAPER_FROM_CV

    c, f = _corners(corners_uv, focal_length)
    rho = float(aspect_ratio)
    if not np.isfinite(rho) or rho <= 0:
        raise ValueError(f"aspect_ratio: expected a positive number L/W, got {aspect_ratio!r}")
    obj = np.array([[0.0, -rho / 2, -0.5], [0.0, rho / 2, -0.5], [0.0, -rho / 2, 0.5], [0.0, rho / 2, 0.5]])
    # plane frame = the camera frame of a face-on view (x right, y down, z into the target):
    # p_plane = B p_t with B = PAPER_FROM_CV^T, so typical solutions are far from a 180° rotation
    # (OpenCV's rvec round trip is ill-conditioned there and IPPE then returns a wrong pose).
    A = PAPER_FROM_CV  # p_t = A p_plane
    obj_plane = obj @ A  # rows A^T p_t = (y, -z, -x)
    flat = c.reshape(-1, 4, 2)
    refs = None if reference is None else np.broadcast_to(
        as_array(reference, "reference", (..., 3, 3)), c.shape[:-2] + (3, 3)).reshape(-1, 3, 3)
    R = np.full((len(flat), 3, 3), np.nan)
    R_alt = np.full((len(flat), 3, 3), np.nan)
    ok = np.zeros(len(flat), bool)
    rep = np.full((len(flat), 2), np.nan)
    S = label_symmetries(4 if np.isclose(rho, 1.0) else 2)
    # image units, not normalised coordinates: IPPE returns NaN on tiny normalised coordinates
    K = np.diag([f, f, 1.0])
    for i, q in enumerate(flat):
        img = np.stack([q[:, 0], -q[:, 1]], -1)  # OpenCV image coordinates about the principal point
        sols = []
        # IPPE returns NaN on some exactly symmetric inputs (noise-free renders of a face seen
        # square-on in one axis); a deterministic nudge of the corners (1e-6, then 1e-4 px) avoids the branch.
        for nudge in (0.0, 1e-6, 1e-4):
            try:
                n, rvecs, _, errs = cv2.solvePnPGeneric(obj_plane, img + nudge * _NUDGE, K, None,
                                                        flags=cv2.SOLVEPNP_IPPE)
            except cv2.error:
                n, rvecs, errs = 0, (), None
            sols = [(float(errs[j, 0]), PAPER_FROM_CV @ cv2.Rodrigues(rv)[0] @ A.T)
                    for j, rv in enumerate(rvecs[:n]) if np.all(np.isfinite(rv))]
            if sols:
                break
        if not sols:
            continue
        sols.sort(key=lambda es: es[0])
        if refs is not None and len(sols) > 1 and sols[1][0] <= ambiguity_ratio * sols[0][0]:
            sols.sort(key=lambda es: -np.max(np.einsum("kij,ij->k", es[1] @ S, refs[i])))
        R[i] = sols[0][1]
        rep[i, 0] = sols[0][0]
        if len(sols) > 1:
            R_alt[i] = sols[1][1]
            rep[i, 1] = sols[1][0]
        ok[i] = True
    shape = c.shape[:-2]
    R, R_alt, ok = R.reshape(shape + (3, 3)), R_alt.reshape(shape + (3, 3)), ok.reshape(shape)
    return _finish(R, ok, c, f, alternative=R_alt, extra={"reprojection_px": rep.reshape(shape + (2,))})


#: Registry of rectangle solvers: name → callable(corners_uv, focal_length, **options).
RECTANGLE_SOLVERS: dict[str, Callable[..., RectangleSolution]] = {
    "zhai": _solve_zhai,
    "homography": _solve_homography,
    "ippe": _solve_ippe,
}


def solve_rectangle(corners_uv, focal_length, method: str = "zhai", **options) -> RectangleSolution:
    """Solve ``R_ct`` with a registered method (:data:`RECTANGLE_SOLVERS`); see each for options.

    ``"zhai"`` and ``"homography"`` are size-free; ``"ippe"`` needs ``aspect_ratio = L / W``.
    """
    try:
        solver = RECTANGLE_SOLVERS[method]
    except KeyError:
        raise ValueError(f"method: expected one of {sorted(RECTANGLE_SOLVERS)}, got {method!r}") from None
    return solver(corners_uv, focal_length, **options)


# ----------------------------------------------------------------------------- multi-face box
def _face(x, y, z):
    return np.stack([x, y, z], -1).astype(float)  # columns: images of the face-local axes


_E = np.eye(3)
#: Face rotations ``F`` (target ← face-local) of a box: the face-local frame is Zhai's (face at
#: local ``x = H/2``, P1..P4 as in eq. 2), so ``R_ct(face) = R_ct(box) @ F``.
BOX_FACES: dict[str, np.ndarray] = {
    "+x": _face(_E[0], _E[1], _E[2]),
    "-x": _face(-_E[0], -_E[1], _E[2]),
    "+y": _face(_E[1], -_E[0], _E[2]),
    "-y": _face(-_E[1], _E[0], _E[2]),
    "+z": _face(_E[2], _E[1], -_E[0]),
    "-z": _face(-_E[2], _E[1], _E[0]),
}


def box_attitude(face_corners: dict, focal_length, method: str = "zhai", weights: dict | None = None,
                 **options) -> RectangleSolution:
    """Attitude of a box from several visible faces: solve each, then average on SO(3).

    ``face_corners`` maps a face name of :data:`BOX_FACES` to its corners ``(..., 4, 2)`` ordered
    P1..P4 in that face's local frame. Each face gives ``R_box = R_face @ F^T``; the estimate is
    the chordal mean ``nearest_rotation(Σ w_k R_box,k)`` over the successful faces (weights default
    to 1). The 180° labelling of each face must already be consistent (e.g. by
    :func:`resolve_labelling` against a common reference).
    """
    if not face_corners:
        raise ValueError("face_corners: expected at least one face, got none")
    acc = None
    n_ok = None
    for name, corners in face_corners.items():
        if name not in BOX_FACES:
            raise ValueError(f"face_corners: unknown face {name!r}, expected one of {sorted(BOX_FACES)}")
        sol = solve_rectangle(corners, focal_length, method=method, **options)
        Rb = sol.rotation @ BOX_FACES[name].T
        w = 1.0 if weights is None else float(weights.get(name, 1.0))
        term = np.where(sol.success[..., None, None], w * np.nan_to_num(Rb), 0.0)
        acc = term if acc is None else acc + term
        n_ok = sol.success.astype(int) if n_ok is None else n_ok + sol.success
    ok = n_ok > 0
    R = nearest_rotation(np.where(ok[..., None, None], acc, np.eye(3)))
    R = np.where(ok[..., None, None], R, np.nan)
    status = np.where(ok, "ok", "failed")
    return RectangleSolution(R, ok, status, None, "ok" if np.all(ok) else "some frames without a solved face",
                             {"n_faces": n_ok})
