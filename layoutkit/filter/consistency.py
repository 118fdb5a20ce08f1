"""Filter consistency over simulated runs: NEES and NIS against their chi² bands.

For a consistent filter the normalised estimation error squared of the pose,
``NEES = e^T P^-1 e`` with ``e = (log(R_true R_est^T), p_true - p_est)`` (6 dof), and the normalised
innovation squared of each sweep, ``NIS = y^T S^-1 y`` (dof = angles used), are chi²-distributed.
Averaged over N independent Monte-Carlo runs at the same time step, ``N · ANEES ~ chi²(6 N)`` and
the summed NIS ``~ chi²(sum of dof)``; the filter is consistent when these stay inside the
two-sided 95 % band (Bar-Shalom, Li & Kirubarajan 2001, §5.4.2, eqs. 5.4.2-2 to 5.4.2-8).

The functions take the sweeps as arrays (the simulator lives in the live room, which this room
does not import): ``benchmarks/bench_filter.py`` and ``tests/test_filter.py`` simulate.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FilterRun", "run_sweeps", "pose_error", "nees", "chi2_band", "ConsistencyResult", "consistency"]


class Sweep:
    """A light sweep record for :meth:`~layoutkit.filter.tracker.Tracker.push` (the fields of
    :class:`layoutkit.live.frames.SweepMeasurement` without its validation, for long runs)."""

    __slots__ = ("t", "station", "axis", "angles", "kind")

    def __init__(self, t, station, axis, angles, kind):
        self.t, self.station, self.axis, self.angles, self.kind = t, station, axis, angles, kind


_Sweep = Sweep  # old private name (do not import it from other rooms: tests/test_architecture.py)


@dataclass(frozen=True)
class FilterRun:
    """Per-sweep filter outputs as arrays over the K sweeps given (NaN / False where no output).

    t (K,) s; has_output, ok (K,) bool; rotvec (K, 3) rad, translation (K, 3) m; pose_cov
    (K, 6, 6); nis (K,), dof (K,) int, used / rejected (K,) int; sweep_rejected (K,) bool;
    correction (K, 6), prior_sigma (K, 6); counters : the tracker's counters at the end.
    """

    t: np.ndarray
    has_output: np.ndarray
    ok: np.ndarray
    rotvec: np.ndarray
    translation: np.ndarray
    pose_cov: np.ndarray
    nis: np.ndarray
    dof: np.ndarray
    used: np.ndarray
    rejected: np.ndarray
    sweep_rejected: np.ndarray
    correction: np.ndarray
    prior_sigma: np.ndarray
    counters: dict


def run_sweeps(tracker, t, station, axis, angles, kind=None) -> FilterRun:
    """Feed K sweeps (t (K,) s, station (K,), axis (K,), angles (K, n) rad NaN = not hit; kind a
    sequence of "lh1"/"lh2" per station index or None = the tracker's stations) to ``tracker``."""
    K = len(t)
    out = dict(has_output=np.zeros(K, bool), ok=np.zeros(K, bool), rotvec=np.full((K, 3), np.nan),
               translation=np.full((K, 3), np.nan), pose_cov=np.full((K, 6, 6), np.nan), nis=np.full(K, np.nan),
               dof=np.zeros(K, int), used=np.zeros(K, int), rejected=np.zeros(K, int),
               sweep_rejected=np.zeros(K, bool), correction=np.full((K, 6), np.nan),
               prior_sigma=np.full((K, 6), np.nan))
    kinds = [s.kind for s in tracker.stations] if kind is None else list(kind)
    for k in range(K):
        s = int(station[k])
        o = tracker.push(Sweep(float(t[k]), s, int(axis[k]), angles[k], kinds[s]))
        if o is None:
            continue
        out["has_output"][k] = True
        out["ok"][k] = o.ok
        out["rotvec"][k] = o.rotvec
        out["translation"][k] = o.translation
        out["pose_cov"][k] = o.pose_cov
        out["nis"][k] = o.nis
        out["dof"][k] = o.dof
        out["used"][k] = o.used
        out["rejected"][k] = o.rejected
        out["sweep_rejected"][k] = o.sweep_rejected
        if o.correction is not None:
            out["correction"][k] = o.correction
            out["prior_sigma"][k] = o.prior_sigma
    return FilterRun(t=np.asarray(t, float), counters=tracker.counters.as_dict(), **out)


def pose_error(rotvec_est, translation_est, rotvec_true, translation_true) -> np.ndarray:
    """(K, 6) error ``(log(R_true R_est^T) rad, p_true - p_est m)`` — the filter's error-state convention."""
    from ..geometry import matrix_to_rotvec, rotvec_to_matrix

    ok = np.all(np.isfinite(rotvec_est), -1)
    e = np.full(np.shape(rotvec_est)[:-1] + (6,), np.nan)
    if ok.any():
        Re = rotvec_to_matrix(np.asarray(rotvec_est)[ok])
        Rt = rotvec_to_matrix(np.asarray(rotvec_true)[ok])
        e[ok, :3] = matrix_to_rotvec(Rt @ np.swapaxes(Re, -1, -2))
        e[ok, 3:] = np.asarray(translation_true)[ok] - np.asarray(translation_est)[ok]
    return e


def nees(error, cov) -> np.ndarray:
    """``e^T P^-1 e`` per row: error (K, d), cov (K, d, d) → (K,) (NaN where either is NaN)."""
    e = np.asarray(error, float)
    P = np.asarray(cov, float)
    good = np.all(np.isfinite(e), -1) & np.all(np.isfinite(P), (-1, -2))
    out = np.full(e.shape[0], np.nan)
    if good.any():
        x = np.linalg.solve(P[good], e[good][..., None])[..., 0]
        out[good] = np.sum(e[good] * x, -1)
    return out


def chi2_band(dof, p: float = 0.95):
    """Two-sided ``p`` band ``(lo, hi)`` of a chi² variable with ``dof`` degrees of freedom."""
    from scipy.stats import chi2

    a = (1.0 - p) / 2.0
    return chi2.ppf(a, dof), chi2.ppf(1.0 - a, dof)


@dataclass(frozen=True)
class ConsistencyResult:
    """NEES / NIS over N runs on a common grid of time steps.

    runs; steps : time steps evaluated; anees (steps,) : NEES averaged over the runs (6 dof per
    run); nees_band : (lo, hi) 95 % band of ANEES; nees_inside : share of steps inside it;
    anees_mean : ANEES averaged over all steps (expected 6); anis_per_dof (steps,) : summed NIS /
    summed dof; nis_inside : share of steps whose summed NIS is inside its chi²(sum dof) band;
    nis_per_dof_mean : over all steps (expected 1); success : both shares >= ``min_inside``.
    """

    runs: int
    steps: int
    anees: np.ndarray
    nees_band: tuple
    nees_inside: float
    anees_mean: float
    anis_per_dof: np.ndarray
    nis_inside: float
    nis_per_dof_mean: float
    success: bool
    status: str

    def as_dict(self) -> dict:
        return {"runs": self.runs, "steps": self.steps, "nees_band": [float(v) for v in self.nees_band],
                "nees_inside": self.nees_inside, "anees_mean": self.anees_mean, "nis_inside": self.nis_inside,
                "nis_per_dof_mean": self.nis_per_dof_mean, "success": self.success, "status": self.status}


def consistency(nees_values, nis_values, dof_values, min_inside: float = 0.9, p: float = 0.95) -> ConsistencyResult:
    """Band checks from per-run series on a common step grid.

    nees_values : (N, T) NEES of N runs at T common steps (NaN = no estimate, the step is then
    skipped); nis_values, dof_values : (N, T2) NIS and dof of the sweep updates at T2 common steps.
    ``success`` when at least ``min_inside`` of the steps (the band's own 95 % minus slack) are
    inside; status "ok" / "inconsistent".
    """
    E = np.asarray(nees_values, float)
    N = E.shape[0]
    cols = np.all(np.isfinite(E), 0)
    E = E[:, cols]
    an = E.mean(0)
    lo, hi = chi2_band(6 * N, p)
    band = (lo / N, hi / N)
    inside_e = float(np.mean((an >= band[0]) & (an <= band[1]))) if an.size else float("nan")
    S = np.asarray(nis_values, float)
    D = np.asarray(dof_values, float)
    use = np.isfinite(S) & (D > 0)
    ssum = np.where(use, S, 0.0).sum(0)
    dsum = np.where(use, D, 0.0).sum(0)
    keep = dsum > 0
    l2, h2 = chi2_band(dsum[keep], p)
    inside_n = float(np.mean((ssum[keep] >= l2) & (ssum[keep] <= h2))) if keep.any() else float("nan")
    apd = ssum[keep] / dsum[keep]
    ok = bool(inside_e >= min_inside and inside_n >= min_inside)
    return ConsistencyResult(N, int(an.size), an, band, inside_e, float(an.mean()) if an.size else float("nan"),
                             apd, inside_n, float(ssum[keep].sum() / dsum[keep].sum()) if keep.any() else float("nan"),
                             ok, "ok" if ok else "inconsistent")
