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

from .bnb_process import start_bnb
from .problem import Problem
from .relaxation import RelaxResult, fallback_bound, relax
from .runcontrol import Interrupted, worker_setup
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
    #: share of the remaining budget the relaxation may use in methods that search afterwards
    relax_share: float = 0.6
    #: set to the signal name when a method stopped early on Ctrl-C / SIGTERM (Interrupted)
    interrupted: "str | None" = None
    #: optional warm start (candidate indices), e.g. the incumbent of a previous round
    warm_start: "np.ndarray | None" = None
    #: pose indices to start the relaxation's pose generation from
    active_poses: "np.ndarray | None" = None
    #: a coverage-feasible selection of at most k sensors (the coverage MILP's cover): the pipeline's last
    #: resort when its relaxation, roundings and greedy give no start within the time (a short budget)
    cover_start: "np.ndarray | None" = None
    #: branch-and-bound on the relaxation (:mod:`layoutkit.optimize.bnb`) in a second process
    #: while the pipeline searches: "auto" (on for the worst case with a finite deadline; after the
    #: search it may keep the rest of the time while the gap exceeds ``bnb_gap``) or "off"
    bnb: str = "auto"
    #: after the search, B&B keeps running only while the gap exceeds this, for at most
    #: ``bnb_wait`` times the time spent so far (at least 2 s) and never past the deadline; past
    #: that, on until the deadline unless it stalls: its bound closed less than ``bnb_progress`` of
    #: the remaining gap over the last ``max(bnb_window, bnb_window_frac * elapsed)`` seconds in
    #: which it solved at least ``bnb_min_nodes`` node relaxations (:func:`bnb_process._stalled`)
    bnb_gap: float = 0.01
    bnb_wait: float = 1.0
    bnb_progress: float = 0.005
    bnb_window: float = 10.0
    bnb_window_frac: float = 0.5
    bnb_min_nodes: int = 50
    #: B&B is started only if the time limit leaves at least this many seconds (a shorter run
    #: would only share its cores with a tree that cannot get far)
    bnb_min_s: float = 5.0
    #: method "polish": also try 2-swaps at a 1-swap local optimum (slower, better)
    two_swap: bool = True
    #: method "polish": a site ranking in [0, 1] (N,), e.g. the relaxed z of an earlier pipeline run on a
    #: similar problem; its kicks then draw sites like the pipeline's (half ∝ z, half uniform) and its 2-swap
    #: pool takes the top z as well. None: uniform
    z_hint: "np.ndarray | None" = None

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


def _relax(problem: Problem, ctx: Context, share=None) -> RelaxResult:
    ctx.report("relaxation (cvxpy/Clarabel)", 0.0)
    dl = ctx.deadline
    if share is not None and math.isfinite(dl):
        dl = time.perf_counter() + share * max(dl - time.perf_counter(), 0.0)
    r = relax_until(problem, dl, ctx.active_poses)
    ctx.report("relaxation (cvxpy/Clarabel)", 1.0)
    ctx.notes.append(f"relaxation {r.status} in {r.time_s:.1f} s")
    if r.certified_by == "none":
        ctx.notes.append("bound: none (the relaxation did not solve to status optimal within its time)")
    return r


def _relax_child(problem, deadline, active, conn):  # pragma: no cover - runs in the forked child
    worker_setup()
    try:
        conn.send(relax(problem, deadline=deadline, active_poses=active))
    except BaseException as exc:  # noqa: BLE001 - reported to the parent as a status
        conn.send(f"{type(exc).__name__}: {exc}")
    finally:
        conn.close()


def relax_until(problem: Problem, deadline: float, active_poses=None) -> RelaxResult:
    """The relaxation, ended at ``deadline`` whatever it is doing.

    cvxpy's problem compilation cannot be interrupted and Clarabel checks its time limit only
    between iterations, so with a finite deadline the relaxation runs in a forked child process
    that is killed at the deadline (then: no bound, uniform z). Ctrl-C / SIGTERM in the parent kill
    the child as well. Without a deadline it runs in-process.
    """
    if not math.isfinite(deadline):
        return relax(problem, active_poses=active_poses)
    import multiprocessing as mp

    import cvxpy  # noqa: F401 - imported once in the parent, so each forked child starts warm

    mpc = mp.get_context("fork")
    recv, send = mpc.Pipe(duplex=False)
    proc = mpc.Process(target=_relax_child, args=(problem, deadline, active_poses, send), daemon=True)
    t_start = time.perf_counter()
    proc.start()
    send.close()
    got = None
    try:
        if recv.poll(max(deadline - time.perf_counter(), 0.0)):
            got = recv.recv()
    except EOFError:
        got = "the relaxation process ended without a result"
    finally:
        if proc.is_alive():
            proc.kill()
        proc.join()
        recv.close()
    if isinstance(got, RelaxResult):
        return got
    why = got if isinstance(got, str) else "relaxation stopped at the time limit"
    return _no_relaxation(problem, why, time.perf_counter() - t_start)  # the time it had, not 0 s


def _no_relaxation(problem: Problem, why: str, time_s: float = 0.0) -> RelaxResult:
    return RelaxResult(np.full(problem.N, problem.k / problem.N), float("nan"), "none", why, float(time_s),
                       fallback_bound(problem))


def _from_cover(problem: Problem, cover, z):
    """A k-subset from a coverage-feasible ``cover`` (at most k indices): the cover, the fixed sensors, then the
    highest-``z`` sites that conflict with none chosen; repaired. None without a cover or if that fails."""
    if cover is None:
        return None
    sel = list(np.union1d(np.asarray(cover, int), problem.fixed))
    z = np.zeros(problem.N) if z is None else np.asarray(z, float)
    for j in np.argsort(-z, kind="stable"):
        if len(sel) >= problem.k:
            break
        if j in sel or (problem.conflict is not None and problem.conflict[j, sel].any()):
            continue
        sel.append(int(j))
    if len(sel) != problem.k:
        return None
    return repair(problem, np.asarray(sel, int), z)


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


def _roundings(problem: Problem, z, rng, n, deadline=math.inf):
    """Randomised rounding: k sites drawn without replacement with probability ∝ z; repaired
    (stops early at ``deadline``)."""
    free = np.setdiff1d(np.arange(problem.N), problem.fixed)
    p = np.maximum(z[free], 1e-9)
    p = p / p.sum()
    kk = problem.k - len(problem.fixed)
    out = []
    for _ in range(n):
        if time.perf_counter() > deadline:
            break
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
    ``patience`` kicks in a row bring nothing or the time is up. The relaxation gets at most
    ``relax_share`` of the time budget. On :class:`Interrupted` / KeyboardInterrupt the best layout
    found so far is returned (``ctx.interrupted`` names the signal)."""
    t_start = time.perf_counter()
    best, bv = None, np.inf
    r = None
    n_ls = 0
    starts = []
    bnb = None
    try:
        bnb = start_bnb(problem, ctx)  # B&B solves its own root (:mod:`layoutkit.optimize.conic`) meanwhile
        r = _relax(problem, ctx, ctx.relax_share)
        if bnb is not None:
            bnb.set_root(r)
        if ctx.warm_start is not None:
            w = repair(problem, np.asarray(ctx.warm_start, int), r.z)
            if w is not None:
                starts.append(w)
        tk = _topk(problem, r.z)
        if tk is not None:
            starts.append(tk)
        g = greedy(problem, deadline=ctx.deadline)
        if g is not None:
            starts.append(g)
        subs = _roundings(problem, r.z, ctx.rng, ctx.n_round, ctx.deadline)
        if subs:
            v, _ = evaluate_subsets(problem, np.array(subs))
            starts += [subs[i] for i in np.argsort(v)[:3]]
        if not starts:
            c = _from_cover(problem, ctx.cover_start, r.z)
            if c is not None:
                starts.append(c)
                ctx.notes.append("no relaxation rounding or greedy start in time: searched from the coverage "
                                 "MILP's cover")
        if not starts:
            if bnb is not None:
                bnb.stop()
            return MethodOutput(None, r)
        sv, feas = evaluate_subsets(problem, np.array(starts))
        i0 = int(np.argmin(np.where(feas, sv, np.inf)))
        if feas[i0]:
            best, bv = starts[i0], float(sv[i0])
        seen = set()

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
                if bnb is not None:
                    bnb.offer(bv)
                return True
            return False

        if bnb is not None and np.isfinite(bv):
            bnb.offer(bv)
        for i, s in enumerate(starts):
            if time.perf_counter() > ctx.deadline:
                break
            ctx.report("local search", i / (len(starts) + ctx.patience), bv)
            run(s)
        fails = 0
        while fails < ctx.patience and time.perf_counter() < ctx.deadline and best is not None:
            ctx.report("local search", (len(starts) + fails) / (len(starts) + ctx.patience), bv)
            kick = _kick(problem, best, ctx.rng, r.z)
            if kick is None or not run(kick):
                fails += 1
            else:
                fails = 0
    except (Interrupted, KeyboardInterrupt) as exc:
        ctx.interrupted = getattr(exc, "signame", "SIGINT")
        ctx.notes.append(f"interrupted by {ctx.interrupted}: best layout found so far")
        if r is None:
            r = _no_relaxation(problem, f"interrupted by {ctx.interrupted} during the relaxation")
        if best is None:
            for s in starts:
                best = s
                break
        if best is None:
            best = repair(problem, np.r_[problem.fixed, np.setdiff1d(np.arange(problem.N), problem.fixed)[
                : problem.k - len(problem.fixed)]], r.z)
    except BaseException:
        if bnb is not None:
            bnb.stop()
        raise
    search_s = time.perf_counter() - t_start  # relaxation + search, without the wait for B&B
    if bnb is not None:
        best, bv, r = bnb.finish(problem, ctx, best, bv, r, t_start)
    ctx.report("local search", 1.0, bv)
    info = {"local_searches": n_ls, "search_s": search_s}
    if bnb is not None:
        info["branch_and_bound"] = bnb.summary
    return MethodOutput(best, r, info=info)


@register_method("polish")
def _m_polish(problem: Problem, ctx: Context) -> MethodOutput:
    """No relaxation: 1- and 2-swap (``ctx.two_swap``) local search from ``ctx.warm_start`` (repaired to coverage; greedy
    without one), then random kicks (2–3 sensors, uniform or half ∝ ``ctx.z_hint``) around the incumbent until ``patience``
    kicks in a row bring nothing or the time is up. For re-optimising an incumbent after a small change
    of the problem (the dense-envelope loop adds poses); the bound is the closed-form trace bound."""
    t_start = time.perf_counter()
    z = np.full(problem.N, problem.k / problem.N)
    hint = None
    if ctx.z_hint is not None:
        hint = np.asarray(ctx.z_hint, float)
        if hint.shape != (problem.N,) or not np.all(np.isfinite(hint)):
            raise ValueError(f"z_hint: expected {problem.N} finite values, got shape {hint.shape}")
        z = np.clip(hint, 0.0, 1.0)
    best, bv, n_ls = None, np.inf, 0
    try:
        s0 = repair(problem, np.asarray(ctx.warm_start, int), z) if ctx.warm_start is not None else None
        if s0 is None:
            s0 = greedy(problem, deadline=ctx.deadline)
        if s0 is None:
            return MethodOutput(None)
        best = s0
        best, bv, _ = local_search(problem, s0, deadline=ctx.deadline, two_swap=ctx.two_swap, z=hint)
        n_ls = 1
        ctx.report("polish", 0.0, bv)
        fails = 0
        while fails < ctx.patience and time.perf_counter() < ctx.deadline:
            kick = _kick(problem, best, ctx.rng, z)
            if kick is None:
                break
            s2, val, _ = local_search(problem, kick, deadline=ctx.deadline, two_swap=ctx.two_swap, z=hint)
            n_ls += 1
            if val < bv * (1 - 1e-9):
                best, bv, fails = s2, val, 0
                ctx.report("polish", None, bv)
            else:
                fails += 1
    except (Interrupted, KeyboardInterrupt) as exc:
        ctx.interrupted = getattr(exc, "signame", "SIGINT")
        ctx.notes.append(f"interrupted by {ctx.interrupted}: best layout found so far")
    return MethodOutput(best, info={"local_searches": n_ls, "search_s": time.perf_counter() - t_start})


def _kick(problem: Problem, sel, rng, z):
    """Replace 2–3 random non-fixed sensors by sites drawn ∝ z (+ uniform), repaired."""
    movable = np.setdiff1d(sel, problem.fixed)
    nk = min(len(movable), int(rng.integers(2, 4)))
    if nk == 0:
        return None
    out = rng.choice(movable, nk, replace=False)
    keep = np.setdiff1d(sel, out)
    cand = np.setdiff1d(np.arange(problem.N), sel)
    if len(cand) < nk:  # k close to N: no kick possible (issue 13: k = N crashed here)
        return None
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
