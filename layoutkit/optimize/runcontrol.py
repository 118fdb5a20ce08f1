"""Run control: Ctrl-C and SIGTERM stop an optimisation cleanly (issue 13, item 5).

Inside :func:`interruptible` both signals raise :class:`Interrupted` (SIGINT also without it, as
KeyboardInterrupt). The pipeline catches it and returns the best layout found so far;
:func:`layoutkit.workflows.optimize.run_optimize` then writes that layout and every finished k of a
``--k-range``, marked ``"interrupted"``. A signal that arrives while a C extension runs (a Clarabel
solve, a HiGHS MILP) takes effect when that call returns — at most one conic solve, bounded by the
solver time limit. Forked workers (the relaxation child, branch-and-bound and its node server) set
their own signals with :func:`worker_setup`.

This module sits below every user of these names (``methods``, ``bnb_process``, ``dense``, the
workflow): nothing in :mod:`layoutkit.optimize` imports upwards into it.
"""
from __future__ import annotations

import contextlib
import signal
import threading

__all__ = ["interruptible", "Interrupted", "worker_setup"]


class Interrupted(Exception):
    """Raised by the signal handlers of :func:`interruptible`; ``signame`` is "SIGINT" or "SIGTERM"."""

    def __init__(self, signame="SIGINT"):
        super().__init__(signame)
        self.signame = signame


@contextlib.contextmanager
def interruptible():
    """Install SIGINT/SIGTERM handlers raising :class:`Interrupted` (main thread only; elsewhere a no-op).

    The previous handlers are restored on exit. A second signal during the clean-up is ignored
    until the handlers are restored."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    state = {"fired": False}

    def handler(signum, frame):
        if state["fired"]:
            return
        state["fired"] = True
        raise Interrupted(signal.Signals(signum).name)

    old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    for s in old:
        signal.signal(s, handler)
    try:
        yield state
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def worker_setup(nice=0):  # pragma: no cover - runs in forked children
    """Signals of a forked worker: the parent decides (Ctrl-C ignored here, the parent kills this
    process; SIGTERM ends it). ``nice`` > 0: a busy machine gives its cores to the parent's search first."""
    import os

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if nice:
        try:
            os.nice(nice)
        except OSError:
            pass
