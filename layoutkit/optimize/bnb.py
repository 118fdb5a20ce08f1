"""Branch-and-bound on the convex relaxation: a tighter certified lower bound (issue 13, item 6).

Worst-case objective with full coverage only (``objective.aggregate == "worst"``, ``n_cover == P``).

Why every number this module reports is a lower bound on the optimum ``d* = min over feasible 0/1
selections z of max_p d_p(z)`` (design §6; Joshi & Boyd 2009 for the relaxation idea):

1. **Node relaxation.** A node fixes some sites to 1 (``lo``) and some to 0 (``hi``) and bounds how
   many sensors some groups of sites hold (``glo <= sum_g z <= ghi``). Its relaxation is the problem
   of :mod:`layoutkit.optimize.relaxation` (matrix-concave GLS information ``F_p(z)``, Gauss–Markov
   ``H_p ⪰ F_p(z)^-1``, valid cuts ``sum z = k``, coverage ``lit @ z >= m``, spacing
   ``z_i + z_j <= 1``) with those bounds instead of ``0 <= z <= 1``. Every feasible 0/1 point of the
   node is feasible in it, and its objective ``max_p trace(W F_p)^-1`` is ``<=`` the exact worst DOP
   there, so the node optimum is a lower bound on every selection in the node. The epigraph is taken
   over a pose working set only: a maximum over fewer poses is smaller, so the bound stays valid
   (pose generation adds poses the node's z violates, which only tightens it). The number used is
   the Lagrangian dual bound of :mod:`layoutkit.optimize.conic`, valid for any dual point, hence
   for any solver outcome (time limit, inaccurate solve, a restricted site set).
2. **Children.** A disjunction splits a node in two: ``z_i = 0`` / ``z_i = 1`` for a free site, or
   ``sum_g z <= f`` / ``sum_g z >= f + 1`` for a group. Every 0/1 point of the parent lies in exactly
   one child, and each child's region is a subset of the parent's, so ``max(parent bound, child
   relaxation)`` bounds the child. A child the solver proves infeasible over all sites (or that
   violates ``#fixed-1 <= k <= #free + #fixed-1``) contains no feasible selection and is dropped.
3. **Leaves and pruning.** A node with every site decided is one selection: its exact value (Chen
   eq. 18, the objective itself) replaces its bound and it is an incumbent. A node whose bound is
   ``>=`` the incumbent value — B&B's own or the value of a layout the search found (``external``)
   — holds nothing better than the incumbent and is closed. When one child of a strong-branching
   probe is closed that way, the node's remaining selections are exactly those of the other child,
   which replaces it (the partition of item 2 again).
4. **Certificate.** The nodes that are open (or closed with their exact value) partition the feasible
   set, so ``min(incumbent, min over open node bounds)`` is a lower bound on ``d*`` at any moment
   (best-first: the node with the smallest bound is expanded next, so this number only rises).

Branching: reliability branching — the candidates (fractional sites and groups of
:func:`site_groups`) are scored by the product of the two children's bound gains, measured by
strong branching (both children solved) for candidates without pseudo-costs and estimated from
pseudo-costs (mean gain per unit of rounding, learned from every branching) otherwise.
Cost: every node is one or a few conic solves (Clarabel, assembled directly; column generation over
sites), each over the node's own pose set (its parent's near-critical poses plus violated ones).
"""
from __future__ import annotations

import heapq
import itertools
import math
import time
from dataclasses import dataclass

import numpy as np

from .conic import DirectRelaxation
from .problem import Problem
from .relaxation import relaxed_pose_values
from .search import evaluate_subsets

__all__ = ["BnbResult", "branch_and_bound", "bnb_applicable", "site_groups"]

# a node's z is integral when every entry is this close to 0 or 1
_INT_TOL = 1e-4
# relative violation above the node bound at which a pose joins the working set
_POSE_TOL = 1e-3


@dataclass(frozen=True)
class BnbResult:
    """bound : certified lower bound on the optimum (d units: deg/rad for ADOP, m/rad for PDOP);
    incumbent : best selection met at integral nodes / leaves (k,) int or None, with exact value
    ``value`` (inf if none); nodes : relaxations solved; open_nodes : nodes left open at the end;
    complete : the tree was exhausted (then ``bound == value``, a proven optimum); status : text;
    time_s : wall time; poses : size of the final pose working set."""

    bound: float
    value: float
    incumbent: "np.ndarray | None"
    nodes: int
    open_nodes: int
    complete: bool
    status: str
    time_s: float
    poses: int


def bnb_applicable(problem: Problem) -> bool:
    """B&B bounds the worst case with full coverage (the joint relaxation's case)."""
    return problem.objective.aggregate == "worst" and problem.n_cover >= problem.P


def site_groups(problem: Problem, min_size=2, max_groups=256):
    """Groups of sites for branching: the clusters (size >= ``min_size``, at most ``max_groups``
    largest) of a Ward hierarchy over the sites' lit patterns (P,) — sites lit at the same poses
    (e.g. one face of a box) substitute for each other, so single-site branching barely moves the
    bound while fixing how many sensors a group holds does. Any grouping keeps the bound valid."""
    from scipy.cluster.hierarchy import linkage

    N = problem.N
    if N < 3:
        return []
    X = np.asarray(problem.lit, float).T  # (N, P)
    Zl = linkage(X, method="ward")
    members = [[i] for i in range(N)]
    out = []
    for a, b, _, _ in Zl:
        m = members[int(a)] + members[int(b)]
        members.append(m)
        if min_size <= len(m) < N:
            out.append(np.asarray(sorted(m), int))
    out.sort(key=len, reverse=True)
    return out[:max_groups]


def _decided(lo, hi, k):
    """The selection if the node fixes everything (k ones, or the free sites fill up to k), else None."""
    ones = np.flatnonzero(lo > 0.5)
    free = np.flatnonzero((lo < 0.5) & (hi > 0.5))
    if len(ones) == k:
        return ones
    if len(ones) + len(free) == k:
        return np.sort(np.r_[ones, free])
    return None


def _candidates(z, lo, hi, groups, glo, ghi):
    """The disjunctions to branch on, best heuristic first: tuples ``(score, size, kind, j, floor,
    f)`` — kind "group" (count of group j ``<= floor`` or ``>= floor + 1``, f = count - floor) or
    "site" (``z_j = 0`` or 1, f = z_j). Heuristic score: the rounding distance divided by the
    rounded-up count (a relative change: a side face holding 0.35 sensors beats the top face holding
    15.43), larger groups first among near-equal scores. An integral z gives the split on its largest
    free site; no free site: empty."""
    free = np.flatnonzero((lo < 0.5) & (hi > 0.5))
    if len(free) == 0:
        return []
    cand = []
    zf = z[free]
    fs = np.minimum(zf, 1 - zf)
    for j in np.flatnonzero(fs > _INT_TOL):
        cand.append((fs[j], 1, "site", int(free[j]), 0.0, float(zf[j])))
    for r, g in enumerate(groups):
        m = float(z[g].sum())
        fl = math.floor(m + _INT_TOL)
        fr = min(m - fl, fl + 1 - m)
        if fr > _INT_TOL and glo[r] <= fl and fl + 1 <= ghi[r]:
            cand.append((fr / max(math.ceil(m), 1), len(g), "group", r, float(fl), m - fl))
    if not cand:
        j = int(free[np.argmax(zf)])
        return [(0.0, 1, "site", j, 0.0, min(max(float(z[j]), _INT_TOL), 1 - _INT_TOL))]
    top = max(c[0] for c in cand)
    cand.sort(key=lambda c: (c[0] >= 0.5 * top, c[1] if c[0] >= 0.5 * top else 0, c[0]), reverse=True)
    return cand


def _child_node(nd, groups, c, side):
    """Child ``side`` (0: down, 1: up) of node ``nd = (lo, hi, glo, ghi)`` for candidate ``c``."""
    lo, hi, glo, ghi = nd
    kind, j, fl = c[2], c[3], c[4]
    clo, chi, cglo, cghi = lo.copy(), hi.copy(), glo.copy(), ghi.copy()
    if kind == "site":
        (clo if side else chi)[j] = float(side)
    elif side == 0:
        cghi[j] = fl  # sum over the group <= floor
        if fl <= 0:
            chi[groups[j]] = 0.0  # none of the group
    else:
        cglo[j] = fl + 1  # sum over the group >= floor + 1
        if fl + 1 >= len(groups[j]):
            clo[groups[j]] = 1.0  # all of the group
    return clo, chi, cglo, cghi


def _solve_node(problem, rel, nd, parent_bound, zp, prices, poses, deadline, use_rho, max_poses_per_round,
                pose_margin):
    """Node relaxation with pose generation: ``(bound, z or None, expandable, prices, poses,
    solves, largest pose set)``. The bound is the dual one of :mod:`layoutkit.optimize.conic` —
    certified for any solver outcome — and never below the parent's (the child's region is a subset
    of the parent's). The node's pose set starts from the parent's near-critical poses; poses whose
    relaxed value at the node's z exceeds its bound join and the node is solved again."""
    k = problem.k
    lo, hi, glo, ghi = nd
    if lo.sum() > k + 0.5 or hi.sum() < k - 0.5 or np.any(glo > ghi + 0.5):
        return math.inf, None, False, None, None, 0, 0  # no k-subset in this node
    Q = np.asarray(poses, int)
    n = 0
    while True:
        tl = None if not math.isfinite(deadline) else deadline - time.perf_counter()
        if tl is not None and tl <= 0:
            return parent_bound, None, False, None, Q, n, len(Q)
        res = rel.solve(Q, lo, hi, glo, ghi, hint=zp, prices=prices, time_limit=tl)
        n += 1
        if res.status == "infeasible":  # the solver's certificate over all sites (module docstring 2)
            return math.inf, None, False, None, None, n, len(Q)
        b = max(res.bound, parent_bound)
        if res.z is None:  # "almost infeasible": no bound of its own, split further (parent's z)
            return b, None, res.status == "almost_infeasible", None, Q, n, len(Q)
        pr = res.prices
        v = np.sqrt(relaxed_pose_values(problem, res.z, use_rho))
        viol = np.setdiff1d(np.flatnonzero(v > res.bound * (1 + _POSE_TOL)), Q)
        if len(viol) == 0 or (tl is not None and tl < 1.0):
            keep = np.union1d(np.flatnonzero(v >= res.bound * (1 - pose_margin)),
                              Q[v[Q] >= res.bound * (1 - pose_margin)])
            return b, res.z, True, pr, keep, n, len(Q)
        Q = np.union1d(Q, viol[np.argsort(-v[viol])][:max_poses_per_round])
        zp, prices, parent_bound = res.z, pr, b


class NodeServer:
    """Solves node relaxations for a branch-and-bound running in another process (the pipeline's
    parent, once its search is done, so that both cores work on the tree): :meth:`serve` takes the
    request tuple the ``remote`` of :func:`branch_and_bound` sends."""

    def __init__(self, problem: Problem, use_rho=True, groups=None):
        self.problem = problem
        self.use_rho = use_rho
        groups = site_groups(problem) if groups is None else groups
        self.rel = DirectRelaxation(problem, groups, use_rho)

    def serve(self, req):
        nd, parent_bound, zp, prices, poses, deadline, max_poses_per_round, pose_margin = req
        return _solve_node(self.problem, self.rel, nd, parent_bound, zp, prices, poses, deadline,
                           self.use_rho, max_poses_per_round, pose_margin)


def branch_and_bound(problem: Problem, *, root_bound=None, root_z=None, poses=None, incumbent=None,
                     deadline=None, max_nodes=None, gap_tol=0.0, on_bound=None, use_rho=True,
                     initial_poses=24, max_poses_per_round=8, groups=None,
                     max_candidates=64, max_strong=32, lookahead=6, external=None,
                     pose_margin=0.1, remote=None) -> BnbResult:
    """Best-first branch-and-bound on the relaxation; certified lower bound (module docstring).

    problem : worst-case objective with full coverage (:func:`bnb_applicable`).
    root_bound, root_z : the root relaxation's certified bound and z (from
        :func:`layoutkit.optimize.relaxation.relax`), reused instead of solving the root again;
        poses : its active pose set, the start of the working set (default: the ``initial_poses``
        worst poses at the uniform z).
    incumbent : optional ``(selection, value)`` known feasible (prunes nodes whose bound reaches it).
    deadline : perf_counter time to stop (each solve gets the remaining time as solver limit);
    max_nodes : stop after this many relaxations; gap_tol : stop once ``value <= (1 + gap_tol) bound``.
    groups : site groups for count branching (default :func:`site_groups`; ``[]``: sites only).
    on_bound : callable ``(bound, value, nodes, open_nodes, incumbent)`` after every expansion
    (streaming the certificate out of a child process that may be killed at any time).
    external : callable returning the value of the best layout found elsewhere (the search beside
    B&B), polled between expansions: a feasible value, so nodes whose bound reaches it are closed
    and the certificate is ``min(that value, B&B's own incumbent, open nodes)``.
    max_candidates, max_strong, lookahead : reliability branching (strong branching on at most
    ``max_strong`` of the ``max_candidates`` best heuristic candidates without pseudo-costs,
    stopping after ``lookahead`` that do not improve the best score). The defaults were measured
    on seeds 101 and 103 of the issue-30 family (N 1000, P 200, k 16; node counts are deterministic
    for a given external value, so compared at equal nodes): 64/32/6 took seed 101's bound to
    1313.2 in 236 relaxations where 16/10/3 reached 1300.1 in 280 (32/16/3: 1309.8 in 249; 128/64/12:
    1308.9 in 239); seed 103: 1517.7 in 237 against 1514.8 in 213. The heuristic order ranks the
    disjunctions that move the bound most too low for a short list to reach them.
    remote : optional second solver of node relaxations (``available()``, ``submit(request)``,
    ``get()``; a :class:`NodeServer` on the other side): while it is available, the two children
    of a disjunction are solved at once, one here and one there.
    """
    if not bnb_applicable(problem):
        raise ValueError("branch_and_bound: only the worst-case objective with full coverage is supported")
    t0 = time.perf_counter()
    deadline = math.inf if deadline is None else float(deadline)
    if poses is None or len(poses) == 0:
        z0 = np.full(problem.N, problem.k / problem.N)
        poses = np.argsort(-relaxed_pose_values(problem, z0, use_rho))[:initial_poses]
    groups = site_groups(problem) if groups is None else [np.asarray(g, int) for g in groups]
    tree = _Tree(problem, groups, poses, deadline, use_rho, max_poses_per_round, pose_margin, remote)
    if incumbent is not None and incumbent[0] is not None and np.isfinite(incumbent[1]):
        tree.best_sel, tree.best_v = np.sort(np.asarray(incumbent[0], int)), float(incumbent[1])
    tree.start(root_bound, root_z)
    status = tree.run(external, on_bound, gap_tol, max_nodes, max_candidates, max_strong, lookahead)
    lb = tree.lower()
    return BnbResult(float(lb), float(tree.best_v), tree.best_sel, tree.nodes, len(tree.heap) + len(tree.stuck),
                     status == "complete", status, time.perf_counter() - t0, tree.n_poses)


class _Tree:
    """The state of one :func:`branch_and_bound` run: the open nodes (a heap by bound), the incumbent, the
    node relaxation and the pseudo-costs; its methods are the steps of the module docstring."""

    def __init__(self, problem, groups, poses, deadline, use_rho, max_poses_per_round, pose_margin, remote):
        self.problem, self.groups, self.deadline, self.use_rho = problem, groups, deadline, use_rho
        self.max_poses_per_round, self.pose_margin, self.remote = max_poses_per_round, pose_margin, remote
        self.k = problem.k
        self.gsize = np.array([len(g) for g in groups], float)
        self.rel = DirectRelaxation(problem, groups, use_rho)
        self.work = np.sort(np.unique(np.asarray(poses, int)))
        self.n_poses = len(self.work)
        self.nodes = 0
        self.best_sel, self.best_v = None, math.inf
        self.counter = itertools.count()
        self.heap = []  # (bound, tie, node arrays, z, expandable, prices, poses)
        self.stuck = []  # bounds of open nodes that cannot be expanded (they still count)
        self.ext = math.inf  # best value found outside B&B
        self.pcost = {}  # pseudo-costs: (kind, j) -> [down gain sum, n, up gain sum, n] per unit of rounding
        self.eps = 1e-6

    # -- incumbent and certificate ------------------------------------------------------------------
    def offer(self, sel):
        """A selection met in the tree: its exact value may improve the incumbent (leaves, module item 3)."""
        v, feas = evaluate_subsets(self.problem, np.asarray(sel, int)[None])
        if feas[0] and v[0] < self.best_v:
            self.best_sel, self.best_v = np.sort(np.asarray(sel, int)), float(v[0])

    def cutoff(self):
        return min(self.best_v, self.ext)

    def lower(self):
        """The certificate: min(incumbent, open node bounds) (module docstring, item 4)."""
        return min(self.cutoff(), self.heap[0][0] if self.heap else math.inf, min(self.stuck, default=math.inf))

    # -- node relaxations ---------------------------------------------------------------------------
    def tally(self, out):
        """Count a node solve's relaxations (here or remote); its ``(bound, z, expandable, prices, poses)``."""
        self.nodes += out[5]
        self.n_poses = max(self.n_poses, out[6])
        return out[:5]

    def solve(self, nd, parent_bound, zp=None, prices=None, poses=None):
        return self.tally(_solve_node(self.problem, self.rel, nd, parent_bound, zp, prices,
                                      self.work if poses is None else poses, self.deadline, self.use_rho,
                                      self.max_poses_per_round, self.pose_margin))

    def start(self, root_bound, root_z):
        """The root node (the caller's relaxation, or solved here)."""
        N = self.problem.N
        lo0, hi0 = np.zeros(N), np.ones(N)
        lo0[self.problem.fixed] = 1.0
        nd0 = (lo0, hi0, np.zeros(len(self.groups)), self.gsize.copy())
        if root_z is not None and root_bound is not None and np.isfinite(root_bound):
            root = (float(root_bound), np.asarray(root_z, float), True, None, self.work)
        else:
            root = self.solve(nd0, -math.inf)
        if np.isfinite(root[0]):
            heapq.heappush(self.heap, (root[0], next(self.counter), nd0, root[1], root[2], root[3], root[4]))
            if root[1] is not None:
                _offer_integral(root[1], self.offer, self.k)
        elif root[0] < 0:
            self.stuck.append(-math.inf)  # the root was not solved (deadline): no certificate
        self.eps = 1e-6 * max(abs(self.heap[0][0]) if self.heap else 1.0, 1e-12)

    def pair(self, nd, c, b, z, prices, Q):
        """Solve both children of disjunction ``c`` (one remotely if a remote solver is free); each
        ``(node arrays, bound, z, expandable, prices, poses)`` or None if it holds no selection
        better than the incumbent (decided children are offered and closed here)."""
        cnds = [_child_node(nd, self.groups, c, side) for side in (0, 1)]
        todo = []
        for side, cnd in enumerate(cnds):
            dsel = _decided(cnd[0], cnd[1], self.k)
            if dsel is not None:
                self.offer(dsel)
            else:
                todo.append(side)
        outs = {}
        remote = self.remote
        if len(todo) == 2 and remote is not None and remote.available():
            remote.submit((cnds[1], b, z, prices, Q, self.deadline, self.max_poses_per_round, self.pose_margin))
            outs[0] = self.solve(cnds[0], b, z, prices, Q)
            outs[1] = self.tally(remote.get())
        else:
            for side in todo:
                outs[side] = self.solve(cnds[side], b, z, prices, Q)
        kids = [None, None]
        for side, (cb, cz, cexp, cpr, cQ) in outs.items():
            if cz is not None:
                _offer_integral(cz, self.offer, self.k)
            if np.isfinite(cb) and cb < self.cutoff():
                kids[side] = (cnds[side], cb, z if cz is None else cz, cexp,
                              None if cpr is None else cpr.astype(np.float32), Q if cQ is None else cQ)
        return kids

    def push(self, kid):
        if kid is not None and kid[1] < self.cutoff():
            heapq.heappush(self.heap, (kid[1], next(self.counter), kid[0], kid[2], kid[3], kid[4], kid[5]))

    # -- reliability branching ------------------------------------------------------------------------
    def learn(self, c, b, kids):
        rec = self.pcost.setdefault((c[2], c[3]), [0.0, 0, 0.0, 0])
        for side, kid in enumerate(kids):
            gain = (self.cutoff() if kid is None else kid[1]) - b
            if math.isfinite(gain):
                rec[2 * side] += max(gain, 0.0) / max(c[5] if side == 0 else 1 - c[5], _INT_TOL)
                rec[2 * side + 1] += 1

    def estimate(self, c):
        rec = self.pcost.get((c[2], c[3]))
        if rec is not None and rec[1] and rec[3]:
            return rec[0] / rec[1] * c[5], rec[2] / rec[3] * (1 - c[5]), True
        obs = [r for r in self.pcost.values() if r[1] and r[3]]
        if not obs:
            return 0.0, 0.0, False
        dn = np.mean([r[0] / r[1] for r in obs])
        up = np.mean([r[2] / r[3] for r in obs])
        return dn * c[5], up * (1 - c[5]), False

    def expand(self, b, nd, z, prices, Q, max_candidates, max_strong, lookahead):
        """Reliability branching (strong branching on candidates without pseudo-costs, product
        score); a strong-branching child that holds nothing better than the incumbent reduces the
        node to its sibling (same partition argument as item 2 of the module docstring)."""
        lo, hi, glo, ghi = nd
        cands = _candidates(z, lo, hi, self.groups, glo, ghi)
        best = None  # (score, candidate, kids)
        n_strong = stale = 0
        for c in cands[:max_candidates]:
            d0, d1, reliable = self.estimate(c)
            kids = None
            if not reliable and n_strong < max_strong and stale < lookahead and time.perf_counter() < self.deadline:
                kids = self.pair(nd, c, b, z, prices, Q)
                n_strong += 1
                self.learn(c, b, kids)
                if kids[0] is None or kids[1] is None:  # one side is closed: the node is its sibling
                    for kid in kids:
                        self.push(kid)
                    return
                d0, d1 = kids[0][1] - b, kids[1][1] - b
            score = max(d0, self.eps) * max(d1, self.eps)
            if best is None or score > best[0]:
                best, stale = (score, c, kids), 0
            elif kids is not None:
                stale += 1
        if best is None:
            return
        _, c, kids = best
        if kids is None:
            kids = self.pair(nd, c, b, z, prices, Q)
            self.learn(c, b, kids)
        for kid in kids:
            self.push(kid)

    # -- best-first loop ----------------------------------------------------------------------------
    def run(self, external, on_bound, gap_tol, max_nodes, max_candidates, max_strong, lookahead):
        """Expand the node with the smallest bound until a stop rule; returns the status."""
        while True:
            if external is not None:
                self.ext = min(self.ext, float(external()))  # a feasible value (its selection stays with the caller)
            lb = self.lower()
            if on_bound is not None:
                on_bound(lb, self.best_v, self.nodes, len(self.heap) + len(self.stuck), self.best_sel)
            if not self.heap:
                return "complete" if not self.stuck else "stuck"
            if self.cutoff() <= (1 + gap_tol) * lb:
                return "gap reached"
            if time.perf_counter() >= self.deadline:
                return "deadline"
            if max_nodes is not None and self.nodes >= max_nodes:
                return "node limit"
            b, _, nd, z, expandable, prices, Q = heapq.heappop(self.heap)
            if b >= self.cutoff():
                continue  # nothing better than the incumbent in here
            if not expandable:
                self.stuck.append(b)
                continue
            sel = _decided(nd[0], nd[1], self.k)
            if sel is not None:
                self.offer(sel)  # a single selection: its exact value closes the node
                continue
            self.expand(b, nd, z, prices, Q, max_candidates, max_strong, lookahead)


def _offer_integral(z, offer, k):
    """An integral relaxed z (k ones) is a selection: offer it as an incumbent."""
    if np.all(np.minimum(z, 1 - z) < _INT_TOL):
        sel = np.flatnonzero(z > 0.5)
        if len(sel) == k:
            offer(sel)
