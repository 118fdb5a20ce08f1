"""The camera half of a live session: grab frames on their own thread, keep them raw, solve them.

``live --camera-device INDEX|URL|FILE|DIR`` opens the source with OpenCV ``VideoCapture`` (a
device index, a stream URL, a video file) or plays an image folder at its frame rate (a camera
capture folder's ``index.csv`` timing, else ``--fps``). :class:`CameraReader` runs two threads:

- the **grabber** takes each frame, stamps it with the host's monotonic clock at grab time (an
  image folder is a virtual camera: its frames are stamped at their scheduled playback times), and
  writes it raw to the capture folder (:class:`layoutkit.io.camera.CameraIndexWriter`) *before*
  anything else touches it; a folder source's file bytes are copied unchanged;
- the **solver** runs :class:`CameraProcessor` (quadrilateral detection → rectangle solve with
  continuity → predicted error) on the frames in order.

A source that stops, stalls or delivers corrupt frames never stops the serial side: the reader
counts what it received, what failed and why (:meth:`CameraReader.stats`), and every received
frame is on disk. ``replay`` runs the same :class:`CameraProcessor` over the folder
(:func:`process_camera_folder`), so live and replay give identical camera results.
"""
from __future__ import annotations

import queue
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["CameraConfig", "CameraFrames", "CameraProcessor", "CameraReader", "LiveCrossCheck",
           "process_camera_folder", "open_camera_source"]


@dataclass(frozen=True)
class CameraConfig:
    """How camera frames are solved.

    focal_length_px : px. principal_point_px : (cx, cy) px or None (image centre).
    method : rectangle solver (``layoutkit.camera.rectangle.RECTANGLE_SOLVERS``). aspect_ratio : face
    L/W (needed by "ippe"; with it the corner noise is estimated from IPPE's residuals for any
    method). corner_sigma_px : corner noise per coordinate, px (None: estimate). fps : frame rate
    of an image folder without an index. camera_model : a
    :class:`layoutkit.io.camera.CameraModel` (matrix + lens distortion, ``--camera-model``); with
    it the detector runs through the lens (corners and their covariance in the undistorted image)
    and the focal length / principal point are the model's ideal camera
    (:func:`layoutkit.camera.lens.ideal_camera`); :meth:`from_model` builds such a config.
    """

    focal_length_px: float
    principal_point_px: tuple | None = None
    method: str = "ippe"
    aspect_ratio: float | None = None
    corner_sigma_px: float | None = None
    fps: float | None = None
    camera_model: object | None = None

    @classmethod
    def from_model(cls, model, **kw) -> "CameraConfig":
        """A config whose focal length and principal point are ``model``'s ideal camera."""
        from ..camera.lens import ideal_camera

        f, cx, cy = ideal_camera(model.matrix)
        return cls(f, (cx, cy), camera_model=model, **kw)

    def __post_init__(self):
        from ..camera.rectangle import RECTANGLE_SOLVERS

        if not (np.isfinite(self.focal_length_px) and self.focal_length_px > 0):
            raise ValueError(f"focal_length_px: expected a positive number, got {self.focal_length_px!r}")
        if self.method not in RECTANGLE_SOLVERS:
            raise ValueError(f"camera method: expected one of {sorted(RECTANGLE_SOLVERS)}, got {self.method!r}")
        if self.method == "ippe" and self.aspect_ratio is None:
            object.__setattr__(self, "aspect_ratio", 1.0)
        if self.aspect_ratio is not None and not (np.isfinite(self.aspect_ratio) and self.aspect_ratio > 0):
            raise ValueError(f"aspect_ratio: expected a positive L/W, got {self.aspect_ratio!r}")

    def solver_options(self) -> dict:
        return {"aspect_ratio": self.aspect_ratio} if self.method == "ippe" else {}


@dataclass
class CameraFrames:
    """Per-frame camera results, growing as frames are processed (arrays via :meth:`arrays`).

    For each frame: t (s, camera clock), status (str), rotation R_ct (3, 3; NaN if not solved),
    corners (4, 2) paper (u, v) as used by the solve, jj_trace (trace of J J^T, rad²/px²: the
    predicted attitude variance per unit i.i.d. corner noise), pred_var (rad²: trace of
    J Σ J^T with the detector's own corner covariance Σ, the default prediction), rep_pred2 (px²:
    the IPPE mean-square reprojection error Σ alone would give, by a 4-draw Monte-Carlo seeded by
    the frame number — its ratio to the observed one is the a-posteriori variance factor), tilt (rad, face normal vs line of sight),
    reprojection_px (IPPE RMS, NaN otherwise), alt_ratio (IPPE second/first reprojection error).
    """

    t: list = field(default_factory=list)
    status: list = field(default_factory=list)
    rotation: list = field(default_factory=list)
    corners: list = field(default_factory=list)
    jj_trace: list = field(default_factory=list)
    pred_var: list = field(default_factory=list)
    rep_pred2: list = field(default_factory=list)
    tilt: list = field(default_factory=list)
    reprojection_px: list = field(default_factory=list)
    alt_ratio: list = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.t)

    def append(self, t, status, R, corners, jj, tilt, rep, alt, pred_var=float("nan"), rep_pred2=float("nan")):
        self.t.append(float(t))
        self.status.append(str(status))
        self.rotation.append(R)
        self.corners.append(corners)
        self.jj_trace.append(float(jj))
        self.pred_var.append(float(pred_var))
        self.rep_pred2.append(float(rep_pred2))
        self.tilt.append(float(tilt))
        self.reprojection_px.append(float(rep))
        self.alt_ratio.append(float(alt))

    def arrays(self) -> dict:
        n = len(self.t)
        return {
            "t": np.array(self.t, float), "status": np.array(self.status, dtype=object).astype(str),
            "rotation": np.array(self.rotation, float).reshape(n, 3, 3),
            "corners": np.array(self.corners, float).reshape(n, 4, 2),
            "jj_trace": np.array(self.jj_trace, float), "pred_var": np.array(self.pred_var, float),
            "rep_pred2": np.array(self.rep_pred2, float),
            "tilt": np.array(self.tilt, float),
            "reprojection_px": np.array(self.reprojection_px, float), "alt_ratio": np.array(self.alt_ratio, float),
        }

    def counts(self) -> dict:
        c = Counter(self.status)
        return {"frames": len(self.t), "solved": int(c.get("ok", 0)), "by_status": dict(sorted(c.items()))}


class CameraProcessor:
    """Frame → detection → rectangle solve with continuity → predicted error (deterministic).

    ``process(t, image_or_None, status_if_none)`` appends one record to :attr:`frames`.
    """

    def __init__(self, config: CameraConfig):
        from ..camera.stream import CornerTracker

        self.config = config
        self.tracker = CornerTracker(config.focal_length_px, config.method, **config.solver_options())
        self.frames = CameraFrames()
        self._n_fold = self.tracker.n_fold

    def process(self, t: float, image, status: str = "corrupt_frame"):
        from ..camera.corners import corners_to_paper, detect_quadrilateral
        from ..camera.uncertainty import attitude_jacobian_corners, face_tilt

        nan4 = np.full((4, 2), np.nan)
        nanR = np.full((3, 3), np.nan)
        if image is None:
            self.frames.append(t, status, nanR, nan4, np.nan, np.nan, np.nan, np.nan)
            return
        cfg = self.config
        model = cfg.camera_model
        if model is not None:
            det = detect_quadrilateral(image, camera_matrix=model.matrix, distortion=model.distortion)
        else:
            det = detect_quadrilateral(image)
        if not det.success:
            self.frames.append(t, det.status, nanR, nan4, np.nan, np.nan, np.nan, np.nan)
            return
        pp = cfg.principal_point_px or ((image.shape[1] - 1) / 2, (image.shape[0] - 1) / 2)
        corners, cov = det.corners_px, det.corner_cov_px
        if model is not None:  # solve in the ideal (undistorted, square-pixel) camera
            if det.corners_ideal_px is not None:
                corners, cov = det.corners_ideal_px, det.corner_cov_ideal_px
            else:
                from ..camera.lens import undistort_pixels

                corners = undistort_pixels(det.corners_px, model.matrix, model.distortion)
        q = corners_to_paper(corners, pp)
        R, st, sol = self.tracker.update(t, q)
        if R is None:
            self.frames.append(t, st, nanR, nan4, np.nan, np.nan, np.nan, np.nan)
            return
        c = self.tracker.last_corners
        f = cfg.focal_length_px
        J = attitude_jacobian_corners(c, f, R, method=cfg.method, n_fold=self._n_fold, **cfg.solver_options())
        rep, alt = np.nan, np.nan
        if cfg.aspect_ratio is not None:
            if cfg.method == "ippe":
                e = sol.extra["reprojection_px"]
            else:
                from ..camera.rectangle import solve_rectangle

                e = solve_rectangle(c, f, method="ippe", aspect_ratio=cfg.aspect_ratio).extra["reprojection_px"]
            rep = float(e[0])
            alt = float(e[1] / e[0]) if e[0] > 0 and np.isfinite(e[1]) else np.nan
        pv, rp2 = np.nan, np.nan
        if cov is not None:
            S = _paper_cov(corners, cov, pp, c)
            pv = float(np.trace(J @ S @ J.T))
            if cfg.aspect_ratio is not None and np.isfinite(rep):
                rp2 = _reprojection_mc(c, f, cfg.aspect_ratio, S, rep, len(self.frames))
        self.frames.append(t, "ok", R, c, float(np.sum(J * J)), float(face_tilt(R, c, f)), rep, alt, pv, rp2)


def _paper_cov(corners_px, cov_px, principal_point, corners_used):
    """The detector's pixel-corner covariance (8, 8) re-expressed for the corners the solve used
    (paper (u, v) = (x - cx, cy - y), in their P1..P4 order)."""
    from ..camera.conventions import pixels_to_paper_uv

    uv = pixels_to_paper_uv(corners_px, principal_point)
    perm = [int(np.argmin(np.linalg.norm(uv - q, axis=1))) for q in corners_used]
    idx = np.array([[2 * p, 2 * p + 1] for p in perm]).ravel()
    S = cov_px[np.ix_(idx, idx)]
    flip = np.tile([1.0, -1.0], 4)
    return S * np.outer(flip, flip)


def _reprojection_mc(c, f, aspect_ratio, S, rep_obs, seed: int, draws: int = 4) -> float:
    """Mean-square IPPE reprojection error (px²) that corner noise of covariance ``S`` adds to
    corners ``c``: ``mean(rms²(c + δ)) - rms²(c)``, ``δ ~ N(0, S)`` (deterministic per ``seed``)."""
    from ..camera.rectangle import solve_rectangle

    rng = np.random.default_rng(seed)
    w, V = np.linalg.eigh(S)
    A = V * np.sqrt(np.clip(w, 0, None))
    d = rng.standard_normal((draws, 8)) @ A.T
    e = []
    for k in range(draws):
        r = solve_rectangle(c + d[k].reshape(4, 2), f, method="ippe", aspect_ratio=aspect_ratio)
        if bool(r.success):
            e.append(float(r.extra["reprojection_px"][0]) ** 2)
    return float(np.mean(e) - rep_obs ** 2) if e else float("nan")


def _decode(data: bytes):
    import cv2

    if not data:
        return None
    arr = np.frombuffer(data, np.uint8)
    return cv2.imdecode(arr, cv2.IMREAD_UNCHANGED)


def process_camera_folder(folder, config: CameraConfig, max_frames: int | None = None) -> tuple[CameraFrames, dict]:
    """Solve every frame of a camera capture folder in order (replay). Returns ``(frames, info)``."""
    from ..io.camera import read_camera_index

    idx = read_camera_index(folder)
    proc = CameraProcessor(config)
    missing = 0
    for k in range(len(idx) if max_frames is None else min(len(idx), max_frames)):
        try:
            data = Path(idx.files[k]).read_bytes()
        except OSError:
            missing += 1
            proc.process(idx.t[k], None, "missing_file")
            continue
        proc.process(idx.t[k], _decode(data))
    return proc.frames, {"index_rows_dropped": idx.dropped_rows, "missing_files": missing,
                         "folder": str(folder)}


def open_camera_source(source, fps: float | None = None):
    """An iterator of ``(image or None, raw bytes or None, suffix, t_source_s, wait_s)`` for a source.

    Image folder: files in order (a capture folder's index order and timing, else sorted names at
    ``fps``, default 30); ``wait_s`` is the time to wait before the frame (its playback timing).
    Device index / URL / video file: OpenCV ``VideoCapture``; ``wait_s`` 0 (the source paces itself),
    except a video file, paced at its frame rate.
    """
    from ..camera.stream import IMAGE_SUFFIXES
    from ..io.camera import INDEX_NAME, read_camera_index

    p = Path(str(source))
    if p.is_dir():
        if (p / INDEX_NAME).is_file():
            idx = read_camera_index(p)
            files, times = list(idx.files), idx.t
        else:
            files = sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
            times = np.arange(len(files)) / float(fps or 30.0)
        if not files:
            raise ValueError(f"{p}: no camera frames (no index.csv and no image files)")

        def gen_folder():
            for k, f in enumerate(files):
                wait = float(times[k] - times[k - 1]) if k else 0.0
                try:
                    data = Path(f).read_bytes()
                except OSError:
                    data = b""
                yield _decode(data), data, Path(f).suffix or ".png", float(times[k]), max(wait, 0.0)
        return gen_folder()
    import cv2

    is_index = isinstance(source, (int, np.integer)) or (isinstance(source, str) and source.isdigit())
    if not is_index and "://" not in str(source) and not p.exists():
        raise ValueError(f"{source}: no such camera device, file or folder")
    cap = cv2.VideoCapture(int(source) if is_index else str(source))
    if not cap.isOpened():
        raise ValueError(f"camera {source}: could not be opened")
    video_fps = cap.get(cv2.CAP_PROP_FPS) if (not is_index and p.is_file()) else 0.0
    pace = 1.0 / video_fps if video_fps and video_fps > 0 else 0.0

    def gen_cap():
        first = True
        try:
            while True:
                ok, frame = cap.read()
                if not ok:
                    return
                tsrc = cap.get(cv2.CAP_PROP_POS_MSEC) / 1e3
                yield frame, None, ".png", tsrc, (0.0 if first else pace)
                first = False
        finally:
            cap.release()
    return gen_cap()


class CameraReader:
    """Grab (own thread, raw first) and solve (own thread) a camera source during a live session.

    source : device index / URL / video / folder. config : :class:`CameraConfig`. record_dir :
    camera capture folder (None: frames are solved but not kept). clock : host clock (default
    ``time.monotonic``). stall_s : a gap longer than this between frames counts as a stall.
    """

    def __init__(self, source, config: CameraConfig, record_dir=None, *, clock=time.monotonic,
                 stall_s: float = 1.0, max_frames: int | None = None):
        from ..io.camera import CameraIndexWriter, CameraMeta

        self.source = source
        self.config = config
        self.clock = clock
        self.stall_s = stall_s
        self.max_frames = max_frames
        self.processor = CameraProcessor(config)
        self.writer = None
        if record_dir is not None:
            # a folder source made by the bench simulator names its serial stream: the recording keeps
            # that tie, so a replay can tell whether the frames belong to the capture (io/runtie.py)
            from ..io.runtie import read_file_tie

            tie = read_file_tie(source) if Path(str(source)).is_dir() else None
            extra = {"run": tie.to_dict()} if tie is not None else {}
            if config.camera_model is not None:  # the capture records the lens it was solved with
                meta = CameraMeta.from_model(config.camera_model, source=str(source), clock="host-monotonic",
                                             aspect_ratio=config.aspect_ratio, extra=extra)
            else:
                meta = CameraMeta(focal_length_px=config.focal_length_px, principal_point_px=config.principal_point_px,
                                  source=str(source), clock="host-monotonic", aspect_ratio=config.aspect_ratio,
                                  extra=extra)
            self.writer = CameraIndexWriter(record_dir, meta)
        self._q: queue.Queue = queue.Queue()
        self._stop = threading.Event()
        self.received = 0
        self.stalls = 0
        self.write_errors = 0
        self.error = None
        self.ended = False
        self._t_last = None
        self._virtual = Path(str(source)).is_dir()
        self._grabber = threading.Thread(target=self._grab, name="camera-grab", daemon=True)
        self._solver = threading.Thread(target=self._solve, name="camera-solve", daemon=True)

    def start(self) -> "CameraReader":
        self._grabber.start()
        self._solver.start()
        return self

    # -- grabber ---------------------------------------------------------------------------
    def _grab(self):
        try:
            frames = open_camera_source(self.source, self.config.fps)
            t_next = None
            for img, raw, suffix, tsrc, wait in frames:
                if self._stop.is_set():
                    break
                if t_next is not None and wait > 0:
                    t_next += wait
                    while not self._stop.is_set():
                        dt = t_next - self.clock()
                        if dt <= 0:
                            break
                        time.sleep(min(dt, 0.05))
                t = self.clock()
                if t_next is None:
                    t_next = t
                if self._virtual:
                    # an image folder is a virtual camera: its frame is exposed at the scheduled
                    # playback time, whatever the load delayed the read by
                    t = t_next
                if self._t_last is not None and t - self._t_last > self.stall_s:
                    self.stalls += 1
                self._t_last = t
                if self.writer is not None:
                    try:
                        if raw is not None:
                            self.writer.add_bytes(raw, t, suffix, tsrc)
                        else:
                            self.writer.add_image(img, t, tsrc)
                    except OSError as exc:  # disk full: keep solving, say so
                        self.write_errors += 1
                        self.error = f"camera capture: {exc}"
                self.received += 1
                self._q.put((t, img))
                if self.max_frames is not None and self.received >= self.max_frames:
                    break
        except Exception as exc:  # a source that fails ends the camera side only
            self.error = f"camera {self.source}: {exc}"
        finally:
            self.ended = True
            self._q.put(None)

    # -- solver ----------------------------------------------------------------------------
    def _solve(self):
        while True:
            item = self._q.get()
            if item is None:
                return
            t, img = item
            try:
                self.processor.process(t, img)
            except Exception as exc:  # never take the session down
                self.processor.frames.append(t, f"solve_error: {type(exc).__name__}", np.full((3, 3), np.nan),
                                             np.full((4, 2), np.nan), np.nan, np.nan, np.nan, np.nan)

    # -- control ---------------------------------------------------------------------------
    @property
    def backlog(self) -> int:
        return self._q.qsize()

    def stop(self, timeout: float = 30.0) -> None:
        """Stop grabbing, solve what was received, close the capture."""
        self._stop.set()
        self._grabber.join(timeout)
        self._solver.join(timeout)
        if self.writer is not None:
            self.writer.close()

    def wait(self, timeout: float | None = None) -> None:
        """Wait for the source to end by itself (a file or folder) and its frames to be solved."""
        self._grabber.join(timeout)
        self._solver.join(timeout)

    def stats(self) -> dict:
        c = self.processor.frames.counts()
        return {"received": self.received, "processed": c["frames"], "solved": c["solved"],
                "by_status": c["by_status"], "stalls": self.stalls, "write_errors": self.write_errors,
                "ended": self.ended, "error": self.error, "backlog": self.backlog,
                "recorded_to": None if self.writer is None else str(self.writer.folder)}


class LiveCrossCheck:
    """The running lighthouse-vs-camera disagreement for the dashboard.

    Once ``align_after_s`` s of camera frames exist, the clock and the alignment are estimated
    once (:func:`layoutkit.live.crosscheck.camera_crosscheck`, on a background thread so the serial
    side never waits); after that each new camera frame's disagreement is computed against the
    lighthouse pose at its time. The report's figures come from the whole session at the end
    (the same computation ``replay`` makes), not from this running view.
    """

    def __init__(self, sigma_theta: float, align_after_s: float = 10.0, face_on_deg: float = 10.0):
        self.sigma_theta = sigma_theta
        self.align_after_s = align_after_s
        self.face_on_deg = face_on_deg
        self._est = None
        self._thread = None
        self._done = 0
        self._sq, self._psq, self._n = 0.0, 0.0, 0
        self.last = None

    def _estimate(self, lh, cam):
        from ..geometry import rotvec_to_matrix
        from .crosscheck import camera_crosscheck

        try:
            cc = camera_crosscheck(lh[:, 0], rotvec_to_matrix(lh[:, 1:4]), lh[:, 7], self.sigma_theta, cam,
                                   face_on_deg=self.face_on_deg)
            s = cc.summary
            if s.get("status") == "ok" and s.get("clock", {}).get("status") == "ok":
                X = rotvec_to_matrix(np.radians(s["alignment"]["camera_from_lighthouse_rotvec_deg"]))
                Y = rotvec_to_matrix(np.radians(s["alignment"]["body_from_face_rotvec_deg"]))
                self._est = (s["clock"]["offset_s"], s["clock"]["drift_ppm"] * 1e-6, X, Y,
                             s.get("camera_variance_factor") or 1.0)
            else:
                self._est = ("failed", s.get("message"))
        except Exception as exc:  # the dashboard must never take the session down
            self._est = ("failed", str(exc))

    def update(self, lh_sample: np.ndarray, frames: CameraFrames) -> dict:
        """Snapshot dict for the dashboard from the session's pose sample and the camera frames."""
        from ..geometry import attitude_error, rotvec_to_matrix
        from ..units import RAD2DEG
        from .crosscheck import lh_at

        n = len(frames)
        out = {"frames": n, "solved": frames.status.count("ok") if n else 0}
        if self._est is None:
            if self._thread is None and n and frames.t[-1] - frames.t[0] >= self.align_after_s and len(lh_sample) >= 10:
                cam = frames.arrays()
                self._thread = threading.Thread(target=self._estimate, args=(lh_sample.copy(), cam), daemon=True)
                self._thread.start()
            out["state"] = "estimating clock and alignment" if self._thread is not None else "collecting frames"
            return out
        if self._est[0] == "failed":
            out["state"] = f"cross-check not usable: {self._est[1]}"
            return out
        off, drift, X, Y, vf = self._est
        new = range(self._done, n)
        self._done = n
        ks = [k for k in new if frames.status[k] == "ok"]
        if len(lh_sample) >= 2 and ks:
            # the pose sample to matrices once per update, all new frames in one interpolation
            lh = lh_sample[np.argsort(lh_sample[:, 0])]
            td = (np.array([frames.t[k] for k in ks]) - off) / (1.0 + drift)
            R, a, w, okm = lh_at(lh[:, 0], rotvec_to_matrix(lh[:, 1:4]), lh[:, 7], td)
            for j, k in enumerate(ks):
                if not okm[j]:
                    continue
                d = float(attitude_error(frames.rotation[k], X @ R[j] @ Y))
                p2 = vf * frames.pred_var[k] + w[j] * (a[j] * self.sigma_theta / RAD2DEG) ** 2
                face_on = frames.tilt[k] < np.radians(self.face_on_deg)
                self.last = {"disagreement_deg": np.degrees(d), "predicted_deg": float(np.degrees(np.sqrt(p2))),
                             "face_on": bool(face_on), "mirror_branch": bool(face_on and d * d > 25 * p2)}
                if not face_on:
                    self._sq += d * d
                    self._psq += p2
                    self._n += 1
        out.update(state="tracking", clock_offset_s=off, last=self.last,
                   disagreement_rms_deg=float(np.degrees(np.sqrt(self._sq / self._n))) if self._n else None,
                   predicted_rms_deg=float(np.degrees(np.sqrt(self._psq / self._n))) if self._n else None)
        return out
