"""What a bound certifies, and why it is loose when it is (issue 27, item 2).

The optimiser's ``bound`` is a lower bound on ``min over k-layouts of the objective`` over a finite **pose
set** and a finite **candidate set** (:mod:`layoutkit.optimize.relaxation`, :mod:`layoutkit.optimize.bnb`):

- without the dense loop: the design poses; with it: a round's working set, a subset of the dense set, so
  the bound holds for the dense set too (:mod:`layoutkit.optimize.dense`);
- for the worst case, a maximum over more poses is larger: the bound also holds for the dense set united
  with the held-out poses, and so for the continuous envelope. The gap stated is therefore
  ``value on (dense set ∪ held-out poses) / bound - 1``: over that finite pose set, the layout is within
  ``gap`` of every k-layout of the candidates (for mean and percentile objectives only the working set is
  certified: a mean over more poses is not bounded by the mean over fewer);
- the candidate set is the problem's: the sites sampled on the mesh (and their tilted orientations).
  A layout with other sensor positions or normals (a shipped device's) is not covered by the certificate.

When the gap is large, :func:`certificate` says which part is loose: the relaxation's fractional optimum
(how many candidates share the k sensors, how much of the mass is fractional, how many tilted sites split
their orientations — an integrality gap), the pose set (the layout's worst moved from the working set to
fresh poses: generalisation, not search), or a missing bound (the relaxation was cut by the budget).
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["certificate", "relaxation_structure"]

#: a gap above this is called loose and explained
LOOSE_GAP = 0.10
#: a gap above this (the bound below half the value) is called uninformative: the bound then only says the
#: layout is within a factor ``1 + gap`` of the best, which no user would call a certificate
UNINFORMATIVE_GAP = 1.0


def relaxation_structure(z, site=None, k=None) -> dict:
    """How a relaxed z ``(N,)`` in [0, 1] spreads k sensors: candidates in use (z > 0.02), fractional
    entries (0.02 < z < 0.98) and their share of the mass, and (``site`` (N,) given) sites whose mass is
    split over two or more orientations."""
    z = np.clip(np.asarray(z, float), 0.0, 1.0)
    frac = (z > 0.02) & (z < 0.98)
    out = {"candidates_used": int((z > 0.02).sum()), "fractional": int(frac.sum()),
           "fractional_mass_share": float(z[frac].sum() / max(z.sum(), 1e-12)), "k": int(k or round(z.sum()))}
    if site is not None:
        site = np.asarray(site)
        used = z > 0.02
        per = np.bincount(site[used], minlength=int(site.max()) + 1)
        out["sites_split_over_orientations"] = int((per >= 2).sum())
    return out


def _describe_candidates(problem) -> str:
    n_sites = int(len(np.unique(problem.site)))
    if problem.max_tilt_deg > 0:
        toward = problem.tilt_toward
        how = ("towards/away from the stations" if toward == "station" else
               "meridional" if toward is not None else f"{problem.tilt_directions} azimuths")
        return (f"{problem.N} candidates: {n_sites} sites with their surface normal or tilted "
                f"{problem.max_tilt_deg:g}° ({how}), one orientation per site")
    return f"{problem.N} candidate sites (surface normals)"


def certificate(problem, spec, res, heldout=None) -> dict:
    """The certificate of optimisation result ``res`` of ``spec`` on ``problem`` (module docstring).

    heldout : :func:`layoutkit.optimize.heldout.heldout_estimate` of the layout, or None.
    Returns a JSON-able dict: ``bound``, ``certified_by``, ``pose_set`` and ``candidate_set`` (what the
    bound is over), ``value_on_pose_set`` (the layout's objective there), ``gap`` (value_on_pose_set /
    bound - 1; None without a bound), ``loose`` (bool), ``verdict`` ("tight": gap <= 10 %, "loose",
    "uninformative": gap > 100 %, "none": no bound), ``why`` (plain-language explanation, "" if tight),
    ``relaxation`` (:func:`relaxation_structure` of the relaxed z when one is known) and ``statement``
    (one sentence for the report).
    """
    dense = res.info.get("dense") if isinstance(res.info, dict) else None
    worst = spec.objective.startswith("worst")
    bound = res.bound if res.bound is not None and np.isfinite(res.bound) and res.certified_by != "none" else None
    if dense is not None and "dense_value" in dense:
        n_dense = int(dense["dense_set_poses"])
        base_set, base_val = f"the dense set ({n_dense} poses: design + dense poses of the envelope)", dense["dense_value"]
        work = f"working set of the best round ({dense['working_set_poses']} poses)"
    else:
        base_set, base_val = f"the {problem.P} design poses", res.value
        work = f"the {problem.P} design poses"
    pose_set, value = base_set, float(base_val)
    if worst and heldout is not None and dense is not None:
        pose_set = f"{base_set} ∪ the {heldout['poses']} held-out poses"
        value = max(value, float(heldout["value"]))
    gap = (value / bound - 1.0) if bound and bound > 0 and math.isfinite(value) else None
    if bound is not None and not math.isfinite(value):
        gap = math.inf
    z = res.info.get("relaxation_z") if isinstance(res.info, dict) else None
    if z is None and dense is not None:
        z = dense.get("relaxation_z")
    struct = relaxation_structure(z, problem.site, spec.k) if z is not None else None
    loose = bound is None or gap is None or gap > LOOSE_GAP
    why = _why(problem, spec, res, bound, gap, value, dense, heldout, struct) if loose else ""
    verdict = ("none" if bound is None else "uninformative" if gap is None or gap > UNINFORMATIVE_GAP else
               "loose" if loose else "tight")
    cand = _describe_candidates(problem)
    spare = spec.dense.spare_lit if spec.dense is not None else 0
    if spare:  # the loop's coverage rows ask for more: the bound is over the layouts that keep that many lit
        cand += f" (layouts keeping >= {spec.min_visible + spare} lit at every pose of the loop, its margin)"
    if bound is None:
        statement = f"no certified bound ({res.message.split('bound: none')[-1].strip(' ();') or res.certified_by})"
    else:
        statement = (f"no {spec.k}-sensor layout of these {cand} has {spec.objective} below {bound:.5g} over "
                     f"{pose_set}; this layout's is {value:.5g} there (gap {_pct(gap)})")
        if verdict == "uninformative":
            statement += (f"; the bound is uninformative: it only says the best layout is no better than "
                          f"{_pct_of(gap)} of this one's value")
    return {"bound": bound, "certified_by": res.certified_by, "pose_set": pose_set, "bound_from": work,
            "candidate_set": cand, "value_on_pose_set": value, "gap": gap, "loose": bool(loose), "why": why,
            "relaxation": struct, "statement": statement, "verdict": verdict}


def _pct(gap) -> str:
    return "none" if gap is None else "∞" if not math.isfinite(gap) else f"{100 * gap:.1f} %"


def _pct_of(gap) -> str:
    return "0 %" if gap is None or not math.isfinite(gap) else f"{100 / (1 + gap):.0f} %"


def _why(problem, spec, res, bound, gap, value, dense, heldout, struct) -> str:
    """Plain-language reasons a certificate is loose, strongest first."""
    if bound is None:
        return ("the relaxation did not finish with status optimal within its share of the budget, so there is "
                "nothing to certify with; a longer --time-limit-s or fewer candidates (--spacing-mm) give it time")
    parts = []
    if res.certified_by == "trace":
        parts.append("no relaxation finished within its share of the budget, so the bound is the closed-form trace "
                     "bound (each pose's best k candidates by the trace of their information, ignoring coverage and "
                     "the other poses): valid but always loose; a longer --time-limit-s or fewer candidates "
                     "(--spacing-mm) give the relaxation time")
    work_val = float(res.value)
    search = work_val / bound if bound > 0 else math.inf
    general = value / work_val if work_val > 0 else math.inf
    if struct is not None:
        s = (f"the relaxation's optimum spreads the {spec.k} sensors over {struct['candidates_used']} candidates "
             f"({struct['fractional']} fractional, {100 * struct['fractional_mass_share']:.0f} % of the mass)")
        if struct.get("sites_split_over_orientations"):
            s += (f", {struct['sites_split_over_orientations']} tilted sites split between orientations (the "
                  "one-orientation-per-site rows cap each site at one sensor in total, not one orientation)")
        parts.append(s + f": an integrality gap — on the poses it was solved for, the best layout is "
                     f"{search:.2f}× the bound (×{search:.2f} of the gap is relaxation plus search)")
    else:
        parts.append(f"layout / bound on the working set = {search:.2f} (relaxation plus search)")
    if not math.isfinite(value):
        parts.append("the layout leaves some poses of that set with fewer than the required lit sensors (a coverage "
                     "failure, not a DOP): its worst there is unbounded")
    elif general > 1.0 + 1e-9:
        parts.append(f"the layout's worst moved from the poses it was tuned on ({work_val:.5g}) to poses it never "
                     f"saw ({value:.5g}): ×{general:.2f} of the gap is generalisation, which no bound over the "
                     "working set can close")
    bnb = res.info.get("branch_and_bound") if isinstance(res.info, dict) else None
    if dense is not None:
        src = ("the largest round relaxation" if "relaxation" in str(res.certified_by) else
               f"the {res.certified_by} bound of its round")
        parts.append("branch-and-bound is off in the dense loop (it would spend the budget certifying one working "
                     f"set); the bound is {src}")
    elif bnb:
        parts.append(f"branch-and-bound raised the bound from {bnb['root_bound']:.5g} to {bnb['bound']:.5g} in "
                     f"{bnb['nodes']} node relaxations before it stopped"
                     + (f" ({bnb['stopped']})" if bnb.get("stopped") else ""))
    elif spec.objective.startswith("worst") and spec.coverage_fraction >= 1:
        parts.append("branch-and-bound did not run (it needs a time limit of at least 5 s; --branch-and-bound)")
    else:
        parts.append("mean/percentile objectives and coverage fractions below 1 have per-pose bounds only, "
                     "valid but loose (each pose gets its own best layout)")
    return "; ".join(parts)
