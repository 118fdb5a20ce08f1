"""Camera files, one owner: the camera model (intrinsics + lens distortion) and the camera capture
folder (raw camera frames plus a time index).

**Camera model** (:class:`CameraModel`, :func:`read_camera_model`, :func:`write_camera_model`):
OpenCV's camera matrix ``K (3, 3)`` (px) and distortion vector ``(k1, k2, p1, p2[, k3[, k4, k5,
k6[, s1, s2, s3, s4[, tx, ty]]]])`` (4, 5, 8, 12 or 14 values: radial, tangential, rational and
thin-prism terms, tilt), the image size and, from a calibration, the parameters' standard
deviations and the RMS reprojection error. Files:

- OpenCV YAML / XML (``.yml``, ``.yaml``, ``.xml``) through ``cv2.FileStorage``, as OpenCV's
  calibration sample writes them (``camera_matrix``, ``distortion_coefficients``, ``image_width``,
  ``image_height``; also accepted on reading: ``cameraMatrix``/``K`` and
  ``dist_coeffs``/``distCoeffs``/``D``, and the ROS ``{rows, cols, data}`` maps). ``layoutkit camera
  calibrate`` adds ``intrinsics_std_dev`` (18 values in OpenCV's order fx, fy, cx, cy, k1, k2, p1,
  p2, k3, k4, k5, k6, s1, s2, s3, s4, tx, ty), ``intrinsics_covariance`` (the full p x p
  covariance of fx, fy, cx, cy and the distortion terms), ``avg_reprojection_error`` and
  ``per_view_reprojection_errors``.
- our JSON (``.json``): ``{"format": "layoutkit-camera-model", "version": 1, "camera_matrix":
  [[...], [...], [...]], "distortion": [...], "image_size": [w, h], "std_dev": [...],
  "covariance": [[...]], "rms_px": ..., "source": ...}``; unknown keys are rejected.


**Capture folder**. Layout of a folder ``DIR`` (written by ``layoutkit live --camera-device ... --record CAP`` into
``CAP.camera/``, and by ``layoutkit fake-fpga --camera-out DIR``):

- ``DIR/frames/NNNNNN.<ext>``: one file per received frame, written **before** it is solved. For
  an image-folder source the file's bytes are copied unchanged (a corrupt file stays corrupt);
  for a device, stream or video source each decoded frame is stored as lossless PNG.
- ``DIR/index.csv``: one row per received frame, appended and flushed as it arrives:
  ``frame`` (int, 0-based), ``t_s`` (s, the camera clock: the host's monotonic clock at grab
  time in a live session, the simulated camera clock for fake-fpga), ``file`` (relative to
  ``DIR``), ``t_source_s`` (the source's own time stamp: video position, image-folder time, or
  empty).
- ``DIR/camera.json``: :class:`CameraMeta` — intrinsics (with the lens distortion and the camera
  model file it came from, version 2), source description and, for
  simulated streams, the truth (clock offset and drift, camera ← lighthouse rotation, face ←
  body rotation) so that estimates can be checked.

A folder is never overwritten: :class:`CameraIndexWriter` refuses a folder that already holds an
index. Reading tolerates a last row cut short (a session ended mid-write): it is dropped and
counted.
"""
from __future__ import annotations

import csv
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from .atomic import atomic_write_text

__all__ = ["CameraModel", "read_camera_model", "write_camera_model", "CAMERA_MODEL_SUFFIXES",
           "DISTORTION_LENGTHS", "STD_DEV_NAMES", "CameraMeta", "CameraIndex", "CameraIndexWriter", "read_camera_index", "read_camera_meta",
           "write_camera_meta", "INDEX_NAME", "META_NAME", "FRAMES_DIR"]

INDEX_NAME = "index.csv"
META_NAME = "camera.json"
FRAMES_DIR = "frames"
INDEX_HEADER = ["frame", "t_s", "file", "t_source_s"]
FORMAT = "layoutkit-camera"
MODEL_FORMAT = "layoutkit-camera-model"

#: Lengths OpenCV accepts for a distortion vector (0 = none).
DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)
#: Order of ``CameraModel.std_dev`` (OpenCV's ``stdDeviationsIntrinsics``).
STD_DEV_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6",
                 "s1", "s2", "s3", "s4", "tx", "ty")
#: File suffixes of a camera model: OpenCV FileStorage (YAML/XML) or our JSON.
CAMERA_MODEL_SUFFIXES = (".yml", ".yaml", ".xml", ".json")
_MATRIX_KEYS = ("camera_matrix", "cameraMatrix", "K")
_DIST_KEYS = ("distortion_coefficients", "dist_coeffs", "distCoeffs", "D")


def _readonly(a) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class CameraModel:
    """A camera: OpenCV matrix + distortion vector (pixels, pixel centres at integer coordinates).

    matrix : (3, 3) ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` px. distortion : (n,) n in
    :data:`DISTORTION_LENGTHS`, OpenCV's order (k1, k2, p1, p2, k3, k4, k5, k6, s1..s4, tx, ty).
    image_size : (width, height) px or None. std_dev : (18,) standard deviations in
    :data:`STD_DEV_NAMES` order (NaN where not estimated) or None. rms_px : RMS reprojection error
    of the calibration (px) or None. source : where it came from (a file path, "calibrate", ...).
    covariance : (p, p) px²/unit² of (fx, fy, cx, cy, distortion...) with p = 4 + len(distortion),
    the calibration's full covariance (correlations included), or None.
    Validated on construction (``ValueError`` naming the field).
    """

    matrix: np.ndarray
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(0))
    image_size: tuple | None = None
    std_dev: np.ndarray | None = None
    rms_px: float | None = None
    source: str = ""
    covariance: np.ndarray | None = None

    def __post_init__(self):
        where = self.source or "camera model"
        K = np.asarray(self.matrix, dtype=float)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise ValueError(f"{where}: camera_matrix: expected a finite 3 x 3 matrix, got {np.asarray(self.matrix).tolist()!r}")
        if not (K[0, 0] > 0 and K[1, 1] > 0) or not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0:
            raise ValueError(f"{where}: camera_matrix: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, "
                             f"got {K.tolist()}")
        D = np.asarray(self.distortion, dtype=float).ravel()
        if D.size not in DISTORTION_LENGTHS or not np.all(np.isfinite(D)):
            raise ValueError(f"{where}: distortion: expected {', '.join(map(str, DISTORTION_LENGTHS[1:]))} finite "
                             f"numbers (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]]) or none, got {D.tolist()}")
        object.__setattr__(self, "matrix", _readonly(K))
        object.__setattr__(self, "distortion", _readonly(D))
        if self.image_size is not None:
            try:
                w, h = (int(v) for v in self.image_size)
            except (TypeError, ValueError):
                raise ValueError(f"{where}: image_size: expected [width, height] px, got {self.image_size!r}") from None
            if w <= 0 or h <= 0:
                raise ValueError(f"{where}: image_size: expected positive [width, height] px, got {[w, h]}")
            object.__setattr__(self, "image_size", (w, h))
        if self.std_dev is not None:
            sd = np.asarray(self.std_dev, dtype=float).ravel()
            if sd.size > len(STD_DEV_NAMES):
                raise ValueError(f"{where}: std_dev: expected at most {len(STD_DEV_NAMES)} values "
                                 f"({' '.join(STD_DEV_NAMES)}), got {sd.size}")
            sd = np.concatenate([sd, np.full(len(STD_DEV_NAMES) - sd.size, np.nan)])
            if np.any(sd[np.isfinite(sd)] < 0):
                raise ValueError(f"{where}: std_dev: standard deviations must be >= 0, got {sd.tolist()}")
            object.__setattr__(self, "std_dev", _readonly(sd))
        if self.rms_px is not None:
            object.__setattr__(self, "rms_px", float(self.rms_px))
        if self.covariance is not None:
            C = np.asarray(self.covariance, dtype=float)
            p = 4 + D.size
            if C.ndim == 1 and C.size == p * p:
                C = C.reshape(p, p)
            if C.shape != (p, p) or not np.all(np.isfinite(C)) or not np.allclose(C, C.T, rtol=1e-6, atol=0):
                raise ValueError(f"{where}: covariance: expected a finite symmetric {p} x {p} matrix of (fx, fy, cx, cy"
                                 f"{', ' + ', '.join(STD_DEV_NAMES[4:p]) if p > 4 else ''}), got shape {C.shape}")
            object.__setattr__(self, "covariance", _readonly(C))

    # -- views ------------------------------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self.matrix[0, 0])

    @property
    def fy(self) -> float:
        return float(self.matrix[1, 1])

    @property
    def principal_point_px(self) -> tuple:
        """(cx, cy) px."""
        return float(self.matrix[0, 2]), float(self.matrix[1, 2])

    @property
    def focal_length_px(self) -> float:
        """The square-pixel focal length of the ideal (undistorted) camera: ``(fx + fy) / 2`` px."""
        return 0.5 * (self.fx + self.fy)

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.distortion != 0))

    @classmethod
    def pinhole(cls, focal_length_px: float, principal_point_px, image_size=None, distortion=(), source: str = ""):
        """Square-pixel camera ``K = [[f, 0, cx], [0, f, cy], [0, 0, 1]]`` (optionally with distortion)."""
        cx, cy = (float(v) for v in principal_point_px)
        f = float(focal_length_px)
        return cls(np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]]), np.asarray(distortion, float),
                   image_size, source=source)

    def std_dev_dict(self) -> dict:
        """Standard deviations by name (only the estimated ones)."""
        if self.std_dev is None:
            return {}
        return {n: float(v) for n, v in zip(STD_DEV_NAMES, self.std_dev) if np.isfinite(v)}

    def to_dict(self) -> dict:
        """Our JSON form (see module docstring)."""
        return {"format": MODEL_FORMAT, "version": 1, "camera_matrix": self.matrix.tolist(),
                "distortion": self.distortion.tolist(),
                "image_size": None if self.image_size is None else list(self.image_size),
                "std_dev": None if self.std_dev is None else [None if not np.isfinite(v) else float(v)
                                                               for v in self.std_dev],
                "rms_px": self.rms_px, "source": self.source,
                "covariance": None if self.covariance is None else self.covariance.tolist()}

    @classmethod
    def from_dict(cls, d: dict, path="camera model") -> "CameraModel":
        if not isinstance(d, dict):
            raise ValueError(f"{path}: expected a JSON object")
        d = dict(d)
        fmt = d.pop("format", None)
        if fmt != MODEL_FORMAT:
            raise ValueError(f"{path}: format: expected {MODEL_FORMAT!r}, got {fmt!r}")
        version = d.pop("version", 1)
        if version != 1:
            raise ValueError(f"{path}: version: expected 1, got {version!r}")
        known = {"camera_matrix", "distortion", "image_size", "std_dev", "rms_px", "source", "covariance"}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"{path}: unknown key(s) {', '.join(unknown)} (known: {', '.join(sorted(known))})")
        if "camera_matrix" not in d:
            raise ValueError(f"{path}: camera_matrix: missing")
        sd = d.get("std_dev")
        try:
            K = np.array(d["camera_matrix"], dtype=float)
            D = np.array(d.get("distortion") or [], dtype=float)
            sd = None if sd is None else np.array([np.nan if v is None else v for v in sd], dtype=float)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: camera_matrix / distortion / std_dev: not numbers ({exc})") from None
        cov = d.get("covariance")
        try:
            cov = None if cov is None else np.array(cov, dtype=float)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: covariance: not numbers ({exc})") from None
        return cls(K, D, d.get("image_size"), sd, d.get("rms_px"), str(d.get("source") or path), cov)


def _fs_node_array(fs, keys, path, required: bool):
    """First of ``keys`` present in a ``cv2.FileStorage`` → float array (matrices and ROS maps)."""
    for k in keys:
        node = fs.getNode(k)
        if node.empty():
            continue
        if node.isMap():  # ROS camera_info YAML: {rows, cols, data: [...]}
            data = node.getNode("data")
            vals = [data.at(i).real() for i in range(data.size())] if data.isSeq() else None
            if vals is None:
                raise ValueError(f"{path}: {k}: a map without a 'data' list")
            return k, np.array(vals, float)
        if node.isSeq():
            return k, np.array([node.at(i).real() for i in range(node.size())], float)
        m = node.mat()
        if m is None:
            raise ValueError(f"{path}: {k}: not a matrix")
        return k, np.asarray(m, float).ravel()
    if required:
        raise ValueError(f"{path}: camera matrix: none of the keys {', '.join(keys)} found")
    return None, None


def _fs_number(fs, key):
    node = fs.getNode(key)
    return None if node.empty() else node.real()


def read_camera_model(path) -> CameraModel:
    """Read a camera model file (OpenCV YAML/XML or our JSON; module docstring).

    ``ValueError`` naming the file and the field on a missing key, a wrong shape, an unreadable file.
    """
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{p}: no such camera model file")
    suffix = p.suffix.lower()
    if suffix == ".json":
        try:
            d = json.loads(p.read_text())
        except (OSError, ValueError) as exc:
            raise ValueError(f"{p}: not readable JSON ({exc})") from None
        return CameraModel.from_dict(d, p)
    if suffix not in CAMERA_MODEL_SUFFIXES:
        raise ValueError(f"{p}: unknown camera model format {suffix!r} (expected {', '.join(CAMERA_MODEL_SUFFIXES)})")
    import cv2

    try:
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # a parse error; the binding sometimes wraps it in SystemError
        cause = exc.__cause__ or exc.__context__ or exc
        msg = str(cause).strip().splitlines()[-1] if str(cause).strip() else "parse error"
        raise ValueError(f"{p}: not an OpenCV YAML/XML file ({msg})") from None
    if not fs.isOpened():
        raise ValueError(f"{p}: not an OpenCV YAML/XML file")
    try:
        _, k = _fs_node_array(fs, _MATRIX_KEYS, p, True)
        if k.size != 9:
            raise ValueError(f"{p}: camera_matrix: expected 9 values (3 x 3), got {k.size}")
        _, dist = _fs_node_array(fs, _DIST_KEYS, p, False)
        w, h = _fs_number(fs, "image_width"), _fs_number(fs, "image_height")
        _, sd = _fs_node_array(fs, ("intrinsics_std_dev",), p, False)
        _, cov = _fs_node_array(fs, ("intrinsics_covariance",), p, False)
        rms = _fs_number(fs, "avg_reprojection_error")
    finally:
        fs.release()
    size = (int(w), int(h)) if w is not None and h is not None else None
    return CameraModel(k.reshape(3, 3), np.zeros(0) if dist is None else dist, size, sd, rms, str(p), cov)


def write_camera_model(path, model: CameraModel, *, per_view_rms_px=None) -> Path:
    """Write ``model`` atomically as OpenCV YAML/XML (by suffix) or our JSON; returns the path.

    per_view_rms_px : optional (n,) per-image RMS of a calibration, stored as
    ``per_view_reprojection_errors`` (YAML/XML) like OpenCV's sample.
    """
    import os
    import tempfile

    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in CAMERA_MODEL_SUFFIXES:
        raise ValueError(f"{p}: unknown camera model format {suffix!r} (expected {', '.join(CAMERA_MODEL_SUFFIXES)})")
    if suffix == ".json":
        d = model.to_dict()
        atomic_write_text(p, json.dumps(d, indent=2) + "\n")
        return p
    import cv2

    folder = p.parent if str(p.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{p.stem}.", suffix=suffix, dir=folder)
    os.close(fd)
    try:
        fs = cv2.FileStorage(tmp, cv2.FILE_STORAGE_WRITE)
        if model.image_size is not None:
            fs.write("image_width", int(model.image_size[0]))
            fs.write("image_height", int(model.image_size[1]))
        fs.write("camera_matrix", np.asarray(model.matrix, float))
        fs.write("distortion_coefficients", np.asarray(model.distortion, float).reshape(-1, 1))
        if model.std_dev is not None:
            fs.write("intrinsics_std_dev", np.nan_to_num(np.asarray(model.std_dev, float), nan=0.0).reshape(-1, 1))
        if model.covariance is not None:
            fs.write("intrinsics_covariance", np.asarray(model.covariance, float))
        if model.rms_px is not None:
            fs.write("avg_reprojection_error", float(model.rms_px))
        if per_view_rms_px is not None:
            fs.write("per_view_reprojection_errors", np.asarray(per_view_rms_px, float).reshape(-1, 1))
        fs.release()
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, p)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return p


@dataclass(frozen=True)
class CameraMeta:
    """What ``camera.json`` holds.

    focal_length_px : float or None. principal_point_px : (cx, cy) or None (image centre).
    width, height : px or None. source : text (device index, URL, path, "fake-fpga").
    clock : what ``t_s`` is ("host-monotonic", "simulated"). aspect_ratio : face L/W if known.
    truth : simulator truth or None: ``clock_offset_s``, ``clock_drift``, ``camera_from_lighthouse_rotvec``,
    ``face_from_body_rotvec`` ... (see :mod:`layoutkit.live.camera_sim`).
    camera_matrix : (3, 3) nested list px or None; distortion : OpenCV distortion vector or None
    (version 2: the camera model the frames were solved with); camera_file : the camera model
    file it was read from, or None. :meth:`camera_model` gives the :class:`CameraModel`.
    """

    focal_length_px: float | None = None
    principal_point_px: tuple | None = None
    width: int | None = None
    height: int | None = None
    source: str = ""
    clock: str = "host-monotonic"
    aspect_ratio: float | None = None
    truth: dict | None = None
    extra: dict = field(default_factory=dict)
    camera_matrix: list | None = None
    distortion: list | None = None
    camera_file: str | None = None

    @classmethod
    def from_model(cls, model: CameraModel, **kw) -> "CameraMeta":
        """Meta recording a camera model (matrix, distortion, size, file)."""
        w, h = model.image_size if model.image_size is not None else (None, None)
        kw.setdefault("width", w)
        kw.setdefault("height", h)
        return cls(focal_length_px=model.focal_length_px, principal_point_px=model.principal_point_px,
                   camera_matrix=model.matrix.tolist(), distortion=model.distortion.tolist(),
                   camera_file=model.source or None, **kw)

    def camera_model(self) -> CameraModel | None:
        """The camera model recorded here: the full matrix + distortion (version 2), else a pinhole
        from ``focal_length_px`` / ``principal_point_px`` (principal point needs the image size when
        absent); None when the focal length is unknown."""
        size = (self.width, self.height) if self.width and self.height else None
        if self.camera_matrix is not None:
            return CameraModel(np.array(self.camera_matrix, float), np.array(self.distortion or [], float), size,
                               source=self.camera_file or "camera.json")
        if self.focal_length_px is None:
            return None
        pp = self.principal_point_px
        if pp is None:
            if size is None:
                return None
            pp = ((size[0] - 1) / 2, (size[1] - 1) / 2)
        return CameraModel.pinhole(self.focal_length_px, pp, size, source="camera.json")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["format"] = FORMAT
        d["version"] = 2
        return d

    @classmethod
    def from_dict(cls, d: dict, path="camera.json") -> "CameraMeta":
        if not isinstance(d, dict):
            raise ValueError(f"{path}: expected a JSON object")
        d = dict(d)
        fmt = d.pop("format", FORMAT)
        version = d.pop("version", 1)
        if fmt != FORMAT:
            raise ValueError(f"{path}: format: expected {FORMAT!r}, got {fmt!r}")
        if version not in (1, 2):
            raise ValueError(f"{path}: version: expected 1 or 2, got {version!r}")
        known = {f for f in cls.__dataclass_fields__}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"{path}: unknown key(s) {', '.join(unknown)}")
        pp = d.get("principal_point_px")
        if pp is not None:
            d["principal_point_px"] = tuple(float(v) for v in pp)
        meta = cls(**d)
        if meta.camera_matrix is not None:
            meta.camera_model()  # validate the recorded model here, naming the file
        return meta


def write_camera_meta(folder, meta: CameraMeta) -> Path:
    """Write ``folder/camera.json`` atomically."""
    p = Path(folder) / META_NAME
    atomic_write_text(p, json.dumps(meta.to_dict(), indent=2) + "\n")
    return p


def read_camera_meta(folder) -> CameraMeta:
    """``folder/camera.json`` → :class:`CameraMeta` (defaults when the file is absent)."""
    p = Path(folder) / META_NAME
    if not p.is_file():
        return CameraMeta(source=str(folder))
    try:
        d = json.loads(p.read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{p}: not readable JSON ({exc})") from None
    return CameraMeta.from_dict(d, p)


@dataclass(frozen=True)
class CameraIndex:
    """A read index: ``frame (F,) int``, ``t (F,) s``, ``files`` (F paths), ``t_source (F,)`` (NaN = none),
    ``dropped_rows`` (rows cut short or unreadable, skipped), ``folder``."""

    frame: np.ndarray
    t: np.ndarray
    files: tuple
    t_source: np.ndarray
    dropped_rows: int
    folder: Path

    def __len__(self) -> int:
        return len(self.t)


def read_camera_index(folder) -> CameraIndex:
    """Read ``folder/index.csv``; ``ValueError`` naming the file when it is missing or has the wrong header."""
    folder = Path(folder)
    p = folder / INDEX_NAME
    if not p.is_file():
        raise ValueError(f"{p}: no camera index (expected a folder written by live --record or fake-fpga --camera-out)")
    frames, ts, files, tsrc = [], [], [], []
    dropped = 0
    with open(p, newline="") as fh:
        rd = csv.reader(fh)
        head = next(rd, None)
        if head is None or [h.strip() for h in head[:4]] != INDEX_HEADER:
            raise ValueError(f"{p}: header: expected {','.join(INDEX_HEADER)}, got {','.join(head or [])}")
        for row in rd:
            try:
                f, t, name = int(row[0]), float(row[1]), row[2]
                s = float(row[3]) if len(row) > 3 and row[3].strip() else float("nan")
            except (ValueError, IndexError):
                dropped += 1
                continue
            if not np.isfinite(t) or not name:
                dropped += 1
                continue
            frames.append(f)
            ts.append(t)
            files.append(folder / name)
            tsrc.append(s)
    return CameraIndex(np.array(frames, int), np.array(ts, float), tuple(files), np.array(tsrc, float), dropped, folder)


class CameraIndexWriter:
    """Append frames to a camera capture folder: raw file first, then its index row (flushed).

    Refuses a folder whose index already exists (a capture is never overwritten).
    """

    def __init__(self, folder, meta: CameraMeta | None = None):
        self.folder = Path(folder)
        idx = self.folder / INDEX_NAME
        if idx.exists():
            raise FileExistsError(f"{idx}: a camera capture is already there; choose another folder "
                                  "(captures are never overwritten)")
        (self.folder / FRAMES_DIR).mkdir(parents=True, exist_ok=True)
        if meta is not None:
            write_camera_meta(self.folder, meta)
        self._fh = open(idx, "x", newline="")
        self._fh.write(",".join(INDEX_HEADER) + "\n")
        self._fh.flush()
        self.count = 0
        self.bytes = 0

    def add_bytes(self, data: bytes, t_s: float, suffix: str = ".png", t_source_s: float | None = None) -> Path:
        """Store one frame's file bytes as they are, then index it. Returns the file path."""
        name = f"{FRAMES_DIR}/{self.count:06d}{suffix}"
        p = self.folder / name
        with open(p, "xb") as fh:
            fh.write(data)
        self.bytes += len(data)
        src = "" if t_source_s is None or not np.isfinite(t_source_s) else f"{t_source_s:.6f}"
        self._fh.write(f"{self.count},{t_s:.6f},{name},{src}\n")
        self._fh.flush()
        self.count += 1
        return p

    def add_image(self, image: np.ndarray, t_s: float, t_source_s: float | None = None) -> Path:
        """Store a decoded frame as lossless PNG, then index it."""
        import cv2

        ok, buf = cv2.imencode(".png", image)
        if not ok:
            raise ValueError("camera frame: could not be encoded as PNG")
        return self.add_bytes(buf.tobytes(), t_s, ".png", t_source_s)

    def close(self) -> None:
        if self._fh is not None and not self._fh.closed:
            self._fh.flush()
            import os

            os.fsync(self._fh.fileno())
            self._fh.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
