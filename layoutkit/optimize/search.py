"""Combinatorial search: greedy, repair, swap local search with low-rank updates, exhaustive.

Local search (Joshi & Boyd 2009, extended): from a feasible k-subset, repeatedly apply the best
improving 1-swap (one sensor out, one in) and, at a 1-swap local optimum, the best improving
2-swap within a short list of promising sites; restarts and random kicks around the incumbent.

Evaluating a 1-swap exactly (rho term included) uses low-rank updates, vectorised over the
removed sensor r, the added candidate j and the poses p: ``A_-r^-1`` comes from one 6 × 6 inverse
per (r, p); adding j is a rank-2S update (Sherman–Morrison–Woodbury) with
``Q = A_-r^-1 U_j^T``, ``S = I + U_j Q``:

    A'^-1 = A_-r^-1 - Q S^-1 Q^T,    u' = A'^-1 b' = u_-r + Q S^-1 (I - Q^T b_-r^T)

For the worst-case objective, moves are screened on the currently critical poses (a move can only
improve the maximum if it improves every pose above the new value) and confirmed on all poses;
poses that refute a move join the critical set, so the 1-swap local optimum found is exact.

``local_search(..., cover=...)`` also keeps coverage-only poses covered (lit counts, no DOP): a
search on a working set of a large pose set then cannot uncover the poses it does not score.
"""
from __future__ import annotations

import itertools
import math
import time

import numpy as np

from .kernels import move_values
from .problem import Problem, aggregate, feasible_counts, pose_values_from_info, subset_info

__all__ = [
    "SearchState", "make_state", "repair", "greedy", "local_search", "exhaustive",
    "evaluate_subsets", "one_swap_values", "cover_one_swaps",
]

_EPS = 1e-9  # relative improvement needed to accept a move


class SearchState:
    """Incumbent subset with its per-pose information (internal, mutable by design)."""

    __slots__ = ("sel", "A", "b", "n", "v", "value")

    def __init__(self, problem: Problem, sel):
        self.sel = np.sort(np.asarray(sel, int))
        A, b, n = subset_info(problem, self.sel[None])
        self.A, self.b, self.n = A[0], b[0], n[0]
        self.v = pose_values_from_info(self.A, self.b, problem.rho, problem.objective.w)
        self.value = float(aggregate(problem, np.sqrt(self.v), self.n))


def make_state(problem, sel) -> SearchState:
    return SearchState(problem, sel)


def evaluate_subsets(problem: Problem, Z, chunk=2048):
    """Objective values ``(B,)`` and coverage feasibility ``(B,)`` of index subsets ``Z (B, k)``."""
    Z = np.asarray(Z, int)
    out = np.empty(len(Z))
    feas = np.empty(len(Z), bool)
    A0 = np.zeros((problem.P, 6, 6))
    b0 = np.zeros((problem.P,) + problem.U.shape[2:])
    allp = np.arange(problem.P)
    for s in range(0, len(Z), chunk):
        z = Z[s:s + chunk]
        n = problem.lit[:, z].sum(axis=2).T
        v = move_values(A0, b0, problem.G, problem.U, allp, np.zeros((len(z), 0), int), z, problem.rho,
                        problem.objective.w)
        out[s:s + chunk] = aggregate(problem, np.sqrt(v), n)
        feas[s:s + chunk] = feasible_counts(problem, n)
    return out, feas


# ----------------------------------------------------------------------------------------- moves

def _allowed_adds(problem: Problem, sel):
    """(N,) bool: candidates not selected; (k, N) bool spacing-allowed for each removed position."""
    N = problem.N
    notsel = np.ones(N, bool)
    notsel[sel] = False
    if problem.conflict is None:
        return notsel, None
    cf = problem.conflict[:, sel]  # (N, k)
    cnt = cf.sum(axis=1)
    ok = (cnt[None, :] - cf.T) == 0  # conflicts with sel minus the removed one
    return notsel, ok


def _swap_feasible(problem: Problem, st: SearchState, adds):
    """(k, M) bool: coverage, spacing and fixed-sensor feasibility of 1-swaps (sel[r] -> adds[j])."""
    lit = problem.lit
    r = st.n[None, :] - lit[:, st.sel].T  # (k, P) counts after removal
    base = (r >= problem.m).sum(axis=1)  # (k,)
    la = lit[:, adds]
    cov = base[:, None]
    for dlt in range(1, int(la.max(initial=1)) + 1):  # lit counts may exceed 1 (joint coverage rule)
        edge = (r == problem.m - dlt).astype(np.int32)  # (k, P): short by dlt after removal
        cov = cov + edge @ (la >= dlt).astype(np.int32)  # (k, M)
    ok = cov >= problem.n_cover
    ok &= ~np.isin(st.sel, problem.fixed)[:, None]
    _, sp = _allowed_adds(problem, st.sel)
    if sp is not None:
        ok &= sp[:, adds]
    return ok


def _removal(problem: Problem, st: SearchState, poses):
    """Inverse information and common-mode terms with each selected sensor removed.

    Returns Ai (k, Pc, 6, 6), bi (k, Pc, C, 6), Yi = Ai bi^T (k, Pc, 6, C), ok (k, Pc) bool.
    """
    sel = st.sel
    A = st.A[poses][None] - problem.G[poses][:, sel].transpose(1, 0, 2, 3)
    bi = st.b[poses][None] - problem.U[poses][:, sel].transpose(1, 0, 2, 3)
    tr = np.trace(A, axis1=-2, axis2=-1)[..., None, None] / 6
    tr = np.where(tr > 0, tr, 1.0)
    An = A / tr
    w, _ = np.linalg.eigh(An)
    ok = w[..., 0] > 1e-10 * w[..., -1]
    Ai = np.linalg.inv(np.where(ok[..., None, None], An, np.eye(6))) / tr
    Yi = Ai @ np.swapaxes(bi, -1, -2)
    return Ai, bi, Yi, ok


def one_swap_values(problem: Problem, st: SearchState, adds, poses, removal=None, chunk=256):
    """Exact squared pose values ``(k, M, Pc)`` after swapping sel[r] -> adds[j], at ``poses``.

    Low-rank (rank 2S) Woodbury update of ``A_-r^-1`` per added candidate; rho term via u.
    Moves whose removal makes a pose singular are evaluated by a direct inverse.
    """
    rho, w = problem.rho, problem.objective.w
    adds = np.asarray(adds, int)
    poses = np.asarray(poses, int)
    Ai, bi, Yi, ok = removal if removal is not None else _removal(problem, st, poses)
    k = len(st.sel)
    C = problem.U.shape[2]
    eye = np.eye(C)
    trWAi = np.einsum("kpii,i->kp", Ai, w)
    YWYi = np.einsum("kpic,i,kpic->kp", Yi, w, Yi)
    out = np.empty((k, len(adds), len(poses)))
    if C == 2:
        for q, p in enumerate(poses):
            out[:, :, q] = _one_swap_pose_c2(problem.U[p, adds], Ai[:, q], Yi[:, q], bi[:, q],
                                             trWAi[:, q], YWYi[:, q], w, rho)
    UpT = None if C == 2 else problem.U[poses].transpose(1, 0, 2, 3)  # (N, Pc, C, 6)
    Ai_ = Ai[:, None]  # (k, 1, Pc, 6, 6)
    bT = np.swapaxes(bi, -1, -2)[:, None]  # (k, 1, Pc, 6, C)
    Yi_ = Yi[:, None]
    for s in range(0, len(adds) if C != 2 else 0, chunk):
        Uj = UpT[adds[s:s + chunk]][None]  # (1, M, Pc, C, 6)
        Q = Ai_ @ np.swapaxes(Uj, -1, -2)  # (k, M, Pc, 6, C) = A_-r^-1 U_j^T
        S = eye + Uj @ Q  # (k, M, Pc, C, C)
        if C == 2:  # explicit 2 x 2 inverse
            det = S[..., 0, 0] * S[..., 1, 1] - S[..., 0, 1] * S[..., 1, 0]
            Sinv = np.stack([np.stack([S[..., 1, 1], -S[..., 0, 1]], -1),
                             np.stack([-S[..., 1, 0], S[..., 0, 0]], -1)], -2) / det[..., None, None]
        else:
            Sinv = np.linalg.inv(S)
        QtWQ = np.swapaxes(Q * w[:, None], -1, -2) @ Q
        trW = trWAi[:, None] - np.sum(Sinv * QtWQ, axis=(-2, -1))  # both symmetric
        val = (1 - rho) * trW
        if rho != 0:
            Mx = eye - np.swapaxes(Q, -1, -2) @ bT  # I - Q^T b_-r^T
            Yn = Yi_ + (Q @ Sinv) @ Mx
            val = val + rho * np.sum(Yn * Yn * w[:, None], axis=(-2, -1))
        out[:, s:s + chunk] = val
    bad = ~ok
    if bad.any():  # direct evaluation where the removal was singular
        rr, pp = np.nonzero(bad)
        for r_, p_ in zip(rr, pp):
            p = poses[p_]
            A = st.A[p] - problem.G[p, st.sel[r_]] + problem.G[p, adds]
            b = st.b[p] - problem.U[p, st.sel[r_]] + problem.U[p, adds]
            out[r_, :, p_] = pose_values_from_info(A, b, rho, w)
    return np.where(np.isfinite(out) & (out >= 0), out, np.inf)


def _mm2(a, b):
    """Batched 2 x 2 matrix product by components (numpy's matmul is slow on tiny stacks)."""
    return np.stack([
        np.stack([a[..., 0, 0] * b[..., 0, 0] + a[..., 0, 1] * b[..., 1, 0],
                  a[..., 0, 0] * b[..., 0, 1] + a[..., 0, 1] * b[..., 1, 1]], -1),
        np.stack([a[..., 1, 0] * b[..., 0, 0] + a[..., 1, 1] * b[..., 1, 0],
                  a[..., 1, 0] * b[..., 0, 1] + a[..., 1, 1] * b[..., 1, 1]], -1)], -2)


def _one_swap_pose_c2(Up, Ai, Yi, bi, trWAi, YWYi, w, rho):
    """One pose, one station (rank-2 update): squared values (k, M). BLAS for every 6-d product.

    Up (M, 2, 6) rows of the added candidates; Ai (k, 6, 6) = A_-r^-1; Yi (k, 6, 2) = A_-r^-1 b_-r^T;
    bi (k, 2, 6); trWAi, YWYi (k,). With V = U_j A_-r^-1 (= Q^T): S = I + V U_j^T,
    tr(W A'^-1) = tr(W A_-r^-1) - tr(S^-1 V W V^T), u' = Y_-r + Q S^-1 (I - V b_-r^T).
    """
    M = Up.shape[0]
    k = Ai.shape[0]
    Uf = Up.reshape(M * 2, 6)
    V = (Uf @ Ai).reshape(k, M, 2, 6)  # GEMM per r
    VW = V * w
    S = np.sum(V[:, :, :, None, :] * Up[None, :, None, :, :], axis=-1)
    S[..., 0, 0] += 1.0
    S[..., 1, 1] += 1.0
    det = S[..., 0, 0] * S[..., 1, 1] - S[..., 0, 1] * S[..., 1, 0]
    Sinv = np.stack([np.stack([S[..., 1, 1], -S[..., 0, 1]], -1),
                     np.stack([-S[..., 1, 0], S[..., 0, 0]], -1)], -2) / det[..., None, None]
    QtWQ = np.sum(VW[:, :, :, None, :] * V[:, :, None, :, :], axis=-1)
    val = (1 - rho) * (trWAi[:, None] - np.sum(Sinv * QtWQ, axis=(-2, -1)))
    if rho != 0:
        QtbT = (Uf @ Yi).reshape(k, M, 2, 2)  # u_c^T A_-r^-1 b_d
        QtWY = (VW.reshape(k, M * 2, 6) @ Yi).reshape(k, M, 2, 2)
        Mx = -QtbT
        Mx[..., 0, 0] += 1.0
        Mx[..., 1, 1] += 1.0
        Z = _mm2(Sinv, Mx)
        val = val + rho * (YWYi[:, None] + 2 * np.sum(QtWY * Z, axis=(-2, -1))
                           + np.sum(_mm2(QtWQ, Z) * Z, axis=(-2, -1)))
    return val


def _apply(problem: Problem, sel, remove, add):
    s = set(int(x) for x in sel)
    for r in np.atleast_1d(remove):
        s.discard(int(r))
    for a in np.atleast_1d(add):
        s.add(int(a))
    return np.array(sorted(s), int)


def cover_one_swaps(cover, m, sel, adds):
    """(k, M) bool: the 1-swaps sel[r] -> adds[j] keep ``m`` lit at every row of ``cover`` (Pc, N) counts."""
    sel = np.asarray(sel, int)
    lit_sel = cover[:, sel].astype(np.int32)  # (Pc, k)
    short = m - (lit_sel.sum(axis=1)[:, None] - lit_sel)  # (Pc, k): what the added candidate must bring
    ok = np.ones((len(sel), len(adds)), bool)
    for r in range(len(sel)):
        rows = np.flatnonzero(short[:, r] > 0)
        if rows.size:
            ok[r] = (cover[np.ix_(rows, adds)] >= short[rows, r][:, None]).all(axis=0)
    return ok


def _two_swap_covered(lit, n, m, out1, out2, in1, in2, chunk):
    """(L,) rows of ``lit`` (R, N) counts with ``m`` lit after each 2-swap (out1, out2) -> (in1, in2);
    ``n`` (R,): the counts before. Only rows a 2-swap can push below m are recounted."""
    risk = np.flatnonzero(n - 2 * int(lit.max(initial=1)) < m)
    lr = lit[risk].astype(np.int16)
    nr = n[risk].astype(np.int16)
    out = np.full(len(out1), len(n) - len(risk))
    for s in range(0, len(out1) if risk.size else 0, chunk):
        sl = slice(s, s + chunk)
        n2 = nr[None] - lr[:, out1[sl]].T - lr[:, out2[sl]].T + lr[:, in1[sl]].T + lr[:, in2[sl]].T
        out[sl] += (n2 >= m).sum(axis=-1)
    return out


def _cover_two_swaps(cover, m, sel, out1, out2, in1, in2, chunk=1024):
    """(L,) bool: the 2-swaps (out1, out2) -> (in1, in2) keep ``m`` lit at every row of ``cover``."""
    n = cover[:, np.asarray(sel, int)].sum(axis=1, dtype=np.int32)
    return _two_swap_covered(cover, n, m, out1, out2, in1, in2, chunk) >= len(cover)


def _best_one_swap(problem: Problem, st: SearchState, crit: set, deadline, cover=None):
    """Best improving 1-swap, or None. Updates ``crit`` (critical pose set) in place."""
    P = problem.P
    notsel, _ = _allowed_adds(problem, st.sel)
    adds = np.flatnonzero(notsel)
    if len(adds) == 0:
        return None
    feas = _swap_feasible(problem, st, adds)
    if cover is not None:
        feas &= cover_one_swaps(cover, problem.m, st.sel, adds)
    if not feas.any():
        return None
    worst = problem.objective.aggregate == "worst" and problem.n_cover >= P
    cur = st.value
    if not worst:
        vals = one_swap_values(problem, st, adds, np.arange(P))  # (k, M, P)
        nmat = st.n[None, None] - problem.lit[:, st.sel].T[:, None, :] + problem.lit[:, adds].T[None]
        agg = aggregate(problem, np.sqrt(vals), nmat)
        agg = np.where(feas & feasible_counts(problem, nmat), agg, np.inf)
        r, j = np.unravel_index(np.argmin(agg), agg.shape)
        if agg[r, j] < cur * (1 - _EPS):
            return st.sel[r], adds[j], float(agg[r, j])
        return None
    while True:
        if time.perf_counter() > deadline:
            return None
        cp_ = np.array(sorted(crit), int)
        vals = one_swap_values(problem, st, adds, cp_)  # (k, M, Pc)
        scr = np.sqrt(vals.max(axis=2))
        scr = np.where(feas, scr, np.inf)
        order = np.argsort(scr, axis=None)
        cand = [np.unravel_index(o, scr.shape) for o in order[:64] if scr.flat[o] < cur * (1 - _EPS)]
        if not cand:
            return None
        rr = np.array([c[0] for c in cand])
        jj = np.array([c[1] for c in cand])
        # full evaluation of the short list by direct factorisation (exact; fused kernel)
        v = np.sqrt(move_values(st.A, st.b, problem.G, problem.U, np.arange(P), st.sel[rr][:, None],
                                adds[jj][:, None], problem.rho, problem.objective.w))  # (L, P)
        full = v.max(axis=1)
        best = int(np.argmin(full))
        if full[best] < cur * (1 - _EPS):
            crit.update(np.argsort(-v[best])[:3].tolist())
            return st.sel[rr[best]], adds[jj[best]], float(full[best])
        # refuted: add the poses that refuted the short list
        new = set(np.argmax(v, axis=1).tolist()) - crit
        if not new:
            return None
        crit.update(new)


def _best_two_swap(problem: Problem, st: SearchState, crit: set, pool, deadline, max_moves=60000, cover=None):
    """Best improving 2-swap with additions from ``pool``, or None (exact evaluation)."""
    sel = st.sel
    rem = [r for r in range(len(sel)) if sel[r] not in set(problem.fixed.tolist())]
    pool = np.array([j for j in pool if j not in set(sel.tolist())], int)
    if len(rem) < 2 or len(pool) < 2:
        return None
    R2 = np.array(list(itertools.combinations(rem, 2)))
    J2 = np.array(list(itertools.combinations(range(len(pool)), 2)))
    if len(R2) * len(J2) > max_moves:
        J2 = J2[: max(1, max_moves // len(R2))]
    ri = np.repeat(np.arange(len(R2)), len(J2))
    ji = np.tile(np.arange(len(J2)), len(R2))
    out1, out2 = sel[R2[ri, 0]], sel[R2[ri, 1]]
    in1, in2 = pool[J2[ji, 0]], pool[J2[ji, 1]]
    lit = problem.lit
    # coverage, chunked; only poses a 2-swap can push below m are counted (the others stay covered)
    ok = _two_swap_covered(lit, st.n, problem.m, out1, out2, in1, in2, 8192) >= problem.n_cover
    if problem.conflict is not None:
        cf = problem.conflict
        for idx in range(len(ri)):
            if not ok[idx]:
                continue
            rest = sel[(sel != out1[idx]) & (sel != out2[idx])]
            if cf[in1[idx], in2[idx]] or cf[in1[idx], rest].any() or cf[in2[idx], rest].any():
                ok[idx] = False
    if cover is not None:
        ok &= _cover_two_swaps(cover, problem.m, sel, out1, out2, in1, in2)
    if not ok.any():
        return None
    ids = np.flatnonzero(ok)
    worst = problem.objective.aggregate == "worst" and problem.n_cover >= problem.P
    cur = st.value

    def vals_at(sub, poses):
        return np.sqrt(move_values(st.A, st.b, problem.G, problem.U, poses, np.c_[out1[sub], out2[sub]],
                                   np.c_[in1[sub], in2[sub]], problem.rho, problem.objective.w))

    if not worst:
        best, bv = None, cur * (1 - _EPS)
        for s in range(0, len(ids), 512):
            sub = ids[s:s + 512]
            v = vals_at(sub, np.arange(problem.P))
            n2 = (st.n[None] - lit[:, out1[sub]].T - lit[:, out2[sub]].T + lit[:, in1[sub]].T + lit[:, in2[sub]].T)
            a = aggregate(problem, v, n2)
            i = int(np.argmin(a))
            if a[i] < bv:
                best, bv = sub[i], float(a[i])
            if time.perf_counter() > deadline:
                break
        return None if best is None else ((out1[best], out2[best]), (in1[best], in2[best]), bv)
    while time.perf_counter() < deadline:
        cp_ = np.array(sorted(crit), int)
        scr = np.empty(len(ids))
        for s in range(0, len(ids), 8192):
            scr[s:s + 8192] = vals_at(ids[s:s + 8192], cp_).max(axis=1)
        order = np.argsort(scr)
        short = ids[order[:64]][scr[order[:64]] < cur * (1 - _EPS)]
        if len(short) == 0:
            return None
        v = vals_at(short, np.arange(problem.P))
        full = v.max(axis=1)
        i = int(np.argmin(full))
        if full[i] < cur * (1 - _EPS):
            crit.update(np.argsort(-v[i])[:3].tolist())
            m = short[i]
            return (out1[m], out2[m]), (in1[m], in2[m]), float(full[i])
        new = set(np.argmax(v, axis=1).tolist()) - crit
        if not new:
            return None
        crit.update(new)
    return None


def local_search(problem: Problem, sel, *, two_swap=True, pool_size=24, deadline=None, z=None,
                 progress=None, max_one_swaps=None, cover=None):
    """Swap local search from a feasible subset; returns ``(sel, value, n_moves)``.

    two_swap : also try 2-swaps among the ``pool_size`` most promising non-selected sites (ranked by
    their best 1-swap screening value and the relaxation ``z``). max_one_swaps : stop after this many
    1-swap moves (None: until a local optimum) — ``1``-swap sweeps of the reference method.
    cover : optional (Pc, N) lit counts (bool or small ints) at further poses whose DOP is not scored
    but where every move must keep ``problem.m`` sensors lit — the rest of a large pose set when the
    problem holds only a working set of it (a pose costs ``N`` bytes here, ~60 N in the problem).
    ``sel`` must already cover them.
    """
    if cover is not None:
        cover = np.asarray(cover)
        if cover.ndim != 2 or cover.shape[1] != problem.N:
            raise ValueError(f"cover: expected (poses, {problem.N}) lit counts, got shape {cover.shape}")
        if (cover[:, np.asarray(sel, int)].sum(axis=1) < problem.m).any():
            raise ValueError(f"cover: the start selection leaves some of its poses with fewer than {problem.m} lit")
    deadline = math.inf if deadline is None else deadline
    st = SearchState(problem, sel)
    crit = set(np.argsort(-st.v)[: min(8, problem.P)].tolist())
    moves = 0
    while time.perf_counter() < deadline:
        mv = _best_one_swap(problem, st, crit, deadline, cover)
        if mv is not None:
            st = SearchState(problem, _apply(problem, st.sel, mv[0], mv[1]))
            moves += 1
            if progress is not None:
                progress(st.value)
            if max_one_swaps is not None and moves >= max_one_swaps:
                break
            continue
        if not two_swap:
            break
        pool = _promising(problem, st, crit, z, pool_size)
        mv2 = _best_two_swap(problem, st, crit, pool, deadline, cover=cover)
        if mv2 is None:
            break
        st = SearchState(problem, _apply(problem, st.sel, mv2[0], mv2[1]))
        moves += 1
        if progress is not None:
            progress(st.value)
    return st.sel, st.value, moves


def _promising(problem: Problem, st: SearchState, crit, z, size):
    """Non-selected sites ranked by their best 1-swap value on the critical poses (and z)."""
    notsel, _ = _allowed_adds(problem, st.sel)
    adds = np.flatnonzero(notsel)
    cp_ = np.array(sorted(crit), int)
    vals = one_swap_values(problem, st, adds, cp_).max(axis=2).min(axis=0)
    order = list(adds[np.argsort(vals)][: size])
    if z is not None:
        zz = np.where(notsel, z, -1)
        for j in np.argsort(-zz)[: size // 2]:
            if j not in order and notsel[j]:
                order.append(int(j))
    return order


# ----------------------------------------------------------------------------- construction / repair

def _deficit(problem: Problem, n):
    """Coverage shortfall: sum over the poses of max(0, m - n), counting only what must be covered."""
    short = np.maximum(problem.m - n, 0)
    if problem.n_cover >= problem.P:
        return short.sum(axis=-1)
    # with a fraction: the (P - n_cover) largest shortfalls are forgiven
    s = np.sort(short, axis=-1)
    return s[..., : problem.n_cover].sum(axis=-1)


def repair(problem: Problem, sel, score=None, max_iter=None):
    """Swap sensors until the coverage (and spacing) constraints hold; None if it cannot.

    Each step takes the 1-swap that reduces the coverage shortfall most (ties: larger ``score``,
    e.g. the relaxation z). Spacing conflicts are removed first.
    """
    sel = np.array(sorted(set(int(s) for s in sel)), int)
    lit = problem.lit
    score = np.zeros(problem.N) if score is None else np.asarray(score, float)
    fixed = set(problem.fixed.tolist())
    max_iter = 4 * problem.k + 10 if max_iter is None else max_iter
    if problem.conflict is not None:  # resolve spacing conflicts greedily
        for _ in range(problem.k):
            cf = problem.conflict[np.ix_(sel, sel)]
            bad = np.flatnonzero(cf.any(axis=1) & ~np.isin(sel, list(fixed)))
            if len(bad) == 0:
                break
            drop = sel[bad[np.argmin(score[sel[bad]])]]
            keep = sel[sel != drop]
            okj = ~problem.conflict[:, keep].any(axis=1)
            okj[keep] = False
            okj[drop] = False
            if not okj.any():
                return None
            cand = np.flatnonzero(okj)
            n = lit[:, keep].sum(axis=1)
            d = _deficit(problem, n[None] + lit[:, cand].T)
            j = cand[np.lexsort((-score[cand], d))[0]]
            sel = np.sort(np.r_[keep, j])
    for _ in range(max_iter):
        n = lit[:, sel].sum(axis=1)
        d0 = _deficit(problem, n)
        if d0 == 0:
            return sel
        st_n = n
        removable = np.array([r for r in range(len(sel)) if sel[r] not in fixed], int)
        notsel = np.ones(problem.N, bool)
        notsel[sel] = False
        adds = np.flatnonzero(notsel)
        best = None
        for r in removable:
            base = st_n - lit[:, sel[r]]
            if problem.n_cover >= problem.P:  # only poses short after the removal add to the shortfall
                short = np.flatnonzero(base < problem.m)
                d = np.maximum(problem.m - (base[short][None] + lit[short][:, adds].T), 0).sum(axis=1)
            else:
                d = _deficit(problem, base[None] + lit[:, adds].T)
            if problem.conflict is not None:
                rest = sel[sel != sel[r]]
                d = np.where(problem.conflict[np.ix_(adds, rest)].any(axis=1), np.iinfo(np.int64).max, d)
            o = np.lexsort((-score[adds], d))[0]
            if best is None or (d[o], -score[adds[o]]) < (best[0], -score[best[2]]):
                best = (d[o], r, adds[o])
        if best is None or best[0] >= d0:
            return None
        sel = np.sort(np.r_[np.delete(sel, best[1]), best[2]])
    return None


def greedy(problem: Problem, rng=None, deadline=None):
    """Greedy construction: add the site that most reduces the coverage shortfall, then the
    regularised objective (``A + delta I`` keeps it defined before 6 angle pairs are in); repair.
    Returns None if ``deadline`` (perf_counter s) passes first."""
    lit = problem.lit
    sel = list(problem.fixed.tolist())
    tg = np.trace(problem.G, axis1=-2, axis2=-1)
    delta = 1e-3 * np.where(lit.any(axis=1), tg.sum(axis=1) / np.maximum(lit.sum(axis=1), 1), 1.0) / 6
    reg = delta[:, None, None] * np.eye(6)
    A = problem.G[:, sel].sum(axis=1) + reg
    b = problem.U[:, sel].sum(axis=1)
    while len(sel) < problem.k:
        if deadline is not None and time.perf_counter() > deadline:
            return None
        ok = np.ones(problem.N, bool)
        ok[sel] = False
        if problem.conflict is not None and sel:
            ok &= ~problem.conflict[:, sel].any(axis=1)
        cand = np.flatnonzero(ok)
        if len(cand) == 0:
            return None
        n = lit[:, sel].sum(axis=1)
        d = _deficit(problem, n[None] + lit[:, cand].T)
        vals = np.empty(len(cand))
        for s in range(0, len(cand), 256):
            if deadline is not None and time.perf_counter() > deadline:
                return None
            c = cand[s:s + 256]
            v = np.sqrt(move_values(A, b, problem.G, problem.U, np.arange(problem.P), np.zeros((len(c), 0), int),
                                    c[:, None], problem.rho, problem.objective.w))
            vals[s:s + 256] = problem.objective.aggregate_values(v)
        j = cand[np.lexsort((vals, d))[0]]
        sel.append(int(j))
        A = A + problem.G[:, j]
        b = b + problem.U[:, j]
    return repair(problem, sel)


# ------------------------------------------------------------------------------------ exhaustive

def exhaustive(problem: Problem, chunk=4096, deadline=None):
    """Best subset by enumerating every k-subset (vectorised numpy); ``(sel, value, n_feasible)``.

    Subsets must contain the fixed sensors and respect coverage and spacing. For small N only
    (C(24, 8) = 735k subsets takes seconds to minutes depending on P).
    """
    fixed = problem.fixed
    free = np.setdiff1d(np.arange(problem.N), fixed)
    kk = problem.k - len(fixed)
    it = itertools.combinations(free.tolist(), kk)
    best_v, best_s, nfeas = np.inf, None, 0
    while True:
        block = list(itertools.islice(it, chunk))
        if not block:
            break
        Z = np.array(block, int).reshape(len(block), kk)
        if len(fixed):
            Z = np.concatenate([np.broadcast_to(fixed, (len(Z), len(fixed))), Z], axis=1)
        if problem.conflict is not None:
            cf = problem.conflict[Z[:, :, None], Z[:, None, :]]
            Z = Z[~cf.any(axis=(1, 2))]
            if len(Z) == 0:
                continue
        n = problem.lit[:, Z].sum(axis=2).T
        Z = Z[feasible_counts(problem, n)]
        if len(Z) == 0:
            continue
        v, _ = evaluate_subsets(problem, Z, chunk=chunk)
        nfeas += len(Z)
        i = int(np.argmin(v))
        if v[i] < best_v:
            best_v, best_s = float(v[i]), np.sort(Z[i])
        if deadline is not None and time.perf_counter() > deadline:
            break
    return best_s, best_v, nfeas
