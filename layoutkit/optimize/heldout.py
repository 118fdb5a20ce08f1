"""The held-out estimate: a layout scored on fresh poses of its envelope, with its sampling uncertainty.

An envelope is a continuous set of poses; an optimiser sees finitely many. What a layout does on the
envelope is estimated on poses no optimiser saw: ``draws`` fresh sets of ``poses_per_draw`` poses (seeds
``envelope.seed + 2 + 1000 i``; the dense loop uses + 1 and + 3), scored with the exact metric (Chen eq. 18
with rho, lit sensors, every station) and the coverage rule, self-occlusion by the problem's mesh included.

What the numbers mean (distribution-free, the poses being i.i.d. draws of the envelope's own sampler):

- ``worst``: the layout's objective over all ``M = draws × poses_per_draw`` fresh poses it covers. The
  envelope's true worst case is at least this (a maximum over a subset), so it is an estimate from below.
- ``exceed_fraction_bound_95 = ln(20) / M``: with 95 % confidence, the share of the envelope (by its pose
  measure) on which the layout does worse than ``worst`` is at most this — if a share ε exceeded it, the
  chance that none of M draws landed there is (1 - ε)^M ≤ exp(-ε M) = 0.05.
- ``uncovered_fraction_bound_95``: the Clopper–Pearson 95 % upper bound on the share of the envelope with
  fewer than ``min_visible`` lit sensors (3.0 / M when no fresh pose is uncovered).
- ``draw_worst``: the worst of each draw on its own: their spread shows how much one 2,000-pose draw (the
  held-out column of a single study) moves.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["heldout_estimate", "HELDOUT_DRAWS", "HELDOUT_POSES_PER_DRAW", "heldout_seed"]

#: default fresh draws and poses per draw of the estimate (10,000 poses: an exceed-fraction bound of 0.03 %)
HELDOUT_DRAWS = 5
HELDOUT_POSES_PER_DRAW = 2000


def heldout_seed(envelope, i: int) -> int:
    """Seed of fresh draw ``i`` of ``envelope`` (draw 0 is the report's historical held-out set, seed + 2)."""
    return int(envelope.seed) + 2 + 1000 * int(i)


def _clopper_pearson_upper(k: int, n: int, alpha: float = 0.05) -> float:
    """One-sided (1 - alpha) upper confidence bound on a binomial share with k successes in n."""
    if n <= 0:
        return 1.0
    if k >= n:
        return 1.0
    from scipy.stats import beta

    return float(beta.ppf(1.0 - alpha, k + 1, n - k))


def heldout_estimate(problem, sel, *, objective="worst-adop", weights=None, rho, min_visible=4,
                     coverage="any-station", draws=HELDOUT_DRAWS, poses_per_draw=HELDOUT_POSES_PER_DRAW) -> dict:
    """The held-out estimate of candidate subset ``sel`` of ``problem`` (module docstring).

    problem : :class:`layoutkit.optimize.DesignProblem` with an envelope; sel : (k,) candidate indices.
    objective, weights : the objective of the estimate (``worst-adop``: ADOP in deg/rad; PDOP objectives in
    m/rad); rho, min_visible, coverage : the exact metric and the coverage rule.
    Returns a JSON-able dict: ``value`` (the objective over the covered fresh poses), ``poses`` (M),
    ``draws`` (per draw: seed, poses, covered fraction, objective value, worst/p99/median ADOP),
    ``worst_adop``, ``p99_adop``, ``median_adop``, ``worst_pdop`` over all of them, ``covered_fraction``,
    ``uncovered`` (count), ``exceed_fraction_bound_95``, ``uncovered_fraction_bound_95`` and
    ``draw_value_min``/``draw_value_max`` (the spread of single draws).
    """
    from ..envelope import envelope_set
    from .objectives import parse_objective
    from .stats import pose_stats

    env = problem.envelope
    if env is None:
        raise ValueError("held-out estimate: the problem has no envelope to draw fresh poses from")
    if env.attitude == "trajectory":
        raise ValueError("held-out estimate: a trajectory envelope is a fixed pose list; there are no fresh poses")
    obj = parse_objective(objective, weights)
    A, Pd, C, rows = [], [], [], []
    for i in range(int(draws)):
        seed = heldout_seed(env, i)
        _, R, t = envelope_set(env, count=int(poses_per_draw), seed=seed)
        a, p, cov = problem.evaluate(sel, R, t, rho=rho, min_visible=min_visible, coverage=coverage)
        st = pose_stats(a, p, cov)
        rows.append({"seed": seed, "poses": int(len(a)), "covered_fraction": st["covered_fraction"],
                     "value": float(obj.aggregate_values(obj.from_dop(a, p), cov)) if cov.any() else math.inf,
                     "worst_adop": st["worst_adop"], "p99_adop": st["p99_adop"], "median_adop": st["median_adop"]})
        A.append(a), Pd.append(p), C.append(cov)
    a, p, cov = np.concatenate(A), np.concatenate(Pd), np.concatenate(C)
    st = pose_stats(a, p, cov)
    M, unc = int(len(a)), int((~cov).sum())
    vals = [r["value"] for r in rows]
    return {"objective": obj.name, "value": float(obj.aggregate_values(obj.from_dop(a, p), cov)) if cov.any()
            else math.inf, "poses": M, "draws": rows, "worst_adop": st["worst_adop"], "p99_adop": st["p99_adop"],
            "median_adop": st["median_adop"], "worst_pdop": st["worst_pdop"], "covered_fraction": st["covered_fraction"],
            "uncovered": unc, "exceed_fraction_bound_95": math.log(20.0) / M,
            "uncovered_fraction_bound_95": _clopper_pearson_upper(unc, M),
            "draw_value_min": float(min(vals)), "draw_value_max": float(max(vals)),
            "rho": float(rho), "min_visible": int(min_visible), "coverage_rule": coverage,
            "self_occlusion": problem.mesh is not None}
