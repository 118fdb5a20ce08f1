"""The node relaxation of branch-and-bound built for Clarabel directly, with a dual (Lagrangian) bound.

Same relaxation as :mod:`layoutkit.optimize.relaxation` (design §6; Joshi & Boyd 2009): per pose
p of a working set, with ``F'_p(z) = A_p(z) - rho sum_c b_c b_c^T / (1 - rho + rho n_c(z))`` (the
GLS information times ``1 - rho``) and whitening ``D_p``, scale ``c_p``, ``g² = rho / (1 - rho + rho n0)``:

    M_p(z, T_p) = [[D A D,        D E / sqrt(c),  g D B   ],
                   [E^T D/sqrt(c), T_p,            0       ],
                   [g B^T D,       0,              diag(s) ]]  ⪰ 0,     (1 - rho) c_p / cbar tr(T_p) <= t

(Schur complements: the ``diag(s)`` block gives ``D F' D``, then ``T_p ⪰ E^T F'^-1 E / c_p``, so
``(1 - rho) c_p tr T_p >= trace(W F_p(z)^-1)``, the relaxed squared DOP). One LMI of size
``6 + w + C`` per pose, no auxiliary matrix variable; minimise t over ``lo <= z <= hi``,
``sum z = k``, group counts, coverage and spacing cuts.

**Why the bound is certified whatever the solver returns.** Clarabel solves the problem restricted
to a few sites (the parent's support plus the sites its dual prices best; column generation adds
more). Its dual ``y`` is then turned into a point of the dual cone that is *exactly* stationary in
the free variables t and T (PSD blocks shifted to their cone, each ``T`` block raised to a multiple
of I, everything scaled so the t-row duals sum to 1) and the Lagrangian with the box
``lo <= z <= hi`` kept primal is evaluated over **all** sites:

    g(y) = -b^T y + sum_i min(r_i lo_i, r_i hi_i),     r_i = A_i^T y   (A_i: site i's column)

Weak duality: ``g(y) <= t`` at every feasible point of the full node relaxation, hence ``sqrt(cbar
g(y))`` is a lower bound on the worst DOP of every 0/1 selection in the node — for any ``y`` in the
dual cone, so also after a time limit, an inaccurate solve or unconverged column generation
(they only make it weaker). Nothing of the solver's own objective value is trusted.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from .problem import Problem, conflict_pairs
from .relaxation import _weight_matrix, _whitening

__all__ = ["NodeSolve", "DirectRelaxation"]

# relative round-off margin on the dual bound (the bound is computed in floating point)
_ROUNDOFF = 1e-9
# column generation stops once the sites outside the restricted set lower the bound by less than
# this relative amount in total (the bound already includes that loss: it stays certified)
_PRICE_TOL = 2e-4
# Clarabel's relative gap tolerance: the bound is read from the dual, so a looser primal is harmless
_GAP_TOL = 1e-6


@dataclass(frozen=True)
class NodeSolve:
    """status : Clarabel's status of the last restricted solve ("infeasible" only for Clarabel's
    primal infeasibility certificate over the full site set; "almost_infeasible" gives no bound);
    bound : certified lower bound (d units) or -inf; z : (N,) primal point of the last restricted
    problem (zeros outside it) or None; rounds : column-generation solves;
    sites : size of the final site set; time_s : wall time; prices : (N,) reduced prices of all
    sites at the last dual point (they seed a child's site set) or None."""

    status: str
    bound: float
    z: "np.ndarray | None"
    rounds: int
    sites: int
    time_s: float
    prices: "np.ndarray | None" = None


def _svec_index(n):
    """Row/column pairs (r >= c) of the scaled upper-triangle vectorisation Clarabel uses
    (column-wise upper triangle == row-wise lower triangle) and the sqrt(2) off-diagonal scale."""
    r, c = np.tril_indices(n)
    return r, c, np.where(r == c, 1.0, math.sqrt(2.0))


class DirectRelaxation:
    """The node relaxation over any pose working set; each pose's LMI columns (over all sites) are
    assembled once, on first use, and cached, so every node may use its own pose set."""

    def __init__(self, problem: Problem, groups=(), use_rho=True, weights=None):
        self.problem = problem
        self.groups = [np.asarray(g, int) for g in groups]
        self.E = _weight_matrix(problem.objective)
        self.w = self.E.shape[1]
        self.use_gls = bool(use_rho and problem.rho > 0)
        self._D, self._c = _whitening(problem, np.arange(problem.P), self.E, weights)  # per pose, once
        self.cbar = float(np.median(self._c))  # one scale of t for every pose set
        self._cache = {}
        self.lit = problem.lit.astype(float)
        self.conflict_pairs = conflict_pairs(problem) if problem.conflict is not None else None

    def _pose(self, p):
        """``(A columns (m, N), b (m,), n, tfac)`` of pose p's LMI (module docstring), cached."""
        if p in self._cache:
            return self._cache[p]
        problem, w, E = self.problem, self.w, self.E
        N, rho = problem.N, problem.rho
        n0 = max(problem.m, 1)
        g = math.sqrt(rho / (1 - rho + rho * n0)) if self.use_gls else 0.0
        D, c = self._D[p], self._c[p]
        cols = [j for j in range(problem.U.shape[2]) if problem.vis[p, j // 2].any()] if self.use_gls else []
        C = len(cols)
        n = 6 + w + C
        r_, c_, sc = _svec_index(n)
        Mi = np.zeros((N, n, n))  # site part of M_p, blockwise
        Mi[:, :6, :6] = np.einsum("ab,nbc,cd->nad", D, problem.G[p], D)
        if C:
            DU = problem.U[p][:, cols] @ D  # (N, C, 6): rows D u_c (D symmetric)
            Mi[:, :6, 6 + w:] = g * DU.transpose(0, 2, 1)
            Mi[:, 6 + w:, :6] = g * DU
            st = np.asarray(cols) // 2
            Mi[:, 6 + w + np.arange(C), 6 + w + np.arange(C)] = (
                rho * problem.vis[p][st].T.astype(float) / (1 - rho + rho * n0))
        M0 = np.zeros((n, n))
        M0[:6, 6:6 + w] = D @ E / math.sqrt(c)
        M0[6:6 + w, :6] = M0[:6, 6:6 + w].T
        if C:
            M0[6 + w + np.arange(C), 6 + w + np.arange(C)] = (1 - rho) / (1 - rho + rho * n0)
        out = (np.ascontiguousarray(-(Mi[:, r_, c_] * sc).T), M0[r_, c_] * sc, n,
               (1.0 - rho) * c / self.cbar)
        self._cache[p] = out
        return out

    def _assemble(self, poses):
        """Stacked PSD rows of ``poses``: A (R, N), b (R,), cone sizes, t factors."""
        blocks = [self._pose(int(p)) for p in poses]
        self.psd, row = [], 0
        for blk in blocks:
            self.psd.append((row, blk[2]))
            row += len(blk[1])
        self.tfac = [blk[3] for blk in blocks]
        self.A_psd = np.vstack([blk[0] for blk in blocks])
        self.b_psd = np.concatenate([blk[1] for blk in blocks])

    # ------------------------------------------------------------------ assembly
    def _T_part(self):
        """Sparse columns of t and the T blocks in the PSD rows and the t rows."""
        import scipy.sparse as sp

        w = self.w
        rows, cols, vals = [], [], []
        trow, tcol, tval = [], [], []
        col = 1  # column 0 is t
        for q, (off, n) in enumerate(self.psd):
            r_, c_, sc = _svec_index(n)
            pos = {(int(a), int(b)): i for i, (a, b) in enumerate(zip(r_, c_))}
            for a in range(w):
                for b in range(a + 1):
                    rows.append(off + pos[(6 + a, 6 + b)])
                    cols.append(col)
                    vals.append(-1.0 if a == b else -math.sqrt(2.0))
                    if a == b:
                        trow.append(q)
                        tcol.append(col)
                        tval.append(self.tfac[q])
                    col += 1
            trow.append(q)
            tcol.append(0)
            tval.append(-1.0)
        nT = col
        A_T = sp.csc_matrix((vals, (rows, cols)), shape=(len(self.b_psd), nT))
        A_t = sp.csc_matrix((tval, (trow, tcol)), shape=(len(self.psd), nT))
        return A_T, A_t, nT

    def _linear_rows(self, lo, hi, glo, ghi, S):
        """Dualised linear rows over all sites: (A (L, N) dense, b (L,)) — sum z = k (zero
        cone, first), then nonnegative rows: non-trivial group bounds, coverage, spacing in S."""
        N, k = self.problem.N, self.problem.k
        A = [np.ones((1, N))]
        b = [np.array([float(k)])]
        for r, grp in enumerate(self.groups):
            if glo is not None and glo[r] > 0.5:
                a = np.zeros(N)
                a[grp] = -1.0
                A.append(a[None])
                b.append(np.array([-float(glo[r])]))
            if ghi is not None and ghi[r] < len(grp) - 0.5:
                a = np.zeros(N)
                a[grp] = 1.0
                A.append(a[None])
                b.append(np.array([float(ghi[r])]))
        A.append(-self.lit)
        b.append(np.full(self.problem.P, -float(self.problem.m)))
        if self.conflict_pairs is not None:
            inS = np.zeros(N, bool)
            inS[S] = True
            i, j = self.conflict_pairs
            keep = inS[i] & inS[j]
            if keep.any():
                a = np.zeros((int(keep.sum()), N))
                a[np.arange(keep.sum()), i[keep]] = 1.0
                a[np.arange(keep.sum()), j[keep]] = 1.0
                A.append(a)
                b.append(np.ones(int(keep.sum())))
        for c in self.problem.cliques:  # one orientation per site, over the sites in S (still valid)
            cs = c[np.isin(c, S)]
            if len(cs) >= 2:
                a = np.zeros(N)
                a[cs] = 1.0
                A.append(a[None])
                b.append(np.ones(1))
        return np.vstack(A), np.concatenate(b)

    # ------------------------------------------------------------------ dual bound
    def _dual_bound(self, y_lin, y_psd, y_t, lo, hi, A_lin, b_lin):
        """Certified Lagrangian value (t units) from any dual point (module docstring)."""
        y_lin = np.array(y_lin, float)
        y_lin[1:] = np.maximum(y_lin[1:], 0.0)  # nonnegative cone; row 0 (sum z = k) is free
        y_psd = np.array(y_psd, float)
        w = self.w
        lam = np.empty(len(self.psd))
        for q, (off, n) in enumerate(self.psd):
            r_, c_, sc = _svec_index(n)
            m = len(r_)
            Y = np.zeros((n, n))
            Y[r_, c_] = y_psd[off:off + m] / sc
            Y = Y + np.tril(Y, -1).T
            ev = np.linalg.eigvalsh(Y)
            if ev[0] < 0:
                Y = Y + (-ev[0]) * (1 + 1e-12) * np.eye(n)
            # T block: raise to lam * tfac * I (a PSD shift keeps Y in the cone)
            Ytt = Y[6:6 + w, 6:6 + w]
            lam_q = max(float(y_t[q]), float(np.linalg.eigvalsh(Ytt)[-1]) / self.tfac[q], 0.0)
            Y[6:6 + w, 6:6 + w] = lam_q * self.tfac[q] * np.eye(w)
            lam[q] = lam_q
            y_psd[off:off + m] = Y[r_, c_] * sc
        s = lam.sum()
        if not s > 0:
            return -math.inf, None
        alpha = 1.0 / s
        r = (A_lin.T @ y_lin + self.A_psd.T @ y_psd) * alpha  # (N,) reduced prices of the sites
        g = alpha * (-(b_lin @ y_lin) - (self.b_psd @ y_psd)) + np.minimum(r * lo, r * hi).sum()
        return float(g), r

    # ------------------------------------------------------------------ solve
    def solve(self, poses, lo, hi, glo=None, ghi=None, hint=None, prices=None, time_limit=None,
              max_rounds=6, add=64, initial_extra=None, max_iter=None) -> NodeSolve:
        """Certified bound of the node ``lo <= z <= hi``, group counts ``glo <= sum_g z <= ghi``,
        over the pose working set ``poses`` (a bound over fewer poses is smaller: still valid).

        hint : (N,) a point whose support starts the site set (the parent's z); prices : (N,)
        reduced prices from the parent (the ``initial_extra`` best-priced free sites join too,
        default 4k). max_iter : Clarabel's iteration cap (default its own). Column generation: up
        to ``max_rounds`` restricted solves, each adding the ``add`` sites whose prices lower the
        bound most; it stops once the sites left out lower it by less than 2e-4 relative in total.
        """
        import clarabel
        import scipy.sparse as sp

        t0 = time.perf_counter()
        problem = self.problem
        N, k = problem.N, problem.k
        lo = np.asarray(lo, float)
        hi = np.asarray(hi, float)
        free = (hi > 0.5)
        ones = np.flatnonzero(lo > 0.5)
        S = set(ones.tolist())
        if hint is not None:
            S |= set(np.flatnonzero((np.asarray(hint) > 1e-7) & free).tolist())
        extra = 4 * k if initial_extra is None else int(initial_extra)
        if prices is not None and extra > 0:
            pr = np.where(free & (lo < 0.5), np.asarray(prices, float), np.inf)
            top = np.argsort(pr)[:extra]
            S |= set(top[np.isfinite(pr[top])].tolist())
        if len(S) < k + 1:
            cand = np.flatnonzero(free)
            S |= set(cand[np.argsort(-self.lit[:, cand].sum(axis=0))][: 2 * k].tolist())
        self._assemble(np.asarray(poses, int))
        A_T, A_t, nT = self._T_part()
        best_g = -math.inf
        status = "not solved"
        rounds = 0
        z_last = prices_last = None
        full = False
        while True:
            Sa = np.array(sorted(S), int)
            full = len(Sa) >= int(free.sum())
            A_lin, b_lin = self._linear_rows(lo, hi, glo, ghi, Sa)
            nS = len(Sa)
            # x = [t, T..., z_S]; rows: zero (1) | nonneg: lin rows (L-1), box (2 nS), t rows | PSD
            Zs = sp.csc_matrix(A_lin[:, Sa])
            L = A_lin.shape[0]
            eye = sp.identity(nS, format="csc")
            A = sp.vstack([
                sp.hstack([sp.csc_matrix((L, nT)), Zs]),
                sp.hstack([sp.csc_matrix((nS, nT)), -eye]),
                sp.hstack([sp.csc_matrix((nS, nT)), eye]),
                sp.hstack([A_t, sp.csc_matrix((A_t.shape[0], nS))]),
                sp.hstack([A_T, sp.csc_matrix(self.A_psd[:, Sa])]),
            ], format="csc")
            b = np.concatenate([b_lin, -lo[Sa], hi[Sa], np.zeros(A_t.shape[0]), self.b_psd])
            q = np.zeros(nT + nS)
            q[0] = 1.0
            cones = [clarabel.ZeroConeT(1), clarabel.NonnegativeConeT(L - 1 + 2 * nS + A_t.shape[0])]
            cones += [clarabel.PSDTriangleConeT(n) for _, n in self.psd]
            st = clarabel.DefaultSettings()
            st.verbose = False
            st.tol_gap_rel = _GAP_TOL
            st.tol_gap_abs = _GAP_TOL
            st.iterative_refinement_enable = False  # ~25 % faster, same iterations; the dual bound needs no more
            if max_iter is not None:
                st.max_iter = int(max_iter)
            if time_limit is not None:
                st.time_limit = max(float(time_limit) - (time.perf_counter() - t0), 0.05)
            P0 = sp.csc_matrix((nT + nS, nT + nS))
            sol = clarabel.DefaultSolver(P0, q, A, b, cones, st).solve()
            rounds += 1
            status = str(sol.status)
            if status == "PrimalInfeasible" and full:
                return NodeSolve("infeasible", math.inf, None, rounds, nS, time.perf_counter() - t0)
            if "PrimalInfeasible" in status:
                if not full:  # restricted infeasibility proves nothing: all sites
                    S |= set(np.flatnonzero(free).tolist())
                    continue
                # only "almost" infeasible: no certificate, no bound beyond the parent's
                return NodeSolve("almost_infeasible", -math.inf, None, rounds, nS, time.perf_counter() - t0)
            y = np.asarray(sol.z, float)
            y_lin = y[:L]
            y_t = y[L + 2 * nS:L + 2 * nS + A_t.shape[0]]
            y_psd = y[L + 2 * nS + A_t.shape[0]:]
            if not (np.all(np.isfinite(y))):
                break
            gval, r = self._dual_bound(y_lin, y_psd, y_t, lo, hi, A_lin, b_lin)
            if r is None:
                break
            x = np.asarray(sol.x, float)
            z_last = np.zeros(N)
            z_last[Sa] = np.clip(x[nT:], 0.0, 1.0)
            best_g = max(best_g, gval)  # every round's dual bound is valid: keep the best
            prices_last = r
            # column generation: free sites outside S whose price lowers the bound
            out = np.setdiff1d(np.flatnonzero(free & (lo < 0.5)), Sa)
            if len(out) == 0 or rounds >= max_rounds or (time_limit is not None and time.perf_counter() - t0 > time_limit):
                break
            neg = out[r[out] < 0]
            if -(r[neg] * hi[neg]).sum() <= _PRICE_TOL * max(abs(gval), 1e-12):
                break
            S |= set(neg[np.argsort(r[neg])][:add].tolist())
        bound = math.sqrt(max(best_g, 0.0) * self.cbar * (1 - _ROUNDOFF)) if np.isfinite(best_g) else -math.inf
        status = {"Solved": "optimal", "AlmostSolved": "optimal_inaccurate"}.get(status, status)
        return NodeSolve(status, bound, z_last, rounds, len(S), time.perf_counter() - t0, prices_last)
