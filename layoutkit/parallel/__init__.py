"""Running many independent tasks on Dask: the scheduler choice, chunked Monte-Carlo plumbing and
mergeable streaming statistics.

- :mod:`.scheduler` — :func:`open_executor`: a ``distributed.LocalCluster`` sized to the machine
  (default), a cluster by address (``tcp://host:8786``), or ``"synchronous"`` (in-process, for
  debugging). One small executor interface (``submit``, ``as_completed``, ``running``) for all three.
- :mod:`.chunks` — :func:`chunk_plan` (frame ranges with ``SeedSequence.spawn`` seeds, so results do
  not depend on how many workers run them) and :func:`map_reduce_ordered` (bounded in-flight tasks,
  merge in chunk order: bit-identical totals for any worker count).
- :mod:`.sketch` — :class:`Moments` and :class:`LogHistogram` (fixed log-spaced bins, exact integer
  merge, percentiles to a stated relative resolution).

Importing this package imports numpy only; dask/distributed are imported when an executor opens.
"""
from __future__ import annotations

from .chunks import Chunk, chunk_plan, map_reduce_ordered
from .scheduler import SYNCHRONOUS, open_executor
from .sketch import LogHistogram, Moments

__all__ = ["Chunk", "chunk_plan", "map_reduce_ordered", "SYNCHRONOUS", "open_executor", "LogHistogram",
           "Moments"]
