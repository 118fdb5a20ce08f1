"""Mergeable streaming statistics with O(1) memory: moments and a fixed log-binned histogram.

Both are built chunk by chunk on workers and merged on the client. Merging is associative; the
integer counts merge exactly, the float sums merge exactly only in a fixed order (see
:func:`layoutkit.parallel.chunks.map_reduce_ordered`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Moments", "LogHistogram"]


@dataclass
class Moments:
    """Count, sum, sum of squares, min and max of a stream of finite floats (NaN/inf are counted
    in ``nonfinite`` and otherwise ignored)."""

    count: int = 0
    total: float = 0.0
    total_sq: float = 0.0
    min: float = math.inf
    max: float = -math.inf
    nonfinite: int = 0

    def add(self, x) -> "Moments":
        x = np.asarray(x, float).ravel()
        ok = np.isfinite(x)
        self.nonfinite += int(x.size - ok.sum())
        x = x[ok]
        if x.size:
            self.count += int(x.size)
            self.total += float(x.sum())
            self.total_sq += float(np.dot(x, x))
            self.min = min(self.min, float(x.min()))
            self.max = max(self.max, float(x.max()))
        return self

    def merge(self, other: "Moments") -> "Moments":
        return Moments(self.count + other.count, self.total + other.total, self.total_sq + other.total_sq,
                       min(self.min, other.min), max(self.max, other.max), self.nonfinite + other.nonfinite)

    @property
    def mean(self) -> float:
        return self.total / self.count if self.count else math.nan

    @property
    def rms(self) -> float:
        return math.sqrt(self.total_sq / self.count) if self.count else math.nan

    @property
    def std(self) -> float:
        """Population standard deviation (from the raw sums: fine for errors around ~0)."""
        if not self.count:
            return math.nan
        return math.sqrt(max(self.total_sq / self.count - self.mean ** 2, 0.0))

    def as_dict(self) -> dict:
        return {"count": self.count, "mean": self.mean, "rms": self.rms, "std": self.std,
                "min": self.min if self.count else math.nan, "max": self.max if self.count else math.nan,
                "nonfinite": self.nonfinite}


@dataclass
class LogHistogram:
    """Counts in fixed log-spaced bins over ``[lo, hi)`` plus under/overflow (a percentile sketch).

    Bin edges ``lo · 10^(j / bins_per_decade)``. A percentile read from it is within one bin of the
    exact one: relative resolution ``10^(1/bins_per_decade) - 1`` (2.3 % at 100 per decade) for
    values inside ``[lo, hi)``; values below ``lo`` (zeros included) report as ``lo``, above as ``hi``.
    Two histograms merge exactly when their edges agree.
    """

    lo: float
    hi: float
    bins_per_decade: int = 100
    counts: np.ndarray = field(default=None)
    under: int = 0
    over: int = 0
    nonfinite: int = 0

    def __post_init__(self):
        if not (0 < self.lo < self.hi) or self.bins_per_decade < 1:
            raise ValueError(f"LogHistogram: need 0 < lo < hi and bins_per_decade >= 1, got "
                             f"{self.lo}, {self.hi}, {self.bins_per_decade}")
        n = int(math.ceil(math.log10(self.hi / self.lo) * self.bins_per_decade))
        if self.counts is None:
            self.counts = np.zeros(n, np.int64)
        elif len(self.counts) != n:
            raise ValueError(f"LogHistogram: {len(self.counts)} counts for {n} bins")

    @property
    def edges(self) -> np.ndarray:
        return self.lo * 10.0 ** (np.arange(len(self.counts) + 1) / self.bins_per_decade)

    @property
    def total(self) -> int:
        return int(self.counts.sum()) + self.under + self.over

    def add(self, x) -> "LogHistogram":
        x = np.asarray(x, float).ravel()
        ok = np.isfinite(x)
        self.nonfinite += int(x.size - ok.sum())
        x = x[ok]
        under = x < self.lo
        over = x >= self.hi
        self.under += int(under.sum())
        self.over += int(over.sum())
        mid = x[~under & ~over]
        if mid.size:
            j = np.floor(np.log10(mid / self.lo) * self.bins_per_decade).astype(np.int64)
            np.clip(j, 0, len(self.counts) - 1, out=j)
            self.counts += np.bincount(j, minlength=len(self.counts))
        return self

    def merge(self, other: "LogHistogram") -> "LogHistogram":
        if (self.lo, self.hi, self.bins_per_decade) != (other.lo, other.hi, other.bins_per_decade):
            raise ValueError("LogHistogram.merge: different bin edges")
        return LogHistogram(self.lo, self.hi, self.bins_per_decade, self.counts + other.counts,
                            self.under + other.under, self.over + other.over, self.nonfinite + other.nonfinite)

    def quantile(self, q) -> float:
        """The ``q``-quantile (0 <= q <= 1), log-interpolated inside its bin; NaN if empty."""
        n = self.total
        if n == 0:
            return math.nan
        target = float(q) * n
        if target <= self.under:
            return self.lo
        c = np.cumsum(self.counts) + self.under
        j = int(np.searchsorted(c, target, side="left"))
        if j >= len(self.counts):
            return self.hi
        before = c[j - 1] if j > 0 else self.under
        frac = (target - before) / max(self.counts[j], 1)
        e = self.edges
        return float(e[j] * (e[j + 1] / e[j]) ** frac)

    def as_dict(self, qs=(0.5, 0.9, 0.95, 0.99, 0.999)) -> dict:
        return {"count": self.total, "under": self.under, "over": self.over, "lo": self.lo, "hi": self.hi,
                "bins_per_decade": self.bins_per_decade,
                "relative_resolution": 10 ** (1 / self.bins_per_decade) - 1,
                **{f"p{100 * q:g}": self.quantile(q) for q in qs}}
