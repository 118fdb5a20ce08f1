"""Old home of :func:`layoutkit.io.jsonfile.to_jsonable` (kept for imports in flight)."""
from __future__ import annotations

from .io.jsonfile import to_jsonable

__all__ = ["to_jsonable"]
