"""Run control: Ctrl-C and SIGTERM stop an optimisation cleanly (issue 13, item 5).

Inside :func:`interruptible` both signals raise :class:`layoutkit.optimize.methods.Interrupted`
(SIGINT also without it, as KeyboardInterrupt). The pipeline catches it and returns the best layout
found so far; :func:`layoutkit.workflows.optimize.run_optimize` then writes that layout and every
finished k of a ``--k-range``, marked ``"interrupted"``. A signal that arrives while a C extension
runs (a Clarabel solve, a HiGHS MILP) takes effect when that call returns — at most one conic
solve, bounded by the solver time limit.
"""
from __future__ import annotations

import contextlib
import signal
import threading

from .methods import Interrupted

__all__ = ["interruptible", "Interrupted"]


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
