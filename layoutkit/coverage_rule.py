"""What "m sensors lit" means with several stations: the coverage rule (issue 13, item 2).

A pose is *covered* when the layout's lit counts satisfy the rule with at least ``m`` (``--min-visible``):

| rule | counted per pose | covered when |
|---|---|---|
| ``any-station`` | sensors lit by at least one station (a sensor seen by two stations counts once) | count >= m |
| ``each-station`` | sensors lit by each station separately | every station's count >= m: each station alone gives a fix |
| ``joint`` | lit (station, sensor) pairs: a sensor seen by two stations counts twice (the joint multi-station solve) | count >= m |

With one station the three rules agree. The DOP itself is always the joint solve over every lit
(station, sensor) pair (Chen eq. 18); the rule only decides which poses count as covered — in
``layoutkit score``, the optimiser's coverage constraint, its report and the envelope map alike.

Each rule maps visibility ``vis (..., S, n)`` bool to count rows ``(..., R, n)`` int8 (``R = S`` for
``each-station``, else 1): the coverage of a selection is ``rows @ z`` and a pose is covered when
all of its R rows reach m (:func:`covered`).
"""
from __future__ import annotations

from typing import Callable

import numpy as np

__all__ = ["COVERAGE_RULES", "DEFAULT_RULE", "coverage_rows", "covered", "check_rule", "layout_counts"]

DEFAULT_RULE = "any-station"


def _any(vis):
    return vis.any(axis=-2, keepdims=True).astype(np.int8)


def _each(vis):
    return vis.astype(np.int8)


def _joint(vis):
    return vis.sum(axis=-2, keepdims=True).astype(np.int8)


#: rule name -> ``vis (..., S, n) -> rows (..., R, n)``; the CLI ``--coverage`` choices.
COVERAGE_RULES: dict[str, Callable] = {"any-station": _any, "each-station": _each, "joint": _joint}


def check_rule(rule: str) -> str:
    if rule not in COVERAGE_RULES:
        raise ValueError(f"coverage: expected one of {', '.join(COVERAGE_RULES)}, got {rule!r}")
    return rule


def coverage_rows(vis, rule: str = DEFAULT_RULE) -> np.ndarray:
    """Count rows ``(..., R, n)`` int8 of visibility ``vis (..., S, n)`` under ``rule``."""
    return COVERAGE_RULES[check_rule(rule)](np.asarray(vis, bool))


def covered(counts, m: int) -> np.ndarray:
    """Covered poses ``(...,)`` from per-row counts ``(..., R)``: every row has at least m."""
    return np.asarray(counts).min(axis=-1) >= int(m)


def layout_counts(vis, rule: str = DEFAULT_RULE) -> np.ndarray:
    """Per-pose per-row counts ``(..., R)`` of a whole layout with visibility ``vis (..., S, n)``."""
    return coverage_rows(vis, rule).sum(axis=-1, dtype=np.int64)
