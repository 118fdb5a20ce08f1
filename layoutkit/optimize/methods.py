"""Method registry: each method maps a :class:`Problem` to a selection (and maybe a relaxation).

``METHODS[name](problem, ctx) -> MethodOutput``; the CLI offers ``sorted(METHODS)`` and the tests
parametrise over it. ``ctx`` carries ``rng``, ``deadline`` (perf_counter seconds), ``progress``
and tuning knobs (``n_random``, ``n_round``, ``patience``).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np

from .problem import Problem
from .relaxation import RelaxResult, relax
from .search import evaluate_subsets, exhaustive, greedy, local_search, repair

__all__ = ["METHODS", "MethodOutput", "Method", "register_method", "Context"]


@dataclass
class Context:
    rng: np.random.Generator
    deadline: float = math.inf
    progress: "Callable | None" = None
    n_random: int = 200
    n_round: int = 64
    patience: int = 6
    notes: list = field(default_factory=list)

    def report(self, stage, fraction=None, best=None):
        if self.progress is not None:
            self.progress(stage, fraction, best)


@dataclass(frozen=True)
class MethodOutput:
    selected: "np.ndarray | None"
    relaxation: "RelaxResult | None" = None
    exact_optimum: bool = False
    info: dict = field(default_factory=dict)


class Method(Protocol):
    def __call__(self, problem: Problem, ctx: Context) -> MethodOutput: ...


METHODS: dict[str, Method] = {}


def register_method(name: str):
    def deco(fn):
        METHODS[name] = fn
        return fn
    return deco


def _random_subset(problem: Problem, rng):
    free = np.setdiff1d(np.arange(problem.N), problem.fixed)
    pick = rng.choice(free, problem.k - len(problem.fixed), replace=False)
    return np.sort(np.r_[problem.fixed, pick]).astype(int)


def _random_feasible(problem: Problem, rng, n, score=None):
    out = []
    tries = 0
    while len(out) < n and tries < 4 * n:
        tries += 1
        s = _random_subset(problem, rng)
        s = repair(problem, s, score)
        if s is not None:
            out.append(s)
    return out


def _best_of(problem: Problem, subsets):
    if not subsets:
        return None, np.inf
    v, feas = evaluate_subsets(problem, np.array(subsets))
    v = np.where(feas, v, np.inf)
    i = int(np.argmin(v))
    return subsets[i], float(v[i])


@register_method("random")
def _m_random(problem: Problem, ctx: Context) -> MethodOutput:
    """Best of ``n_random`` random k-subsets, each repaired to coverage feasibility."""
    ctx.report("random layouts", 0.0)
    subs = _random_feasible(problem, ctx.rng, ctx.n_random)
    sel, v = _best_of(problem, subs)
    ctx.report("random layouts", 1.0, v)
    return MethodOutput(sel, info={"n_feasible": len(subs)})


@register_method("greedy")
def _m_greedy(problem: Problem, ctx: Context) -> MethodOutput:
    """Greedy forward selection (coverage first, then the regularised objective)."""
    ctx.report("greedy", 0.0)
    return MethodOutput(greedy(problem))


def _relax(problem: Problem, ctx: Context) -> RelaxResult:
    ctx.report("relaxation (cvxpy/Clarabel)", 0.0)
    r = relax(problem)
    ctx.report("relaxation (cvxpy/Clarabel)", 1.0)
    ctx.notes.append(f"relaxation {r.status} in {r.time_s:.1f} s")
    return r


def _topk(problem: Problem, z):
    zz = z.copy()
    zz[problem.fixed] = np.inf
    sel = np.sort(np.argsort(-zz)[: problem.k])
    return repair(problem, sel, z)


@register_method("topk")
def _m_topk(problem: Problem, ctx: Context) -> MethodOutput:
    """Convex relaxation, then the k largest z (repaired if the coverage fails)."""
    r = _relax(problem, ctx)
    return MethodOutput(_topk(problem, r.z), r)


def _roundings(problem: Problem, z, rng, n):
    """Randomised rounding: k sites drawn without replacement with probability ∝ z; repaired."""
    free = np.setdiff1d(np.arange(problem.N), problem.fixed)
    p = np.maximum(z[free], 1e-9)
    p = p / p.sum()
    kk = problem.k - len(problem.fixed)
    out = []
    for _ in range(n):
        pick = _gumbel_topk(rng, free, kk, p)
        s = repair(problem, np.r_[problem.fixed, pick], z)
        if s is not None:
            out.append(s)
    return out


def _gumbel_topk(rng, items, k, p):
    """k items sampled without replacement with probability ∝ p (Gumbel top-k trick)."""
    g = np.log(p) - np.log(-np.log(rng.random(len(p))))
    return items[np.argsort(-g)[:k]]


@register_method("relax-round")
def _m_relax_round(problem: Problem, ctx: Context) -> MethodOutput:
    """Relaxation + randomised rounding with repair + 1-swap sweeps from the best 3 roundings
    (the reference method of the issue)."""
    r = _relax(problem, ctx)
    subs = _roundings(problem, r.z, ctx.rng, ctx.n_round)
    if not subs:
        return MethodOutput(None, r)
    v, _ = evaluate_subsets(problem, np.array(subs))
    best, bv = None, np.inf
    for t, i in enumerate(np.argsort(v)[:3]):
        ctx.report("1-swap sweeps", t / 3, bv)
        s, val, _ = local_search(problem, subs[i], two_swap=False, deadline=ctx.deadline)
        if val < bv:
            best, bv = s, val
    return MethodOutput(best, r)


@register_method("pipeline")
def _m_pipeline(problem: Problem, ctx: Context) -> MethodOutput:
    """Relaxation bound; starts from top-k, greedy and the best randomised roundings; 1- and 2-swap
    local search from each; then random kicks (2–3 sensors) around the incumbent until
    ``patience`` kicks in a row bring nothing or the time is up."""
    r = _relax(problem, ctx)
    t_start = time.perf_counter()
    starts = []
    tk = _topk(problem, r.z)
    if tk is not None:
        starts.append(tk)
    g = greedy(problem)
    if g is not None:
        starts.append(g)
    subs = _roundings(problem, r.z, ctx.rng, ctx.n_round)
    if subs:
        v, _ = evaluate_subsets(problem, np.array(subs))
        starts += [subs[i] for i in np.argsort(v)[:3]]
    if not starts:
        return MethodOutput(None, r)
    best, bv = None, np.inf
    seen = set()
    n_ls = 0

    def run(s):
        nonlocal best, bv, n_ls
        key = tuple(np.sort(s))
        if key in seen:
            return False
        seen.add(key)
        s2, val, _ = local_search(problem, s, deadline=ctx.deadline, z=r.z)
        n_ls += 1
        seen.add(tuple(s2))
        if val < bv * (1 - 1e-9):
            best, bv = s2, val
            return True
        return False

    for i, s in enumerate(starts):
        ctx.report("local search", i / (len(starts) + ctx.patience), bv)
        run(s)
        if time.perf_counter() > ctx.deadline:
            break
    fails = 0
    while fails < ctx.patience and time.perf_counter() < ctx.deadline and best is not None:
        ctx.report("local search", (len(starts) + fails) / (len(starts) + ctx.patience), bv)
        kick = _kick(problem, best, ctx.rng, r.z)
        if kick is None or not run(kick):
            fails += 1
        else:
            fails = 0
    ctx.report("local search", 1.0, bv)
    return MethodOutput(best, r, info={"local_searches": n_ls, "search_s": time.perf_counter() - t_start})


def _kick(problem: Problem, sel, rng, z):
    """Replace 2–3 random non-fixed sensors by sites drawn ∝ z (+ uniform), repaired."""
    movable = np.setdiff1d(sel, problem.fixed)
    nk = min(len(movable), int(rng.integers(2, 4)))
    if nk == 0:
        return None
    out = rng.choice(movable, nk, replace=False)
    keep = np.setdiff1d(sel, out)
    cand = np.setdiff1d(np.arange(problem.N), sel)
    p = 0.5 * z[cand] / max(z[cand].sum(), 1e-12) + 0.5 / len(cand)
    add = rng.choice(cand, nk, replace=False, p=p / p.sum())
    return repair(problem, np.r_[keep, add], z)


@register_method("exhaustive")
def _m_exhaustive(problem: Problem, ctx: Context) -> MethodOutput:
    """Every k-subset (small N only): the exact optimum, used as the independent reference."""
    n = math.comb(problem.N - len(problem.fixed), problem.k - len(problem.fixed))
    if n > 5_000_000:
        ctx.notes.append(f"exhaustive: {n} subsets is too many (limit 5,000,000)")
        return MethodOutput(None, info={"n_subsets": n})
    ctx.report("exhaustive", 0.0)
    sel, v, nf = exhaustive(problem, deadline=ctx.deadline)
    complete = time.perf_counter() <= ctx.deadline
    return MethodOutput(sel, exact_optimum=complete and sel is not None,
                        info={"n_subsets": n, "n_feasible": nf})
