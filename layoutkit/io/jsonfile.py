"""JSON values and files: one conversion of numpy values to plain JSON types, one atomic writer.

Used by every room that writes JSON (reports, summaries, sidecars, layouts).
"""
from __future__ import annotations

import json

import numpy as np

__all__ = ["to_jsonable", "write_json"]


def to_jsonable(o):
    """Recursively convert numpy arrays/scalars to lists and Python numbers; inf/NaN → None."""
    if isinstance(o, dict):
        return {str(k): to_jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [to_jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return to_jsonable(o.tolist())
    if isinstance(o, (np.floating, float)):
        v = float(o)
        return v if np.isfinite(v) else None
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    return o


def write_json(path, obj, *, indent: int = 2):
    """Write ``to_jsonable(obj)`` to ``path`` atomically (:func:`layoutkit.io.atomic.atomic_write_text`)."""
    from .atomic import atomic_write_text

    atomic_write_text(path, json.dumps(to_jsonable(obj), indent=indent) + "\n")
    return path
