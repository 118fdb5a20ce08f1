"""The selection problem in array form, exact evaluation and feasibility checks.

Notation (design §6): candidates i = 1..N, poses p = 1..P, stations s = 1..S. Per candidate,
pose and station the angle Jacobian ``J_isp`` (2 × 6, Chen eqs. 10–14) is stacked into the rows
``U[p, i]`` (2S × 6), zero where the candidate is not lit. Information ``A_p = sum_i z_i U^T U``,
common-mode vectors ``b_p = sum_i z_i U[p, i]`` (one row per station and axis) and the exact
covariance ``H_p = (1 - rho) A_p^-1 + rho sum_c u_c u_c^T``, ``u_c = A_p^-1 b_pc`` (Chen eq. 18
rewritten, see :func:`layoutkit.dop.dop_from_jacobian`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..dop import dop_from_jacobian
from .objectives import Objective

__all__ = ["Problem", "build_problem", "pose_values_from_info", "exact_dop", "conflict_pairs"]


@dataclass(frozen=True)
class Problem:
    """Arrays of one selection problem (all SI, station frames).

    jac : (P, S, N, 2, 6) angle Jacobians; vis : (P, S, N) bool lit; rho : same-rotor correlation;
    k : sensors to choose; m : lit sensors needed per pose; fixed : (F,) indices forced in;
    conflict : (N, N) bool or None, pairs that cannot both be chosen (closer than the minimum spacing,
    two orientations of one site); n_cover : poses that must be covered (P for coverage_fraction = 1);
    objective : :class:`Objective`. cliques : tuple of index arrays of which at most one may be chosen
    (the orientations of one site: its pairs are conflicts too); the relaxations add ``sum_c z <= 1``
    for each, which is tighter than the pairwise ``z_i + z_j <= 1`` for three or more orientations.
    Derived: U (P, N, 2S, 6), G (P, N, 6, 6), lit (P, N) bool (lit by any station).
    """

    jac: np.ndarray
    vis: np.ndarray
    rho: float
    k: int
    m: int
    fixed: np.ndarray
    conflict: "np.ndarray | None"
    n_cover: int
    objective: Objective
    U: np.ndarray = field(repr=False, default=None)
    G: np.ndarray = field(repr=False, default=None)
    lit: np.ndarray = field(repr=False, default=None)
    cliques: tuple = ()

    @property
    def P(self) -> int:
        return self.jac.shape[0]

    @property
    def N(self) -> int:
        return self.jac.shape[2]

    @property
    def S(self) -> int:
        return self.jac.shape[1]


def build_problem(jac, vis, rho, k, m, objective, fixed=(), conflict=None, n_cover=None, lit=None,
                  cliques=()) -> Problem:
    """Assemble a :class:`Problem` from Jacobians ``(P, S, N, 2, 6)`` and visibility ``(P, S, N)``.

    lit : optional (P, N) coverage counts (bool or small ints) replacing "lit by any station"
    (the coverage rule, :mod:`layoutkit.coverage_rule`)."""
    jac = np.asarray(jac, float)
    vis = np.asarray(vis, bool)
    P, S, N = vis.shape
    U = (jac * vis[..., None, None]).transpose(0, 2, 1, 3, 4).reshape(P, N, 2 * S, 6)
    G = np.einsum("pnci,pncj->pnij", U, U)
    lit = vis.any(axis=1) if lit is None else np.asarray(lit)
    fixed = np.unique(np.asarray(fixed, int)).astype(int)
    cliques = tuple(np.asarray(c, int) for c in cliques if len(c) >= 2)
    return Problem(jac, vis, float(rho), int(k), int(m), fixed, conflict,
                   P if n_cover is None else int(n_cover), objective, U, G, lit, cliques)


def pose_values_from_info(A, b, rho, w, cond_max=1e12):
    """Squared weighted DOP per pose from information ``A (..., 6, 6)`` and ``b (..., C, 6)``.

    Returns ``(..., )`` values ``trace(W H)`` (inf where A is singular), W = diag(w). Computed by the
    fused kernel :func:`layoutkit.optimize.kernels.pose_values` (~100× the batched numpy algebra of
    :func:`pose_values_numpy`, which it matches to rounding and in the singular-pose test).
    """
    from .kernels import pose_values

    return pose_values(A, b, rho, w, cond_max)


def pose_values_numpy(A, b, rho, w, cond_max=1e12):
    """Batched-numpy reference of :func:`pose_values_from_info` (same arguments and result)."""
    A = np.asarray(A, float)
    tr = np.trace(A, axis1=-2, axis2=-1)[..., None, None] / 6.0
    tr = np.where(tr > 0, tr, 1.0)
    An = A / tr
    try:
        L = np.linalg.cholesky(An + 0.0)
        ok = np.ones(A.shape[:-2], bool)
    except np.linalg.LinAlgError:
        w_ = np.linalg.eigvalsh(An)
        ok = w_[..., 0] > w_[..., -1] / cond_max
        An = np.where(ok[..., None, None], An, np.eye(6))
        L = np.linalg.cholesky(An)
    # condition check on the Cholesky diagonal (cheap)
    d = np.diagonal(L, axis1=-2, axis2=-1)
    ok &= (d.min(-1) ** 2) > (d.max(-1) ** 2) / cond_max
    Ainv = np.linalg.inv(np.where(ok[..., None, None], An, np.eye(6))) / tr
    val = (1.0 - rho) * np.einsum("...ii,i->...", Ainv, w)
    if rho != 0.0:
        u = np.einsum("...ij,...cj->...ci", Ainv, b)
        val = val + rho * np.einsum("...ci,i,...ci->...", u, w, u)
    return np.where(ok, val, np.inf)


def subset_info(problem: Problem, Z):
    """Information ``A (B, P, 6, 6)``, ``b (B, P, C, 6)`` and lit counts ``(B, P)`` of subsets.

    Z : (B, N) 0/1 float or (B, k) int index arrays.
    """
    Z = np.asarray(Z)
    if Z.dtype.kind in "iu":
        A = problem.G[:, Z].sum(axis=2).transpose(1, 0, 2, 3)
        b = problem.U[:, Z].sum(axis=2).transpose(1, 0, 2, 3)
        n = problem.lit[:, Z].sum(axis=2).T
        return A, b, n
    P, N = problem.P, problem.N
    A = (Z @ problem.G.transpose(1, 0, 2, 3).reshape(N, -1)).reshape(len(Z), P, 6, 6)
    b = (Z @ problem.U.transpose(1, 0, 2, 3).reshape(N, -1)).reshape(len(Z), P, -1, 6)
    n = Z @ problem.lit.T.astype(float)
    return A, b, np.rint(n).astype(int)


def subset_pose_values(problem: Problem, sel) -> tuple[np.ndarray, np.ndarray]:
    """Per-pose d_p (P,) and lit counts (P,) of one subset (fast path, same math as exact_dop)."""
    A, b, n = subset_info(problem, np.asarray(sel, int)[None])
    v = pose_values_from_info(A[0], b[0], problem.rho, problem.objective.w)
    return np.sqrt(v), n[0]


def aggregate(problem: Problem, d, n):
    """Objective value from per-pose values ``d (..., P)`` and lit counts ``n (..., P)``.

    Poses with fewer than m lit sensors are excluded (they only occur when coverage_fraction < 1).
    """
    mask = n >= problem.m
    return problem.objective.aggregate_values(d, mask)


def feasible_counts(problem: Problem, n) -> np.ndarray:
    """Whether lit counts ``n (..., P)`` satisfy the coverage constraint."""
    return (np.asarray(n) >= problem.m).sum(axis=-1) >= problem.n_cover


def exact_dop(problem: Problem, sel):
    """:class:`layoutkit.dop.DopResult` of subset ``sel`` at every pose, from the core metric."""
    sel = np.asarray(sel, int)
    return dop_from_jacobian(problem.jac[:, :, sel], problem.rho, problem.vis[:, :, sel])


def conflict_pairs(problem: Problem):
    """``(i, j)`` index arrays (i < j) of the conflicting pairs the relaxations must state one by one: those
    not inside one clique of ``problem.cliques`` (whose single row ``sum_c z <= 1`` implies them)."""
    if problem.conflict is None:
        return np.zeros(0, int), np.zeros(0, int)
    i, j = np.nonzero(np.triu(problem.conflict, 1))
    if problem.cliques:
        label = np.full(problem.N, -1)
        for r, c in enumerate(problem.cliques):
            label[c] = r
        keep = (label[i] < 0) | (label[i] != label[j])
        i, j = i[keep], j[keep]
    return i, j
