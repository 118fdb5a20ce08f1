"""A bright (or dark) rectangular face in a real photograph: candidates, a robust outline, sub-pixel corners.

:func:`layoutkit.camera.corners.detect_quadrilateral` takes the largest region of one global
threshold — right for a rendered face on black, wrong for a photograph, where the face's region
merges with whatever bright clutter touches it at that threshold and where a lens bends its
straight edges. :func:`detect_face` works in the **ideal** (undistorted) image when a camera is
given, and searches:

1. **segmentations** (for a bright face; a dark face uses the inverted image): Otsu's threshold
   and three levels above it (towards the 99th percentile), and two locally adaptive thresholds
   (``cv2.adaptiveThreshold``, mean of a window of 1/16 and 1/8 of the image, 5 grey levels
   above it: a face next to a darker rim separates even when the lighting varies);
2. **outlines**: the external contours of each segmentation over ``min_area_frac`` of the image,
   undistorted; each gives up to two quadrilaterals — the convex hull reduced to four vertices
   (Douglas–Peucker), and a **robust four-line outline**: the contour's polygon (tolerance 0.5 %
   of its perimeter) gives straight runs; every four of its longest runs, in contour order,
   give a quadrilateral by intersecting lines fitted to their points — so a face whose region
   has clutter attached on one part still yields its outline;
3. **support**: each quadrilateral is sampled along its sides (1 px steps); a sample is
   supported when a contour point lies within ``support_tol_px`` (ideal px). Kept: convex, not
   within 2 px of the image border, every side ≥ ``min_side_support`` supported, the face brighter
   (darker) than a ring just outside it; duplicates (corners within 3 px) merged;
4. **sub-pixel corners**: the edge-profile refinement of :mod:`layoutkit.camera.corners` (the
   integral of the normalised step along each side's normal, Huber line fits, corners at the
   intersections, two rounds), with the profiles laid along the *ideal* straight sides and
   sampled in the observed image through the lens (``to_image``);
5. **choice**: among the refined candidates with edge RMS ≤ ``max_rms_px``, the one with the
   largest ``area × min side support`` (the most complete large outline); its corner covariance
   (line-fit offsets and angles, :func:`layoutkit.camera.corners.line_corner_covariance`) is
   carried into observed pixels by the lens Jacobian.

Statuses: "ok"; "not_found" (no candidate survived; the message says how many were tried and
why the best failed). Coordinates: pixels (x right, y down), centres at integers.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations

import numpy as np

from .._validate import as_array
from .corners import _initial_quad, _line_intersections, _refine

__all__ = ["FaceDetection", "detect_face"]


@dataclass(frozen=True)
class FaceDetection:
    """Result of :func:`detect_face`.

    corners_px (4, 2) observed pixels going round the face; corners_ideal_px (4, 2) undistorted
    (= corners_px without a lens); corner_cov_px (8, 8) px² covariance of corners_px (flattened
    x1, y1, ...); rms_px: edge-point RMS about the fitted sides (ideal px); contrast: median
    face − surround grey-level step; support: smallest per-side fraction of the outline found on
    the segmentation's contour; polarity "bright" or "dark"; candidates: outlines refined;
    source: which segmentation gave it.
    """

    corners_px: np.ndarray
    success: bool
    status: str
    message: str
    corners_ideal_px: np.ndarray = field(default_factory=lambda: np.full((4, 2), np.nan))
    corner_cov_px: np.ndarray | None = None
    rms_px: float = float("nan")
    contrast: float = float("nan")
    support: float = float("nan")
    polarity: str = ""
    candidates: int = 0
    source: str = ""


def _segmentations(g, polarity):
    import cv2

    n = max(g.shape)
    for pol in (("bright", "dark") if polarity == "auto" else (polarity,)):
        img = g if pol == "bright" else 255 - g
        t0, _ = cv2.threshold(img, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
        top = float(np.percentile(img, 99))
        for t in np.linspace(t0, max(t0, 0.5 * (t0 + top)), 4):
            yield pol, f"threshold {t:.0f}", ((img > t) * 255).astype(np.uint8)
        for frac in (16, 8):
            bs = max(3, (n // frac) | 1)
            yield pol, f"adaptive {bs}", cv2.adaptiveThreshold(img, 255, cv2.ADAPTIVE_THRESH_MEAN_C,
                                                                 cv2.THRESH_BINARY, bs, -5)


def _fit_line(pts):
    """Total-least-squares line through ``pts (n, 2)``: (centroid, unit direction)."""
    c = pts.mean(0)
    _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
    return c, vt[0]


def _robust_quads(cu, max_runs: int = 7):
    """Quadrilaterals from the longest straight runs of a closed contour ``cu (n, 2)`` (ideal)."""
    import cv2

    peri = cv2.arcLength(cu.astype(np.float32)[:, None, :], True)
    approx = cv2.approxPolyDP(cu.astype(np.float32)[:, None, :], 0.005 * peri, True)[:, 0, :]
    if len(approx) < 4:
        return []
    # index of each polygon vertex on the contour
    idx = [int(np.argmin(np.sum((cu - v) ** 2, axis=1))) for v in approx]
    runs = []
    for k in range(len(idx)):
        a, b = idx[k], idx[(k + 1) % len(idx)]
        seg = cu[a:b + 1] if b >= a else np.concatenate([cu[a:], cu[:b + 1]])
        length = float(np.linalg.norm(approx[(k + 1) % len(idx)] - approx[k]))
        if len(seg) >= 5:
            m = max(1, int(0.1 * len(seg)))  # the run's ends bend into the neighbouring sides
            runs.append((length, k, _fit_line(seg[m:len(seg) - m] if len(seg) > 2 * m + 2 else seg)))
    runs = sorted(runs, key=lambda r: -r[0])[:max_runs]
    out = []
    for combo in combinations(sorted(runs, key=lambda r: r[1]), 4):
        lines = [r[2] for r in combo]
        P = np.array([ln[0] for ln in lines])
        Dd = np.array([ln[1] for ln in lines])
        try:
            corners = _line_intersections(P, Dd)
        except np.linalg.LinAlgError:
            continue
        out.append(np.roll(corners, -1, axis=0))
    return out


def _convex(q):
    d = np.roll(q, -1, 0) - q
    cr = d[:, 0] * np.roll(d, -1, 0)[:, 1] - d[:, 1] * np.roll(d, -1, 0)[:, 0]
    return bool(np.all(cr > 0) or np.all(cr < 0))


def _side_support(q, tree, tol):
    sup = []
    for i in range(4):
        p0, p1 = q[i], q[(i + 1) % 4]
        L = float(np.linalg.norm(p1 - p0))
        s = np.linspace(0.0, 1.0, max(int(L), 4))
        pts = p0 + s[:, None] * (p1 - p0)
        d, _ = tree.query(pts)
        sup.append(float(np.mean(d <= tol)))
    return np.array(sup)


def detect_face(image, camera_matrix=None, distortion=None, *, polarity: str = "auto",
                min_area_frac: float = 0.01, support_tol_px: float = 2.0, min_side_support: float = 0.8,
                max_rms_px: float = 1.0, profile_half_px: float = 4.0, corner_margin: float = 0.15,
                min_contrast: float = 10.0, max_candidates: int = 8) -> FaceDetection:
    """Find a rectangular face in a photograph and its corners to sub-pixel accuracy (module docstring).

    image : (H, W) or (H, W, 3) uint8. camera_matrix (3, 3), distortion : the lens (OpenCV); None =
    an ideal camera (no undistortion). polarity : "bright", "dark" or "auto" (both).
    Returns a :class:`FaceDetection`; failure is a status, never an exception.
    """
    import cv2
    from scipy.spatial import cKDTree

    from .lens import distort_jacobian, distort_pixels, ideal_camera, undistort_pixels

    if polarity not in ("auto", "bright", "dark"):
        raise ValueError(f"polarity: expected 'auto', 'bright' or 'dark', got {polarity!r}")
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3].astype(np.uint8), cv2.COLOR_BGR2GRAY)
    img = as_array(img, "image", (None, None))
    g = np.clip(img, 0, 255).astype(np.uint8)
    H, W = g.shape
    lens = camera_matrix is not None and distortion is not None and np.any(np.asarray(distortion, float) != 0)
    if lens:
        K = np.asarray(camera_matrix, float)
        D = np.asarray(distortion, float)
        f = ideal_camera(K)[0]

        def to_ideal(p):
            return undistort_pixels(p, K, D, f)

        def to_image(p):
            return distort_pixels(p, K, D, f)
    else:
        to_ideal = to_image = None
    gf = g.astype(np.float32)
    cands = []  # (score, area, quad_ideal, support, pol, src)
    n_tried = 0
    for pol, src, bw in _segmentations(g, polarity):
        contours, _ = cv2.findContours(bw, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        for c in contours:
            if cv2.contourArea(c) < min_area_frac * H * W:
                continue
            pts = c[:, 0, :].astype(float)
            cu = to_ideal(pts) if lens else pts
            tree = cKDTree(cu)
            quads = []
            q0 = _initial_quad(cu.astype(np.float32)[:, None, :])
            if q0 is not None:
                quads.append(q0)
            quads += _robust_quads(cu)
            for q in quads:
                n_tried += 1
                if not np.all(np.isfinite(q)) or not _convex(q):
                    continue
                qo = to_image(q) if lens else q
                if (not np.all(np.isfinite(qo)) or qo[:, 0].min() < 2 or qo[:, 1].min() < 2
                        or qo[:, 0].max() > W - 3 or qo[:, 1].max() > H - 3):
                    continue
                area = float(cv2.contourArea(q.astype(np.float32)))
                if area < min_area_frac * H * W:
                    continue
                sup = _side_support(q, tree, support_tol_px)
                if sup.min() < min_side_support:
                    continue
                cands.append((area * sup.min(), area, q, float(sup.min()), pol, src))
    # merge duplicates: keep the best-supported of quads whose corners agree within 3 px
    cands.sort(key=lambda c: -c[0])
    uniq = []
    for c in cands:
        if not any(np.max(np.min(np.linalg.norm(c[2][:, None] - u[2][None], axis=-1), axis=1)) < 3.0 for u in uniq):
            uniq.append(c)
    best, reasons = None, []
    for score, area, q, sup, pol, src in uniq[:max_candidates]:
        quad = q
        out = None
        for _ in range(2):
            out = _refine(gf, quad, corner_margin, profile_half_px, 0.5, min_contrast, 2.0, to_image, "measured")
            if out is None:
                break
            quad = out[0]
        if out is None:
            reasons.append(f"{src}: too few edge points on a side")
            continue
        corners, rms, nps, cov, contr = out
        sign = 1.0 if pol == "bright" else -1.0
        if rms > max_rms_px:
            reasons.append(f"{src}: edge RMS {rms:.2f} px > {max_rms_px:g}")
            continue
        if np.max(np.linalg.norm(corners - q, axis=1)) > 3.0 + 0.03 * np.sqrt(area):
            reasons.append(f"{src}: refined corners moved far from the outline")
            continue
        co = to_image(corners) if lens else corners
        if not np.all(np.isfinite(co)):
            continue
        # face vs surround: every side's edge step (inside minus outside) has the polarity's sign
        if np.min(sign * np.asarray(contr)) <= 0:
            reasons.append(f"{src}: a side is not {pol}er inside than outside")
            continue
        if best is None or area * sup > best[0]:
            best = (area * sup, corners, co, rms, cov, float(np.median(np.abs(contr))), sup, pol, src)
    n_ref = min(len(uniq), max_candidates)
    if best is None:
        why = "; ".join(reasons[:3]) if reasons else "no closed outline with four supported straight sides"
        return FaceDetection(np.full((4, 2), np.nan), False, "not_found",
                             f"no rectangular face found ({n_tried} outlines tried, {n_ref} refined): {why}",
                             candidates=n_ref)
    _, ci, co, rms, cov, contr, sup, pol, src = best
    if lens:
        F = distort_jacobian(ci, K, D, f)
        B = np.zeros((8, 8))
        for i in range(4):
            B[2 * i:2 * i + 2, 2 * i:2 * i + 2] = F[i]
        cov_o = B @ cov @ B.T
    else:
        cov_o = cov
    return FaceDetection(co, True, "ok", f"{pol} face from {src}; edge RMS {rms:.2f} px", ci, cov_o, rms, contr, sup,
                         pol, n_ref, src)

