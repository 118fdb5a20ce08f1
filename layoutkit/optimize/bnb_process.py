"""Branch-and-bound beside the pipeline's search: the forked B&B child, its node server and the
shared-memory certificate (:mod:`layoutkit.optimize.bnb` does the tree; this module the processes).

Processes: the B&B child (niced) runs :func:`layoutkit.optimize.bnb.branch_and_bound` and publishes
its bound through shared memory; once the search is done, a forked node server (at the parent's
priority) solves one child of every disjunction for it (both cores on the tree); the parent only
waits, and kills both at the end.
Every published bound is valid on its own, so either process may be killed at any moment.
"""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from .bnb import NodeServer, bnb_applicable, branch_and_bound
from .problem import Problem
from .relaxation import RelaxResult
from .runcontrol import Interrupted, worker_setup

__all__ = ["start_bnb"]


def start_bnb(problem: Problem, ctx):
    """Start branch-and-bound in a forked child when it can help (worst case with full coverage,
    finite deadline with room left); None otherwise. It starts before the pipeline's relaxation and
    solves its own root."""
    if ctx.bnb == "off" or not bnb_applicable(problem):
        return None
    if not math.isfinite(ctx.deadline) or ctx.deadline - time.perf_counter() < ctx.bnb_min_s:
        return None
    return _BnbChild(problem, ctx.deadline)


class _BnbChild:
    """Branch-and-bound in a forked process; its certificate is published through shared memory
    (lower bound, B&B's own incumbent value and selection, nodes, open nodes, done), so the child never
    blocks on the parent and may be killed at any moment: every published bound is valid on its
    own (:mod:`layoutkit.optimize.bnb`)."""

    def __init__(self, problem: Problem, deadline: float):
        import multiprocessing as mp

        mpc = mp.get_context("fork")
        self.root = -math.inf  # the pipeline's relaxation bound, once known (:meth:`set_root`)
        # lower bound, B&B incumbent value, nodes, open nodes, done, the search's incumbent value,
        # a node server is running (1) or not (0), node solves the server has answered
        self.state = mpc.Array("d", [-math.inf, math.inf, 0.0, 1.0, 0.0, math.inf, 0.0, 0.0], lock=False)
        self.mpc = mpc
        self.server = None
        self.sel = mpc.Array("l", [-1] * problem.k, lock=False)
        self.summary = {}
        self.conn, child_conn = mpc.Pipe()
        self.proc = mpc.Process(target=_bnb_child, args=(problem, deadline, self.state, self.sel, child_conn),
                                daemon=True)
        self.proc.start()
        child_conn.close()  # the child's end lives in the child: EOF here once it exits

    def set_root(self, r: RelaxResult):
        """The pipeline's relaxation: its certified bound is also a floor of the certificate."""
        if r.certified_by == "relaxation" and np.isfinite(r.bound):
            self.root = float(r.bound)

    def stop(self):
        for proc in (self.proc, self.server):
            if proc is not None:
                if proc.is_alive():
                    proc.kill()
                proc.join()

    def done(self) -> bool:
        return self.state[4] > 0 or not self.proc.is_alive()

    def offer(self, value: float):
        """Tell the child the value of a feasible layout the search found (it prunes with it)."""
        if value < self.state[5]:
            self.state[5] = float(value)

    def finish(self, problem: Problem, ctx, best, bv, r: RelaxResult, t_start: float):
        """Wait (while the gap exceeds ``ctx.bnb_gap``, for at most ``ctx.bnb_wait`` times the time
        since ``t_start``, within the deadline, unless interrupted), stop the child, and fold its
        bound into the result. Past that wait the tree keeps the time while it progresses
        (:func:`_stalled`). Why B&B stopped is ``summary["stopped"]`` and part of the notes."""
        now = time.perf_counter()
        until = min(ctx.deadline, now + max(ctx.bnb_wait * (now - t_start), 2.0))
        history = []  # (time since t_start, bound, nodes) while waiting
        why = None

        def progressing(t):
            nonlocal why
            lb = max(self.state[0], self.root)
            history.append((t - t_start, lb, float(self.state[2])))
            if t < until:
                return True
            if t >= ctx.deadline:
                why = "deadline"
                return False
            why = _stalled(history, ctx, bv)
            return why is None

        try:
            if ctx.interrupted is not None:
                why = f"interrupted ({ctx.interrupted})"
            elif best is None:
                why = "no layout to certify"
            else:
                while True:
                    if self.done():
                        why = self.end_reason()
                        break
                    if bv <= (1 + ctx.bnb_gap) * max(self.state[0], self.root):
                        why = f"gap reached (<= {100 * ctx.bnb_gap:g} %)"
                        break
                    if not progressing(time.perf_counter()):
                        break
                    if self.server is None:  # the search is done: its core solves nodes for the tree too,
                        # in a forked process (solver thread pools in this process would not survive the
                        # forks of later runs)
                        self.server = self.mpc.Process(target=_serve_child, args=(problem, self.conn, self.state),
                                                       daemon=True)
                        self.server.start()
                        self.state[6] = 1.0
                    time.sleep(0.05)
        except (Interrupted, KeyboardInterrupt) as exc:
            ctx.interrupted = getattr(exc, "signame", "SIGINT")
            ctx.notes.append(f"interrupted by {ctx.interrupted}: best layout found so far")
            why = f"interrupted ({ctx.interrupted})"
        finally:
            self.state[6] = 0.0
            self.stop()
        # only the bound is taken: the layout stays the search's (B&B's progress depends on timing,
        # the selection of a run that finishes before its deadline must not)
        lb, v, nodes, n_open = (float(x) for x in self.state[:4])
        root = self.root if np.isfinite(self.root) else lb
        self.summary = {"nodes": int(nodes), "open_nodes": int(n_open), "root_bound": root,
                        "bound": max(lb, root), "complete": self.state[4] == _END_CODES["complete"],
                        "served_by_parent": int(self.state[7]),  # by the node server, on the parent's core
                        "stopped": why, "stopped_at_s": time.perf_counter() - t_start,
                        "history": _thin(history)}
        if np.isfinite(max(lb, root)):
            ctx.notes.append(f"branch-and-bound: {int(nodes)} node relaxations, bound {root:.6g} -> "
                             f"{max(lb, root):.6g}, stopped: {why}")
        else:
            ctx.notes.append("branch-and-bound: no bound (its root relaxation did not finish before the deadline)")
        if np.isfinite(lb) and (lb > r.bound or not np.isfinite(r.bound)):
            r = dataclasses.replace(r, bound=lb, certified_by="branch-and-bound")
        return best, bv, r

    def end_reason(self) -> str:
        """Why the child ended by itself: its branch_and_bound status, or how the process died."""
        code = self.state[4]
        for name, c in _END_CODES.items():
            if code == c:
                return {"complete": "tree exhausted (the bound is the optimum over the candidate set)",
                        "stuck": "no expandable open node left (the bound is the smallest stuck node's)",
                        }.get(name, f"branch-and-bound ended: {name}")
        self.proc.join(timeout=1.0)
        return f"branch-and-bound process died (exit code {self.proc.exitcode}) before finishing"


#: ``state[4]`` of the B&B child when it ended by itself: its :class:`layoutkit.optimize.bnb.BnbResult` status
_END_CODES = {"deadline": 1.0, "complete": 2.0, "stuck": 3.0, "gap reached": 4.0, "node limit": 5.0}


def _stalled(history, ctx, bv):
    """Why the tree counts as stalled at ``history[-1]`` (None while it progresses): over the last
    ``max(ctx.bnb_window, ctx.bnb_window_frac * elapsed)`` seconds its bound closed less than
    ``ctx.bnb_progress`` of the remaining gap although it solved at least ``ctx.bnb_min_nodes``
    node relaxations. A best-first bound rises in steps (the smallest open bound moves only once
    every node near it is expanded), so the window grows with the run; a tree that got no CPU
    (a loaded machine, the child is niced) is starved, not stalled, and keeps its time."""
    t, lb, nodes = history[-1]
    window = max(ctx.bnb_window, ctx.bnb_window_frac * t)
    old = [h for h in history if h[0] <= t - window]
    if not old:
        return None
    _, lb0, n0 = old[-1]
    if nodes - n0 < ctx.bnb_min_nodes:
        return None
    if lb - lb0 >= ctx.bnb_progress * (bv - lb):
        return None
    return (f"stalled: bound rose {lb - lb0:.4g} in the last {window:.0f} s ({nodes - n0:.0f} node relaxations), "
            f"less than {100 * ctx.bnb_progress:g} % of the remaining gap {bv - lb:.4g}")


def _thin(history, n=60):
    """At most ``n`` evenly spaced samples of the wait's (time, bound, nodes) history, the last kept."""
    if len(history) <= n:
        return [list(h) for h in history]
    idx = np.unique(np.r_[np.linspace(0, len(history) - 1, n).astype(int), len(history) - 1])
    return [list(history[i]) for i in idx]


class _ServerSolver:
    """The B&B child's view of the node server process (:func:`_serve_child`) as its ``remote``."""

    def __init__(self, conn, state):
        self.conn, self.state = conn, state

    def available(self):
        return self.state[6] > 0

    def submit(self, request):
        self.conn.send(request)

    def get(self):
        return self.conn.recv()  # the server answers, or the parent kills this process


def _serve_child(problem, conn, state):  # pragma: no cover - runs in a forked child
    """Node relaxations for the B&B child (:class:`layoutkit.optimize.bnb.NodeServer`) until its pipe closes."""
    worker_setup(nice=0)  # the parent only waits once the search is done: this is its core, at its priority
    server = NodeServer(problem)
    while True:
        try:
            req = conn.recv()
        except (EOFError, OSError):
            return
        conn.send(server.serve(req))
        state[7] += 1


def _bnb_child(problem, deadline, state, sel, conn):  # pragma: no cover - runs in the forked child
    worker_setup(nice=10)  # a busy machine gives its cores to the search first (the layout), B&B second

    def publish(lb, value, nodes, n_open, inc=None):
        if inc is not None:
            sel[:] = [int(x) for x in inc]
        state[1] = value
        state[2] = nodes
        state[3] = n_open
        if lb > state[0]:
            state[0] = lb  # one 8-byte store: the certificate is never torn

    res = branch_and_bound(problem, deadline=deadline, on_bound=publish, external=lambda: state[5],
                           remote=_ServerSolver(conn, state))
    publish(res.bound, res.value, res.nodes, res.open_nodes, res.incumbent)
    state[4] = _END_CODES.get(res.status, 1.0)
