"""One small helper for shape checks at the public boundary."""
from __future__ import annotations

import numpy as np

__all__ = ["as_array", "check_finite", "read_structured"]


def as_array(x, name: str, shape: tuple, dtype=float) -> np.ndarray:
    """Return ``x`` as an array whose trailing dimensions match ``shape``.

    ``shape`` is a tuple of ints, ``None`` (any size) and at most one leading
    ``...`` (any number of batch dimensions). Raises ``ValueError`` naming the
    expected and the actual shape.
    """
    a = np.asarray(x, dtype=dtype)
    spec = list(shape)
    batch = bool(spec) and spec[0] is Ellipsis
    if batch:
        spec = spec[1:]
    want = "(" + ", ".join("..." if s is Ellipsis else ("*" if s is None else str(s)) for s in shape) + ")"
    if (batch and a.ndim < len(spec)) or (not batch and a.ndim != len(spec)):
        raise ValueError(f"{name}: expected shape {want}, got {a.shape}")
    tail = a.shape[a.ndim - len(spec):] if spec else ()
    for want_n, got_n in zip(spec, tail):
        if want_n is not None and want_n != got_n:
            raise ValueError(f"{name}: expected shape {want}, got {a.shape}")
    return a


def check_finite(a: np.ndarray, name: str) -> np.ndarray:
    """Raise ``ValueError`` if ``a`` holds NaN or inf."""
    if not np.all(np.isfinite(a)):
        bad = int(np.size(a) - np.count_nonzero(np.isfinite(a)))
        raise ValueError(f"{name}: {bad} non-finite value(s) (NaN or inf)")
    return a


def read_structured(path, what: str, fmt: str, parse, errors):
    """Read and parse a text file, turning a missing file or a syntax error into ``ValueError``.

    what : what the file is ("layout", "envelope", ...); fmt : its syntax ("JSON", "TOML", ...);
    parse : text → object; errors : the parser's exception type(s).
    """
    from pathlib import Path

    path = Path(path)
    try:
        return parse(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"{path}: no such {what} file") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not valid {fmt} (a binary file, not text)") from None
    except errors as exc:
        raise ValueError(f"{path}: not valid {fmt} ({exc})") from None
