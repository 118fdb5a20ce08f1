"""Sub-pixel quadrilateral corners from an image (a bright face on a darker background or vice versa).

Pipeline of :func:`detect_quadrilateral`:

1. segment (Otsu threshold, a given threshold, or a given mask) and take the largest external
   contour (OpenCV);
2. initial quadrilateral: Douglas–Peucker on the contour's convex hull, tolerance raised until
   four vertices remain;
3. per side, intensity profiles along the side normal (bilinear samples every 0.25 px over
   ±``profile_half_px``, the 15 % nearest each corner left out); the edge position on each profile
   is the **integral of the normalised step** (Σ (I - I_out)/(I_in - I_out) · Δs), which is exact
   for pixel-coverage (area-sampled) edges and unaffected by a symmetric blur; a second pass reads
   the outside level just beyond the edge and cuts the integral there (``outer_px``);
4. a robust (Huber) line fit per side (``cv2.fitLine``) and the four corners as intersections of
   adjacent lines; steps 3–4 are repeated once with the refined quadrilateral.

Quality: the RMS perpendicular distance (px) of the edge points to their fitted lines, and the
number of edge points per side. Corners are returned in image order (counter-clockwise on screen
i.e. clockwise in pixel coordinates with y down); :func:`corners_to_paper` labels them P1..P4 in
Zhai's (u, v).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._validate import as_array
from .conventions import pixels_to_paper_uv
from .rectangle import order_corners

__all__ = ["QuadDetection", "detect_quadrilateral", "corners_to_paper", "line_corner_covariance"]


@dataclass(frozen=True)
class QuadDetection:
    """Result of :func:`detect_quadrilateral`.

    corners_px : (4, 2) pixel coordinates (x right, y down, pixel centres at integers), going
        round the quadrilateral; NaN when not found.
    success, status ("ok", "no_contour", "not_quadrilateral", "touches_border", "refine_failed"),
    message; rms_px : RMS edge-point distance to the fitted side lines (px);
    n_points : (4,) edge points used per side; initial_px : (4, 2) contour-based corners.
    corner_cov_px : (8, 8) predicted covariance (px²) of ``corners_px`` flattened (x1, y1, ..., y4):
        each side's line fit has offset variance ``s²/n_eff`` and angle variance
        ``s²/sum((t - t̄)²)`` (s the side's residual RMS, one independent edge sample per pixel
        of side length: the 0.5 px profiles share pixels), propagated through the corner
        intersections (:func:`line_corner_covariance`).
    corners_ideal_px, corner_cov_ideal_px : with a lens (``camera_matrix`` + ``distortion``) the
        corners and their covariance in the undistorted image (the line fits run there, the
        sides being straight only there); ``corners_px`` / ``corner_cov_px`` are then the same
        carried back into the observed image. None without a lens.
    """

    corners_px: np.ndarray
    success: bool
    status: str
    message: str
    rms_px: float = float("nan")
    n_points: tuple = (0, 0, 0, 0)
    initial_px: np.ndarray | None = None
    corner_cov_px: np.ndarray | None = None
    corners_ideal_px: np.ndarray | None = None
    corner_cov_ideal_px: np.ndarray | None = None


def _fail(status, message, initial=None):
    return QuadDetection(np.full((4, 2), np.nan), False, status, message, initial_px=initial)


def _initial_quad(contour):
    import cv2

    hull = cv2.convexHull(contour)
    peri = cv2.arcLength(hull, True)
    for eps in np.geomspace(0.005, 0.2, 40):
        approx = cv2.approxPolyDP(hull, eps * peri, True)
        if len(approx) <= 4:
            break
    if len(approx) != 4:
        return None
    return approx[:, 0, :].astype(float)


def _line_intersections(points, dirs):
    """Corner i+1 = intersection of line i (side i → i+1) and line i+1 (cyclic): ``(4, 2)``."""
    out = np.empty((4, 2))
    for i in range(4):
        j = (i + 1) % 4
        A = np.array([dirs[i], -dirs[j]]).T
        s = np.linalg.solve(A, points[j] - points[i])
        out[j] = points[i] + s[0] * dirs[i]
    return out


def line_corner_covariance(points, dirs, var_offset, var_angle, h: float = 1e-4) -> np.ndarray:
    """Covariance ``(8, 8)`` of the corners of four lines with independent offset / angle errors.

    points, dirs : (4, 2) a point (the fit's centroid) and unit direction per side; var_offset,
    var_angle : (4,) px² and rad². Corners as :func:`_line_intersections`; Jacobian by central
    differences in (offset along the normal, rotation about the point) of each line.
    """
    P = np.asarray(points, float)
    D = np.asarray(dirs, float)
    J = np.zeros((8, 8))
    for i in range(4):
        n = np.array([D[i, 1], -D[i, 0]])
        for k, (dp, da) in enumerate(((h * n, 0.0), (np.zeros(2), h))):
            out = []
            for sgn in (1.0, -1.0):
                Pp, Dp = P.copy(), D.copy()
                Pp[i] = P[i] + sgn * dp
                a = sgn * da
                c, s_ = np.cos(a), np.sin(a)
                Dp[i] = np.array([c * D[i, 0] - s_ * D[i, 1], s_ * D[i, 0] + c * D[i, 1]])
                out.append(_line_intersections(Pp, Dp).ravel())
            J[:, 2 * i + k] = (out[0] - out[1]) / (2 * h)
    var = np.empty(8)
    var[0::2] = var_offset
    var[1::2] = var_angle
    return (J * var) @ J.T


def _integrated_autocorrelation(r, max_lag: int = 8) -> float:
    """``τ = 1 + 2 Σ ρ_k`` of a residual sequence, summed while the autocorrelation stays positive
    (Geyer's initial positive sequence, simplified); ≥ 1. Neighbouring edge profiles share pixels
    (bilinear sampling, blur), so their offsets are correlated: n samples count as n / τ."""
    r = np.asarray(r, float) - np.mean(r)
    n = len(r)
    v = float(r @ r)
    if n < 4 or v <= 0:
        return 1.0
    tau = 1.0
    for k in range(1, min(max_lag, n - 2)):
        rho = float(r[:-k] @ r[k:]) / v
        if rho <= 0:
            break
        tau += 2.0 * rho
    return tau


def _refine(img, quad, margin, half, step_px, min_contrast, outer_px=None, to_image=None, tau_mode="pixel"):
    """One refinement round (module docstring, steps 3-4). ``quad`` and every returned coordinate
    are in the *ideal* image; ``to_image`` maps ideal pixels ``(..., 2)`` to the observed image
    where the intensities are sampled (a lens, :mod:`layoutkit.camera.lens`; None = identity), so
    profiles run along the ideal (straight) sides and their offsets are in ideal pixels."""
    import cv2
    from scipy.ndimage import map_coordinates

    cen = quad.mean(0)
    pts_all, dirs, nps, resid, var_off, var_ang, contr = [], [], [], [], [], [], []
    offs = np.arange(-half, half + 1e-9, 0.25)
    for i in range(4):
        p0, p1 = quad[i], quad[(i + 1) % 4]
        d = p1 - p0
        length = np.linalg.norm(d)
        d = d / length
        n = np.array([d[1], -d[0]])
        if np.dot(n, (p0 + p1) / 2 - cen) < 0:
            n = -n  # outward normal
        s = np.arange(margin * length, (1 - margin) * length, step_px)
        if len(s) < 3:
            return None
        base = p0 + s[:, None] * d  # (m, 2)
        xy = base[:, None, :] + offs[None, :, None] * n  # (m, k, 2)
        if to_image is not None:
            xy = to_image(xy)
        prof = map_coordinates(img, [xy[..., 1].ravel(), xy[..., 0].ravel()], order=1, mode="nearest")
        prof = prof.reshape(xy.shape[:2])
        lin = prof[:, :3].mean(1)
        lout = prof[:, -3:].mean(1)
        contrast = lin - lout
        good = np.abs(contrast) >= min_contrast
        c = np.clip((prof - lout[:, None]) / np.where(good, contrast, 1.0)[:, None], -0.5, 1.5)
        # edge offset = -half + integral of the normalised step (trapezoid rule)
        e = -half + np.trapezoid(c, offs, axis=1)
        if outer_px is not None:
            # second pass: outside level taken just outside this edge (e + outer_px) and the
            # integral cut there, so that another edge further out (a thin sliver of a side face
            # next to the face) does not bias the estimate
            for _ in range(2):
                j = np.clip(np.searchsorted(offs, e + outer_px), 1, len(offs) - 2)
                lout = np.take_along_axis(prof, np.stack([j - 1, j, j + 1], 1), 1).mean(1)
                contrast = lin - lout
                good &= np.abs(contrast) >= min_contrast
                c = np.clip((prof - lout[:, None]) / np.where(good, contrast, 1.0)[:, None], -0.5, 1.5)
                c = np.where(offs[None, :] <= offs[j][:, None], c, 0.0)
                e = -half + np.trapezoid(c, offs, axis=1)
        pts = base + e[:, None] * n
        keep = good & (np.abs(e) < half - 0.5)
        pts = pts[keep]
        contr.append(float(np.median(contrast[keep])) if keep.any() else 0.0)  # inside - outside
        if len(pts) < 3:
            return None
        vx, vy, x0, y0 = cv2.fitLine(pts.astype(np.float32), cv2.DIST_HUBER, 0, 0.01, 0.01).ravel()
        dl = np.array([vx, vy], float)
        pl = np.array([x0, y0], float)
        r = (pts - pl) @ np.array([dl[1], -dl[0]])
        tpos = (pts - pl) @ dl
        tau = _integrated_autocorrelation(r[np.argsort(tpos)]) if tau_mode == "measured" else 1.0 / step_px
        n_eff = max(len(pts) / tau, 2.0)  # independent edge samples along the side
        s2 = float(np.sum(r ** 2) / max(len(pts) - 2, 1))
        var_off.append(s2 / n_eff)
        var_ang.append(s2 / max(np.sum((tpos - tpos.mean()) ** 2) / tau, 1e-12))
        pts_all.append(pl)
        dirs.append(dl)
        nps.append(len(pts))
        resid.append(r)
    try:
        corners = _line_intersections(np.array(pts_all), np.array(dirs))
    except np.linalg.LinAlgError:
        return None
    rms = float(np.sqrt(np.mean(np.concatenate(resid) ** 2)))
    cov = line_corner_covariance(np.array(pts_all), np.array(dirs), np.array(var_off), np.array(var_ang))
    return corners, rms, tuple(nps), cov, contr


def detect_quadrilateral(image, *, mask=None, threshold: float | None = None, invert: bool = False,
                         min_area_px: float = 50.0, corner_margin: float = 0.15,
                         profile_half_px: float = 4.0, min_contrast: float = 10.0,
                         max_shift_px: float | None = None, outer_px: float | None = 2.0,
                         camera_matrix=None, distortion=None, edge_correlation: str = "pixel") -> QuadDetection:
    """Find the largest quadrilateral in ``image`` and its corners to sub-pixel accuracy.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array (uint8 or float grey levels).
    mask : optional (H, W) bool — the region to take the contour from (overrides thresholding);
        the sub-pixel step always uses the intensities of ``image``.
    threshold : grey level separating face from background; None = Otsu. ``invert`` for a dark
        face on a bright background.
    corner_margin : fraction of each side left out at both ends of the line fit.
    profile_half_px : half length of the edge profiles (px); must exceed the blur radius.
    min_contrast : minimum |I_in - I_out| (grey levels) for a profile to count.
    outer_px : second pass with the outside level read ``outer_px`` beyond the first estimate and
        the integral cut there (robust to a second edge a few pixels out, e.g. a sliver of a side
        face); None = single pass over the whole profile.
    max_shift_px : refined corners further than this from the contour corners → "refine_failed"
        (default 3 px + 3 % of the mean side: acute corners of steeply tilted faces are cut off by
        rasterisation and blur, so their contour corners are several pixels short).
    camera_matrix, distortion : a lens (OpenCV model, :mod:`layoutkit.camera.lens`): the contour is
        undistorted, the profiles run along the straight sides of the ideal image and sample the
        observed image through the lens; see :class:`QuadDetection` for the outputs.
    edge_correlation : how many of the edge samples along a side count as independent for the
        covariance: "pixel" (one per pixel of side, the 0.5 px profiles sharing pixels) or
        "measured" (n / τ with τ the integrated autocorrelation of the side's residuals over lags
        up to 3.5 px: blur and bilinear sampling correlate neighbouring profiles; Monte-Carlo on a
        blurred distorted render: scatter / predicted 0.96, where "pixel" gave 1.44).

    Returns a :class:`QuadDetection`; failures are statuses, not exceptions.
    """
    import cv2

    if edge_correlation not in ("pixel", "measured"):
        raise ValueError(f"edge_correlation: expected 'pixel' or 'measured', got {edge_correlation!r}")
    img = np.asarray(image)
    if img.ndim == 3:
        img = img[..., :3].astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
    img = as_array(img, "image", (None, None)).astype(np.float32)
    if mask is None:
        u8 = np.clip(img, 0, 255).astype(np.uint8)
        if threshold is None:
            _, bw = cv2.threshold(u8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
        else:
            bw = ((u8 > threshold) * 255).astype(np.uint8)
        if invert:
            bw = 255 - bw
    else:
        m = np.asarray(mask, bool)
        if m.shape != img.shape:
            raise ValueError(f"mask: expected shape {img.shape}, got {m.shape}")
        bw = m.astype(np.uint8) * 255
    contours, _ = cv2.findContours(bw, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return _fail("no_contour", "no foreground region found")
    cnt = max(contours, key=cv2.contourArea)
    if cv2.contourArea(cnt) < min_area_px:
        return _fail("no_contour", f"largest region has area {cv2.contourArea(cnt):.0f} px < {min_area_px}")
    x, y, w, h = cv2.boundingRect(cnt)
    if x <= 0 or y <= 0 or x + w >= img.shape[1] or y + h >= img.shape[0]:
        return _fail("touches_border", "the region touches the image border")
    lens = camera_matrix is not None and distortion is not None and np.any(np.asarray(distortion, float) != 0)
    to_image = None
    if lens:
        from .lens import distort_jacobian, distort_pixels, ideal_camera, undistort_pixels

        Km, Dv = np.asarray(camera_matrix, float), np.asarray(distortion, float)
        f = ideal_camera(Km)[0]

        def to_image(q):
            return distort_pixels(q, Km, Dv, f)

        cnt = undistort_pixels(cnt[:, 0, :].astype(float), Km, Dv, f).astype(np.float32)[:, None, :]
    quad0 = _initial_quad(cnt)
    if quad0 is None:
        return _fail("not_quadrilateral", "the region's outline is not four-sided")
    quad = quad0
    rms, nps, cov = float("nan"), (0, 0, 0, 0), None
    for _ in range(2):
        out = _refine(img, quad, corner_margin, profile_half_px, 0.5, min_contrast, outer_px, to_image,
                      edge_correlation)
        if out is None:
            return _fail("refine_failed", "too few edge points on a side", quad0)
        quad, rms, nps, cov, _ = out
    if max_shift_px is None:
        max_shift_px = 3.0 + 0.03 * float(np.mean(np.linalg.norm(quad0 - np.roll(quad0, 1, axis=0), axis=1)))
    if np.max(np.linalg.norm(quad - quad0, axis=1)) > max_shift_px:
        return _fail("refine_failed", "refined corners moved too far from the contour corners", quad0)
    if not lens:
        return QuadDetection(quad, True, "ok", "ok", rms, nps, quad0, cov)
    F = distort_jacobian(quad, Km, Dv, f)
    B = np.zeros((8, 8))
    for i in range(4):
        B[2 * i:2 * i + 2, 2 * i:2 * i + 2] = F[i]
    return QuadDetection(to_image(quad), True, "ok", "ok", rms, nps, to_image(quad0), B @ cov @ B.T, quad, cov)


def corners_to_paper(corners_px, principal_point, first: int | None = None) -> np.ndarray:
    """Pixel corners ``(..., 4, 2)`` (any order round the face) → Zhai P1..P4 in (u, v) pixels (v up).

    See :func:`layoutkit.camera.rectangle.order_corners` for the labelling rule and ``first``.
    """
    return order_corners(pixels_to_paper_uv(corners_px, principal_point), first=first)
