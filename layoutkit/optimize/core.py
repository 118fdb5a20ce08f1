"""The array core of the optimiser: :func:`optimize_stations` (Jacobians + visibility in, an
:class:`OptimizeResult` with a certified bound out) and the per-candidate helpers it needs.

:func:`layoutkit.optimize.solve` (a :class:`~layoutkit.optimize.design.DesignProblem` and an
:class:`~layoutkit.optimize.spec.OptimizeSpec`) and :func:`layoutkit.optimize.optimize_layout` (arrays of
one station) both end here.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np

from .._validate import as_array
from ..dop import angle_jacobian
from .coverage import analyse_coverage, minimum_k
from .methods import METHODS, Context, MethodOutput
from .objectives import parse_objective
from .problem import build_problem, exact_dop
from .relaxation import fallback_bound
from .runcontrol import Interrupted
from .spec import BNB_CHOICES
from .stats import nested_stats, pose_stats

# wall-time budget of the default pipeline when the caller gives none (s); small problems stop
# much earlier (when random kicks stop improving)
DEFAULT_PIPELINE_TIME_S = 100.0
# seconds of a time limit kept for the exact evaluation of the result after the method stops
_FINISH_RESERVE_S = 0.05

__all__ = ["OptimizeResult", "optimize_stations", "candidate_jacobians", "spacing_conflicts"]


@dataclass(frozen=True)
class OptimizeResult:
    """Result of :func:`layoutkit.optimize.solve`, :func:`layoutkit.optimize.optimize_layout` and
    :func:`optimize_stations`.

    selected : (k,) int, sorted candidate indices (empty if nothing feasible was found).
    value : objective of ``selected`` with the exact metric (Chen eq. 18 with rho, lit sensors only,
        all stations); deg/rad for ADOP objectives, m/rad for PDOP, inf if none.
    bound : certified lower bound on the optimum of the same objective over all feasible selections.
    gap : value / bound - 1 (0 for a proven optimum). certified_by : how the bound was obtained —
        "relaxation" (joint), "branch-and-bound" (:mod:`layoutkit.optimize.bnb`), "per-pose
        relaxation", "trace" (closed form) or "exhaustive".
    success : a feasible layout was found; status : "optimal" (proven), "ok", "infeasible",
        "uncoverable", "no_feasible_found", "interrupted", "incomplete" (the dense loop ended with poses
        short of lit sensors: optimize.dense); message : plain-language summary.
    adop, pdop : (P,) exact per-pose ADOP (deg/rad) and PDOP (m/rad); n_lit : (P,) lit counts.
    min_k : smallest k keeping m lit everywhere (set when infeasible); uncoverable : (U,) poses with
        fewer than m lit candidates at all. timings : seconds per stage. method, objective : names.
    """

    selected: np.ndarray
    value: float
    bound: float
    gap: float
    success: bool
    status: str
    message: str
    adop: np.ndarray
    pdop: np.ndarray
    n_lit: np.ndarray
    method: str
    objective: str
    certified_by: str = ""
    min_k: "int | None" = None
    uncoverable: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    timings: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)

    def stats(self) -> dict:
        """Per-pose DOP statistics (median, mean, p95, max) over the poses with a finite ADOP (the covered
        ones: an uncovered pose has ADOP inf), :func:`layoutkit.optimize.stats.nested_stats`."""
        return nested_stats(pose_stats(self.adop, self.pdop, np.isfinite(self.adop)))


def candidate_jacobians(positions, rotations, translations, stations=None):
    """Per-candidate angle Jacobians ``(P, S, N, 2, 6)`` (Chen eqs. 10–14).

    positions : (N, 3) body frame, m; rotations (P, 3, 3), translations (P, 3): body pose in the
    frame of the single station (``stations=None``) or in the world frame of ``stations``
    (:class:`layoutkit.lighthouse.Station` list). points_lh = R p + t, lever = R p.
    """
    p = np.asarray(positions, float)
    R = np.asarray(rotations, float)
    t = np.asarray(translations, float)
    lever = np.einsum("pij,nj->pni", R, p)
    pw = lever + t[:, None, :]
    if stations is None:
        return angle_jacobian(pw, lever)[:, None]
    out = []
    for st in stations:
        ps = (pw - st.translation) @ st.rotation
        out.append(angle_jacobian(ps, lever, st.rotation))
    return np.stack(out, axis=1)


def spacing_conflicts(positions, min_spacing):
    """(N, N) bool: pairs of distinct candidates closer than ``min_spacing`` (m); None if 0."""
    if not min_spacing or min_spacing <= 0:
        return None
    from scipy.spatial import cKDTree

    p = np.asarray(positions, float)
    pairs = cKDTree(p).query_pairs(float(min_spacing), output_type="ndarray")
    C = np.zeros((len(p), len(p)), bool)
    if len(pairs):
        C[pairs[:, 0], pairs[:, 1]] = True
        C[pairs[:, 1], pairs[:, 0]] = True
    return C


def optimize_stations(jac, visible, k, *, objective="worst-adop", rho=0.0, min_visible=4,
                      method="pipeline", rng=None, fixed=(), conflict=None, coverage_fraction=1.0,
                      weights=None, time_limit=None, progress=None, ctx_options=None,
                      coverage="any-station", branch_and_bound="auto", cliques=()) -> OptimizeResult:
    """Choose ``k`` of N candidates from arrays (the core of :func:`layoutkit.optimize.solve`).

    jac : (P, S, N, 2, 6) per-candidate angle Jacobians; visible : (P, S, N) bool.
    coverage : what "m lit" means with several stations (:mod:`layoutkit.coverage_rule`):
    "any-station" (a sensor lit by any station counts once), "each-station" (every station alone
    sees m; implemented by one copy of the pose per station carrying that station's lit counts —
    worst, mean and percentiles are unchanged by the copies; ``coverage_fraction`` then counts
    (pose, station) pairs), "joint" (lit station-sensor pairs). The DOP is always the joint solve.
    k, objective, weights, rho, min_visible, coverage_fraction, method, branch_and_bound : as the fields of
    :class:`layoutkit.optimize.spec.OptimizeSpec`; rng : seed or ``np.random.Generator``; fixed : (F,)
    candidate indices placed in advance; conflict : (N, N) bool pairs that cannot both be chosen
    (spacing, one orientation per site) or None; time_limit : s or None; progress : callable
    ``(stage, fraction, best)``; ctx_options : tuning knobs of :class:`layoutkit.optimize.methods.Context`;
    cliques : index arrays of which at most one may be chosen (the orientations of one site; their pairs
    must be in ``conflict`` too): the relaxations state them as one row each, tighter than the pairs.
    """
    from ..coverage_rule import check_rule

    check_rule(coverage)
    if branch_and_bound not in BNB_CHOICES:
        raise ValueError(f"branch_and_bound: expected one of {list(BNB_CHOICES)}, got {branch_and_bound!r}")
    ctx_options = {"bnb": branch_and_bound, **(ctx_options or {})}
    jac = as_array(jac, "jac", (None, None, None, 2, 6))
    P, S, N = jac.shape[:3]
    visible = np.asarray(visible, bool)
    if visible.shape != (P, S, N):
        raise ValueError(f"visible: expected shape ({P}, {S}, {N}), got {visible.shape}")
    if coverage == "each-station" and S > 1:
        r = _optimize_core(np.repeat(jac, S, axis=0), np.repeat(visible, S, axis=0), k, objective, rho,
                           min_visible, method, rng, fixed, conflict, coverage_fraction, weights, time_limit,
                           progress, ctx_options, "_rows", cliques)
        n_lit = r.n_lit.reshape(P, S).min(axis=1) if len(r.n_lit) == P * S else r.n_lit
        return dataclasses.replace(r, adop=r.adop[::S], pdop=r.pdop[::S], n_lit=n_lit,
                                   uncoverable=np.unique(r.uncoverable // S))
    return _optimize_core(jac, visible, k, objective, rho, min_visible, method, rng, fixed, conflict,
                          coverage_fraction, weights, time_limit, progress, ctx_options, coverage, cliques)


def _optimize_core(jac, visible, k, objective, rho, min_visible, method, rng, fixed, conflict,
                   coverage_fraction, weights, time_limit, progress, ctx_options, coverage, cliques=()):
    t0 = time.perf_counter()
    P, S, N = jac.shape[:3]
    if coverage == "_rows":  # pose copies p*S + s of each-station: station s's lit sensors
        lit = visible[np.arange(P), np.arange(P) % S]
    elif coverage == "joint":
        lit = visible.sum(axis=1).astype(np.int8)
    else:
        lit = None
    if method not in METHODS:
        raise ValueError(f"method: expected one of {sorted(METHODS)}, got {method!r}")
    obj = parse_objective(objective, weights)
    k = int(k)
    if not 1 <= k <= N:
        raise ValueError(f"k: expected 1 <= k <= {N} (number of candidates), got {k}")
    if not 0.0 <= rho < 1.0:
        raise ValueError(f"rho: expected 0 <= rho < 1, got {rho}")
    if not 0.0 < coverage_fraction <= 1.0:
        raise ValueError(f"coverage_fraction: expected 0 < f <= 1, got {coverage_fraction}")
    fixed = np.unique(np.asarray(fixed, int).ravel()).astype(int)
    if len(fixed) and (fixed.min() < 0 or fixed.max() >= N):
        raise ValueError(f"fixed: indices must be in [0, {N - 1}], got {fixed.tolist()}")
    if len(fixed) > k:
        raise ValueError(f"fixed: {len(fixed)} fixed sensors exceed k = {k}")
    n_cover = int(math.ceil(coverage_fraction * P - 1e-9))
    rng = np.random.default_rng(rng)
    problem = build_problem(jac, visible, rho, k, int(min_visible), obj, fixed, conflict, n_cover, lit, cliques)
    empty = np.zeros(0, int)
    nan_p = np.full(P, np.inf)

    def fail(status, msg, cov=None):
        return OptimizeResult(empty, np.inf, np.nan, np.nan, False, status, msg, nan_p, nan_p,
                              np.zeros(P, int), method, obj.name,
                              min_k=None if cov is None else cov.min_k,
                              uncoverable=empty if cov is None else cov.uncoverable,
                              timings={"total_s": time.perf_counter() - t0})

    if len(fixed) and conflict is not None and conflict[np.ix_(fixed, fixed)].any():
        return fail("infeasible", "two fixed sensors are closer than the minimum spacing")
    # coverage first (exact set-multicover MILP, fast): an impossible request is a status
    # (a warm start that covers is the proof without the MILP, e.g. the dense loop's later rounds)
    cov = analyse_coverage(problem.lit, k, problem.m, n_cover, fixed, conflict,
                           witness=(ctx_options or {}).get("warm_start"))
    if not cov.feasible:
        return fail(cov.status, cov.message, cov)
    if k == N:  # one selection only (scoring an existing layout): its value is the optimum
        out = MethodOutput(np.arange(N), exact_optimum=True, info={"note": "k = N: the only selection"})
        return _finish(problem, obj, out, method, t0, t0, t0, [], P)
    if time_limit is None and method == "pipeline":
        time_limit = DEFAULT_PIPELINE_TIME_S
    # the budget counts from the call (coverage analysis and relaxation included); the final exact
    # evaluation after the deadline takes well under a second
    deadline = (math.inf if time_limit is None
                else t0 + float(time_limit) - min(max(_FINISH_RESERVE_S, 0.08 * float(time_limit)), 2.0))
    ctx = Context(rng=rng, deadline=deadline, progress=progress, cover_start=cov.selection, **(ctx_options or {}))
    if not cov.decided:
        ctx.notes.append(cov.message)
    t1 = time.perf_counter()
    try:
        out = METHODS[method](problem, ctx)
    except (Interrupted, KeyboardInterrupt) as exc:
        sig = getattr(exc, "signame", "SIGINT")
        r = fail("interrupted", f"{method}: interrupted by {sig} before a layout was found")
        return dataclasses.replace(r, info={"interrupted": sig})
    t2 = time.perf_counter()
    if out.selected is None and ctx.interrupted:
        return dataclasses.replace(fail("interrupted", f"{method}: interrupted by {ctx.interrupted} before a "
                                        f"layout was found"), info={"interrupted": ctx.interrupted})
    if out.selected is None:
        cov = analyse_coverage(problem.lit, k, problem.m, n_cover, fixed, conflict)
        if not cov.feasible:
            return fail(cov.status, cov.message, cov)
        why = ("; ".join(ctx.notes) + "; ") if ctx.notes else ""
        if not cov.decided:  # the MILP's time limit: a k-cover is neither found nor ruled out
            return fail("no_feasible_found", f"{why}method {method!r} found no feasible layout; {cov.message}", cov)
        kmin = cov.min_k if cov.min_k is not None else minimum_k(problem.lit, problem.m, n_cover, fixed, conflict)[0]
        cov = dataclasses.replace(cov, min_k=kmin)
        hint = "give it more time (--time-limit-s)" if method == "pipeline" else "try method 'pipeline'"
        return fail("no_feasible_found", f"{why}method {method!r} found no feasible layout although one "
                    f"exists (smallest k = {kmin}); {hint}", cov)
    res = _finish(problem, obj, out, method, t0, t1, t2, ctx.notes, P)
    if ctx.interrupted:
        res = dataclasses.replace(res, status="interrupted", info={**res.info, "interrupted": ctx.interrupted},
                                  message=res.message + " [interrupted: best so far]")
    return res


def _finish(problem, obj, out, method, t0, t1, t2, notes, P):
    """OptimizeResult of a method's selection: exact values, bound, gap, status, message."""
    empty = np.zeros(0, int)
    sel = np.sort(np.asarray(out.selected, int))
    d = exact_dop(problem, sel)
    adop = np.asarray(d.adop, float)
    pdop = np.asarray(d.pdop, float)
    n_lit = problem.lit[:, sel].sum(axis=1)
    mask = n_lit >= problem.m
    value = float(obj.aggregate_values(obj.from_dop(adop, pdop), mask))
    if out.exact_optimum:
        bound, how = value, "exhaustive"
    elif out.relaxation is not None:
        bound, how = out.relaxation.bound, out.relaxation.certified_by
    else:
        bound, how = fallback_bound(problem), "trace"
    if how == "none":  # no valid bound: say so instead of a meaningless gap (issue 13, item 5)
        gap = float("nan")
        why = out.relaxation.status if out.relaxation is not None else ""
        bound_txt = f"bound: none ({why})"
    else:
        gap = value / bound - 1.0 if bound > 0 and np.isfinite(bound) else np.inf
        bound_txt = f"certified bound {bound:.6g} ({how}), gap {100 * gap:.2f}%"
    status = "optimal" if out.exact_optimum else "ok"
    msg = (f"{method}: {obj.name} = {value:.6g} ({'deg/rad' if obj.metric == 'adop' else 'm/rad' if obj.metric == 'pdop' else 'weighted'}), "
           + bound_txt)
    if notes:
        msg += "; " + "; ".join(notes)
    timings = {"total_s": time.perf_counter() - t0, "method_s": t2 - t1}
    info = dict(out.info)
    if out.relaxation is not None:
        timings["relaxation_s"] = out.relaxation.time_s
        if out.relaxation.active is not None and len(out.relaxation.active):
            info["active_poses"] = np.asarray(out.relaxation.active, int)
        if how in ("relaxation", "branch-and-bound"):  # the fractional z: a site ranking for later searches
            info["relaxation_z"] = np.asarray(out.relaxation.z, float)
    return OptimizeResult(sel, value, float(bound), float(gap), True, status, msg, adop, pdop, n_lit,
                          method, obj.name, how, None, empty, timings, info)
