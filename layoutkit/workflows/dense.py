"""Dense envelopes by adaptive pose generation (issue 13, item 1).

Worst-case optimisation over a small pose sample fits the sample. Here the optimiser works on a
*working set* (the envelope's design poses), the incumbent is evaluated on a *dense set* of the
same envelope (design poses + ``dense_poses`` more from another seed; the fused DOP kernel
:func:`layoutkit.dop_batch.batch_dop` makes that cheap), the worst dense poses that exceed the
working-set value (and dense poses the coverage rule leaves uncovered) join the working set, and
the optimiser runs again warm-started from the incumbent and the relaxation's active poses — until
the dense-set objective stops improving (``patience`` rounds), no dense pose exceeds the working-set
value, or the budget ends. The result with the best dense-set value is kept.

Certificate: the working set is a subset of the dense set, so the relaxation bound of any round
(a lower bound for the working set) is also a lower bound for the dense set; the gap reported is
``dense value / bound - 1``.
"""
from __future__ import annotations

import math
import time

import numpy as np

__all__ = ["dense_optimize", "evaluate_selection"]


def evaluate_selection(prep, sel, R, t, rho, min_visible, coverage):
    """Per-pose ADOP, PDOP and coverage of candidate subset ``sel`` at world poses ``R, t``."""
    from ..coverage_rule import covered, layout_counts
    from ..dop_batch import batch_dop
    from .score import layout_visibility

    cand = prep["candidates"]
    pos, nor = cand.positions[sel], cand.normals[sel]
    vis = layout_visibility(prep["mesh"], pos, nor, R, t, prep["stations"], prep["sensor_half_angle_deg"])
    d = batch_dop(pos, R, t, rho=rho, visible=vis, stations=prep["stations"])
    cov = covered(layout_counts(vis, coverage), min_visible)
    return d.adop, d.pdop, cov


def _dense_value(obj, adop, pdop, cov, need_all, uncoverable):
    """``(short, value)``: dense poses left uncovered that are not known to be uncoverable (with full
    coverage required; else 0), and the objective over the covered poses. Rounds compare
    lexicographically; the reported dense value is inf while ``short > 0``."""
    short = int(np.sum(~cov & ~uncoverable)) if need_all else 0
    val = float(obj.aggregate_values(obj.from_dop(adop, pdop), cov)) if cov.any() else math.inf
    return short, val


def dense_optimize(prep, k, kw, *, dense_poses, seed=0, coverage="any-station", rounds=6, add=24,
                   patience=2, time_limit=None, echo=None):
    """Adaptive pose generation around :func:`layoutkit.optimize.optimize_stations`.

    prep : :func:`layoutkit.workflows.optimize.prepare_problem` output (working set = its poses);
    kw : optimize_stations keywords (objective, rho, min_visible, coverage_fraction, ...);
    dense_poses : extra poses drawn from the envelope (seed ``envelope.seed + 1``) that, with the
    design poses, form the dense set. time_limit : total budget of all rounds (s); each round gets
    half of what is left (the last round the rest); None: each round uses the optimiser's default.
    Returns ``(result, info)``: the OptimizeResult of the best round (its per-pose arrays are for the
    final working set) and a dict with per-round values, the dense-set per-pose DOP and sizes.
    """
    import dataclasses

    from ..coverage_rule import covered, layout_counts
    from ..optimize import candidate_jacobians, optimize_stations, parse_objective
    from ..visibility import envelope_visibility
    from .score import envelope_set

    t0 = time.perf_counter()
    env = prep["envelope"]
    _, Rd, td = envelope_set(env, count=int(dense_poses), seed=env.seed + 1)
    Rw, tw = prep["rotations"], prep["translations"]
    RD, tD = np.concatenate([Rw, Rd]), np.concatenate([tw, td])  # dense set ⊇ working set
    in_work = np.zeros(len(RD), bool)
    in_work[: len(Rw)] = True
    jac, vis = prep["jac"], prep["visible"]
    obj = parse_objective(kw.get("objective", "worst-adop"), kw.get("weights"))
    rho, m = kw.get("rho", 0.0), kw.get("min_visible", 4)
    need_all = kw.get("coverage_fraction", 1.0) >= 1.0
    cand = prep["candidates"]
    best = None
    hist = []
    warm, active = None, None
    stall = 0
    uncoverable = np.zeros(len(RD), bool)  # dense poses with fewer than m lit candidates (by the rule)
    note = ""
    for rnd in range(int(rounds)):
        kwr = dict(kw)
        if time_limit is not None:
            left = t0 + float(time_limit) - time.perf_counter()
            if left <= 0.05 * float(time_limit):
                break
            kwr["time_limit"] = left if rnd == rounds - 1 else 0.5 * left
        kwr["ctx_options"] = {**(kw.get("ctx_options") or {}), "warm_start": warm, "active_poses": active}
        res = optimize_stations(jac, vis, k, rng=seed + rnd, coverage=coverage, **kwr)
        if not res.success:
            if best is None:
                return res, {"rounds": hist, "dense_set_poses": int(len(RD))}
            note = f"round {rnd}: {res.status}: {res.message}"
            break
        a, p, cov = evaluate_selection(prep, res.selected, RD, tD, rho, m, coverage)
        dval = _dense_value(obj, a, p, cov, need_all, uncoverable)
        hist.append({"round": rnd, "working_poses": int(in_work.sum()), "working_value": res.value,
                     "dense_value_covered": dval[1], "dense_uncovered": dval[0], "bound": res.bound,
                     "status": res.status})
        if echo is not None:
            echo(f"dense round {rnd}: working set {int(in_work.sum())} poses, value {res.value:.5g}, "
                 f"dense-set value {dval[1]:.5g} over covered poses, {dval[0]} coverable poses uncovered")
        if best is None or dval[0] < best[1][0] or (dval[0] == best[1][0] and dval[1] < best[1][1] * (1 - 1e-3)):
            best = (res, dval, a, p, cov)
            stall = 0
        else:
            stall += 1
        if res.status == "interrupted" or stall >= patience:
            break
        d = obj.from_dop(a, p)
        score = np.where(cov, d, np.inf)
        viol = np.flatnonzero(~in_work & ~uncoverable & (score > res.value * (1 + 1e-6)))
        if len(viol) == 0:
            break  # no dense pose above the working-set value: the working optimum holds on the dense set
        order = viol[np.argsort(-score[viol], kind="stable")]
        new, v_new = [], []
        for s0 in range(0, len(order), 4 * add):  # skip poses no layout can cover (too few lit candidates)
            chunk = order[s0:s0 + 4 * add]
            vc = envelope_visibility(prep["mesh"], cand.positions, cand.normals, RD[chunk], tD[chunk],
                                     prep["stations"], sensor_half_angle_deg=prep["sensor_half_angle_deg"])
            ok = covered(layout_counts(vc, coverage), m)
            uncoverable[chunk[~ok]] = True
            new += list(chunk[ok])
            v_new += list(vc[ok])
            if len(new) >= add:
                break
        if not new:
            break
        new, v_new = np.array(new[:add]), np.array(v_new[:add])
        R_new, t_new = RD[new], tD[new]
        j_new = candidate_jacobians(cand.positions, R_new, t_new, prep["stations"])
        jac = np.concatenate([jac, j_new])
        vis = np.concatenate([vis, v_new])
        in_work[new] = True
        warm = res.selected
        active = None
        if isinstance(res.info, dict) and res.info.get("active_poses") is not None:
            active = res.info["active_poses"]
    res, dval, a, p, cov = best
    # poses found uncoverable after the best round: its value over the coverable ones
    short, dval = _dense_value(obj, a, p, cov, need_all, uncoverable)
    if short:
        dval = math.inf
    # every round's working set is a subset of the dense set: the largest round bound holds for it
    bounds = [h["bound"] for h in hist if h["bound"] is not None and np.isfinite(h["bound"])]
    if bounds and not (np.isfinite(res.bound) and res.bound >= max(bounds)):
        src = int(np.argmax(bounds))
        res = dataclasses.replace(res, bound=float(max(bounds)), certified_by="relaxation (dense round "
                                  f"{[h['round'] for h in hist if h['bound'] is not None and np.isfinite(h['bound'])][src]})",
                                  gap=res.value / max(bounds) - 1)
    gap = dval / res.bound - 1 if np.isfinite(res.bound) and res.bound > 0 else float("nan")
    info = {"rounds": hist, "dense_set_poses": int(len(RD)), "working_set_poses": int(in_work.sum()),
            "dense_value": dval, "dense_gap": gap, "dense_adop": a, "dense_pdop": p, "dense_covered": cov,
            "time_s": time.perf_counter() - t0, "uncoverable_dense_poses": int(uncoverable.sum()), "uncovered_dense_poses": int(short),
            "note": note}
    return res, info
