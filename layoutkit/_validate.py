"""Small helpers for checks at the public boundary: shapes, finite values, structured files,
fixed-length number lists, unknown keys, plausible sizes (one wording everywhere)."""
from __future__ import annotations

import warnings

import numpy as np

__all__ = ["as_array", "check_finite", "read_structured", "number_list", "unknown_keys", "check_extent",
           "ValidationWarning", "OddSizeWarning", "MIN_PLAUSIBLE_EXTENT_M", "MAX_PLAUSIBLE_EXTENT_M",
           "MAX_PLAUSIBLE_RANGE_M", "check_range"]

#: Smallest / largest plausible extent of a spacecraft (mesh or sensor layout) in metres; outside
#: this the length unit of the file is suspect.
MIN_PLAUSIBLE_EXTENT_M = 0.01
MAX_PLAUSIBLE_EXTENT_M = 100.0
#: Farthest plausible lighthouse-to-target distance in metres (LH2 base stations are specified to
#: ~7-10 m; laser sweeps are useless far beyond): a larger range is read in the wrong unit.
MAX_PLAUSIBLE_RANGE_M = 30.0


class ValidationWarning(UserWarning):
    """Input that is accepted but probably not what was meant (unknown key, missing id)."""


class OddSizeWarning(UserWarning):
    """A size is implausible for a spacecraft in the stated unit (probably the wrong unit). The
    CLI turns it into an error unless ``--allow-odd-size``."""


def number_list(x, name: str, n: int = 3) -> list:
    """``x`` as a list of ``n`` finite floats; ValueError ``"<name>: expected n numbers [x, y, z], got ..."``."""
    want = "[x, y, z]" if n == 3 else f"{n} numbers"
    if isinstance(x, (str, bytes)) or not hasattr(x, "__len__"):
        raise ValueError(f"{name}: expected {n} numbers {want}, got {x!r}")
    if len(x) != n:
        raise ValueError(f"{name}: expected {n} numbers {want}, got {len(x)}: {list(x)!r}")
    try:
        v = [float(c) for c in x]
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected {n} numbers {want}, got {list(x)!r}") from None
    if not all(np.isfinite(v)):
        raise ValueError(f"{name}: NaN or infinite value in {v}")
    return v


def unknown_keys(d: dict, known, where: str) -> list:
    """Warn (:class:`ValidationWarning`) once per key of ``d`` not in ``known`` (a typo, most
    often); keys starting with ``x-`` are the user's own and pass. Returns the unknown keys."""
    bad = [k for k in d if k not in known and not str(k).startswith("x-")]
    for k in bad:
        warnings.warn(ValidationWarning(f"{where}: unknown key {k!r} (kept; known: {', '.join(sorted(known))}; "
                                        "prefix your own keys with 'x-')"), stacklevel=3)
    return bad


def check_extent(extent_m: float, what: str, units: str, lo: float = MIN_PLAUSIBLE_EXTENT_M,
                 hi: float = MAX_PLAUSIBLE_EXTENT_M) -> None:
    """Warn (:class:`OddSizeWarning`) when a spacecraft extent of ``extent_m`` metres (read in
    ``units``) is outside [lo, hi]: the numbers are probably in another unit."""
    if not (lo <= extent_m <= hi):
        side = "smaller" if extent_m < lo else "larger"
        warnings.warn(OddSizeWarning(f"{what} span {extent_m:.4g} m read as {units!r}, {side} than any plausible "
                                     f"spacecraft ({lo:g}-{hi:g} m): the numbers are probably in another unit"),
                      stacklevel=3)


def check_range(range_m: float, what: str, hi: float = MAX_PLAUSIBLE_RANGE_M) -> None:
    """Warn (:class:`OddSizeWarning`) when a lighthouse-to-target distance of ``range_m`` metres is
    farther than any lighthouse reaches: the numbers are probably millimetres."""
    if range_m > hi:
        warnings.warn(OddSizeWarning(f"{what}: {range_m:.4g} m is farther than any lighthouse reaches (<= {hi:g} m): "
                                     f"the numbers are probably millimetres ({range_m / 1000:.4g} m?)"), stacklevel=3)


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
