"""Where tasks run: a Dask LocalCluster (default), a Dask cluster by address, or in-process.

:func:`open_executor` is a context manager returning an executor with one small interface::

    h = ex.submit(fn, *args, key="cell-3")    # args may hold earlier handles (resolved on the worker)
    for h, ok, value in ex.completed([h, ...]):  # as they finish; value is the result or the exception
        ...
    ex.running(handles)                        # how many of them are executing now

Choices (``scheduler``):
- ``None`` — a :class:`distributed.LocalCluster` on this machine, ``workers`` processes (default: the
  CPUs this process may use) with one thread each; the dashboard address is in ``ex.dashboard``.
- an address (``tcp://host:8786``, ``tls://...``, ``host:8786``) — connect a :class:`distributed.Client`
  to a running ``dask scheduler``; the cluster's workers do the work.
- ``"synchronous"`` — no cluster: each task runs in this thread, in submission order, through
  dask's synchronous scheduler (debugging, profiling, tests).

Tasks must be module-level functions of an importable package (they are pickled by reference), and
their arguments picklable: on a cluster every worker needs ``layoutkit`` installed. Tasks may start
child processes (:func:`allow_child_processes`); the LocalCluster's workers are non-daemonic.
"""
from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
import uuid
from collections import deque
from typing import Any, Callable, Iterator

__all__ = ["SYNCHRONOUS", "open_executor", "allow_child_processes", "DistributedExecutor", "SynchronousExecutor", "default_workers"]

SYNCHRONOUS = "synchronous"


def default_workers() -> int:
    """Worker processes of the default LocalCluster: the CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


class _SyncHandle:
    __slots__ = ("fn", "args", "key", "done", "ok", "value")

    def __init__(self, fn, args, key):
        self.fn, self.args, self.key = fn, args, key
        self.done, self.ok, self.value = False, False, None


class SynchronousExecutor:
    """Runs every task in the calling thread when its result is first needed (submission order)."""

    kind = SYNCHRONOUS
    dashboard = None
    n_workers = 1
    address = SYNCHRONOUS

    def __init__(self):
        self._current = None

    def submit(self, fn: Callable, *args, key: str | None = None) -> _SyncHandle:
        return _SyncHandle(fn, args, key or f"{getattr(fn, '__name__', 'task')}-{uuid.uuid4().hex[:8]}")

    def share(self, obj) -> Any:
        """An object every task may take as an argument (here: the object itself)."""
        return obj

    def _run(self, h: _SyncHandle) -> None:
        if h.done:
            return
        import dask

        args = []
        for a in h.args:
            if isinstance(a, _SyncHandle):
                self._run(a)
                if not a.ok:
                    h.done, h.ok, h.value = True, False, a.value
                    return
                a = a.value
            args.append(a)
        self._current = h
        try:
            h.value = dask.delayed(h.fn, pure=False)(*args).compute(scheduler="synchronous")
            h.ok = True
        except Exception as exc:  # a failed task is a result; KeyboardInterrupt goes through
            h.value, h.ok = exc, False
        finally:
            self._current = None
            h.done = True

    def completed(self, handles, tick: Callable[[], None] | None = None) -> "_Completed":
        return _Completed(self, handles, tick)

    def running(self, handles) -> int:
        """Tasks among ``handles`` executing now: the next one while the caller waits for it."""
        return int(any(not h.done for h in handles))

    def cancel(self, handles) -> None:
        pass


@contextlib.contextmanager
def _sigint_deferred():
    """Ctrl-C held back for the duration of one of distributed's blocking calls (``Client.sync``:
    ``processing()``, ``scheduler_info()``, ``Future.result()``) and delivered right after it, in our
    code. Landing inside ``sync()`` itself, a KeyboardInterrupt makes distributed's cancel callback log a
    NameError traceback through tornado (distributed's ``utils.sync``: ``future`` not yet bound) while the
    sweep stops. Main thread only (elsewhere signal handlers cannot be set and Ctrl-C does not land)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    got = []
    old = signal.signal(signal.SIGINT, lambda signum, frame: got.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)
        if got:
            signal.raise_signal(signal.SIGINT)  # the original handler (KeyboardInterrupt, runcontrol's), now


class _Completed:
    """Iterator over ``(handle, ok, value)`` in completion order; ``add(handle)`` extends it."""

    def __init__(self, ex, handles, tick=None):
        self.ex = ex
        self.tick = tick
        self.queue = deque()
        if isinstance(ex, DistributedExecutor):
            from distributed import as_completed

            self._ac = as_completed(list(handles))
        else:
            self._ac = None
            self.queue.extend(handles)

    def add(self, h) -> None:
        if self._ac is not None:
            self._ac.add(h)
        else:
            self.queue.append(h)

    def __iter__(self) -> Iterator:
        return self

    def __next__(self):
        if self._ac is None:
            if not self.queue:
                raise StopIteration
            h = self.queue.popleft()
            if self.tick is not None:
                self.tick()
            self.ex._run(h)
            return h, h.ok, h.value
        # poll, so a progress display sees tasks start between completions, and Ctrl-C lands in
        # time.sleep here, not inside distributed's blocking sync() (whose cancel callback then logs
        # a NameError traceback through tornado while the sweep stops)
        while not self._ac.is_empty() and not self._ac.has_ready():
            if self.tick is not None:
                self.tick()
            time.sleep(0.1 if self.tick is None else 0.25)
        with _sigint_deferred():
            f = next(self._ac)
            if f.status == "finished":
                return f, True, f.result()
            try:
                exc = f.exception()
            except Exception as e:  # cancelled, lost
                exc = e
        return f, False, exc if exc is not None else RuntimeError(f"task {f.key} ended as {f.status}")


class DistributedExecutor:
    """Tasks on a ``distributed.Client`` (LocalCluster or a cluster by address)."""

    def __init__(self, client, kind: str, cluster=None):
        self.client = client
        self.kind = kind
        self.cluster = cluster
        self._proc_cache = (0.0, set())

    @property
    def address(self) -> str:
        return self.client.scheduler.address

    @property
    def dashboard(self) -> str | None:
        try:
            return self.client.dashboard_link
        except Exception:
            return None

    @property
    def n_workers(self) -> int:
        with _sigint_deferred():
            return len(self.client.scheduler_info().get("workers", {}))

    def submit(self, fn: Callable, *args, key: str | None = None):
        key = f"{key}-{uuid.uuid4().hex[:8]}" if key else None  # unique: two sweeps may share a cluster
        return self.client.submit(fn, *args, key=key, pure=False)

    def share(self, obj):
        """A future holding ``obj`` on a worker (recomputable from the graph if that worker dies)."""
        return self.client.submit(_identity, obj, pure=False)

    def completed(self, handles, tick: Callable[[], None] | None = None) -> _Completed:
        return _Completed(self, handles, tick)

    def running(self, handles) -> int:
        now = time.monotonic()
        t, keys = self._proc_cache
        if now - t > 0.5:
            try:
                with _sigint_deferred():
                    keys = {k for ks in self.client.processing().values() for k in ks}
            except Exception:
                keys = set()
            self._proc_cache = (now, keys)
        return sum(1 for h in handles if h.key in keys)

    def cancel(self, handles) -> None:
        with contextlib.suppress(Exception):
            self.client.cancel(list(handles))


@contextlib.contextmanager
def _children_ignore_sigint():
    """Processes started inside (the LocalCluster's nannies and workers) ignore SIGINT: Ctrl-C in a
    terminal reaches the whole process group, and workers that take it die with a traceback each
    (printed twice through the nanny) while the parent is still stopping them cleanly. The parent
    keeps its own handler; it closes the cluster."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


@contextlib.contextmanager
def allow_child_processes():
    """Let code in a Dask worker start ``multiprocessing`` children.

    Dask's worker processes are daemonic by default (``distributed.worker.daemon``) and
    ``multiprocessing`` refuses children in a daemonic process; the optimiser's relaxation runs in
    a forked child so that a time limit can end it. On a worker started without
    ``DASK_DISTRIBUTED__WORKER__DAEMON=False`` this lifts the flag for the duration of the block
    (the child is itself daemonic and killed at its deadline by the task).
    """
    import multiprocessing

    cfg = multiprocessing.current_process()._config
    was = cfg.get("daemon")
    if was:
        cfg["daemon"] = False
    try:
        yield
    finally:
        if was:
            cfg["daemon"] = was


#: modules whose objects travel between workers (a DesignProblem holds a trimesh.Trimesh)
WARM_IMPORTS = ("numpy", "scipy.sparse", "trimesh", "layoutkit.optimize", "layoutkit.envelope")


def _warm_imports_plugin():
    """A worker plugin importing :data:`WARM_IMPORTS` when a worker starts (every worker, later ones
    too). Without it a worker could unpickle a Trimesh fetched from another worker on its comm thread
    while its task thread was still importing trimesh: Python then hands out the half-imported package
    ("cannot import name 'Trimesh' from partially initialized module"), seen on a loaded machine."""
    from distributed.diagnostics.plugin import WorkerPlugin

    class WarmImports(WorkerPlugin):
        name = "layoutkit-warm-imports"

        def setup(self, worker):
            import importlib

            for mod in WARM_IMPORTS:
                importlib.import_module(mod)

    return WarmImports()


def _identity(x):
    return x


def _is_address(s: str) -> bool:
    return "://" in s or (":" in s and s.rsplit(":", 1)[1].isdigit())


@contextlib.contextmanager
def open_executor(scheduler: str | None = None, workers: int | None = None):
    """Open the executor for ``scheduler`` (see the module docstring); closes what it started.

    workers : processes of the LocalCluster (only without ``scheduler``). Raises ``ValueError``
    with a plain message for a bad choice or an address that does not answer.
    """
    if workers is not None and int(workers) < 1:
        raise ValueError(f"--workers: expected >= 1, got {workers}")
    if scheduler is not None and scheduler.strip().lower() == SYNCHRONOUS:
        if workers not in (None, 1):
            raise ValueError("--workers: the synchronous scheduler runs everything in this process "
                             "(drop --workers, or drop --scheduler synchronous for a LocalCluster)")
        yield SynchronousExecutor()
        return
    import logging

    import dask
    from distributed import Client, LocalCluster

    if scheduler is None:
        n = int(workers) if workers is not None else default_workers()
        # non-daemonic workers: a task may start a child process (the optimiser runs its relaxation
        # in a forked child to enforce time limits); the nanny still stops its worker on exit
        with dask.config.set({"distributed.worker.daemon": False}), _children_ignore_sigint():
            cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0",
                                   silence_logs=logging.ERROR)
        client = Client(cluster)
        client.register_plugin(_warm_imports_plugin())
        try:
            yield DistributedExecutor(client, "local", cluster)
        finally:
            with contextlib.suppress(Exception):
                client.close()
            with contextlib.suppress(Exception):
                cluster.close()
        return
    if workers is not None:
        raise ValueError("--workers: the cluster at --scheduler decides how many workers run "
                         "(start more `dask worker` processes there)")
    if not _is_address(scheduler):
        raise ValueError(f"--scheduler: expected an address like tcp://host:8786 or 'synchronous', got {scheduler!r}")
    try:
        client = Client(scheduler, timeout="15s")
    except (OSError, TimeoutError) as exc:
        raise ValueError(f"--scheduler {scheduler}: no Dask scheduler answers there ({exc})") from None
    try:
        client.register_plugin(_warm_imports_plugin())
        yield DistributedExecutor(client, "cluster")
    finally:
        with contextlib.suppress(Exception):
            client.close()
