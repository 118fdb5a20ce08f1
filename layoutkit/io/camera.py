"""The camera capture folder: raw camera frames plus a time index (one owner of the format).

Layout of a folder ``DIR`` (written by ``layoutkit live --camera-device ... --record CAP`` into
``CAP.camera/``, and by ``layoutkit fake-fpga --camera-out DIR``):

- ``DIR/frames/NNNNNN.<ext>``: one file per received frame, written **before** it is solved. For
  an image-folder source the file's bytes are copied unchanged (a corrupt file stays corrupt);
  for a device, stream or video source each decoded frame is stored as lossless PNG.
- ``DIR/index.csv``: one row per received frame, appended and flushed as it arrives:
  ``frame`` (int, 0-based), ``t_s`` (s, the camera clock: the host's monotonic clock at grab
  time in a live session, the simulated camera clock for fake-fpga), ``file`` (relative to
  ``DIR``), ``t_source_s`` (the source's own time stamp: video position, image-folder time, or
  empty).
- ``DIR/camera.json``: :class:`CameraMeta` — intrinsics, source description and, for
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

__all__ = ["CameraMeta", "CameraIndex", "CameraIndexWriter", "read_camera_index", "read_camera_meta",
           "write_camera_meta", "INDEX_NAME", "META_NAME", "FRAMES_DIR"]

INDEX_NAME = "index.csv"
META_NAME = "camera.json"
FRAMES_DIR = "frames"
INDEX_HEADER = ["frame", "t_s", "file", "t_source_s"]
FORMAT = "layoutkit-camera"


@dataclass(frozen=True)
class CameraMeta:
    """What ``camera.json`` holds.

    focal_length_px : float or None. principal_point_px : (cx, cy) or None (image centre).
    width, height : px or None. source : text (device index, URL, path, "fake-fpga").
    clock : what ``t_s`` is ("host-monotonic", "simulated"). aspect_ratio : face L/W if known.
    truth : simulator truth or None: ``clock_offset_s``, ``clock_drift``, ``camera_from_lighthouse_rotvec``,
    ``face_from_body_rotvec`` ... (see :mod:`layoutkit.live.camera_sim`).
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

    def to_dict(self) -> dict:
        d = asdict(self)
        d["format"] = FORMAT
        d["version"] = 1
        return d

    @classmethod
    def from_dict(cls, d: dict, path="camera.json") -> "CameraMeta":
        if not isinstance(d, dict):
            raise ValueError(f"{path}: expected a JSON object")
        d = dict(d)
        fmt = d.pop("format", FORMAT)
        d.pop("version", None)
        if fmt != FORMAT:
            raise ValueError(f"{path}: format: expected {FORMAT!r}, got {fmt!r}")
        known = {f for f in cls.__dataclass_fields__}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"{path}: unknown key(s) {', '.join(unknown)}")
        pp = d.get("principal_point_px")
        if pp is not None:
            d["principal_point_px"] = tuple(float(v) for v in pp)
        return cls(**d)


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
