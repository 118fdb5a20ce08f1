"""Atomic writes of derived files: the whole file or nothing.

``with atomic_write(path) as fh: ...`` writes to a temporary file in the same folder, flushes and
fsyncs it, and renames it over ``path`` only when the block ends without an exception. On any
error (``ENOSPC``, a signal turned into an exception, a bug) the temporary file is removed and
``path`` is left as it was. ``OSError`` keeps its ``filename`` set to the target, so the CLI prints
``error: <path>: No space left on device``.
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

__all__ = ["atomic_write", "atomic_write_text", "atomic_write_bytes"]


@contextlib.contextmanager
def atomic_write(path, mode: str = "w", *, newline=None, encoding: str | None = None):
    """Context manager yielding a file object; ``path`` appears complete or not at all.

    mode : ``"w"`` (text, UTF-8 unless ``encoding``) or ``"wb"``.
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write: mode must be 'w' or 'wb', got {mode!r}")
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
    except OSError as exc:
        if exc.filename is None or exc.filename != str(path):
            exc.filename = str(path)
        raise
    try:
        umask = os.umask(0o022)  # mkstemp makes 0600: give the file the permissions open() would
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)
        if mode == "wb":
            fh = os.fdopen(fd, "wb")
        else:
            fh = os.fdopen(fd, "w", newline=newline, encoding=encoding or "utf-8")
        with fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError):
            exc.filename = str(path)
        raise


def atomic_write_text(path, text: str) -> None:
    """Write ``text`` to ``path`` atomically."""
    with atomic_write(path, "w") as fh:
        fh.write(text)


def atomic_write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_write(path, "wb") as fh:
        fh.write(data)
