"""Objectives over the operating envelope: worst / mean / percentile of ADOP, PDOP or a weighted sum.

Every objective is built from one per-pose quantity, a weighted DOP

    d_p = sqrt(trace(W H_p)),   W = diag(w_rot, w_rot, w_rot, w_t, w_t, w_t)

with H_p the pose covariance of Chen eq. (18) (rotation block first). ADOP is ``w_rot = (180/pi)²,
w_t = 0`` (deg per rad, Chen eq. 22), PDOP is ``w_rot = 0, w_t = 1`` (m per rad), and
``"weighted"`` is ``sqrt(a ADOP² + b PDOP²)`` with user weights ``(a, b)``. The envelope
aggregate is the maximum ("worst"), the mean, or a percentile ("p95") over the poses.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from ..units import RAD2DEG

__all__ = ["Objective", "parse_objective", "OBJECTIVE_METRICS", "OBJECTIVE_AGGREGATES"]

OBJECTIVE_METRICS = ("adop", "pdop", "weighted")
OBJECTIVE_AGGREGATES = ("worst", "mean", "pNN")


@dataclass(frozen=True)
class Objective:
    """A parsed objective.

    name : e.g. ``"worst-adop"``; aggregate : ``"worst"``, ``"mean"`` or ``"percentile"``;
    q : percentile in [0, 100] (only for ``"percentile"``); metric : ``"adop"``, ``"pdop"``,
    ``"weighted"``; w : (6,) diagonal of W (see module docstring).
    """

    name: str
    aggregate: str
    metric: str
    w: np.ndarray
    q: float = 100.0

    def pose_values(self, h_diag_sums) -> np.ndarray:
        """Per-pose d_p from ``(..., 2)`` traces ``[tr H_rot, tr H_t]`` (rad²/rad², m²/rad²)."""
        s = np.asarray(h_diag_sums, float)
        return np.sqrt(np.maximum(self.w[0] * s[..., 0] + self.w[3] * s[..., 1], 0.0))

    def from_dop(self, adop, pdop) -> np.ndarray:
        """Per-pose d_p from ADOP (deg/rad) and PDOP (m/rad) arrays (inf stays inf)."""
        a = np.asarray(adop, float) / RAD2DEG
        p = np.asarray(pdop, float)
        with np.errstate(invalid="ignore"):
            out = np.sqrt(self.w[0] * a * a + self.w[3] * p * p)
        return np.where(np.isfinite(a) & np.isfinite(p), out, np.inf)

    def aggregate_values(self, d, mask=None, axis=-1) -> np.ndarray:
        """Envelope aggregate of per-pose values ``d`` (..., P) over the poses where ``mask``."""
        d = np.asarray(d, float)
        if mask is not None:
            d = np.where(mask, d, np.nan)
        with np.errstate(invalid="ignore"), _warnings_off():
            if self.aggregate == "worst":
                return np.nanmax(d, axis=axis)
            if self.aggregate == "mean":
                return np.nanmean(d, axis=axis)
            return np.nanpercentile(d, self.q, axis=axis)


class _warnings_off:
    def __enter__(self):
        import warnings

        self._c = warnings.catch_warnings()
        self._c.__enter__()
        warnings.simplefilter("ignore", RuntimeWarning)

    def __exit__(self, *a):
        return self._c.__exit__(*a)


def objective_unit(name: str) -> str:
    """The unit of an objective's value: ``deg/rad`` (ADOP), ``m/rad`` (PDOP) or the weighted
    combination's ``sqrt(a deg² + b m²)/rad``; ``""`` for a name that does not parse."""
    metric = str(name).strip().lower().rpartition("-")[2]
    return {"adop": "deg/rad", "pdop": "m/rad", "weighted": "√(a·deg² + b·m²)/rad"}.get(metric, "")


def parse_objective(name: str, weights=None) -> Objective:
    """Parse ``"<aggregate>-<metric>"``: aggregate ``worst`` | ``mean`` | ``pNN`` (percentile NN,
    e.g. ``p95``), metric ``adop`` | ``pdop`` | ``weighted``. ``weights = (a, b)`` (default (1, 1))
    weigh ADOP² (deg²) and PDOP² (m²) in ``"weighted"``. Raises ``ValueError`` with the accepted forms.
    """
    m = re.fullmatch(r"(worst|mean|p(\d+(?:\.\d+)?))-(adop|pdop|weighted)", str(name).strip().lower())
    if m is None:
        raise ValueError(
            f"objective: expected '<worst|mean|pNN>-<adop|pdop|weighted>' (e.g. 'worst-adop', "
            f"'mean-pdop', 'p95-adop'), got {name!r}")
    agg, q, metric = m.group(1), m.group(2), m.group(3)
    if metric == "adop":
        wr, wt = RAD2DEG**2, 0.0
    elif metric == "pdop":
        wr, wt = 0.0, 1.0
    else:
        a, b = (1.0, 1.0) if weights is None else (float(weights[0]), float(weights[1]))
        if not (a >= 0 and b >= 0 and a + b > 0 and np.isfinite(a + b)):
            raise ValueError(f"weights: expected two non-negative numbers (ADOP², PDOP²), got {weights!r}")
        wr, wt = a * RAD2DEG**2, b
    w = np.array([wr] * 3 + [wt] * 3)
    if q is not None:
        qq = float(q)
        if not 0 <= qq <= 100:
            raise ValueError(f"objective: percentile must be in [0, 100], got {qq}")
        return Objective(name, "percentile", metric, w, qq)
    return Objective(name, agg, metric, w)
