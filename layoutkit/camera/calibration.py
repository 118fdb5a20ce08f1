"""Camera calibration from photos of a planar pattern (OpenCV's detector and ``calibrateCamera``).

:func:`find_pattern` locates a pattern in one grey image:

- ``chessboard``: ``cv2.findChessboardCorners`` (adaptive threshold + normalised image) then
  ``cv2.cornerSubPix`` (window ``subpix_window`` px half-size, 30 iterations / 1e-3 px, as OpenCV's
  calibration sample); object points are the inner corners ``(col, row) × square`` on ``z = 0``
  (m), in OpenCV's corner order;
- ``charuco``: ``cv2.aruco.CharucoDetector`` (contrib-free in OpenCV ≥ 4.7); ``inner = W x H``
  inner chessboard corners means a board of ``(W + 1) x (H + 1)`` squares; markers of
  ``marker`` m from ``dictionary`` (``cv2.aruco`` name, default ``DICT_5X5_100``). A partial
  view counts from ``min_charuco_corners`` corners on.

:func:`calibrate_camera` runs ``cv2.calibrateCameraExtended`` on every view where the pattern was
found (distortion model from :data:`DISTORTION_MODELS`), then reports per view the RMS
reprojection error (px, ``sqrt(mean |x - x̂|²)``, OpenCV's ``perViewErrors``) and the residual
vectors; a view is an **outlier** when its RMS exceeds both ``1.5 ×`` the median and the median
``+ 3 × 1.4826 × MAD`` (a robust 3-sigma rule). ``drop_outliers`` calibrates once more without
them. Standard deviations of the parameters come from OpenCV (``stdDeviationsIntrinsics``).

Status: "ok"; "high_residual" when the overall RMS exceeds ``max_rms_px`` (the model or the
corners are off: the result is returned but must not be trusted); "too_few_views" (fewer than
3 usable views, nothing calibrated; ``success`` False).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["PATTERNS", "DISTORTION_MODELS", "PatternView", "CalibrationResult", "find_pattern",
           "calibrate_camera", "pattern_object_points", "parse_inner", "outlier_views", "charuco_board",
           "board_rectangle", "BOARD_FROM_FACE", "grid_corner_sigma", "intrinsics_covariance"]

#: Pattern kinds :func:`find_pattern` knows.
PATTERNS = ("chessboard", "charuco")


#: Distortion model name → (``cv2`` flag names for ``calibrateCamera``, number of coefficients):
#: "standard" (k1 k2 p1 p2 k3), "rational" (+ k4 k5 k6), "thin-prism" (+ s1..s4; k4..k6 kept 0),
#: "rational-thin-prism" (all twelve).
DISTORTION_MODELS = {
    "standard": ((), 5),
    "rational": (("CALIB_RATIONAL_MODEL",), 8),
    "thin-prism": (("CALIB_THIN_PRISM_MODEL",), 12),
    "rational-thin-prism": (("CALIB_RATIONAL_MODEL", "CALIB_THIN_PRISM_MODEL"), 12),
}


def parse_inner(text) -> tuple[int, int]:
    """``"9x6"`` → (9, 6) inner corners (columns, rows); ValueError naming the flag value."""
    try:
        w, h = (int(v) for v in str(text).lower().replace("×", "x").split("x"))
    except ValueError:
        raise ValueError(f"inner: expected WxH inner corners such as 9x6, got {text!r}") from None
    if w < 2 or h < 2:
        raise ValueError(f"inner: expected at least 2x2 inner corners, got {text!r}")
    return w, h


def pattern_object_points(inner, square_m: float) -> np.ndarray:
    """Inner-corner coordinates ``(W*H, 3)`` m of a chessboard, OpenCV's order (row-major, z = 0)."""
    w, h = inner
    obj = np.zeros((w * h, 3))
    obj[:, :2] = np.mgrid[0:w, 0:h].T.reshape(-1, 2) * float(square_m)
    return obj


@dataclass(frozen=True)
class PatternView:
    """A pattern found (or not) in one image: ``image_points (n, 2)`` px, ``object_points (n, 3)``
    m (board frame), ``ids (n,)`` corner indices (chessboard: 0..W*H-1), ``found``, ``name``,
    ``image_size (w, h)``, ``message``."""

    name: str
    found: bool
    image_size: tuple
    image_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    object_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    message: str = ""


def _gray(image):
    import cv2

    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2GRAY)
    return np.ascontiguousarray(img.astype(np.uint8))


def find_pattern(image, pattern: str = "chessboard", inner=(9, 6), square_m: float = 0.025, *, name: str = "",
                 subpix_window: int = 11, marker_m: float | None = None, dictionary: str = "DICT_5X5_100",
                 min_charuco_corners: int = 8) -> PatternView:
    """Detect ``pattern`` in ``image`` (grey or BGR uint8); see module docstring."""
    import cv2

    g = _gray(image)
    size = (g.shape[1], g.shape[0])
    w, h = inner
    if pattern == "chessboard":
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        ok, corners = cv2.findChessboardCorners(g, (w, h), flags=flags)
        if not ok:
            return PatternView(name, False, size, message=f"no {w}x{h} chessboard found")
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
        corners = cv2.cornerSubPix(g, corners, (subpix_window, subpix_window), (-1, -1), crit)
        return PatternView(name, True, size, corners.reshape(-1, 2).astype(float), pattern_object_points(inner, square_m),
                           np.arange(w * h), "ok")
    if pattern == "charuco":
        if marker_m is None:
            raise ValueError("marker size: required for a ChArUco board (--marker-mm)")
        board = charuco_board(inner, square_m, marker_m, dictionary)
        det = cv2.aruco.CharucoDetector(board)
        cc, cid, _, _ = det.detectBoard(g)
        n = 0 if cid is None else len(cid)
        if n < min_charuco_corners:
            return PatternView(name, False, size, message=f"{n} ChArUco corners found (< {min_charuco_corners})")
        ids = cid.ravel().astype(int)
        obj = np.asarray(board.getChessboardCorners(), float)[ids]
        return PatternView(name, True, size, cc.reshape(-1, 2).astype(float), obj, ids, f"{n} ChArUco corners")
    raise ValueError(f"pattern: expected one of {', '.join(PATTERNS)}, got {pattern!r}")


def charuco_board(inner, square_m: float, marker_m: float, dictionary: str = "DICT_5X5_100"):
    """The ``cv2.aruco.CharucoBoard`` of ``(W + 1) x (H + 1)`` squares for ``inner = (W, H)``."""
    import cv2

    if not hasattr(cv2, "aruco") or not hasattr(cv2.aruco, "CharucoDetector"):
        raise ValueError("ChArUco: this OpenCV has no cv2.aruco.CharucoDetector (needs OpenCV >= 4.7)")
    if not hasattr(cv2.aruco, dictionary):
        raise ValueError(f"dictionary: unknown ArUco dictionary {dictionary!r} (e.g. DICT_5X5_100, DICT_6X6_250)")
    if not 0 < marker_m < square_m:
        raise ValueError(f"marker size: expected 0 < marker < square ({square_m * 1e3:g} mm), got {marker_m * 1e3:g} mm")
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    return cv2.aruco.CharucoBoard((inner[0] + 1, inner[1] + 1), float(square_m), float(marker_m), d)


def outlier_views(rms_px) -> np.ndarray:
    """Bool ``(n,)``: views whose RMS exceeds 1.5 × median and median + 3 × 1.4826 × MAD."""
    r = np.asarray(rms_px, float)
    med = float(np.median(r))
    mad = float(np.median(np.abs(r - med)))
    return (r > 1.5 * med) & (r > med + 3.0 * 1.4826 * mad)


@dataclass(frozen=True)
class CalibrationResult:
    """Result of :func:`calibrate_camera`.

    camera_matrix (3, 3), distortion (n,), std_dev (18,) (OpenCV's order), rms_px (overall),
    image_size (w, h); per view (in ``names`` order, only views used): rms_px_per_view, residuals
    (list of (n_i, 2) px, observed − projected), image_points (list of (n_i, 2)), rvecs, tvecs
    (board → OpenCV camera); covariance (p, p) of (fx, fy, cx, cy, distortion...) from
    :func:`intrinsics_covariance` (its square-root diagonal equals ``std_dev``: tested); outliers (names); not_found (names, with the reason in ``view_messages``);
    dropped (names left out by ``drop_outliers``); first_pass (the calibration before dropping, or None).
    """

    success: bool
    status: str
    message: str
    camera_matrix: np.ndarray | None = None
    distortion: np.ndarray | None = None
    std_dev: np.ndarray | None = None
    rms_px: float = float("nan")
    image_size: tuple | None = None
    names: tuple = ()
    rms_px_per_view: np.ndarray = field(default_factory=lambda: np.zeros(0))
    residuals: tuple = ()
    image_points: tuple = ()
    rvecs: np.ndarray | None = None
    tvecs: np.ndarray | None = None
    covariance: np.ndarray | None = None
    outliers: tuple = ()
    not_found: tuple = ()
    dropped: tuple = ()
    view_messages: dict = field(default_factory=dict)
    model: str = "standard"
    first_pass: "CalibrationResult | None" = None

    def summary(self) -> dict:
        """JSON-able summary (no residual arrays)."""
        from ..io.camera import STD_DEV_NAMES

        sd = {} if self.std_dev is None else {n: float(v) for n, v in zip(STD_DEV_NAMES, self.std_dev)
                                              if np.isfinite(v) and v > 0}
        out = {"success": self.success, "status": self.status, "message": self.message, "model": self.model,
               "rms_px": self.rms_px, "image_size": self.image_size,
               "camera_matrix": self.camera_matrix, "distortion": self.distortion, "std_dev": sd,
               "views": [{"image": n, "rms_px": float(r), "points": int(len(p)), "outlier": n in self.outliers}
                         for n, r, p in zip(self.names, self.rms_px_per_view, self.image_points)],
               "outliers": list(self.outliers), "not_found": {n: self.view_messages.get(n, "") for n in self.not_found},
               "dropped": list(self.dropped)}
        if self.first_pass is not None:
            out["before_dropping"] = {"rms_px": self.first_pass.rms_px, "camera_matrix": self.first_pass.camera_matrix,
                                      "distortion": self.first_pass.distortion}
        return out


def calibrate_camera(views, model: str = "standard", *, drop_outliers: bool = False, max_rms_px: float = 1.0,
                     flags: int = 0) -> CalibrationResult:
    """Intrinsics + distortion from :class:`PatternView` s (module docstring).

    views : PatternView list (not-found views are reported, not used). model : a
    :data:`DISTORTION_MODELS` name. flags : extra ``cv2.CALIB_*`` flags.
    """
    import cv2

    if model not in DISTORTION_MODELS:
        raise ValueError(f"model: expected one of {', '.join(DISTORTION_MODELS)}, got {model!r}")
    views = list(views)
    used = [v for v in views if v.found]
    not_found = tuple(v.name for v in views if not v.found)
    msgs = {v.name: v.message for v in views if not v.found}
    sizes = {tuple(v.image_size) for v in views}
    if len(sizes) > 1:
        first = views[0]
        other = next(v for v in views if tuple(v.image_size) != tuple(first.image_size))
        raise ValueError(f"{other.name}: image size {other.image_size[0]}x{other.image_size[1]} differs from "
                         f"{first.name} ({first.image_size[0]}x{first.image_size[1]}): one camera, one size")
    if len(used) < 3:
        return CalibrationResult(False, "too_few_views",
                                 f"the pattern was found in {len(used)} of {len(views)} images; at least 3 are needed",
                                 not_found=not_found, view_messages=msgs, model=model,
                                 image_size=next(iter(sizes)) if sizes else None)
    size = tuple(used[0].image_size)
    obj = [v.object_points.astype(np.float32) for v in used]
    img = [v.image_points.astype(np.float32).reshape(-1, 1, 2) for v in used]
    names_fl, n_dist = DISTORTION_MODELS[model]
    fl = int(flags)
    for nm in names_fl:
        fl |= int(getattr(cv2, nm))
    rms, K, D, rv, tv, sd_int, _, _ = cv2.calibrateCameraExtended(obj, img, size, None, None, flags=fl)
    D = np.asarray(D, float).ravel()[:n_dist]
    residuals, rms_v = [], []
    for v, r, t in zip(used, rv, tv):
        proj = cv2.projectPoints(v.object_points, r, t, K, D)[0].reshape(-1, 2)
        e = v.image_points - proj
        residuals.append(e)
        rms_v.append(float(np.sqrt(np.mean(np.sum(e ** 2, 1)))))
    rms_v = np.array(rms_v)
    out_mask = outlier_views(rms_v)
    names = tuple(v.name for v in used)
    outliers = tuple(n for n, o in zip(names, out_mask) if o)
    sd = np.asarray(sd_int, float).ravel()
    cov = intrinsics_covariance(used, K, D, rv, tv)
    status = "ok" if rms <= max_rms_px else "high_residual"
    msg = (f"RMS {rms:.3f} px over {len(used)} views" + (f"; outlier views: {', '.join(outliers)}" if outliers else "")
           + (f"; pattern not found in {', '.join(not_found)}" if not_found else "")
           + ("" if status == "ok" else f"; RMS above {max_rms_px:g} px: do not trust this calibration"))
    res = CalibrationResult(True, status, msg, np.asarray(K, float), D, sd, float(rms), size, names, rms_v,
                            tuple(residuals), tuple(v.image_points for v in used), np.asarray(rv, float).reshape(-1, 3),
                            np.asarray(tv, float).reshape(-1, 3), cov, outliers, not_found, (), msgs, model)
    if drop_outliers and outliers:
        keep = [v for v in views if v.name not in outliers]
        second = calibrate_camera(keep, model, drop_outliers=False, max_rms_px=max_rms_px, flags=flags)
        if second.success:
            from dataclasses import replace

            return replace(second, dropped=outliers, first_pass=res,
                           message=second.message + f"; dropped outlier views {', '.join(outliers)} "
                                                    f"(RMS with them {rms:.3f} px)")
    return res


def intrinsics_covariance(views, camera_matrix, distortion, rvecs, tvecs) -> np.ndarray:
    """Covariance ``(p, p)`` of (fx, fy, cx, cy, distortion...) after ``cv2.calibrateCamera``.

    Gauss-Newton at the solution: per view the Jacobian of ``cv2.projectPoints`` (intrinsic columns
    ``J_i``, pose columns ``J_e``), the poses eliminated by their Schur complement,
    ``A = Σ_v J_iᵀ J_i - J_iᵀ J_e (J_eᵀ J_e)⁻¹ J_eᵀ J_i``, and ``C = s² A⁻¹`` with ``s²`` the residual
    sum of squares over ``2N - p - 6 n_views`` — OpenCV's own computation, which returns only the
    diagonal (``stdDeviationsIntrinsics``); the off-diagonal terms matter: k1, k2, k3 correlate to
    |ρ| ≈ 0.97 on the 13 OpenCV sample photos, so independent std devs would overstate the
    attitude error the calibration causes.
    """
    import cv2

    K = np.asarray(camera_matrix, float)
    D = np.asarray(distortion, float).ravel()
    p = 4 + D.size
    A = np.zeros((p, p))
    ssr, n = 0.0, 0
    for v, r, t in zip(views, rvecs, tvecs):
        proj, J = cv2.projectPoints(v.object_points, np.asarray(r, float), np.asarray(t, float), K, D)
        e = (v.image_points - proj.reshape(-1, 2)).ravel()
        ssr += float(e @ e)
        n += e.size
        Je, Ji = J[:, :6], J[:, 6:6 + p]
        A += Ji.T @ Ji - Ji.T @ Je @ np.linalg.solve(Je.T @ Je, Je.T @ Ji)
    dof = max(n - p - 6 * len(views), 1)
    return ssr / dof * np.linalg.pinv(A)


def board_rectangle(view: PatternView, inner) -> tuple[np.ndarray, float]:
    """The four extreme inner corners of a full chessboard view as a rectangle, labelled P1..P4.

    Returns ``(corners_px (4, 2), aspect_ratio)``: with the board frame (x along the W corners, y
    along the H corners, z into the board, away from the camera) the face frame of
    :mod:`layoutkit.camera.rectangle` is ``x_t = -z_b, y_t = x_b, z_t = -y_b``, so P1 is corner
    ``(0, H-1)``, P2 ``(W-1, H-1)``, P3 ``(0, 0)``, P4 ``(W-1, 0)`` (col, row); ``L / W = (W-1)/(H-1)``
    in squares. ``R_ct = PAPER_FROM_CV R_board B`` with ``B`` = :data:`BOARD_FROM_FACE`.
    """
    w, h = inner
    if not view.found or len(view.image_points) != w * h:
        raise ValueError(f"{view.name}: needs a full {w}x{h} chessboard view")
    idx = [(h - 1) * w, h * w - 1, 0, w - 1]
    return view.image_points[idx].copy(), (w - 1) / (h - 1)


#: Face frame in the board frame (columns: x_t, y_t, z_t) for :func:`board_rectangle`'s labelling.
BOARD_FROM_FACE = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])


def grid_corner_sigma(view: PatternView, camera_matrix, distortion) -> float:
    """Per-coordinate noise (ideal px) of a view's corners: RMS of the residuals of a homography
    (board plane → undistorted image, ``cv2.findHomography`` least squares) with ``2n - 8`` degrees
    of freedom. It holds the detector's noise and what the lens model leaves."""
    import cv2

    from .lens import undistort_pixels

    ideal = undistort_pixels(view.image_points, camera_matrix, distortion)
    Hm, _ = cv2.findHomography(view.object_points[:, :2], ideal, 0)
    if Hm is None:
        return float("nan")
    proj = cv2.perspectiveTransform(view.object_points[:, None, :2].astype(float), Hm).reshape(-1, 2)
    n = len(ideal)
    return float(np.sqrt(np.sum((ideal - proj) ** 2) / max(2 * n - 8, 1)))
