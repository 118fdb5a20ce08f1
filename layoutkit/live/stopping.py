"""Stop requests for long runs: SIGTERM and SIGHUP end a live run like Ctrl-C does.

``with stop_on_signals() as stop: ... if stop.requested: break`` — while the block runs, SIGTERM
and SIGHUP (where the platform has them) set ``stop.signum`` instead of killing the process, so
the run can close its capture (fsync), solve what is pending, write the report and exit with
``128 + signum`` (the shell's convention for "ended by that signal"). Outside the main thread
(where Python cannot install handlers) nothing is installed and ``requested`` stays False.
"""
from __future__ import annotations

import contextlib
import signal
import threading

__all__ = ["StopRequest", "stop_on_signals", "STOP_SIGNALS"]

STOP_SIGNALS = tuple(getattr(signal, n) for n in ("SIGTERM", "SIGHUP") if hasattr(signal, n))


class StopRequest:
    """Set by a signal handler; ``signum`` is the first stop signal received (None: none)."""

    def __init__(self):
        self.signum: int | None = None

    @property
    def requested(self) -> bool:
        return self.signum is not None

    @property
    def name(self) -> str | None:
        return None if self.signum is None else signal.Signals(self.signum).name

    def _handler(self, signum, frame):  # noqa: ARG002 - signal handler signature
        if self.signum is None:
            self.signum = signum


@contextlib.contextmanager
def stop_on_signals(signals=STOP_SIGNALS):
    """Context manager yielding a :class:`StopRequest`; previous handlers are restored at exit."""
    stop = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return
    old = {}
    try:
        for s in signals:
            old[s] = signal.signal(s, stop._handler)
        yield stop
    finally:
        for s, h in old.items():
            signal.signal(s, h)
