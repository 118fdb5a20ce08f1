"""One conversion of numpy values to plain JSON types, used by every room that writes JSON."""
from __future__ import annotations

import numpy as np

__all__ = ["to_jsonable"]


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
