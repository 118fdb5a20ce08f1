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
from per-pose closed-form bounds (see :func:`pose_trace_bounds`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .problem import Problem

__all__ = ["RelaxResult", "relax", "pose_trace_bounds"]

# relative safety margin on the solver's optimal value (Clarabel's default gap tolerance is 1e-8)
_SAFETY = 1e-5


@dataclass(frozen=True)
class RelaxResult:
    """z : (N,) fractional selection in [0, 1]; bound : certified lower bound on the objective
    (d units: deg/rad for ADOP, m/rad for PDOP), or the fallback bound; certified_by :
    "relaxation" or "trace"; status : solver status; time_s : wall time of build + solve."""

    z: np.ndarray
    bound: float
    certified_by: str
    status: str
    time_s: float


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


def _fallback_bound(problem: Problem) -> float:
    L = pose_trace_bounds(problem)
    agg = problem.objective.aggregate
    if problem.n_cover < problem.P:
        # the worst over >= n_cover poses is at least the n_cover-th smallest L_p
        Ls = np.sort(L)
        if agg == "worst":
            return float(Ls[problem.n_cover - 1])
        return float(Ls[0])  # a loose but valid bound for mean/percentile over an unknown subset
    if agg == "worst":
        return float(L.max())
    if agg == "mean":
        return float(L.mean())
    return float(np.percentile(L, problem.objective.q))


def relaxed_pose_values(problem: Problem, z, use_rho=True) -> np.ndarray:
    """Per-pose relaxed squared values ``trace(W F_p(z)^-1)`` (P,) at a fractional z (numpy)."""
    rho = problem.rho
    A = np.einsum("pnij,n->pij", problem.G, z)
    if use_rho and rho > 0:
        b = np.einsum("pncj,n->pcj", problem.U, z)
        C = b.shape[1]
        n_s = np.einsum("psn,n->ps", problem.vis.astype(float), z)[:, np.arange(C) // 2]
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


def relax(problem: Problem, solver: str = "CLARABEL", time_limit=None, use_rho=True,
          initial_poses=24, add_poses=16, max_rounds=6) -> RelaxResult:
    """Convex relaxation by pose generation; return the fractional z and a certified lower bound.

    The worst case over a subset of poses is a lower bound on the worst case over all poses, so the
    relaxation starts from the ``initial_poses`` poses that are worst at the uniform z = k/N, adds
    the ``add_poses`` most violated poses at the relaxed z and re-solves, until no pose exceeds the
    relaxed optimum (then it equals the full relaxation) or ``max_rounds``. Every round's value is a
    valid bound. use_rho : bound the rho term through the GLS information (module docstring);
    False gives the design's ``(1 - rho) A^-1`` relaxation.
    """
    t0 = time.perf_counter()
    P = problem.P
    if problem.objective.aggregate != "worst" or P <= initial_poses:
        r = _relax_poses(problem, np.arange(P), solver, time_limit, use_rho)
        return RelaxResult(r.z, r.bound, r.certified_by, r.status, time.perf_counter() - t0)
    if problem.n_cover < P:
        max_rounds = 1  # the relaxation only seeds the rounding here (the bound is the trace bound)
    z0 = np.full(problem.N, problem.k / problem.N)
    v0 = relaxed_pose_values(problem, z0, use_rho)
    active = np.argsort(-v0)[:initial_poses]
    best = None
    for rnd in range(max_rounds):
        r = _relax_poses(problem, np.sort(active), solver, time_limit, use_rho)
        if best is None or (r.certified_by == "relaxation" and r.bound >= best.bound) or best.certified_by != "relaxation":
            best = r
        if r.certified_by != "relaxation" and not r.status.startswith("optimal"):
            break
        v = np.sqrt(relaxed_pose_values(problem, r.z, use_rho))
        viol = np.setdiff1d(np.flatnonzero(v > r.bound * (1 + 1e-4)), active)
        if len(viol) == 0:
            break
        active = np.r_[active, viol[np.argsort(-v[viol])][:add_poses]]
    return RelaxResult(best.z, best.bound, best.certified_by,
                       f"{best.status} ({len(active)} of {P} poses active)", time.perf_counter() - t0)


def _relax_poses(problem: Problem, poses, solver="CLARABEL", time_limit=None, use_rho=True) -> RelaxResult:
    """One relaxation with the DOP epigraph over ``poses`` (coverage cuts over all poses)."""
    import cvxpy as cp

    t0 = time.perf_counter()
    P, N, k, rho = problem.P, problem.N, problem.k, problem.rho
    obj = problem.objective
    wsel = np.flatnonzero(obj.w > 0)
    E = np.zeros((6, len(wsel)))
    E[wsel, np.arange(len(wsel))] = np.sqrt(obj.w[wsel])
    C = problem.U.shape[2]
    station_of_row = np.arange(C) // 2

    z = cp.Variable(N)
    cons = [z >= 0, z <= 1, cp.sum(z) == k]
    if len(problem.fixed):
        cons.append(z[problem.fixed] == 1)
    if problem.n_cover >= P:
        cons.append(problem.lit.astype(float) @ z >= problem.m)
    if problem.conflict is not None:
        i, j = np.nonzero(np.triu(problem.conflict, 1))
        if len(i):
            cons.append(z[i] + z[j] <= 1)
    use_gls = use_rho and rho > 0
    t = cp.Variable(len(poses)) if obj.aggregate != "worst" else cp.Variable()
    Gsum = problem.G.sum(axis=1) * (k / N)
    Ds, cs = [], []
    for p in poses:
        ev, evec = np.linalg.eigh(Gsum[p])
        ev = np.maximum(ev, max(ev.max(), 1e-300) * 1e-12)
        D = (evec / np.sqrt(ev)) @ evec.T  # D_p = (k/N sum_i G_ip)^(-1/2)
        Ds.append(D)
        cs.append(float(np.sum((D @ E) ** 2)))  # value at the uniform z = k/N (whitened A = I)
    cbar = float(np.median(cs))
    for q, p in enumerate(poses):
        idx = np.flatnonzero(problem.lit[p])
        if len(idx) == 0:
            continue
        D, c = Ds[q], cs[q]
        DE = D @ E / np.sqrt(c)
        Gw = np.einsum("ab,nbc,cd->nad", D, problem.G[p, idx], D).reshape(len(idx), 36).T
        zi = z[idx]
        Ax = cp.reshape(Gw @ zi, (6, 6), order="C")
        Ax = (Ax + Ax.T) / 2
        if use_gls:
            n0 = max(problem.m, 1)
            g = np.sqrt(rho / (1 - rho + rho * n0))
            Bw = np.einsum("ab,ncb->nca", D, problem.U[p, idx]).reshape(len(idx), C * 6).T
            Bx = cp.reshape(Bw @ zi, (C, 6), order="C").T * g  # (6, C) = g D [b_1 .. b_C]
            vis_s = problem.vis[p][:, idx].astype(float)  # (S, n_p)
            s = (1 - rho + rho * (vis_s @ zi)) / (1 - rho + rho * n0)  # g² s_c / rho, (S,)
            X = cp.Variable((6, 6), symmetric=True)
            Sd = cp.diag(cp.hstack([s[int(r)] for r in station_of_row]))
            M = cp.bmat([[Ax - X, Bx], [Bx.T, Sd]])
            cons.append((M + M.T) / 2 >> 0)
            info, fac = X, 1 - rho
        else:
            info, fac = Ax, 1.0 - rho  # H ⪰ (1 - rho) A^-1 (design §6)
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
    fallback = _fallback_bound(problem)
    if (status == "optimal" and obj.aggregate == "worst" and problem.n_cover >= P
            and prob.value is not None and np.isfinite(prob.value)):
        b = float(np.sqrt(max(prob.value, 0.0) * cbar * (1 - _SAFETY)))
        bound, how = max(b, fallback), "relaxation" if b >= fallback else "trace"
    else:
        bound, how = fallback, "trace"
    return RelaxResult(zval, bound, how, status, time.perf_counter() - t0)
