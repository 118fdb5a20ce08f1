"""Camera input for the live mode: frames or corner tables → a timestamped attitude stream.

Sources (:func:`attitude_stream`): a folder of images, a video file, an OpenCV capture device
(an integer index), or a corners CSV. Each frame goes image → :func:`detect_quadrilateral` →
P1..P4 → a rectangle solver, with **temporal continuity**: the corner-labelling symmetry (90°/180°
about the face normal) and, for IPPE, the Necker branch are resolved against the previous
successful estimate (or ``initial``). :func:`align_rotation_streams` then estimates the fixed
rotation between this stream and the lighthouse attitude stream and reports the disagreement.

Corners CSV: a header row and one row per frame, either ``t,u1,v1,u2,v2,u3,v3,u4,v4`` (paper
(u, v) in pixels, v up, principal point at 0, already ordered P1..P4) or ``t,x1,y1,...,x4,y4``
(pixel coordinates, any order round the face; ordered with :func:`corners_to_paper`). Times in s.
"""
from __future__ import annotations

import csv
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._validate import as_array
from ..rotations import fit_rotation_pair
from .corners import corners_to_paper, detect_quadrilateral
from .rectangle import resolve_labelling, solve_rectangle

__all__ = [
    "AttitudeStream",
    "CornerTracker",
    "track_corners",
    "read_corners_csv",
    "iter_frames",
    "attitude_stream",
    "RotationAlignment",
    "align_rotation_streams",
]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm")


@dataclass(frozen=True)
class AttitudeStream:
    """Timestamped camera attitudes.

    t : (T,) s. rotation : (T, 3, 3) R_ct (paper conventions), NaN where not solved.
    success : (T,) bool. status : (T,) str (detector or solver status). corners_uv : (T, 4, 2)
    paper (u, v) px, P1..P4. rms_px : (T,) detector line-fit RMS (NaN for CSV input).
    """

    t: np.ndarray
    rotation: np.ndarray
    success: np.ndarray
    status: np.ndarray
    corners_uv: np.ndarray
    rms_px: np.ndarray
    meta: dict = field(default_factory=dict)
    message: str = ""


def _label_folds(method: str, aspect_ratio) -> int:
    if method == "ippe" and aspect_ratio is not None and not np.isclose(float(aspect_ratio), 1.0):
        return 2
    return 4


_SHIFT_ONE = np.array([1, 3, 0, 2])  # P1..P4 relabelled one corner further round the face


class CornerTracker:
    """Incremental form of :func:`track_corners`: feed one corner set at a time (live mode).

    ``update(t, corners_uv (4, 2)) -> (rotation (3, 3) or None, status, solution)``; the state is
    the last ``predict_window`` solutions (the reference for labelling / IPPE branch choice).
    ``last_corners`` holds the corners in the order the last solve used (IPPE on a non-square
    face may relabel them one corner round).
    """

    def __init__(self, focal_length, method: str = "zhai", initial=None, n_fold: int | None = None,
                 predict_window: int = 10, **options):
        self.focal_length = float(focal_length)
        self.method = method
        self.options = options
        self.n_fold = _label_folds(method, options.get("aspect_ratio")) if n_fold is None else n_fold
        self.ref = None if initial is None else as_array(initial, "initial", (3, 3))
        self.predict_window = predict_window
        self.last = []  # (t, R) of the last predict_window solutions
        self.last_corners = None

    def update(self, t: float, corners_uv):
        from ..geometry import matrix_to_rotvec, rotvec_to_matrix

        c = np.asarray(corners_uv, float)
        if c.shape != (4, 2) or not np.all(np.isfinite(c)):
            return None, "no_corners", None
        last, ref = self.last, self.ref
        if self.predict_window > 1 and len(last) >= 2 and last[-1][0] > last[0][0]:
            w = matrix_to_rotvec(last[-1][1] @ last[0][1].T) / (last[-1][0] - last[0][0])
            ref = rotvec_to_matrix(w * (t - last[-1][0])) @ last[-1][1]
        opts = dict(self.options)
        if self.method == "ippe" and ref is not None:
            opts["reference"] = ref
        sol = solve_rectangle(c, self.focal_length, method=self.method, **opts)
        if self.n_fold == 2 and self.method == "ippe":
            # a non-square face: which pair of sides is the long one is data, not labelling —
            # the corner order shifted by one round the face (P1 P2 P4 P3 → P2 P4 P3 P1) is
            # tried too and the lower reprojection error wins
            alt = solve_rectangle(c[_SHIFT_ONE], self.focal_length, method=self.method, **opts)
            e0 = sol.extra["reprojection_px"][0] if bool(sol.success) else np.inf
            e1 = alt.extra["reprojection_px"][0] if bool(alt.success) else np.inf
            if e1 < e0:
                sol, c = alt, c[_SHIFT_ONE]
        status = str(sol.status)
        self.last_corners = c
        if not bool(sol.success):
            self.ref = ref
            return None, status, sol
        Rk = sol.rotation  # for IPPE the solver already chose the branch (data first, then reference)
        if ref is not None:
            Rk = resolve_labelling(Rk, ref, self.n_fold)
        self.ref = Rk
        self.last = (last + [(t, Rk)])[-max(self.predict_window, 1):]
        return Rk, status, sol


def track_corners(times, corners_uv, focal_length, method: str = "zhai", initial=None,
                  n_fold: int | None = None, predict_window: int = 10, **options) -> AttitudeStream:
    """Solve a sequence of corner sets with temporal continuity.

    times : (T,) s. corners_uv : (T, 4, 2) paper (u, v), P1..P4 (NaN rows = no detection).
    initial : (3, 3) prior attitude for the first frame's labelling (None: take the first solve as is).
    n_fold : labelling symmetry to resolve (default 4, or 2 for IPPE with aspect ratio ≠ 1).
    predict_window : the reference for frame k is the constant-rate extrapolation from the
        oldest to the newest of the last ``predict_window`` solutions (≤ 1: the last solution).
        Needed for IPPE through face-on, where its two branches touch and "nearest to the
        previous" cannot tell which one continues.
    options : passed to the solver (e.g. ``aspect_ratio`` for "ippe").
    """
    t = as_array(times, "times", (None,))
    c = as_array(corners_uv, "corners_uv", (None, 4, 2))
    if len(t) != len(c):
        raise ValueError(f"times: expected {len(c)} values (one per corner set), got {len(t)}")
    tracker = CornerTracker(focal_length, method, initial, n_fold, predict_window, **options)
    R = np.full((len(t), 3, 3), np.nan)
    ok = np.zeros(len(t), bool)
    status = np.full(len(t), "no_corners", dtype=object)
    for k in range(len(t)):
        Rk, status[k], _ = tracker.update(t[k], c[k])
        if Rk is not None:
            R[k], ok[k] = Rk, True
    n_ok = int(ok.sum())
    return AttitudeStream(t, R, ok, status.astype(str), c, np.full(len(t), np.nan), {"method": method},
                          message=f"{n_ok} of {len(t)} frames solved")


def read_corners_csv(path, principal_point=(0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Read a corners CSV (see module docstring) → ``(t (T,), corners_uv (T, 4, 2))`` paper (u, v) px."""
    try:
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text file (a corners CSV is text)") from None
    if not rows:
        raise ValueError(f"{path}: empty corners CSV")
    head = [h.strip().lower() for h in rows[0]]
    uv_cols = ["t"] + [f"{a}{i}" for i in range(1, 5) for a in "uv"]
    xy_cols = ["t"] + [f"{a}{i}" for i in range(1, 5) for a in "xy"]
    if all(h in head for h in uv_cols):
        cols, pixels = uv_cols, False
    elif all(h in head for h in xy_cols):
        cols, pixels = xy_cols, True
    else:
        raise ValueError(f"{path}: expected columns {','.join(uv_cols)} or {','.join(xy_cols)}, got {','.join(head)}")
    idx = [head.index(h) for h in cols]
    try:
        data = np.array([[float(r[i]) for i in idx] for r in rows[1:] if r], float).reshape(-1, 9)
    except (ValueError, IndexError) as e:
        raise ValueError(f"{path}: could not parse a data row ({e})") from None
    t, q = data[:, 0], data[:, 1:].reshape(-1, 4, 2)
    if pixels:
        q = corners_to_paper(q, principal_point)
    return t, q


def iter_frames(source, fps: float | None = None, max_frames: int | None = None):
    """Yield ``(t_s, image)`` from an image folder, a video file or a capture device index.

    Folder: sorted image files, ``t = index / fps`` (fps default 1). Video: the container's
    timestamps. Device (int or a string of digits): wall-clock ``time.monotonic()``.
    """
    import cv2

    n = 0
    if isinstance(source, (int, np.integer)) or (isinstance(source, str) and source.isdigit()):
        cap = cv2.VideoCapture(int(source))
        if not cap.isOpened():
            raise ValueError(f"capture device {source}: could not be opened")
        t0 = time.monotonic()
        try:
            while max_frames is None or n < max_frames:
                ok, frame = cap.read()
                if not ok:
                    break
                yield time.monotonic() - t0, frame
                n += 1
        finally:
            cap.release()
        return
    p = Path(source)
    if p.is_dir():
        files = sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise ValueError(f"{p}: no image files ({', '.join(IMAGE_SUFFIXES)})")
        step = 1.0 / (fps or 1.0)
        for i, f in enumerate(files[: max_frames]):
            img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise ValueError(f"{f}: not a readable image")
            yield i * step, img
        return
    if not p.exists():
        raise ValueError(f"{p}: no such file or folder")
    if p.suffix.lower() in IMAGE_SUFFIXES:
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f"{p}: not a readable image")
        yield 0.0, img
        return
    cap = cv2.VideoCapture(str(p))
    if not cap.isOpened():
        raise ValueError(f"{p}: not a readable video")
    try:
        while max_frames is None or n < max_frames:
            ok, frame = cap.read()
            if not ok:
                break
            yield cap.get(cv2.CAP_PROP_POS_MSEC) / 1e3, frame
            n += 1
    finally:
        cap.release()


def attitude_stream(source, focal_length_px: float, principal_point=None, method: str = "zhai",
                    initial=None, fps: float | None = None, max_frames: int | None = None,
                    detector_options: dict | None = None, **solver_options) -> AttitudeStream:
    """Camera attitude stream from a folder / video / device / corners CSV (see module docstring).

    principal_point : (cx, cy) px; default the image centre ((W - 1)/2, (H - 1)/2) for images, and
    (0, 0) for CSVs (i.e. the CSV holds (u, v) or centred pixel coordinates).
    """
    if isinstance(source, (str, Path)) and str(source).lower().endswith(".csv"):
        t, q = read_corners_csv(source, (0.0, 0.0) if principal_point is None else principal_point)
        return track_corners(t, q, focal_length_px, method=method, initial=initial, **solver_options)
    ts, qs, rms, st = [], [], [], []
    for t, img in iter_frames(source, fps=fps, max_frames=max_frames):
        det = detect_quadrilateral(img, **(detector_options or {}))
        pp = ((img.shape[1] - 1) / 2, (img.shape[0] - 1) / 2) if principal_point is None else principal_point
        ts.append(t)
        rms.append(det.rms_px)
        st.append(det.status)
        qs.append(corners_to_paper(det.corners_px, pp) if det.success else np.full((4, 2), np.nan))
    if not ts:
        raise ValueError(f"{source}: no frames")
    s = track_corners(np.array(ts), np.array(qs), focal_length_px, method=method, initial=initial, **solver_options)
    status = np.where(np.array(st) == "ok", s.status, np.array(st))
    return AttitudeStream(s.t, s.rotation, s.success, status, s.corners_uv, np.array(rms), s.meta,
                          message=f"{int(s.success.sum())} of {len(ts)} frames solved")


# ----------------------------------------------------------------------------- alignment
@dataclass(frozen=True)
class RotationAlignment:
    """Fixed rotations between two attitude streams: ``R_a ≈ X @ R_b @ Y``.

    rotation : (3, 3) X (frame of stream a ← frame of stream b, e.g. camera ← lighthouse).
    body_rotation : (3, 3) Y (target frame of b ← target frame of a; identity unless estimated).
    t : (M,) s matched times (of stream a). disagreement_rad : (M,) attitude error of
    ``R_a`` vs ``X R_b(t) Y`` per matched frame. inlier : (M,) bool used in the final average.
    """

    rotation: np.ndarray
    body_rotation: np.ndarray
    t: np.ndarray
    disagreement_rad: np.ndarray
    inlier: np.ndarray
    success: bool
    status: str
    message: str

    @property
    def rms_rad(self) -> float:
        d = self.disagreement_rad[self.inlier]
        return float(np.sqrt(np.mean(d ** 2))) if d.size else float("nan")


def align_rotation_streams(t_a, R_a, t_b, R_b, max_dt: float | None = None, body_offset: bool = False,
                           outlier_factor: float = 5.0, iterations: int = 20) -> RotationAlignment:
    """Estimate the fixed rotation between two attitude streams and the per-frame disagreement.

    Stream a (e.g. the camera, ``R_a (Ta, 3, 3)`` at ``t_a (Ta,)`` s) and stream b (e.g. the
    lighthouse PnP, ``R_b (Tb, 3, 3)`` at ``t_b``) observe the same rigid target. Stream b is
    interpolated (SLERP) at the times of a; pairs further than ``max_dt`` (s; default 1.5× the median
    spacing of b) from a b sample, or outside b's time span, are dropped. Model ``R_a = X R_b Y``:
    X by rotation averaging (chordal L2 mean of ``R_a Y^T R_b^T``); with ``body_offset`` also Y
    (alternating averages, needs enough attitude change); then pairs whose disagreement exceeds
    ``outlier_factor`` × the median are dropped and X (, Y) re-averaged once.
    NaN rotations (failed frames) are ignored. Failures are a status, not an exception.
    """
    from scipy.spatial.transform import Rotation, Slerp

    ta = as_array(t_a, "t_a", (None,))
    Ra = as_array(R_a, "R_a", (None, 3, 3))
    tb = as_array(t_b, "t_b", (None,))
    Rb = as_array(R_b, "R_b", (None, 3, 3))
    if len(ta) != len(Ra) or len(tb) != len(Rb):
        raise ValueError(f"t_a/R_a and t_b/R_b must have equal lengths, got {len(ta)}/{len(Ra)} and {len(tb)}/{len(Rb)}")
    eye = np.eye(3)

    def _fail(status, msg):
        return RotationAlignment(np.full((3, 3), np.nan), eye, np.zeros(0), np.zeros(0), np.zeros(0, bool),
                                 False, status, msg)

    okb = np.all(np.isfinite(Rb), axis=(1, 2))
    oka = np.all(np.isfinite(Ra), axis=(1, 2))
    if okb.sum() < 2 or oka.sum() < 1:
        return _fail("too_few_samples", "need ≥ 2 valid samples in stream b and ≥ 1 in stream a")
    order = np.argsort(tb[okb])
    tbv, Rbv = tb[okb][order], Rb[okb][order]
    keep = np.concatenate([[True], np.diff(tbv) > 0])
    tbv, Rbv = tbv[keep], Rbv[keep]
    if len(tbv) < 2:
        return _fail("too_few_samples", "stream b has fewer than 2 distinct times")
    if max_dt is None:
        max_dt = 1.5 * float(np.median(np.diff(tbv)))
    near = np.abs(tbv[np.clip(np.searchsorted(tbv, ta), 0, len(tbv) - 1)] - ta)
    near = np.minimum(near, np.abs(tbv[np.clip(np.searchsorted(tbv, ta) - 1, 0, len(tbv) - 1)] - ta))
    m = oka & (ta >= tbv[0]) & (ta <= tbv[-1]) & (near <= max_dt)
    if m.sum() < 1:
        return _fail("no_overlap", "no time-matched pairs (check clocks and max_dt)")
    Rbi = Slerp(tbv, Rotation.from_matrix(Rbv))(ta[m]).as_matrix()
    fit = fit_rotation_pair(Ra[m], Rbi, body_offset=body_offset, outlier_factor=outlier_factor,
                            iterations=iterations, require_motion=False)
    return RotationAlignment(fit.X, fit.Y, ta[m], fit.residual_rad, fit.inlier, fit.success, fit.status,
                             f"{int(m.sum())} matched pairs, {int((~fit.inlier).sum())} outliers, "
                             f"rms {np.degrees(fit.rms_rad):.3g} deg")
