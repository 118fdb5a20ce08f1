"""Convex relaxation (cvxpy + Clarabel) and certified lower bounds (design §6; Joshi & Boyd 2009).

For a 0/1 selection z the exact pose covariance is the least-squares one,
``H_p = A^-1 J^T R J A^-1`` (Chen eq. 18). The Gauss–Markov theorem gives
``H_p ⪰ (J^T R^-1 J)^-1`` and, per station and axis, ``R^-1 = ((1-rho) I + rho 11^T)^-1 =
(I - rho 11^T / (1 - rho + rho n)) / (1 - rho)`` (Sherman–Morrison), so

    J^T R^-1 J = (A_p - rho sum_c b_c b_c^T / (1 - rho + rho n_s(c))) / (1 - rho)   =: F_p(z)

with A, b, n affine in z. ``b b^T / s`` is matrix-convex in (b, s), so F_p is matrix-concave and
``trace(W F_p(z)^-1)`` is convex in z: relaxing z to [0, 1]^N keeps a convex problem whose optimum
is a lower bound on the exact objective over every feasible 0/1 selection. This bounds the rho term
instead of dropping it; ``(1 - rho) A^-1`` (the design's bound) is the special case b = 0 and is
never tighter. As cvxpy constraints, per pose p (whitened with ``D_p = ((k/N) sum_i G_ip)^(-1/2)``):

    [[D A D - X_p, g D B], [g B^T D, g² diag(s)/rho]] ⪰ 0,   (1 - rho) matrix_frac(D E, X_p) <= t

plus the valid cuts ``sum_i lit_ip z_i >= m`` (coverage), ``z_i + z_j <= 1`` (spacing) and
``z_fixed = 1``. Worst case: minimise t (epigraph). For mean/percentile objectives the joint
relaxation of the mean of squared DOP gives the fractional z for rounding, and the bound comes
from per-pose bounds (:func:`pose_relaxation_bounds`, :func:`pose_trace_bounds`) aggregated by
:func:`aggregate_pose_bounds`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .problem import Problem, conflict_pairs

__all__ = ["RelaxResult", "relax", "pose_trace_bounds", "fallback_bound"]

# relative safety margin on the solver's optimal value (Clarabel's default gap tolerance is 1e-8)
_SAFETY = 1e-5
# per-pose bounds come from a decoupled sum: each pose's share of the solver tolerance is larger
_POSE_SAFETY = 1e-4


@dataclass(frozen=True)
class RelaxResult:
    """z : (N,) fractional selection in [0, 1]; bound : certified lower bound on the objective
    (d units: deg/rad for ADOP, m/rad for PDOP), or the fallback bound; certified_by :
    "relaxation", "trace", "per-pose relaxation" or "none" (no valid relaxation bound: bound NaN, reason
    in status); status : solver status; time_s : wall time of build + solve; trace_bound : the
    closed-form bound (always valid, loose); active : pose indices of the last pose-generation round."""

    z: np.ndarray
    bound: float
    certified_by: str
    status: str
    time_s: float
    trace_bound: float = float("nan")
    active: np.ndarray = None


def pose_trace_bounds(problem: Problem) -> np.ndarray:
    """Closed-form per-pose lower bounds ``L_p`` (P,) on d_p for any k-subset.

    ``(A^-1)_rr ⪰ (A_rr)^-1`` and ``tr(X^-1) >= 9 / tr(X)`` for 3 × 3 X ≻ 0, and
    ``tr(A_rr(z)) <= sum of the k largest lit tr(G_ip,rr)``; with ``H ⪰ (1 - rho) A^-1``:
    ``d_p² >= (1 - rho) (w_r 9 / top_k tr G_rr + w_t 9 / top_k tr G_tt)``.
    """
    w = problem.objective.w
    tr_r = np.trace(problem.G[..., :3, :3], axis1=-2, axis2=-1)
    tr_t = np.trace(problem.G[..., 3:, 3:], axis1=-2, axis2=-1)
    k = problem.k
    top_r = -np.sort(-tr_r, axis=1)[:, :k].sum(axis=1)
    top_t = -np.sort(-tr_t, axis=1)[:, :k].sum(axis=1)
    with np.errstate(divide="ignore"):
        v = (1 - problem.rho) * (w[0] * 9 / top_r + w[3] * 9 / top_t)
    return np.sqrt(np.where(np.isfinite(v), v, np.inf))


def _pose_information(cp, problem: Problem, p, zi, idx, D, use_gls):
    """Whitened information of pose p as a cvxpy expression: ``(info, fac, constraints)`` with
    ``trace(W H_p) >= fac * matrix_frac(D E, info)`` at every 0/1 point (module docstring)."""
    rho = problem.rho
    C = problem.U.shape[2]
    Gw = np.einsum("ab,nbc,cd->nad", D, problem.G[p, idx], D).reshape(len(idx), 36).T
    Ax = cp.reshape(Gw @ zi, (6, 6), order="C")
    Ax = (Ax + Ax.T) / 2
    if not use_gls:
        return Ax, 1.0 - rho, []  # H ⪰ (1 - rho) A^-1 (design §6)
    n0 = max(problem.m, 1)
    g = np.sqrt(rho / (1 - rho + rho * n0))
    Bw = np.einsum("ab,ncb->nca", D, problem.U[p, idx]).reshape(len(idx), C * 6).T
    Bx = cp.reshape(Bw @ zi, (C, 6), order="C").T * g  # (6, C) = g D [b_1 .. b_C]
    vis_s = problem.vis[p][:, idx].astype(float)  # (S, n_p)
    s = (1 - rho + rho * (vis_s @ zi)) / (1 - rho + rho * n0)  # g² s_c / rho, (S,)
    X = cp.Variable((6, 6), symmetric=True)
    Sd = cp.diag(cp.hstack([s[int(r)] for r in np.arange(C) // 2]))
    M = cp.bmat([[Ax - X, Bx], [Bx.T, Sd]])
    return X, 1 - rho, [(M + M.T) / 2 >> 0]


def _whitening(problem: Problem, poses, E, weights=None):
    """Per-pose ``D_p = (sum_i w_i G_ip)^(-1/2)`` and the scale ``c_p = |D_p E|_F²``, at site weights
    ``w`` (N,) — default the uniform ``w = k/N`` (whitened A = I there). A branch-and-bound node that
    forbids many sites centres it on its own region instead. Scaling changes conditioning only."""
    if weights is None:
        Gsum = problem.G[poses].sum(axis=1) * (problem.k / problem.N)
    else:
        Gsum = np.einsum("pnij,n->pij", problem.G[poses], np.asarray(weights, float))
    Ds, cs = [], []
    for Gp in Gsum:
        ev, evec = np.linalg.eigh(Gp)
        ev = np.maximum(ev, max(ev.max(), 1e-300) * 1e-12)
        D = (evec / np.sqrt(ev)) @ evec.T
        Ds.append(D)
        cs.append(float(np.sum((D @ E) ** 2)))
    return Ds, cs


def _weight_matrix(obj):
    wsel = np.flatnonzero(obj.w > 0)
    E = np.zeros((6, len(wsel)))
    E[wsel, np.arange(len(wsel))] = np.sqrt(obj.w[wsel])
    return E


def pose_relaxation_bounds(problem: Problem, poses=None, batch=16, use_rho=True, deadline=None,
                           solver="CLARABEL") -> np.ndarray:
    """Per-pose certified lower bounds ``L_p`` on d_p (P,), each from its own relaxation.

    For each pose alone: minimise the relaxed value over its lit candidates with
    ``0 <= z <= 1``, ``sum z <= k``, ``sum z >= m``, fixed lit sensors = 1 (a relaxation of every
    feasible layout, so ``d_p >= L_p`` whenever the pose is covered). Poses are solved in decoupled
    batches; poses not reached before ``deadline`` keep the closed-form trace bound. Each entry is
    the larger of the two bounds.
    """
    import warnings

    import cvxpy as cp

    L = pose_trace_bounds(problem)
    poses = np.arange(problem.P) if poses is None else np.asarray(poses, int)
    E = _weight_matrix(problem.objective)
    use_gls = use_rho and problem.rho > 0
    fixed = set(problem.fixed.tolist())
    for s0 in range(0, len(poses), batch):
        if deadline is not None and time.perf_counter() > deadline:
            break
        chunk = [p for p in poses[s0:s0 + batch] if problem.lit[p].sum() >= problem.m
                 and problem.vis[p].any(axis=0).sum() >= 3]
        if not chunk:
            continue
        Ds, cs = _whitening(problem, chunk, E)
        t = cp.Variable(len(chunk))
        cons = []
        for q, p in enumerate(chunk):
            idx = np.flatnonzero(problem.vis[p].any(axis=0))  # information: lit by any station
            zp = cp.Variable(len(idx))
            # coverage cut in the rule's counts (lit by a given station / station-sensor pairs)
            cons += [zp >= 0, zp <= 1, cp.sum(zp) <= problem.k,
                     problem.lit[p, idx].astype(float) @ zp >= problem.m]
            fx = [j for j, i in enumerate(idx) if i in fixed]
            if fx:
                cons.append(zp[fx] == 1)
            info, fac, extra = _pose_information(cp, problem, p, zp, idx, Ds[q], use_gls)
            cons += extra
            cons.append(fac * cp.matrix_frac(Ds[q] @ E / np.sqrt(cs[q]), info) <= t[q])
        prob = cp.Problem(cp.Minimize(cp.sum(t)), cons)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                prob.solve(solver=solver)
        except cp.error.SolverError:
            continue
        if prob.status != "optimal" or t.value is None:
            continue
        for q, p in enumerate(chunk):
            v = float(np.sqrt(max(t.value[q], 0.0) * cs[q] * (1 - _POSE_SAFETY)))
            L[p] = max(L[p], v)
    return L


def aggregate_pose_bounds(problem: Problem, L) -> float:
    """Bound on the objective from per-pose bounds ``L (P,)`` (valid with coverage_fraction too).

    The objective is taken over the covered poses C, ``|C| >= n_cover``, and ``d_p >= L_p`` there;
    the worst, mean and any percentile of the ``j`` smallest L grow with j, so the smallest value
    over all admissible C comes from the ``n_cover`` smallest L.
    """
    L = np.asarray(L, float)
    if problem.n_cover < problem.P:
        L = np.sort(L)[: problem.n_cover]
    agg = problem.objective.aggregate
    if agg == "worst":
        return float(L.max())
    if agg == "mean":
        return float(L.mean())
    return float(np.percentile(L, problem.objective.q))


def fallback_bound(problem: Problem) -> float:
    """The cheap bound (per-pose trace bounds, aggregated) used when the relaxation is not solved."""
    return aggregate_pose_bounds(problem, pose_trace_bounds(problem))


def relaxed_pose_values(problem: Problem, z, use_rho=True) -> np.ndarray:
    """Per-pose relaxed squared values ``trace(W F_p(z)^-1)`` (P,) at a fractional z (numpy); only
    the sites with z != 0 are summed (z is sparse in branch-and-bound)."""
    rho = problem.rho
    nz = np.flatnonzero(np.asarray(z) != 0)
    z = np.asarray(z, float)[nz]
    A = np.einsum("pnij,n->pij", problem.G[:, nz], z)
    if use_rho and rho > 0:
        b = np.einsum("pncj,n->pcj", problem.U[:, nz], z)
        C = b.shape[1]
        n_s = np.einsum("psn,n->ps", problem.vis[:, :, nz].astype(float), z)[:, np.arange(C) // 2]
        A = A - rho * np.einsum("pci,pcj,pc->pij", b, b, 1.0 / (1 - rho + rho * n_s))
        fac = 1 - rho
    else:
        fac = 1 - rho
    with np.errstate(all="ignore"):
        ev = np.linalg.eigvalsh(A)
        ok = ev[:, 0] > 1e-12 * np.abs(ev[:, -1])
        Ainv = np.linalg.inv(np.where(ok[:, None, None], A, np.eye(6)))
    v = fac * np.einsum("pii,i->p", Ainv, problem.objective.w)
    return np.where(ok, v, np.inf)


def relax(problem: Problem, solver: str = "CLARABEL", time_limit=60.0, use_rho=True,
          initial_poses=24, add_poses=16, max_rounds=6, pose_bound_budget_s=30.0, deadline=None,
          active_poses=None) -> RelaxResult:
    """Convex relaxation by pose generation; return the fractional z and a certified lower bound.

    Worst case with full coverage: the worst case over a subset of poses is a lower bound on the
    worst case over all poses, so the relaxation starts from the ``initial_poses`` poses that are
    worst at the uniform z = k/N, adds the ``add_poses`` most violated poses at the relaxed z and
    re-solves, until no pose exceeds the relaxed optimum (then it equals the full relaxation) or
    ``max_rounds``. Every round's value is a valid bound.
    Mean / percentile objectives or ``coverage_fraction < 1``: the joint relaxation (mean of the
    squared values) only gives z for the rounding; the bound aggregates per-pose relaxation
    bounds (:func:`pose_relaxation_bounds`, within ``pose_bound_budget_s``) and the closed-form
    trace bounds (:func:`aggregate_pose_bounds`).
    use_rho : bound the rho term through the GLS information (module docstring); False gives the
    design's ``(1 - rho) A^-1`` relaxation.
    time_limit : seconds per conic solve (badly scaled input, e.g. a mesh in the wrong units, can
    make Clarabel crawl). deadline : perf_counter time by which the whole relaxation must end: each
    solve gets the remaining time as Clarabel's time limit, pose generation stops there (the last
    completed round's bound stays valid). A solve that ends without status ``optimal`` (time limit,
    ``optimal_inaccurate``, numerical failure) gives **no** relaxation bound: ``certified_by`` is then
    "none" and ``bound`` NaN, with the reason in ``status`` (the closed-form trace bound is kept in
    ``trace_bound``; it is valid but usually far too loose to be a meaningful gap).
    active_poses : pose indices to start the pose generation from (e.g. the previous round's).
    """
    t0 = time.perf_counter()
    deadline = float("inf") if deadline is None else float(deadline)

    def tl():
        rem = deadline - time.perf_counter()
        return max(min(time_limit if time_limit is not None else rem, rem), 0.05)
    P = problem.P
    joint = problem.objective.aggregate == "worst" and problem.n_cover >= P
    if not joint or P <= initial_poses:
        act = np.arange(P) if P <= initial_poses or problem.objective.aggregate != "worst" else None
        if act is None:  # worst case with a coverage fraction: z from the initial poses only
            z0 = np.full(problem.N, problem.k / problem.N)
            act = np.sort(np.argsort(-relaxed_pose_values(problem, z0, use_rho))[:initial_poses])
        best = _relax_poses(problem, act, solver, tl(), use_rho)
        n_active = len(act)
    else:
        z0 = np.full(problem.N, problem.k / problem.N)
        v0 = relaxed_pose_values(problem, z0, use_rho)
        active = np.argsort(-v0)[:initial_poses]
        if active_poses is not None:
            active = np.unique(np.r_[np.asarray(active_poses, int), active[: max(0, initial_poses - len(active_poses))]])
        best = None
        for rnd in range(max_rounds):
            if best is not None and time.perf_counter() >= deadline:
                break
            r = _relax_poses(problem, np.sort(active), solver, tl(), use_rho)
            if best is None or best.certified_by != "relaxation" or (
                    r.certified_by == "relaxation" and r.bound >= best.bound):
                best = r
            if r.certified_by != "relaxation" and not r.status.startswith("optimal"):
                break
            v = np.sqrt(relaxed_pose_values(problem, r.z, use_rho))
            viol = np.setdiff1d(np.flatnonzero(v > r.bound * (1 + 1e-4)), active)
            if len(viol) == 0:
                break
            active = np.r_[active, viol[np.argsort(-v[viol])][:add_poses]]
        n_active = len(active)
    bound, how = best.bound, best.certified_by
    if not joint:
        L = pose_relaxation_bounds(problem, use_rho=use_rho, solver=solver,
                                   deadline=min(time.perf_counter() + pose_bound_budget_s, deadline))
        b = aggregate_pose_bounds(problem, L)
        if b > bound:
            bound, how = b, "per-pose relaxation"
    return RelaxResult(best.z, bound, how, f"{best.status} ({n_active} of {P} poses active)",
                       time.perf_counter() - t0, best.trace_bound, np.asarray(active if joint and P > initial_poses else [], int))


def _relax_poses(problem: Problem, poses, solver="CLARABEL", time_limit=None, use_rho=True) -> RelaxResult:
    """One relaxation with the DOP epigraph over ``poses`` (coverage cuts over all poses)."""
    import cvxpy as cp

    t0 = time.perf_counter()
    P, N, k, rho = problem.P, problem.N, problem.k, problem.rho
    obj = problem.objective
    E = _weight_matrix(obj)

    z = cp.Variable(N)
    cons = [z >= 0, z <= 1, cp.sum(z) == k]
    if len(problem.fixed):
        cons.append(z[problem.fixed] == 1)
    if problem.n_cover >= P:
        cons.append(problem.lit.astype(float) @ z >= problem.m)
    i, j = conflict_pairs(problem)
    if len(i):
        cons.append(z[i] + z[j] <= 1)
    for c in problem.cliques:  # one orientation per site (tighter than its pairs)
        cons.append(cp.sum(z[c]) <= 1)
    use_gls = use_rho and rho > 0
    t = cp.Variable(len(poses)) if obj.aggregate != "worst" else cp.Variable()
    Ds, cs = _whitening(problem, poses, E)
    cbar = float(np.median(cs))
    for q, p in enumerate(poses):
        idx = np.flatnonzero(problem.vis[p].any(axis=0))  # information: lit by any station
        if len(idx) == 0:
            continue
        D, c = Ds[q], cs[q]
        DE = D @ E / np.sqrt(c)
        info, fac, extra = _pose_information(cp, problem, p, z[idx], idx, D, use_gls)
        cons += extra
        tp = t if obj.aggregate == "worst" else t[q]
        cons.append((fac * c / cbar) * cp.matrix_frac(DE, info) <= tp)
    if obj.aggregate == "worst":
        goal = cp.Minimize(t)
    else:
        goal = cp.Minimize(cp.sum(t) / len(poses))
    prob = cp.Problem(goal, cons)
    kw = {}
    if time_limit is not None:
        kw["time_limit"] = float(time_limit)
    import warnings

    try:
        with warnings.catch_warnings():  # an inaccurate solve is reported through the status
            warnings.simplefilter("ignore", UserWarning)
            prob.solve(solver=solver, **kw)
        status = str(prob.status)
    except cp.error.SolverError as exc:  # numerical failure is a status
        status = f"solver_error: {exc}"
    zval = None if z.value is None else np.clip(np.asarray(z.value, float), 0, 1)
    if zval is None:
        zval = np.full(N, k / N)
    fallback = fallback_bound(problem)
    joint = obj.aggregate == "worst" and problem.n_cover >= P
    if status == "optimal" and joint and prob.value is not None and np.isfinite(prob.value):
        b = float(np.sqrt(max(prob.value, 0.0) * cbar * (1 - _SAFETY)))
        bound, how = max(b, fallback), "relaxation" if b >= fallback else "trace"
    elif joint:  # inaccurate / cut / failed solve: its value certifies nothing (issue 13, item 5)
        bound, how = float("nan"), "none"
    else:
        bound, how = fallback, "trace"
    return RelaxResult(zval, bound, how, status, time.perf_counter() - t0, fallback)
