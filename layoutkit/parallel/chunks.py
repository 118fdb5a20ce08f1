"""Chunked Monte-Carlo: frame ranges with their own seeds, and an order-preserving streaming reduce.

Reproducibility: chunk ``i`` always draws from ``SeedSequence(seed).spawn(n)[i]``, whatever worker
runs it, and partial results are merged in chunk order (a re-order buffer holds the few that finish
early), so floating-point totals are bit-identical for 1, 2 or 100 workers. They do depend on the
chunk size (a different split is a different random stream): it is part of the configuration.

Memory: at most ``max_in_flight`` chunks are submitted at a time and each returns a small summary,
so the client holds O(max_in_flight) summaries and each worker O(chunk size) frames.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Iterable

import numpy as np

__all__ = ["Chunk", "chunk_plan", "map_reduce_ordered"]


@dataclass(frozen=True)
class Chunk:
    """Frames ``[start, start + count)`` of a run, drawn from ``seed`` (a spawned SeedSequence)."""

    index: int
    start: int
    count: int
    seed: np.random.SeedSequence

    def rng(self) -> np.random.Generator:
        return np.random.default_rng(self.seed)


def chunk_plan(total: int, chunk_size: int, seed) -> list[Chunk]:
    """Split ``total`` frames into chunks of ``chunk_size`` (the last may be shorter).

    seed : int or ``SeedSequence``; chunk ``i`` gets ``SeedSequence(seed).spawn(n)[i]``.
    """
    total, chunk_size = int(total), int(chunk_size)
    if total < 0:
        raise ValueError(f"frames: expected >= 0, got {total}")
    if chunk_size < 1:
        raise ValueError(f"chunk_size: expected >= 1, got {chunk_size}")
    n = math.ceil(total / chunk_size)
    ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(int(seed))
    kids = ss.spawn(n)
    return [Chunk(i, i * chunk_size, min(chunk_size, total - i * chunk_size), kids[i]) for i in range(n)]


def map_reduce_ordered(executor, fn: Callable, items: Iterable, merge: Callable[[Any, Any], Any], init: Any, *,
                       shared_args: tuple = (), max_in_flight: int | None = None,
                       progress: Callable[[Any, Any], None] | None = None, key: str = "chunk"):
    """``merge(...merge(merge(init, fn(*shared, items[0])), fn(*shared, items[1]))...)`` on ``executor``.

    Tasks run anywhere in any order; results are merged strictly in item order. At most
    ``max_in_flight`` (default ``4 × workers``, at least 4) tasks are outstanding. ``progress(item,
    result)`` is called as each result arrives (in completion order). A failed task raises
    ``RuntimeError`` naming the item index (after cancelling the rest).
    """
    items = iter(enumerate(items))
    limit = max_in_flight or max(4, 4 * max(1, executor.n_workers))
    acc = init
    pending: dict[int, Any] = {}
    index_of = {}
    next_merge = 0
    flight = {}

    def submit_one():
        try:
            i, it = next(items)
        except StopIteration:
            return None
        h = executor.submit(fn, *shared_args, it, key=f"{key}-{i}")
        index_of[h.key] = (i, it)
        flight[h.key] = h
        return h

    first = [h for h in (submit_one() for _ in range(limit)) if h is not None]
    if not first:
        return acc
    done = executor.completed(first)
    for h, ok, value in done:
        i, it = index_of.pop(h.key)
        flight.pop(h.key, None)
        if not ok:
            executor.cancel(list(flight.values()))
            raise RuntimeError(f"{key} {i} failed: {type(value).__name__}: {value}") from (
                value if isinstance(value, BaseException) else None)
        if progress is not None:
            progress(it, value)
        pending[i] = value
        while next_merge in pending:
            acc = merge(acc, pending.pop(next_merge))
            next_merge += 1
        nxt = submit_one()
        if nxt is not None:
            done.add(nxt)
    return acc
