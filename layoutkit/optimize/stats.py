"""DOP statistics of a layout over a pose set, built in one place (:func:`pose_stats`).

Every report of the optimiser (``OptimizeResult.stats()``, the summary's ``envelope_sets``, the layout
JSON's ``dop_stats``) and of ``layoutkit score`` takes its numbers from :func:`pose_stats`; the JSON
shapes they print are views of its one flat record (:func:`nested_stats`, :func:`set_stats`).
"""
from __future__ import annotations

import numpy as np

__all__ = ["pose_stats", "nested_stats", "set_stats"]

_QUANTITIES = ("adop", "pdop")


def pose_stats(adop, pdop, mask) -> dict:
    """Statistics over the poses where ``mask``.

    adop (P,) deg/rad, pdop (P,) m/rad, mask (P,) bool (the poses that count: covered by the rule,
    or with a finite DOP — the caller says which). Returns a flat dict: ``poses``, ``covered_poses``,
    ``covered_fraction`` and, for q in adop/pdop, ``worst_q`` (max), ``median_q``, ``mean_q``,
    ``p95_q``, ``p99_q`` — floats, or None when no pose counts.
    """
    adop, pdop, mask = np.asarray(adop, float), np.asarray(pdop, float), np.asarray(mask, bool)
    n = int(mask.sum())
    out = {"poses": int(len(adop)), "covered_poses": n,
           "covered_fraction": float(mask.mean()) if len(mask) else float("nan")}
    for q, a in zip(_QUANTITIES, (adop, pdop)):
        x = a[mask]
        with np.errstate(invalid="ignore"):  # an inf DOP among the poses: inf - inf in the percentile
                out.update({f"worst_{q}": float(np.max(x)) if n else None,
                        f"median_{q}": float(np.median(x)) if n else None,
                        f"mean_{q}": float(np.mean(x)) if n else None,
                        f"p95_{q}": float(np.percentile(x, 95)) if n else None,
                        f"p99_{q}": float(np.percentile(x, 99)) if n else None})
    return out


def nested_stats(s: dict) -> dict:
    """The optimiser's ``stats`` / ``dop_stats`` shape of :func:`pose_stats`: ``{"adop_deg_per_rad":
    {median, mean, p95, max}, "pdop_m_per_rad": {...}, "poses", "poses_covered"}`` ({} per quantity
    when no pose counts)."""
    out = {}
    for q, key in zip(_QUANTITIES, ("adop_deg_per_rad", "pdop_m_per_rad")):
        out[key] = ({"median": s[f"median_{q}"], "mean": s[f"mean_{q}"], "p95": s[f"p95_{q}"],
                     "max": s[f"worst_{q}"]} if s["covered_poses"] else {})
    out["poses"] = s["poses"]
    out["poses_covered"] = s["covered_poses"]
    return out


def set_stats(s: dict) -> dict:
    """The summary's ``envelope_sets`` shape of :func:`pose_stats` (one pose set: design, working,
    dense, held-out): poses, covered_fraction, worst/median/p95/p99 ADOP, worst PDOP (None: no pose)."""
    return {"poses": s["poses"], "covered_fraction": s["covered_fraction"], "worst_adop": s["worst_adop"],
            "median_adop": s["median_adop"], "p95_adop": s["p95_adop"], "p99_adop": s["p99_adop"],
            "worst_pdop": s["worst_pdop"]}
