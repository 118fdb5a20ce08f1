"""Why the pipeline's branch-and-bound stopped (issue 30, item 2): the forked B&B child's end is reported.

Proof kinds: exhaustive search (a small tree run to its end must report "tree exhausted" with the
exhaustive optimum as its bound), a real killed process (its exit code is named, the relaxation
bound is kept), and the documented stall rule on constructed bound histories (a best-first bound
that rises in steps, or a child that got no CPU, is not "stalled"; a flat bound over many node
relaxations is).
"""
import time

import numpy as np
import pytest

from layoutkit.optimize.bnb_process import _BnbChild, _stalled
from layoutkit.optimize.core import candidate_jacobians
from layoutkit.optimize.instances import synthetic_instance
from layoutkit.optimize.methods import Context
from layoutkit.optimize.objectives import parse_objective
from layoutkit.optimize.problem import build_problem
from layoutkit.optimize.relaxation import relax
from layoutkit.optimize.search import exhaustive
from layoutkit.units import RHO_PAPER

N, K, P = 16, 5, 20


def _problem(seed=1):
    inst = synthetic_instance(N, P, rng=seed, cone_deg=20, half_angle_deg=89)
    jac = candidate_jacobians(inst["positions"], inst["rotations"], inst["translations"])
    return build_problem(jac, inst["visible"][:, None], RHO_PAPER, K, 4, parse_objective("worst-adop"))


def test_tree_that_ends_by_itself_reports_exhausted_with_the_exhaustive_optimum():
    pb = _problem()
    sel, opt, _ = exhaustive(pb)
    r = relax(pb)
    t0 = time.perf_counter()
    ctx = Context(rng=np.random.default_rng(0), deadline=t0 + 120.0, bnb_gap=0.0, bnb_wait=100.0)
    child = _BnbChild(pb, ctx.deadline)
    # a poor layout (twice the optimum) is never within gap 0 of the bound: only the tree's own end stops the wait
    child.finish(pb, ctx, np.asarray(sel), 2 * opt, r, t0)
    s = child.summary
    assert s["stopped"].startswith("tree exhausted") and s["complete"]
    assert s["bound"] == pytest.approx(opt, rel=1e-6)
    assert any("stopped: tree exhausted" in n for n in ctx.notes)
    assert not child.proc.is_alive()


def test_child_that_dies_is_named_with_its_exit_code_and_the_relaxation_bound_kept():
    pb = _problem()
    sel, opt, _ = exhaustive(pb)
    r = relax(pb)
    t0 = time.perf_counter()
    ctx = Context(rng=np.random.default_rng(0), deadline=t0 + 60.0)
    child = _BnbChild(pb, ctx.deadline)
    child.set_root(r)
    child.proc.kill()
    child.proc.join()
    _, _, r2 = child.finish(pb, ctx, np.asarray(sel), opt * 1.5, r, t0)
    assert "died (exit code -9)" in child.summary["stopped"]
    assert r2.bound >= r.bound and r2.bound <= opt * (1 + 1e-9)


def _ctx(**kw):
    return Context(rng=np.random.default_rng(0), **kw)


def test_stall_rule_steps_and_starvation_are_not_stalls():
    ctx = _ctx()  # window max(10 s, 0.5 * elapsed), >= 50 node relaxations, 0.5 % of the gap
    value = 1100.0
    # a best-first bound flat for 24 s after a step (measured on seed 102: 60 s -> 84 s) is no stall at 84 s
    steps = [(t, 1000.0 if t < 60 else 1013.0, 3.0 * t) for t in range(40, 85)]
    assert _stalled(steps, ctx, value) is None
    # flat over the whole window but with only 20 node relaxations: starved (no CPU), not stalled
    starved = [(t, 1000.0, 100 + 0.2 * t) for t in range(0, 101)]
    assert _stalled(starved, ctx, value) is None
    # flat over the window with hundreds of relaxations: stalled, and the reason says by how much
    flat = [(t, 1000.0 + 1e-3 * t, 5.0 * t) for t in range(0, 101)]
    why = _stalled(flat, ctx, value)
    assert why is not None and why.startswith("stalled:") and "last 50 s" in why
