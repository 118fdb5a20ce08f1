"""A rectangular face seen through a real lens: observed pixel corners → attitude + predicted σ.

The pipeline of :func:`face_attitude`:

1. the four observed corners (pixels of the real, distorted image; any order round the face) are
   undistorted to the ideal square-pixel camera (:mod:`layoutkit.camera.lens`, focal ``f``,
   principal point ``(cx, cy)`` of K), turned into the paper's ``(u, v)`` and labelled P1..P4
   (:func:`layoutkit.camera.rectangle.order_corners`, or the order given);
2. a registered rectangle solver (:data:`layoutkit.camera.rectangle.RECTANGLE_SOLVERS`; ``zhai``
   and ``homography`` size-free, ``ippe`` with the face's aspect ratio ``L / W``; for IPPE on a
   non-square face both assignments of the long side are tried and the lower reprojection error
   wins);
3. the face's aspect ratio and its centre *up to scale* from Zhai's depth ratios (eqs. 8, 9 and
   the corrected eq. 10: ``x4c / x1c = a + b - 1``): the corners in the camera frame are
   ``P_i = x_ic (1, -u_i / f, -v_i / f)`` (eq. 3), so with ``x1c = -1`` they are known up to the
   face's scale; ``aspect_ratio = |P2 - P1| / |P3 - P1|`` and ``position_over_width = T / W``
   (the centre in units of the face's width W: multiply by W in metres for a position);
4. the **predicted attitude covariance** (rad², of ``dphi`` with ``R_est = exp([dphi]x) R``)

       C = J_px Σ_px J_pxᵀ + J_θ Σ_θ J_θᵀ

   ``J_px (3, 8)``: attitude per *observed* pixel coordinate = the solver's Jacobian in (u, v)
   (:func:`layoutkit.camera.uncertainty.attitude_jacobian_corners`, central differences through
   the solver, branch and labelling held) times ``d(u, v)/d(ideal px)`` (``diag(1, -1)``) times the
   undistortion Jacobian per corner (:func:`layoutkit.camera.lens.undistort_jacobian`): the lens
   stretches or shrinks the corner noise (a barrel lens, k1 < 0, stretches it towards the image
   edge); ``Σ_px (8, 8)``: the corner covariance in observed pixels (the detector's, or
   ``sigma_px² I``); ``J_θ (3, p)``: attitude per camera parameter (fx, fy, cx, cy, k1, ...) by
   central differences through steps 1–2 (undistortion *and* the ideal camera change), ``Σ_θ``
   the diagonal of the calibration's standard deviations. ``sigma_deg = sqrt(trace C)`` in
   degrees (the RMS total attitude error a Monte-Carlo of the same noise gives).

Conventions: rotations are Zhai's ``R_ct`` (paper camera frame ← face frame, docs/camera.md);
``rotvec_cv`` is the same attitude in OpenCV's camera frame (``PAPER_FROM_CV^T R_ct``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .._validate import as_array
from ..geometry import matrix_to_rotvec
from .conventions import PAPER_FROM_CV, pixels_to_paper_uv
from .lens import (ideal_camera, model_from_parameters, model_parameter_vector, undistort_jacobian,
                   undistort_pixels)
from .rectangle import order_corners, resolve_labelling, solve_rectangle, zhai_depth_ratios
from .uncertainty import attitude_jacobian_corners, face_tilt

__all__ = ["FaceAttitude", "face_attitude", "order_pixel_corners", "pixels_to_ideal_uv", "face_geometry",
           "attitude_jacobian_pixels", "attitude_jacobian_camera", "FACE_ON_DEG"]

#: Face tilts (normal vs line of sight) below this are the face-on band: the tilt sign is nearly
#: unobservable there and the linear σ is not trustworthy (docs/camera.md).
FACE_ON_DEG = 10.0
_SHIFT_ONE = np.array([1, 3, 0, 2])  # P1..P4 relabelled one corner further round the face


@dataclass(frozen=True)
class FaceAttitude:
    """Result of :func:`face_attitude` (see module docstring for frames and the covariance).

    rotation (3, 3) R_ct; rotvec (3,) rad of R_ct; rotvec_cv (3,) rad of the OpenCV-frame attitude;
    corners_px (4, 2) observed pixels in P1..P4 order; corners_ideal_px (4, 2) undistorted pixels;
    corners_uv (4, 2) paper (u, v) px; aspect_ratio L/W (size-free estimate); position_over_width
    (3,) face centre / W, paper camera frame; tilt_deg; covariance (3, 3) rad² (NaN without a corner
    noise); sigma_deg; sigma_deg_per_px (σ for 1 px of i.i.d. corner noise, lens and solver only);
    sigma_camera_deg (the calibration-uncertainty share, 0 without std devs); alternative (3, 3) or
    None (IPPE's other branch); reprojection_px (IPPE RMS of the chosen / other branch).
    """

    rotation: np.ndarray
    success: bool
    status: str
    message: str
    method: str
    focal_length_px: float
    rotvec: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    rotvec_cv: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    corners_px: np.ndarray = field(default_factory=lambda: np.full((4, 2), np.nan))
    corners_ideal_px: np.ndarray = field(default_factory=lambda: np.full((4, 2), np.nan))
    corners_uv: np.ndarray = field(default_factory=lambda: np.full((4, 2), np.nan))
    aspect_ratio: float = float("nan")
    position_over_width: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    tilt_deg: float = float("nan")
    covariance: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))
    sigma_deg: float = float("nan")
    sigma_deg_per_px: float = float("nan")
    sigma_camera_deg: float = 0.0
    alternative: np.ndarray | None = None
    reprojection_px: tuple = (float("nan"), float("nan"))

    def to_dict(self) -> dict:
        """JSON-able summary (angles in deg beside rad where named so)."""
        return {
            "success": self.success, "status": self.status, "message": self.message, "method": self.method,
            "rotvec": self.rotvec, "rotvec_cv": self.rotvec_cv, "rotation": self.rotation,
            "sigma_deg": self.sigma_deg, "sigma_deg_per_px": self.sigma_deg_per_px,
            "sigma_camera_deg": self.sigma_camera_deg, "covariance_rad2": self.covariance,
            "corners_px": self.corners_px, "corners_ideal_px": self.corners_ideal_px, "corners_uv_px": self.corners_uv,
            "aspect_ratio": self.aspect_ratio, "position_over_width": self.position_over_width,
            "tilt_deg": self.tilt_deg, "focal_length_px": self.focal_length_px,
            "reprojection_px": list(self.reprojection_px),
            "alternative_rotvec": None if self.alternative is None else matrix_to_rotvec(self.alternative),
        }


def pixels_to_ideal_uv(corners_px, K, dist) -> tuple[np.ndarray, np.ndarray, float]:
    """Observed pixels ``(..., 2)`` → ``(ideal pixels (..., 2), paper (u, v) (..., 2), f)``."""
    f, cx, cy = ideal_camera(K)
    ideal = undistort_pixels(corners_px, K, dist, f)
    return ideal, pixels_to_paper_uv(ideal, (cx, cy)), f


def order_pixel_corners(corners_px, K, dist) -> np.ndarray:
    """Four observed corners ``(4, 2)`` in any order round the face → the same points in P1..P4
    order (non-mirrored, P1 lower left in the ideal image; :func:`order_corners`)."""
    c = as_array(corners_px, "corners_px", (4, 2))
    _, uv, _ = pixels_to_ideal_uv(c, K, dist)
    q = order_corners(uv)
    perm = [int(np.argmin(np.linalg.norm(uv - qi, axis=1))) for qi in q]
    if sorted(perm) != [0, 1, 2, 3]:
        raise ValueError("corners_px: two corners coincide")
    return c[perm]


def face_geometry(corners_uv, focal_length) -> tuple[np.ndarray, np.ndarray]:
    """Aspect ratio ``L / W (...)`` and centre / W ``(..., 3)`` (paper camera frame) from P1..P4 (u, v).

    Size-free (Zhai eqs. 8, 9, corrected eq. 10; module docstring); NaN for degenerate corners.
    """
    c = as_array(corners_uv, "corners_uv", (..., 4, 2))
    a, b, d = zhai_depth_ratios(c)
    x = -np.stack([np.ones_like(a), a, b, d], -1)  # x_ic with x1c = -1 (in front: x < 0)
    f = float(focal_length)
    P = np.stack([x, -x * c[..., 0] / f, -x * c[..., 1] / f], -1)  # (..., 4, 3), eq. (3) inverted
    with np.errstate(invalid="ignore", divide="ignore"):
        L = np.linalg.norm(P[..., 1, :] - P[..., 0, :], axis=-1)
        W = np.linalg.norm(P[..., 2, :] - P[..., 0, :], axis=-1)
        return L / W, P.mean(-2) / W[..., None]


def _solve_uv(uv, f, method, aspect_ratio, reference, try_shift: bool = True):
    """Solve one labelled corner set; for IPPE on a non-square face also the labelling one corner
    round (which pair of sides is long is data) — returns (solution, uv used, perm used)."""
    opts = {}
    if method == "ippe":
        opts["aspect_ratio"] = 1.0 if aspect_ratio is None else float(aspect_ratio)
        if reference is not None:
            opts["reference"] = reference
    sol = solve_rectangle(uv, f, method=method, **opts)
    perm = np.arange(4)
    if try_shift and method == "ippe" and not np.isclose(opts["aspect_ratio"], 1.0):
        alt = solve_rectangle(uv[_SHIFT_ONE], f, method=method, **opts)
        e0 = sol.extra["reprojection_px"][0] if bool(sol.success) else np.inf
        e1 = alt.extra["reprojection_px"][0] if bool(alt.success) else np.inf
        if e1 < e0:
            sol, uv, perm = alt, uv[_SHIFT_ONE], _SHIFT_ONE
    return sol, uv, perm


def _n_fold(method, aspect_ratio):
    return 2 if (method == "ippe" and aspect_ratio is not None and not np.isclose(aspect_ratio, 1.0)) else 4


def attitude_jacobian_pixels(corners_px, K, dist, rotation, method: str = "zhai", aspect_ratio=None,
                             step_px: float = 1e-3) -> np.ndarray:
    """``J_px (3, 8)`` rad/px: attitude per observed pixel coordinate (x1, y1, ..., x4, y4) of the
    corners ``(4, 2)`` in P1..P4 order (as the solve used them): solver Jacobian in (u, v) × diag(1, −1)
    × per-corner undistortion Jacobian (module docstring)."""
    c = as_array(corners_px, "corners_px", (4, 2))
    _, uv, f = pixels_to_ideal_uv(c, K, dist)
    opts = {"aspect_ratio": 1.0 if aspect_ratio is None else aspect_ratio} if method == "ippe" else {}
    J_uv = attitude_jacobian_corners(uv, f, rotation, method=method, step_px=step_px,
                                     n_fold=_n_fold(method, aspect_ratio), **opts)
    A = undistort_jacobian(c, K, dist, f)  # (4, 2, 2) d ideal / d observed
    flip = np.array([[1.0, 0.0], [0.0, -1.0]])
    B = np.zeros((8, 8))
    for i in range(4):
        B[2 * i:2 * i + 2, 2 * i:2 * i + 2] = flip @ A[i]
    return J_uv @ B


def attitude_jacobian_camera(corners_px, K, dist, rotation, method: str = "zhai", aspect_ratio=None,
                             which=None, rel_step: float = 1e-4) -> np.ndarray:
    """``J_θ (3, 18)``: attitude (rad) per camera parameter in OpenCV's std-dev order (fx, fy, cx,
    cy, k1, k2, p1, p2, k3, k4, k5, k6, s1..s4, tx, ty) by central differences through
    undistortion + ideal camera + solve; columns not in ``which`` (indices) or beyond the distortion
    vector's length are 0."""
    c = as_array(corners_px, "corners_px", (4, 2))
    Km = np.asarray(K, float)
    D = np.asarray(dist if dist is not None else [], float).ravel()
    v0 = model_parameter_vector(Km, D)
    n = 4 + D.size
    cols = range(n) if which is None else [i for i in which if i < n]
    J = np.zeros((3, 18))
    n_fold = _n_fold(method, aspect_ratio)
    for i in cols:
        h = rel_step * max(abs(v0[i]), 1.0) if i < 4 else rel_step
        out = []
        for s in (1.0, -1.0):
            v = v0.copy()
            v[i] += s * h
            Ki, Di = model_from_parameters(v, D.size, skew=Km[0, 1])
            _, uv, f = pixels_to_ideal_uv(c, Ki, Di)
            sol, _, _ = _solve_uv(uv, f, method, aspect_ratio, rotation, try_shift=False)
            if not bool(sol.success):
                return np.full((3, 18), np.nan)
            out.append(resolve_labelling(sol.rotation, rotation, n_fold))
        J[:, i] = (matrix_to_rotvec(out[0] @ rotation.T) - matrix_to_rotvec(out[1] @ rotation.T)) / (2 * h)
    return J


def face_attitude(corners_px, K, dist=None, *, method: str = "zhai", aspect_ratio: float | None = None,
                  ordered: bool = False, corner_cov_px=None, corner_sigma_px: float | None = None,
                  camera_std=None, camera_cov=None, reference=None, ambiguity_ratio: float = 2.0,
                  predict: bool = True) -> FaceAttitude:
    """Attitude of a rectangular face from its observed pixel corners through a real lens.

    corners_px : (4, 2) observed pixels (x right, y down), going round the face in any order, or
        P1..P4 with ``ordered=True``. K (3, 3), dist : the camera (OpenCV), dist None = no distortion.
    method : a rectangle solver name; aspect_ratio : L/W for "ippe" (default 1).
    corner_cov_px : (8, 8) covariance of ``corners_px`` (x1, y1, ..., as given) in px², or
        corner_sigma_px for i.i.d. noise; neither → ``sigma_deg`` NaN (``sigma_deg_per_px`` is
        always given). camera_cov : (p, p) covariance of (fx, fy, cx, cy, distortion...) (p = 4 +
        len(dist), a calibration's :func:`layoutkit.camera.calibration.intrinsics_covariance`) →
        its share of the covariance; or camera_std : (18,) standard deviations (OpenCV's order,
        NaN/0 = exact) taken as independent when no covariance is known.
    reference : (3, 3) a prior attitude for the labelling (and the IPPE branch when ambiguous).
    predict : False skips the covariance (NaN; for Monte-Carlo loops).

    Status: "ok"; "ambiguous" when IPPE's two branches fit within ``ambiguity_ratio`` of each
    other (both returned: ``alternative``); the solver's "degenerate" / "mirrored" otherwise.
    The message flags a face within :data:`FACE_ON_DEG` of face-on (σ not trustworthy there).
    """
    c_in = as_array(corners_px, "corners_px", (4, 2)).astype(float)
    Km = as_array(K, "camera_matrix", (3, 3)).astype(float)
    D = np.asarray(dist if dist is not None else [], float).ravel()
    if not np.all(np.isfinite(c_in)):
        return FaceAttitude(np.full((3, 3), np.nan), False, "no_corners", "corners are not finite", method,
                            ideal_camera(Km)[0])
    if ordered:
        c, perm_in = c_in, np.arange(4)
    else:
        c = order_pixel_corners(c_in, Km, D)
        perm_in = np.array([int(np.argmin(np.linalg.norm(c_in - ci, axis=1))) for ci in c])
    ideal, uv, f = pixels_to_ideal_uv(c, Km, D)
    ref = None if reference is None else as_array(reference, "reference", (3, 3))
    sol, uv, perm = _solve_uv(uv, f, method, aspect_ratio, ref)
    c, ideal, perm_in = c[perm], ideal[perm], perm_in[perm]
    if not bool(sol.success):
        return FaceAttitude(np.full((3, 3), np.nan), False, str(sol.status),
                            f"rectangle solve: {sol.status}", method, f, corners_px=c, corners_ideal_px=ideal,
                            corners_uv=uv)
    R = sol.rotation
    n_fold = _n_fold(method, aspect_ratio)
    if ref is not None:
        R = resolve_labelling(R, ref, n_fold)
    status, msg = "ok", "ok"
    alt, rep = None, (float("nan"), float("nan"))
    if method == "ippe":
        rep = tuple(float(v) for v in sol.extra["reprojection_px"])
        if np.all(np.isfinite(sol.alternative)):
            alt = sol.alternative
            if rep[1] <= ambiguity_ratio * max(rep[0], 1e-12):
                status = "ambiguous"
                msg = (f"IPPE's two poses fit within {ambiguity_ratio:g}x of each other "
                       f"({rep[0]:.3g} vs {rep[1]:.3g} px): the data cannot decide; both returned")
    aspect, pos = face_geometry(uv, f)
    tilt = float(np.degrees(face_tilt(R, uv, f)))
    if tilt < FACE_ON_DEG:
        msg = (msg if status != "ok" else "solved") + (f"; face within {FACE_ON_DEG:g} deg of face-on "
                                                       f"({tilt:.1f} deg): tilt sign nearly unobservable")
    if not predict:
        return FaceAttitude(R, True, status, msg, method, f, matrix_to_rotvec(R),
                            matrix_to_rotvec(PAPER_FROM_CV.T @ R), c, ideal, uv, float(aspect), pos, tilt,
                            alternative=alt, reprojection_px=rep)
    # predicted covariance (module docstring)
    J_px = attitude_jacobian_pixels(c, Km, D, R, method, aspect_ratio)
    per_px = float(np.degrees(np.sqrt(np.trace(J_px @ J_px.T))))
    C_cam = np.zeros((3, 3))
    if camera_cov is not None:
        Ct = np.asarray(camera_cov, float)
        p = Ct.shape[0]
        J_t = attitude_jacobian_camera(c, Km, D, R, method, aspect_ratio, range(p))[:, :p]
        C_cam = J_t @ Ct @ J_t.T
    elif camera_std is not None:
        sd = np.nan_to_num(np.asarray(camera_std, float).ravel(), nan=0.0)
        sd = np.concatenate([sd, np.zeros(18 - sd.size)])[:18]
        which = [i for i in range(18) if sd[i] > 0]
        if which:
            J_t = attitude_jacobian_camera(c, Km, D, R, method, aspect_ratio, which)
            C_cam = (J_t * sd ** 2) @ J_t.T
    if corner_cov_px is not None:
        S_in = as_array(corner_cov_px, "corner_cov_px", (8, 8))
        idx = np.array([[2 * p, 2 * p + 1] for p in perm_in]).ravel()
        S = S_in[np.ix_(idx, idx)]
        C = J_px @ S @ J_px.T + C_cam
    elif corner_sigma_px is not None:
        C = float(corner_sigma_px) ** 2 * (J_px @ J_px.T) + C_cam
    else:
        C = np.full((3, 3), np.nan)
    sigma = float(np.degrees(np.sqrt(np.trace(C)))) if np.all(np.isfinite(C)) else float("nan")
    return FaceAttitude(R, True, status, msg, method, f, matrix_to_rotvec(R), matrix_to_rotvec(PAPER_FROM_CV.T @ R),
                        c, ideal, uv, float(aspect), pos, tilt, C, sigma, per_px,
                        float(np.degrees(np.sqrt(np.trace(C_cam)))), alt, rep)
