"""Evidence tied to its capture: the identity of a simulated byte stream, recorded in every file
made with it, and the check that a file given beside a capture belongs to it (issue 29, item 3).

``fake-fpga`` knows the exact bytes it emits, so the files it writes beside them record the
stream's identity, a :class:`StreamTie`:

- ``stream_sha256`` / ``stream_bytes``: SHA-256 and length of the whole byte stream
  (``stream_id`` = its first 16 hex digits, for messages);
- ``head_sha256`` of its first ``head_bytes`` (1024) bytes: a capture that ``live`` recorded from
  the simulator's pty is a prefix of the stream (the simulator starts sending only once its reader
  has opened and flushed the port), so its first bytes identify the run even when the recording
  was stopped early;
- ``seed`` and ``source`` (``"fake-fpga"``), for the messages.

Where it is written (one owner: this module):

- a pose table (``TRUTH.csv``) ends with ONE comment line ``# layoutkit-run {json}``
  (:func:`write_tied_poses`; the pose table reader, :mod:`layoutkit.io.poses`, and
  ``numpy.loadtxt`` skip ``#`` lines; the columns are unchanged);
- the capture sidecar of ``fake-fpga --out`` holds it under the key ``run``
  (:class:`~layoutkit.io.sidecar.CaptureSidecar` keeps unknown keys in ``extra``);
- a camera capture folder's ``camera.json`` under ``extra.run`` (the bench camera of
  ``fake-fpga --camera-out``, and a folder that ``live`` recorded from such a folder).

:func:`check_tie` compares the tie of a file given beside a capture with the capture: the
sidecar's own tie when it has one (exact: the same stream or not), else the capture's bytes
(the whole stream's hash when the lengths agree, else the hash of its first ``head_bytes``).
Another stream → ``ValueError`` naming both files and what differs; a file with no tie (a
motion-capture file, a camera of one's own) or a capture too short to compare → accepted with a
note saying the file was not checked.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

__all__ = ["StreamTie", "HEAD_BYTES", "TIE_PREFIX", "stream_tie", "HeadHash", "tie_line", "write_tied_poses",
           "read_file_tie", "sidecar_tie", "check_tie", "check_tie_head"]

HEAD_BYTES = 1024
#: The comment line that closes a tied pose table.
TIE_PREFIX = "# layoutkit-run "
_TAIL = 1 << 14  # the tie line is the last line: read at most this many bytes from the end


@dataclass(frozen=True)
class StreamTie:
    """The identity of one simulated byte stream (module docstring). Hashes are hex SHA-256."""

    stream_sha256: str
    stream_bytes: int
    head_sha256: str
    head_bytes: int = HEAD_BYTES
    seed: int | None = None
    source: str = "fake-fpga"

    @property
    def stream_id(self) -> str:
        return self.stream_sha256[:16]

    def describe(self) -> str:
        """``stream 3fa2c1d09e1b77aa (fake-fpga --seed 0, 453,600 bytes)``."""
        seed = f" --seed {self.seed}" if self.seed is not None else ""
        return f"stream {self.stream_id} ({self.source}{seed}, {self.stream_bytes:,} bytes)"

    def to_dict(self) -> dict:
        return {"stream_id": self.stream_id, "stream_sha256": self.stream_sha256, "stream_bytes": self.stream_bytes,
                "head_sha256": self.head_sha256, "head_bytes": self.head_bytes, "seed": self.seed,
                "source": self.source}

    @classmethod
    def from_dict(cls, d, where: str) -> "StreamTie":
        """Inverse of :meth:`to_dict`; ``ValueError`` naming ``where`` and the field."""
        if not isinstance(d, dict):
            raise ValueError(f"{where}: expected an object, got {type(d).__name__}")
        for k in ("stream_sha256", "head_sha256"):
            v = d.get(k)
            if not (isinstance(v, str) and len(v) == 64 and all(c in "0123456789abcdef" for c in v)):
                raise ValueError(f"{where}.{k}: expected 64 hex digits, got {v!r}")
        for k in ("stream_bytes", "head_bytes"):
            if not (isinstance(d.get(k), int) and d[k] >= 0):
                raise ValueError(f"{where}.{k}: expected a byte count, got {d.get(k)!r}")
        seed = d.get("seed")
        if seed is not None and not isinstance(seed, int):
            raise ValueError(f"{where}.seed: expected an integer or null, got {seed!r}")
        return cls(d["stream_sha256"], d["stream_bytes"], d["head_sha256"], d["head_bytes"], seed,
                   str(d.get("source") or "fake-fpga"))


class HeadHash:
    """SHA-256 of the first ``n`` bytes of a stream fed in pieces (``update``), and its length."""

    def __init__(self, n: int = HEAD_BYTES):
        self.n = int(n)
        self._h = hashlib.sha256()
        self.bytes = 0

    def update(self, data: bytes) -> None:
        if self.bytes < self.n and data:
            take = data[: self.n - self.bytes]
            self._h.update(take)
            self.bytes += len(take)

    @property
    def complete(self) -> bool:
        return self.bytes >= self.n

    def hexdigest(self) -> str:
        return self._h.hexdigest()


def stream_tie(blocks, *, seed: int | None = None, source: str = "fake-fpga", head_bytes: int = HEAD_BYTES) -> StreamTie:
    """The :class:`StreamTie` of the byte stream ``blocks`` (an iterable of ``bytes``, in order)."""
    full = hashlib.sha256()
    head = HeadHash(head_bytes)
    n = 0
    for b in blocks:
        full.update(b)
        head.update(b)
        n += len(b)
    return StreamTie(full.hexdigest(), n, head.hexdigest(), head.bytes if n < head_bytes else head_bytes, seed, source)


def tie_line(tie: StreamTie) -> str:
    """The closing comment line of a tied pose table (with its newline)."""
    return TIE_PREFIX + json.dumps(tie.to_dict(), sort_keys=True) + "\n"


def write_tied_poses(path, table, tie: StreamTie | None) -> Path:
    """Write the pose table ``table`` (:mod:`layoutkit.io.poses`) atomically, ended by the tie line."""
    from .atomic import atomic_write_text
    from .poses import format_poses, write_poses

    if tie is None:
        return write_poses(path, table)
    atomic_write_text(path, format_poses(table) + tie_line(tie))
    return Path(path)


def _camera_folder_tie(folder: Path) -> StreamTie | None:
    p = folder / "camera.json"
    if not p.is_file():
        return None
    try:
        d = json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        return None  # the camera reader names the broken file itself
    run = (d.get("extra") or {}).get("run") if isinstance(d, dict) else None
    return None if run is None else StreamTie.from_dict(run, f"{p}: extra.run")


def read_file_tie(path) -> StreamTie | None:
    """The tie recorded in ``path``: a pose table's closing ``# layoutkit-run`` line, or a camera
    capture folder's ``camera.json`` ``extra.run``; None when it has none (any other file)."""
    path = Path(path)
    if path.is_dir():
        return _camera_folder_tie(path)
    try:
        with open(path, "rb") as fh:
            fh.seek(0, 2)
            size = fh.tell()
            fh.seek(max(0, size - _TAIL))
            tail = fh.read()
    except OSError:
        return None
    for raw in reversed(tail.splitlines()):
        line = raw.decode("utf-8", "replace").strip()
        if not line:
            continue
        if not line.startswith(TIE_PREFIX.strip()):
            return None  # the tie is the last line or absent
        try:
            d = json.loads(line[len(TIE_PREFIX.strip()):])
        except json.JSONDecodeError:
            raise ValueError(f"{path}: its last line '{TIE_PREFIX.strip()} ...' is not valid JSON") from None
        return StreamTie.from_dict(d, f"{path}: {TIE_PREFIX.strip()}")
    return None


def sidecar_tie(sidecar, capture) -> StreamTie | None:
    """The tie a capture's sidecar records (``fake-fpga --out``), or None (a ``live`` recording)."""
    run = (getattr(sidecar, "extra", None) or {}).get("run")
    return None if run is None else StreamTie.from_dict(run, f"{capture}.json: run")


def _file_sha256(path, limit: int | None = None) -> tuple[str, int]:
    h = hashlib.sha256()
    n = 0
    with open(path, "rb") as fh:
        while limit is None or n < limit:
            b = fh.read(1 << 20 if limit is None else min(1 << 20, limit - n))
            if not b:
                break
            h.update(b)
            n += len(b)
    return h.hexdigest(), n


def _result(option, path, status, message, tie=None) -> dict:
    return {"option": option, "file": str(path), "status": status, "message": message,
            "stream_id": None if tie is None else tie.stream_id}


def _untied(option, path) -> dict:
    return _result(option, path, "untied",
                   f"{path} records no run id: not checked against the capture (accepted as given)")


def check_tie(path, option: str, capture, sidecar) -> dict:
    """Does the file ``path`` (given as ``option``, e.g. ``"--truth"``) belong to ``capture``?

    Returns ``{"option", "file", "status", "message", "stream_id"}`` with status ``"tied"`` (the
    same stream), ``"untied"`` (the file records no run: a note) or ``"unchecked"`` (the capture is
    too short to compare: a note). Raises ``ValueError`` naming both files and what differs when
    the file was made with another stream.
    """
    tie = read_file_tie(path)
    if tie is None:
        return _untied(option, path)
    capture = Path(capture)
    other = "if the file does belong to this capture, delete its tie" + (
        " (camera.json extra.run)" if Path(path).is_dir() else f" (its last line, '{TIE_PREFIX.strip()} ...')")
    own = sidecar_tie(sidecar, capture)
    if own is not None:
        if own.stream_sha256 == tie.stream_sha256:
            return _result(option, path, "tied", f"{path} belongs to {capture} ({tie.describe()})", tie)
        raise ValueError(f"{option} {path}: belongs to another run: it was made with {tie.describe()}, the capture "
                         f"{capture} is {own.describe()}")
    size = capture.stat().st_size
    if size == tie.stream_bytes:
        digest, _ = _file_sha256(capture)
        if digest == tie.stream_sha256:
            return _result(option, path, "tied", f"{path} belongs to {capture} (the whole {tie.describe()})", tie)
    elif size >= tie.head_bytes and tie.head_bytes > 0:
        digest, _ = _file_sha256(capture, tie.head_bytes)
        if digest == tie.head_sha256:
            return _result(option, path, "tied", f"{path} belongs to {capture} (its first {tie.head_bytes} bytes are "
                                                 f"those of {tie.describe()})", tie)
    else:
        return _result(option, path, "unchecked", f"{path} was made with {tie.describe()}; the capture {capture} "
                                                  f"holds only {size} bytes, too few to compare: not checked", tie)
    what = ("its bytes differ" if size == tie.stream_bytes else f"its first {tie.head_bytes} bytes differ")
    raise ValueError(f"{option} {path}: belongs to another run: it was made with {tie.describe()}; the capture "
                     f"{capture} ({size:,} bytes) is not that stream: {what} (sha256 {digest[:16]} vs "
                     f"{(tie.stream_sha256 if size == tie.stream_bytes else tie.head_sha256)[:16]}); {other}")


def check_tie_head(path, option: str, head: HeadHash, port: str) -> dict:
    """:func:`check_tie` for a live run: the first bytes received from ``port`` (``head``)
    against the tie of ``path``. Never raises on a mismatch (the run has happened): the result's
    status is ``"other_run"`` and its message says what differs."""
    tie = read_file_tie(path)
    if tie is None:
        return _untied(option, path)
    if head.bytes < tie.head_bytes:
        return _result(option, path, "unchecked", f"{path} was made with {tie.describe()}; only {head.bytes} bytes "
                                                  f"arrived from {port}, too few to compare: not checked", tie)
    if head.n != tie.head_bytes:
        return _result(option, path, "unchecked", f"{path}: its tie hashes {tie.head_bytes} bytes, not {head.n}: "
                                                  "not checked", tie)
    if head.hexdigest() == tie.head_sha256:
        return _result(option, path, "tied", f"{path} belongs to this run (the first {tie.head_bytes} bytes from "
                                             f"{port} are those of {tie.describe()})", tie)
    return _result(option, path, "other_run",
                   f"{option} {path} belongs to another run: it was made with {tie.describe()}, but the first "
                   f"{tie.head_bytes} bytes from {port} are not that stream's — its comparison with this run is "
                   "meaningless (the simulator started with another --seed or settings?)", tie)


def check_ties(capture, sidecar, files: dict, soft=()) -> list[dict]:
    """:func:`check_tie` for each ``{option: path}`` of ``files`` (None paths skipped), before a
    replay: the first file of another run raises ``ValueError`` — except for the options in
    ``soft`` (a file found beside the capture rather than given), whose result is then status
    ``"other_run"`` with the refusal as its message. Returns the results."""
    out = []
    for opt, p in files.items():
        if p is None:
            continue
        try:
            out.append(check_tie(p, opt, capture, sidecar))
        except ValueError as exc:
            if opt not in soft:
                raise
            out.append(_result(opt, p, "other_run", str(exc)))
    return out


def check_ties_head(head: HeadHash, port: str, files: dict) -> list[dict]:
    """:func:`check_tie_head` for each ``{option: path}`` of ``files`` (None paths skipped), after
    a live run; never raises on a mismatch (status ``"other_run"``)."""
    return [check_tie_head(p, opt, head, port) for opt, p in files.items() if p is not None]
