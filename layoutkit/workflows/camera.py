"""What ``layoutkit camera calibrate`` and ``layoutkit camera attitude`` do with files.

- :func:`calibrate_images`: pattern photos → :class:`layoutkit.camera.calibration.CalibrationResult`,
  the camera model file (:func:`layoutkit.io.camera.write_camera_model`) and a residual figure;
- :func:`image_attitude`: one photo + a camera model file → the face attitude
  (:func:`layoutkit.camera.face.face_attitude`) from given corners, the face detector
  (:func:`layoutkit.camera.face_detect.detect_face`) or a chessboard's extreme corners, and a
  picture with the corners drawn.

Both return JSON-able dicts (angles in degrees where the key says ``_deg``, rotation vectors in rad).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["calibrate_images", "write_calibration_figure", "image_attitude", "parse_corners", "read_image",
           "DETECTORS"]

#: How ``camera attitude`` finds the four corners (besides ``--corners``).
DETECTORS = ("face", "chessboard")


def read_image(path) -> np.ndarray:
    """Grey uint8 image of ``path``; ValueError naming the file when it is not a readable image or
    a JPEG / PNG cut short (OpenCV decodes those partially, with the rest grey, and says nothing)."""
    import cv2

    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{p}: no such image file")
    data = p.read_bytes()
    if data[:3] == b"\xff\xd8\xff" and not data.rstrip(b"\x00").endswith(b"\xff\xd9"):
        raise ValueError(f"{p}: truncated JPEG (no end-of-image marker)")
    if data[:8] == b"\x89PNG\r\n\x1a\n" and b"IEND" not in data[-16:]:
        raise ValueError(f"{p}: truncated PNG (no IEND chunk)")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE) if data else None
    if img is None:
        raise ValueError(f"{p}: not a readable image")
    return img


def parse_corners(text) -> np.ndarray:
    """``"x,y;x,y;x,y;x,y"`` (pixels) → ``(4, 2)``; ValueError naming the flag."""
    try:
        pts = [[float(v) for v in p.split(",")] for p in str(text).strip().strip(";").split(";")]
        arr = np.array(pts, float)
    except ValueError:
        raise ValueError(f"--corners: expected four x,y pixel pairs separated by ';', got {text!r}") from None
    if arr.shape != (4, 2) or not np.all(np.isfinite(arr)):
        raise ValueError(f"--corners: expected four x,y pixel pairs separated by ';', got {text!r}")
    return arr


# ----------------------------------------------------------------------------- calibrate
def calibrate_images(images, out, *, pattern: str = "chessboard", inner=(9, 6), square_mm: float = 25.0,
                     model: str = "standard", drop_outliers: bool = False, figure=None,
                     marker_mm: float | None = None, dictionary: str = "DICT_5X5_100", max_rms_px: float = 1.0) -> dict:
    """Calibrate from pattern photos; write ``out`` (camera model) and ``figure`` (PNG; default
    ``<out stem>_residuals.png`` beside ``out``) unless the calibration failed. Returns the summary."""
    from ..camera.calibration import calibrate_camera, find_pattern
    from ..io.camera import CameraModel, write_camera_model

    files = []
    for p in images:
        p = Path(p)
        if p.is_dir():
            from ..camera.stream import IMAGE_SUFFIXES

            files += sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
        else:
            files.append(p)
    if not files:
        raise ValueError("IMAGES: no image files given")
    names = [f.name for f in files]
    if len(set(names)) != len(names):
        names = [str(f) for f in files]
    views = []
    for f, name in zip(files, names):
        views.append(find_pattern(read_image(f), pattern, inner, square_mm * 1e-3, name=name,
                                  marker_m=None if marker_mm is None else marker_mm * 1e-3, dictionary=dictionary))
    res = calibrate_camera(views, model, drop_outliers=drop_outliers, max_rms_px=max_rms_px)
    summary = res.summary()
    summary.update(pattern=pattern, inner=list(inner), square_mm=square_mm, images=len(files))
    if not res.success:
        summary.update(out=None, figure=None)
        return summary
    cam = CameraModel(res.camera_matrix, res.distortion, res.image_size, res.std_dev, res.rms_px,
                      source=f"layoutkit camera calibrate ({len(res.names)} views)", covariance=res.covariance)
    out = Path(out)
    write_camera_model(out, cam, per_view_rms_px=res.rms_px_per_view)
    fig_path = Path(figure) if figure else out.with_name(out.stem + "_residuals.png")
    write_calibration_figure(res, fig_path)
    summary.update(out=str(out), figure=str(fig_path))
    return summary


def write_calibration_figure(res, path) -> Path:
    """Per-view RMS (outliers red), every residual vector (px), residual size vs distance from the
    principal point (what an unmodelled lens term would show)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io.figures import save_figure

    fig, ax = plt.subplots(1, 3, figsize=(13, 4.2))
    names = list(res.names)
    col = ["tab:red" if n in res.outliers else "tab:blue" for n in names]
    ax[0].bar(range(len(names)), res.rms_px_per_view, color=col)
    ax[0].set_xticks(range(len(names)))
    ax[0].set_xticklabels([Path(n).stem for n in names], rotation=70, fontsize=7)
    ax[0].axhline(res.rms_px, color="k", lw=0.8, ls="--", label=f"overall {res.rms_px:.3f} px")
    ax[0].set_xlabel("image")
    ax[0].set_ylabel("RMS reprojection error (px)")
    ax[0].set_title("Per image (red: outlier)")
    ax[0].legend(fontsize=8)
    cx, cy = res.camera_matrix[0, 2], res.camera_matrix[1, 2]
    for n, e, p in zip(names, res.residuals, res.image_points):
        mk = "x" if n in res.outliers else "."
        ax[1].plot(e[:, 0], e[:, 1], mk, ms=3, alpha=0.7)
        ax[2].plot(np.hypot(p[:, 0] - cx, p[:, 1] - cy), np.hypot(e[:, 0], e[:, 1]), mk, ms=3, alpha=0.7)
    lim = max(1e-3, float(np.max(np.abs(np.concatenate(res.residuals))))) * 1.05
    ax[1].set_xlim(-lim, lim)
    ax[1].set_ylim(-lim, lim)
    ax[1].set_aspect("equal")
    ax[1].set_xlabel("residual x (px)")
    ax[1].set_ylabel("residual y (px)")
    ax[1].set_title("Residuals (observed - projected)")
    ax[2].set_xlabel("distance from the principal point (px)")
    ax[2].set_ylabel("|residual| (px)")
    ax[2].set_title("Residual vs image radius")
    fig.suptitle(f"Camera calibration ({res.model} model): RMS {res.rms_px:.3f} px over {len(names)} views")
    fig.tight_layout(rect=(0, 0.05, 1, 0.95))
    cap = (f"fx {res.camera_matrix[0, 0]:.2f} px, fy {res.camera_matrix[1, 1]:.2f} px, "
           f"cx {cx:.2f} px, cy {cy:.2f} px; distortion {np.array2string(res.distortion, precision=4)}"
           + (f"; outliers: {', '.join(res.outliers)}" if res.outliers else ""))
    return save_figure(fig, path, caption=cap)


# ----------------------------------------------------------------------------- attitude
def image_attitude(image, camera_file, *, corners=None, detect: str = "face", inner=(9, 6),
                   method: str = "zhai", aspect_ratio: float | None = None, corner_sigma_px: float | None = None,
                   polarity: str = "auto", picture=None) -> dict:
    """Face attitude in one photo (module docstring). ``corners``: (4, 2) observed pixels, any
    order round the face (then ``detect`` is ignored). ``picture``: PNG path or None.

    The predicted σ uses, in this order: ``corner_sigma_px`` (i.i.d., observed px) if given; the
    face detector's own corner covariance; for a chessboard, the grid's homography residual RMS.
    With ``--corners`` and no ``corner_sigma_px`` only ``sigma_deg_per_px`` is known.
    """
    from ..camera.face import face_attitude
    from ..io.camera import read_camera_model

    cam = read_camera_model(camera_file)
    img = read_image(image)
    if cam.image_size is not None and tuple(cam.image_size) != (img.shape[1], img.shape[0]):
        raise ValueError(f"{image}: image is {img.shape[1]}x{img.shape[0]} px but {camera_file} was calibrated for "
                         f"{cam.image_size[0]}x{cam.image_size[1]} px")
    K, D = cam.matrix, cam.distortion
    det_info: dict = {}
    cov = None
    ordered = False
    if corners is not None:
        c = np.asarray(corners, float)
        det_info = {"detector": "given"}
    elif detect == "face":
        from ..camera.face_detect import detect_face

        d = detect_face(img, K, D, polarity=polarity)
        det_info = {"detector": "face", "detector_status": d.status, "detector_message": d.message,
                    "edge_rms_px": d.rms_px, "edge_contrast": d.contrast, "outline_support": d.support}
        if not d.success:
            out = {"success": False, "status": d.status, "message": d.message, "rotvec": None, "sigma_deg": None,
                   "corners_px": None, "image": str(image), "camera": str(camera_file), **det_info}
            if picture:
                out["picture"] = str(_write_picture(img, None, None, picture, d.message, K, D))
            return out
        c, cov = d.corners_px, d.corner_cov_px
    elif detect == "chessboard":
        from ..camera.calibration import board_rectangle, find_pattern, grid_corner_sigma
        from ..camera.lens import distort_jacobian, ideal_camera, undistort_pixels

        v = find_pattern(img, "chessboard", inner, 1.0, name=str(image))
        if not v.found:
            msg = f"{image}: {v.message}"
            out = {"success": False, "status": "not_found", "message": msg, "rotvec": None, "sigma_deg": None,
                   "corners_px": None, "image": str(image), "camera": str(camera_file), "detector": "chessboard"}
            if picture:
                out["picture"] = str(_write_picture(img, None, None, picture, msg, K, D))
            return out
        c, ar = board_rectangle(v, inner)
        ordered = True
        if aspect_ratio is None and method == "ippe":
            aspect_ratio = ar
        s = grid_corner_sigma(v, K, D)
        F = distort_jacobian(undistort_pixels(c, K, D), K, D, ideal_camera(K)[0])
        cov = np.zeros((8, 8))
        for i in range(4):
            cov[2 * i:2 * i + 2, 2 * i:2 * i + 2] = s ** 2 * F[i] @ F[i].T
        det_info = {"detector": "chessboard", "grid_sigma_px": s, "board_aspect_ratio": ar}
    else:
        raise ValueError(f"--detect: expected one of {', '.join(DETECTORS)}, got {detect!r}")
    fa = face_attitude(c, K, D, method=method, aspect_ratio=aspect_ratio, ordered=ordered,
                       corner_cov_px=None if corner_sigma_px is not None else cov, corner_sigma_px=corner_sigma_px,
                       camera_cov=cam.covariance, camera_std=None if cam.covariance is not None else cam.std_dev)
    out = fa.to_dict()
    out.update(image=str(image), camera=str(camera_file), **det_info)
    out["camera_uncertainty"] = ("covariance" if cam.covariance is not None else
                                 "std devs only (correlations unknown: treated as independent)"
                                 if cam.std_dev is not None else "none (the camera model is taken as exact)")
    out["sigma_source"] = ("--corner-sigma-px" if corner_sigma_px is not None else
                           {"face": "detector line fits", "chessboard": "grid homography residuals"}.get(
                               det_info.get("detector"), None))
    if not np.isfinite(fa.sigma_deg):
        out["sigma_deg"] = None
    if picture:
        out["picture"] = str(_write_picture(img, fa, c, picture, fa.message, K, D))
    return out


def _write_picture(img, fa, corners, path, message, K, D) -> Path:
    """The photo with the face outline (straight in the ideal image, so curved here), P1..P4 and
    the result written on it; PNG, atomically."""
    import cv2

    from ..camera.lens import distort_pixels, ideal_camera, undistort_pixels
    from ..io.atomic import atomic_write_bytes

    vis = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    ok = fa is not None and fa.success
    if corners is not None:
        q = fa.corners_px if fa is not None else np.asarray(corners, float)
        ideal = undistort_pixels(q, K, D)
        ring = ideal[[0, 1, 3, 2]] if fa is not None else ideal
        s = np.linspace(0.0, 1.0, 40, endpoint=False)
        poly = np.concatenate([ring[i] + (ring[(i + 1) % 4] - ring[i]) * s[:, None] for i in range(4)])
        curve = distort_pixels(poly, K, D, ideal_camera(K)[0])
        cv2.polylines(vis, [np.round(curve * 8).astype(np.int32)], True, (0, 200, 0) if ok else (0, 0, 255), 1,
                      cv2.LINE_AA, shift=3)
        for i, p in enumerate(q):
            cv2.drawMarker(vis, (int(round(p[0])), int(round(p[1]))), (0, 0, 255), cv2.MARKER_CROSS, 12, 1)
            if fa is not None:
                cv2.putText(vis, f"P{i + 1}", (int(p[0]) + 5, int(p[1]) - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                            (0, 0, 255), 1, cv2.LINE_AA)
    lines = [message[:90]]
    if ok:
        rv = np.degrees(fa.rotvec)
        lines = [f"{fa.method}: rotvec [{rv[0]:.2f}, {rv[1]:.2f}, {rv[2]:.2f}] deg  status {fa.status}",
                 (f"sigma {fa.sigma_deg:.3f} deg" if np.isfinite(fa.sigma_deg) else "sigma unknown (no corner noise)")
                 + f"  tilt {fa.tilt_deg:.1f} deg  aspect {fa.aspect_ratio:.3f}"]
    for k, ln in enumerate(lines):
        (w, h), base = cv2.getTextSize(ln, cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)
        y = 18 + 18 * k
        cv2.rectangle(vis, (4, y - h - 4), (12 + w, y + base), (0, 0, 0), -1)
        cv2.putText(vis, ln, (8, y), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 255, 255), 1, cv2.LINE_AA)
    okenc, buf = cv2.imencode(".png", vis)
    if not okenc:
        raise ValueError(f"{path}: could not encode the picture")
    atomic_write_bytes(path, buf.tobytes())
    return Path(path)
