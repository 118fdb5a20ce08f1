"""Capture files: raw received bytes, a timing index and a sidecar JSON (docs/live-io.md).

A capture ``run.lkcap`` is three files:

- ``run.lkcap``        the raw bytes exactly as received, appended *before* any decoding;
- ``run.lkcap.idx``    one 16-byte record per received chunk: ``<Q d`` = (byte offset of the
  chunk's first byte, host arrival time in seconds since the capture's start);
- ``run.lkcap.json``   the sidecar (:class:`layoutkit.io.sidecar.CaptureSidecar`): layout, station
  set-up, port settings, protocol (+ options), start time (UTC ISO 8601), and at close the byte
  count and end time.
"""
from __future__ import annotations

import os
import struct
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from ..io.sidecar import FORMAT, FORMAT_VERSION, CaptureSidecar, sidecar_path, write_sidecar
from ..io.sidecar import read_sidecar as _read_sidecar
from ..io.stations import station_from_dict, station_to_dict  # re-exported (old import path)

__all__ = [
    "CaptureExists",
    "check_new_capture",
    "CaptureWriter",
    "CaptureReader",
    "sidecar_path",
    "index_path",
    "read_sidecar",
    "station_to_dict",
    "station_from_dict",
    "CaptureSidecar",
    "FORMAT",
    "FORMAT_VERSION",
]

_IDX = struct.Struct("<Qd")
def index_path(path) -> Path:
    """``<capture>.idx``."""
    return Path(str(path) + ".idx")


class CaptureExists(ValueError):
    """A capture (or its index/sidecar) is already at the path: it is never replaced silently."""


def check_new_capture(path) -> None:
    """Raise :class:`CaptureExists` (naming the file and its size) when ``path`` or its
    ``.idx``/``.json`` exists: a capture is never overwritten without ``--overwrite``."""
    path = Path(path)
    for p in (path, index_path(path), sidecar_path(path)):
        if p.exists():
            size = p.stat().st_size if p.is_file() else 0
            what = "a capture" if p == path else "a capture's " + p.suffix + " file"
            raise CaptureExists(f"{p}: {what} already exists ({size:,} bytes); a capture is never overwritten: "
                                "record to a new file, or pass --overwrite to replace it")


class CaptureWriter:
    """Append-only raw capture with a timing index and a sidecar JSON; never overwrites one.

    path : capture file. It must not exist (nor its ``.idx``/``.json``): :class:`CaptureExists`
    (a ValueError naming the file and its size) otherwise, unless ``overwrite=True``. The capture
    is locked (``flock``) while open, so a second writer of the same file is refused instead of
    truncating it under the first one (whose later writes would leave a hole of zero bytes).
    sidecar : :class:`CaptureSidecar` (or its dict) written to ``<path>.json`` at once
    (``start_time_utc`` is added).
    flush_interval : s between fsyncs of the raw bytes and index.
    ``write(data, t=None)`` appends bytes with unbuffered writes (a failed write, e.g. disk full,
    leaves exactly the bytes received so far, in order: a valid prefix; the index only points into
    bytes that are on disk); ``t`` is the arrival time in s since the start (default: host
    monotonic clock since the writer opened). After a failed write ``error`` holds the OSError
    and the writer accepts no more bytes.
    """

    def __init__(self, path, sidecar: dict | None = None, *, flush_interval: float = 0.25,
                 overwrite: bool = False):
        import fcntl

        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.closed = True
        self.error = None
        if not overwrite:
            check_new_capture(self.path)
        flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND | getattr(os, "O_CLOEXEC", 0)
        if not overwrite:
            flags |= os.O_EXCL
        try:
            self._fd = os.open(self.path, flags, 0o644)
        except FileExistsError:  # created between the check and the open
            raise CaptureExists(f"{self.path}: a capture already exists; a capture is never overwritten") from None
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(self._fd)
            raise ValueError(f"{self.path}: the capture is being written by another process; "
                             "not touching it") from None
        if overwrite:
            os.ftruncate(self._fd, 0)  # only once we hold the lock: never under a running writer
        self._idx = os.open(index_path(self.path), os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_APPEND, 0o644)
        self._t0 = time.monotonic()
        self._last_flush = self._t0
        self.flush_interval = float(flush_interval)
        self.bytes_written = 0
        sc = CaptureSidecar.from_dict(sidecar or {})
        if sc.start_time_utc is None:
            sc = sc.updated(start_time_utc=datetime.now(timezone.utc).isoformat())
        self.sidecar = sc
        self.closed = False
        try:
            self._write_sidecar()
        except OSError:
            self._close_fds()
            raise

    def _write_sidecar(self) -> None:
        write_sidecar(self.path, self.sidecar)

    def write(self, data: bytes, t: float | None = None) -> None:
        """Append ``data`` (before decoding) with its arrival time ``t`` (s since start).

        Raises OSError (``filename`` = the capture) when the bytes cannot be written; what was
        written before (and any part of ``data`` the OS took) stays, in order.
        """
        if not data:
            return
        if self.error is not None:
            raise self.error
        now = time.monotonic()
        t = now - self._t0 if t is None else float(t)
        view = memoryview(data)
        start = self.bytes_written
        try:
            while view:
                k = os.write(self._fd, view)
                self.bytes_written += k
                view = view[k:]
        except OSError as exc:
            exc.filename = str(self.path)
            self.error = exc
            raise
        finally:
            if self.bytes_written > start:  # index only what is on disk
                try:
                    os.write(self._idx, _IDX.pack(start, t))
                except OSError:
                    pass  # the index is a timing aid; the raw bytes are the record
        if now - self._last_flush >= self.flush_interval:
            self.flush()
            self._last_flush = now

    def flush(self) -> None:
        """Push the raw bytes and the index to the disk (fsync)."""
        for fd in (self._fd, self._idx):
            try:
                os.fsync(fd)
            except OSError:
                pass

    def _close_fds(self) -> None:
        for fd in (self._fd, self._idx):
            try:
                os.close(fd)
            except OSError:
                pass
        self.closed = True

    def close(self, **extra) -> None:
        """fsync, close, and record ``bytes``, ``end_time_utc`` (and ``extra``) in the sidecar.

        The sidecar update is best effort on a full disk (the raw bytes are the record); raises
        nothing for it, but keeps the OSError in ``sidecar_error``.
        """
        if self.closed:
            return
        self.flush()
        self._close_fds()
        changes = dict(extra, bytes=self.bytes_written, end_time_utc=datetime.now(timezone.utc).isoformat())
        if self.error is not None:
            changes["write_error"] = f"{self.error.strerror or self.error}"
        self.sidecar = self.sidecar.updated(**changes)
        self.sidecar_error = None
        try:
            self._write_sidecar()
        except OSError as exc:
            self.sidecar_error = exc

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def read_sidecar(path) -> dict:
    """The sidecar of a capture as a plain dict (``{}`` when there is none); ValueError on bad JSON.

    Old entry point: new code uses :func:`layoutkit.io.sidecar.read_sidecar` (a :class:`CaptureSidecar`).
    """
    if not sidecar_path(path).exists():
        return {}
    return _read_sidecar(path).to_dict()


class CaptureReader:
    """Replay a capture's bytes; a source with ``read(max_bytes)`` and ``close()``.

    realtime : if True, bytes are released no earlier than their recorded arrival time
        (scaled by ``speed``); otherwise as fast as asked. ``read`` returns ``b""`` at the end.
    ``chunks()`` iterates the recorded (arrival time, bytes) chunks.
    """

    def __init__(self, path, *, realtime: bool = False, speed: float = 1.0):
        self.path = Path(path)
        if not self.path.is_file():
            raise ValueError(f"{self.path}: no such capture file")
        self.sidecar = _read_sidecar(self.path)
        self._fh = open(self.path, "rb")
        self.size = self.path.stat().st_size
        self.realtime = bool(realtime)
        self.speed = float(speed)
        self._index = self._load_index()
        self._t_start = None

    def _load_index(self) -> np.ndarray:
        p = index_path(self.path)
        if not p.exists():
            return np.zeros((0, 2))
        raw = p.read_bytes()
        raw = raw[: len(raw) - len(raw) % _IDX.size]
        rec = np.frombuffer(raw, dtype=[("off", "<u8"), ("t", "<f8")])
        return np.stack([rec["off"].astype(float), rec["t"]], -1) if rec.size else np.zeros((0, 2))

    @property
    def index(self) -> np.ndarray:
        """(C, 2) float: byte offset and arrival time (s) of each recorded chunk."""
        return self._index

    @property
    def eof(self) -> bool:
        return self._fh.tell() >= self.size

    def read(self, max_bytes: int = 65536) -> bytes:
        pos = self._fh.tell()
        n = max(1, int(max_bytes))
        if self.realtime and len(self._index):
            if self._t_start is None:
                self._t_start = time.monotonic() - self._index[0, 1] / self.speed
            # bytes whose arrival time has passed
            now = (time.monotonic() - self._t_start) * self.speed
            k = np.searchsorted(self._index[:, 1], now, side="right")
            limit = int(self._index[k, 0]) if k < len(self._index) else self.size
            if limit <= pos:
                wait = self._index[k, 1] - now if k < len(self._index) else 0.0
                time.sleep(min(max(wait / self.speed, 0.0), 0.1))
                return b""
            n = min(n, limit - pos)
        return self._fh.read(n)

    def chunks(self):
        """Yield ``(t_arrival_s, bytes)`` per recorded chunk (one chunk of everything without index)."""
        with open(self.path, "rb") as fh:
            if not len(self._index):
                yield 0.0, fh.read()
                return
            offs = list(self._index[:, 0].astype(np.int64)) + [self.size]
            for k in range(len(self._index)):
                yield float(self._index[k, 1]), fh.read(int(offs[k + 1] - offs[k]))

    def close(self) -> None:
        self._fh.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
