"""Coverage (at least m lit sensors per pose): feasibility analysis and the smallest k.

The smallest k is a set-multicover integer program, solved exactly with
``scipy.optimize.milp`` (HiGHS):

    minimise sum_i z_i  s.t.  sum_i v_ip z_i >= m y_p,  sum_p y_p >= n_cover,
    z_i + z_j <= 1 for pairs closer than the spacing,  z_fixed = 1,  z, y binary

(``y`` only when a fraction of poses may stay uncovered; otherwise ``y = 1``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["CoverageReport", "analyse_coverage", "minimum_k"]


@dataclass(frozen=True)
class CoverageReport:
    """Result of :func:`analyse_coverage`.

    feasible : whether k sensors can keep m lit at the required poses; min_k : smallest k that can
    (None if no k can or it was not computed exactly); uncoverable : (U,) pose indices with fewer than m lit candidates at all;
    status : "ok" | "infeasible" | "uncoverable"; success : ``status == "ok"``; message :
    plain-language explanation; decided : False when the MILP stopped at its time limit before it could
    prove or refute feasibility (``feasible`` is then True: not proven infeasible); selection : a cover of
    at most k sensors the MILP found (index array; None when feasibility was shown otherwise) — a start for
    searches that have found none of their own.
    """

    feasible: bool
    min_k: "int | None"
    uncoverable: np.ndarray
    status: str
    message: str
    decided: bool = True
    selection: "np.ndarray | None" = None

    @property
    def success(self) -> bool:
        """The request can be met (``status == "ok"``; layoutkit.status convention)."""
        return self.status == "ok"


def _counts(lit):
    """(P, N) coverage counts: bool (lit) or small non-negative ints (joint rule), kept as given."""
    lit = np.asarray(lit)
    return lit if lit.dtype == bool else lit.astype(np.int16)


def minimum_k(lit, m, n_cover=None, fixed=(), conflict=None, time_limit=30.0, return_bound=False):
    """Smallest number of sensors keeping ``m`` lit at ``n_cover`` poses (exact MILP).

    lit : (P, N) bool; m : int; n_cover : poses that must be covered (default all P);
    fixed : indices forced in; conflict : (N, N) bool pairs that cannot both be chosen.
    Returns ``(k_min, selection)`` or ``(None, None)`` if no selection works (or none was found within
    ``time_limit`` s). When HiGHS stops at the time limit its incumbent is only an upper bound on the
    smallest k: with ``return_bound`` the result is ``(k_upper, selection, k_lower)``, ``k_lower`` the
    MILP's proven lower bound (``k_upper == k_lower`` when solved to optimality; ``k_upper`` None when
    no cover was found in time, ``k_lower`` None when none exists).
    """
    from scipy.optimize import Bounds, LinearConstraint, milp
    from scipy.sparse import csr_matrix, hstack, vstack, identity, coo_matrix

    lit = _counts(lit)
    P, N = lit.shape
    n_cover = P if n_cover is None else int(n_cover)
    full = n_cover >= P
    V = csr_matrix(lit.astype(float))
    rows, lo, hi = [], [], []
    if full:
        nvar = N
        c = np.ones(N)
        rows.append(V)
        lo.append(np.full(P, float(m)))
        hi.append(np.full(P, np.inf))
    else:
        nvar = N + P
        c = np.r_[np.ones(N), np.zeros(P)]
        rows.append(hstack([V, -m * identity(P)]))
        lo.append(np.zeros(P))
        hi.append(np.full(P, np.inf))
        rows.append(csr_matrix(np.r_[np.zeros(N), np.ones(P)][None]))
        lo.append([float(n_cover)])
        hi.append([np.inf])
    if conflict is not None:
        i, j = np.nonzero(np.triu(np.asarray(conflict, bool), 1))
        if len(i):
            r = np.repeat(np.arange(len(i)), 2)
            C = coo_matrix((np.ones(2 * len(i)), (r, np.c_[i, j].ravel())), shape=(len(i), nvar))
            rows.append(C.tocsr())
            lo.append(np.full(len(i), -np.inf))
            hi.append(np.ones(len(i)))
    lb = np.zeros(nvar)
    ub = np.ones(nvar)
    lb[np.asarray(fixed, int)] = 1.0
    cons = LinearConstraint(vstack(rows).tocsr(), np.concatenate(lo), np.concatenate(hi))
    res = milp(c, constraints=cons, integrality=np.ones(nvar), bounds=Bounds(lb, ub),
               options={"time_limit": float(time_limit)})
    lower = None
    if res.status == 0:
        lower = int(round(res.fun))
    elif res.status == 1:  # time limit: the dual bound is what is proven (at least m, and the fixed sensors)
        dual = getattr(res, "mip_dual_bound", None)
        lower = max(len(np.unique(np.asarray(fixed, int))), int(m) if n_cover > 0 else 0,
                    int(np.ceil(dual - 1e-6)) if dual is not None and np.isfinite(dual) else 0)
    if res.x is None or res.status not in (0, 1):
        return (None, None, lower) if return_bound else (None, None)
    z = np.rint(res.x[:N]).astype(bool)
    out = (int(z.sum()), np.flatnonzero(z))
    return out + (lower,) if return_bound else out


def analyse_coverage(lit, k, m, n_cover=None, fixed=(), conflict=None, witness=None,
                     time_limit=30.0) -> CoverageReport:
    """Can ``k`` sensors keep ``m`` lit at the required poses? Explain if not.

    lit : (P, N) bool. Poses with fewer than m lit candidates in total are ``uncoverable``; the
    smallest workable k comes from :func:`minimum_k` (``time_limit`` s). witness : an index selection
    (e.g. the caller's warm start) that proves feasibility without the MILP when it has at most k
    sensors, holds the fixed ones, respects ``conflict`` and covers the required poses. "infeasible" is
    reported only when proven: a MILP stopped at its time limit whose lower bound is at most k leaves
    the request undecided, which is reported feasible (the search then finds a cover or says it found none).
    """
    lit = _counts(lit)
    P, N = lit.shape
    n_cover = P if n_cover is None else int(n_cover)
    counts = lit.sum(axis=1)
    unc = np.flatnonzero(counts < m)
    if len(unc) > P - n_cover:
        show = ", ".join(f"{p} ({counts[p]} lit)" for p in unc[:20]) + (" ..." if len(unc) > 20 else "")
        return CoverageReport(False, None, unc, "uncoverable",
                              f"{len(unc)} pose(s) have fewer than {m} lit candidate sites at all, so no "
                              f"layout covers them: poses {show}. Add candidate sites that these poses "
                              f"see, lower --min-visible, or drop these poses from the envelope.")
    if witness is not None and _witness_covers(lit, k, m, n_cover, fixed, conflict, witness):
        return CoverageReport(True, None, unc, "ok", f"coverage feasible (the given {len(witness)}-sensor "
                              "selection covers the required poses)")
    if n_cover >= P and conflict is None:
        g = greedy_cover_size(lit, m, fixed)
        if g is not None and g <= k:  # a greedy cover fits: feasible without the exact MILP (fast path)
            return CoverageReport(True, None, unc, "ok", f"coverage feasible (a greedy cover uses {g} sensors)")
    kmin, cover, klow = minimum_k(lit, m, n_cover, fixed, conflict, time_limit=time_limit, return_bound=True)
    if kmin is not None and kmin <= k:
        exact = klow == kmin
        return CoverageReport(True, kmin if exact else None, unc, "ok",
                              f"coverage feasible (smallest k = {kmin})" if exact else
                              f"coverage feasible (a {kmin}-sensor cover exists)", selection=cover)
    if klow is not None and klow <= k:  # time limit before the MILP decided: not proven infeasible
        return CoverageReport(True, None, unc, "ok",
                              f"coverage undecided: the set-multicover MILP stopped at its {time_limit:g} s "
                              f"time limit (smallest k " + (f"between {klow} and {kmin}" if kmin is not None
                                                            else f"at least {klow}, no cover found yet") +
                              f"); the search will show whether "
                              f"{k} sensors can cover the required poses", decided=False)
    if klow is None:  # the MILP proved that no selection covers them
        return CoverageReport(False, None, unc, "infeasible",
                              f"no selection keeps {m} sensors lit at {n_cover} of {P} poses with the "
                              f"fixed sensors and spacing given")
    # proven (klow > k): every cover needs more than k sensors
    need = (f"the smallest k that works is {kmin}" if klow == kmin else
            f"every cover needs at least {klow} (" + (f"a {kmin}-sensor cover exists" if kmin is not None else
                                                      "none found yet") +
            f"; the MILP stopped at its {time_limit:g} s time limit)")
    # which poses cannot be covered with k sensors: the best k-cover leaves them short
    short = _poses_short_with_k(lit, k, m, fixed)
    show = ", ".join(str(p) for p in short[:20]) + (" ..." if len(short) > 20 else "")
    return CoverageReport(False, kmin if klow == kmin else None, unc, "infeasible",
                          f"{k} sensors cannot keep {m} lit at every required pose: {need}. Poses left "
                          f"with fewer than {m} lit by the best {k}-sensor cover: {show} ({len(short)} pose(s)).")


def _witness_covers(lit, k, m, n_cover, fixed, conflict, witness):
    """Whether index selection ``witness`` proves the request feasible (see :func:`analyse_coverage`)."""
    w = np.union1d(np.asarray(witness, int), np.asarray(fixed, int))  # sorted, unique, the fixed ones held
    if not len(w) or w[0] < 0 or w[-1] >= lit.shape[1] or len(w) > k:
        return False
    if conflict is not None and np.asarray(conflict, bool)[np.ix_(w, w)][~np.eye(len(w), dtype=bool)].any():
        return False
    return int((lit[:, w].sum(axis=1) >= m).sum()) >= n_cover


def greedy_cover_size(lit, m, fixed=()):
    """Sensors a greedy set multicover needs to give every pose ``m`` (lit counts ``(P, N)``); None if
    the candidates cannot. An upper bound on the smallest k (the exact one is :func:`minimum_k`)."""
    lit = _counts(lit).astype(np.int32)
    P, N = lit.shape
    need = np.full(P, int(m), np.int32)
    chosen = np.zeros(N, bool)
    for i in np.asarray(fixed, int):
        chosen[i] = True
        need -= lit[:, i]
    while (need > 0).any():
        gain = (np.minimum(lit, np.maximum(need, 0)[:, None])).sum(axis=0)
        gain[chosen] = -1
        j = int(np.argmax(gain))
        if gain[j] <= 0:
            return None
        chosen[j] = True
        need -= lit[:, j]
    return int(chosen.sum())


def _poses_short_with_k(lit, k, m, fixed):
    """Poses left short by a k-sensor cover maximising the number of covered poses (MILP)."""
    from scipy.optimize import Bounds, LinearConstraint, milp
    from scipy.sparse import csr_matrix, hstack, identity, vstack

    P, N = lit.shape
    V = csr_matrix(lit.astype(float))
    A = vstack([hstack([V, -m * identity(P)]), csr_matrix(np.r_[np.ones(N), np.zeros(P)][None])])
    lo = np.r_[np.zeros(P), k]
    hi = np.r_[np.full(P, np.inf), k]
    lb = np.zeros(N + P)
    lb[np.asarray(fixed, int)] = 1
    c = np.r_[np.zeros(N), -np.ones(P)]
    res = milp(c, constraints=LinearConstraint(A.tocsr(), lo, hi), integrality=np.ones(N + P),
               bounds=Bounds(lb, np.ones(N + P)), options={"time_limit": 20.0})
    if res.x is None:
        return np.arange(P)
    z = np.rint(res.x[:N]).astype(bool)
    return np.flatnonzero(lit[:, z].sum(axis=1) < m)
