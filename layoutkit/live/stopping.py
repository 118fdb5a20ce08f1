"""Stop requests for long runs: SIGTERM, SIGHUP (and, on request, Ctrl-C) end a run between steps.

``with stop_on_signals() as stop: ... if stop.requested: break`` — while the block runs, SIGTERM
and SIGHUP (where the platform has them) set ``stop.signum`` instead of killing the process, so
the run can close its capture (fsync), solve what is pending, write the report and exit with
``128 + signum`` (the shell's convention for "ended by that signal"). Outside the main thread
(where Python cannot install handlers) nothing is installed and ``requested`` stays False.

``interrupt=True`` treats the first SIGINT (Ctrl-C) the same way: a flag, not a
``KeyboardInterrupt`` raised wherever the main thread happens to be. An exception raised in the
middle of a step loses that step's work — in ``live`` the frames being solved between "written
to the capture" and "written to poses.csv" (issue 29: the last 3 of 576 frames, in 1 run of 2).
A second SIGINT raises ``KeyboardInterrupt`` (the usual "press again to force"). ``on_request``
(called with the signal's name on the first request) lets a run say at once that it heard the
signal when its current step may take minutes.
"""
from __future__ import annotations

import contextlib
import signal
import threading

__all__ = ["STOP_SIGNALS", "StopRequest", "stop_on_signals"]

STOP_SIGNALS = tuple(getattr(signal, n) for n in ("SIGTERM", "SIGHUP") if hasattr(signal, n))


class StopRequest:
    """Set by a signal handler; ``signum`` is the first stop signal received (None: none)."""

    def __init__(self, on_request=None):
        self.signum: int | None = None
        self._on_request = on_request

    @property
    def requested(self) -> bool:
        return self.signum is not None

    @property
    def name(self) -> str | None:
        return None if self.signum is None else signal.Signals(self.signum).name

    def _handler(self, signum, frame):  # noqa: ARG002 - signal handler signature
        if self.signum is None:
            self.request(signum)
        elif signum == signal.SIGINT:  # Ctrl-C again: the user insists
            raise KeyboardInterrupt

    def request(self, signum: int) -> None:
        """Ask for a stop as if ``signum`` had arrived (the first request wins and calls ``on_request``)."""
        if self.signum is None:
            self.signum = int(signum)
            if self._on_request is not None:
                self._on_request(self.name)


@contextlib.contextmanager
def stop_on_signals(signals=STOP_SIGNALS, *, interrupt: bool = False, on_request=None):
    """Context manager yielding a :class:`StopRequest`; previous handlers are restored at exit.

    interrupt : also catch SIGINT (Ctrl-C) as a stop request (a second one raises
    ``KeyboardInterrupt``). on_request : optional callable, called with the signal's name on the
    first request (from the handler: keep it short, e.g. a print)."""
    stop = StopRequest(on_request)
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return
    sigs = tuple(signals) + ((signal.SIGINT,) if interrupt and signal.SIGINT not in signals else ())
    old = {}
    try:
        for s in sigs:
            old[s] = signal.signal(s, stop._handler)
        yield stop
    finally:
        for s, h in old.items():
            signal.signal(s, h)
