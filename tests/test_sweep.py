"""`layoutkit sweep` on Dask.

Proof kinds: (1) same-computation comparison — the same sweep through a real LocalCluster and
through the synchronous scheduler gives identical cells, and each cell equals a direct call of
``layoutkit optimize`` on the same problem; (2) fault injection on real processes — a real
``dask scheduler`` + ``dask worker`` on 127.0.0.1, the worker SIGKILLed mid-sweep, a new worker
started: the sweep completes; a sweep process SIGKILLed halfway resumes and runs only the missing
cells (files of finished cells byte-identical afterwards); (3) bad input — unknown keys rejected
naming the file and key.
"""
from __future__ import annotations

import contextlib
import csv
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from layoutkit.cli import main
from layoutkit.workflows.sweep_config import load_sweep

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def _sweep_dir(tmp_path, small_envelope, axes="k = [5, 6]\nmethod = [\"greedy\", \"pipeline\"]\n", base_extra=""):
    shutil.copy(REPO / "models" / "chen_target.stl", tmp_path / "target.stl")
    shutil.copy(small_envelope, tmp_path / "envelope.toml")
    (tmp_path / "sweep.toml").write_text(f"""[base]
mesh = "target.stl"
envelope = "envelope.toml"
spacing_mm = 20.0
max_candidates = 40
rho = 0.8717
time_limit_s = 120
{base_extra}
[axes]
{axes}""")
    return tmp_path / "sweep.toml"


def _cells(out):
    d = {}
    for p in (Path(out) / "cells").glob("*.json"):
        if not p.name.endswith(".layout.json"):
            d[p.stem] = json.loads(p.read_text())
    return d


KEYS = ("status", "value", "bound", "gap", "selected_ids", "certified_by", "input_hash")


@pytest.mark.slow
def test_localcluster_and_synchronous_give_identical_cells(tmp_path, small_envelope):
    sweep = _sweep_dir(tmp_path, small_envelope)
    r = CliRunner()
    a = r.invoke(main, ["sweep", str(sweep), "--out", str(tmp_path / "sync"), "--scheduler", "synchronous"])
    assert a.exit_code == 0, a.output
    b = r.invoke(main, ["sweep", str(sweep), "--out", str(tmp_path / "local"), "--workers", "2"])
    assert b.exit_code == 0, b.output
    assert "dashboard http" in b.output  # the LocalCluster's dashboard address is printed
    ca, cb = _cells(tmp_path / "sync"), _cells(tmp_path / "local")
    assert len(ca) == 4 and ca.keys() == cb.keys()
    for cid in ca:
        assert ca[cid]["status"] == "ok"
        assert {k: ca[cid][k] for k in KEYS} == {k: cb[cid][k] for k in KEYS}, cid
    rows = list(csv.DictReader(open(tmp_path / "local" / "summary.csv")))
    assert [c for c in rows[0]][:7] == ["k", "method", "status", "value", "bound", "gap", "wall_s"]
    assert sorted((r["k"], r["method"]) for r in rows) == [("5", "greedy"), ("5", "pipeline"),
                                                           ("6", "greedy"), ("6", "pipeline")]
    for p in ("objective_vs_axes.png", "pareto_worst_adop_vs_k.png", "summary.json"):
        assert (tmp_path / "local" / p).stat().st_size > 0
    # a cell equals `layoutkit optimize` run directly on the same problem (independent path)
    from layoutkit.optimize import DesignProblem, OptimizeSpec
    from layoutkit.workflows.optimize import run_optimize

    cell = next(c for c in ca.values() if c["axes"] == {"k": 6, "method": "pipeline"})
    spec = OptimizeSpec(k=6, rho=0.8717, time_limit_s=120, method="pipeline")
    problem = DesignProblem.for_spec(str(tmp_path / "target.stl"), str(tmp_path / "envelope.toml"), spec, spacing=0.02,
                                     max_candidates=40)
    direct = run_optimize(problem, spec, render=False)
    assert direct["selected_ids"] == cell["selected_ids"]
    assert direct["value"] == pytest.approx(cell["value"], rel=1e-12)
    lay = json.loads((tmp_path / "local" / "cells" / cell["layout"]).read_text())
    assert [s["candidate"] for s in lay["sensors"]] == cell["selected_ids"]


def test_sweep_file_errors_name_file_and_key(tmp_path, small_envelope):
    sweep = _sweep_dir(tmp_path, small_envelope, base_extra="spacing = 3\n")
    r = CliRunner().invoke(main, ["sweep", str(sweep), "--out", str(tmp_path / "o"), "--scheduler", "synchronous"])
    assert r.exit_code == 2 and "error:" in r.output and "sweep.toml" in r.output and "base.spacing" in r.output
    sweep = _sweep_dir(tmp_path, small_envelope, axes="k = [5, 'x']\n")
    with pytest.raises(ValueError, match=r"sweep.toml: axes.k\[1\]: expected an integer"):
        load_sweep(sweep)
    sweep = _sweep_dir(tmp_path, small_envelope, axes="k = [5]\nmax_tilt_deg = [0.0, 95.0]\n")
    with pytest.raises(ValueError, match=r"sweep.toml: axes.max_tilt_deg\[1\]: expected a number in \[0.0, 90.0\)"):
        load_sweep(sweep)
    sweep = _sweep_dir(tmp_path, small_envelope, axes="k = [5]\nunits = ['m', 'mm']\n")
    with pytest.raises(ValueError, match="axes.units: cannot be swept"):
        load_sweep(sweep)


@pytest.mark.slow
def test_failed_cell_is_recorded_and_the_sweep_goes_on(tmp_path, small_envelope):
    sweep = _sweep_dir(tmp_path, small_envelope, axes="k = [5, 400]\nmethod = [\"greedy\"]\n")
    r = CliRunner().invoke(main, ["sweep", str(sweep), "--out", str(tmp_path / "o"), "--scheduler", "synchronous"])
    assert r.exit_code == 1
    cells = _cells(tmp_path / "o")
    by_k = {c["axes"]["k"]: c for c in cells.values()}
    assert by_k[5]["status"] == "ok"
    assert by_k[400]["status"] == "error" and "k: expected 1 <= k <=" in by_k[400]["message"]
    # re-run: the ok cell is reused, the failed one retried
    r = CliRunner().invoke(main, ["sweep", str(sweep), "--out", str(tmp_path / "o"), "--scheduler", "synchronous",
                                  "--json"])
    s = json.loads(r.stdout)
    assert (s["ran"], s["skipped"]) == (1, 1)
    # a changed input invalidates the cells it feeds: another envelope seed reruns both
    env = tmp_path / "envelope.toml"
    env.write_text(env.read_text().replace("seed = 3", "seed = 4"))
    r = CliRunner().invoke(main, ["sweep", str(sweep), "--out", str(tmp_path / "o"), "--scheduler", "synchronous",
                                  "--json"])
    assert json.loads(r.stdout)["ran"] == 2 and "changed inputs" in r.stderr


def test_tilt_axis_equals_optimize_with_tilt(tmp_path, small_envelope):
    """Same-computation check: a tilted cell equals `run_optimize` with the same tilt directly."""
    sweep = _sweep_dir(tmp_path, small_envelope, axes="k = [6]\nmax_tilt_deg = [0.0, 20.0]\n",
                       base_extra='method = "greedy"\n')
    r = CliRunner().invoke(main, ["sweep", str(sweep), "--out", str(tmp_path / "o"), "--scheduler", "synchronous"])
    assert r.exit_code == 0, r.output
    cells = {c["axes"]["max_tilt_deg"]: c for c in _cells(tmp_path / "o").values()}
    from layoutkit.optimize import DesignProblem, OptimizeSpec
    from layoutkit.workflows.optimize import run_optimize

    spec = OptimizeSpec(k=6, rho=0.8717, method="greedy", max_tilt_deg=20.0)
    problem = DesignProblem.for_spec(str(tmp_path / "target.stl"), str(tmp_path / "envelope.toml"), spec, spacing=0.02,
                                     max_candidates=40)
    direct = run_optimize(problem, spec, render=False)
    assert cells[20.0]["status"] == direct["status"] == "ok"
    assert cells[20.0]["value"] == pytest.approx(direct["value"], rel=1e-12)
    assert cells[20.0]["candidates"] > cells[0.0]["candidates"]  # tilted orientations are candidates


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait(cond, timeout, what):
    t = time.monotonic() + timeout
    while time.monotonic() < t:
        if cond():
            return
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


def _start(cmd, **kw):
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True, **kw)


def _kill(p):
    if p.poll() is None:
        os.killpg(p.pid, signal.SIGKILL)
        p.wait(10)


SLOW_AXES = "k = [5, 6, 7]\nmethod = [\"pipeline\"]\nseed = [1, 2]\n"


@pytest.mark.slow
def test_real_scheduler_worker_killed_midsweep_then_completes(tmp_path, small_envelope):
    sweep = _sweep_dir(tmp_path, small_envelope, axes=SLOW_AXES).read_text().replace("time_limit_s = 120", "time_limit_s = 1.0")
    (tmp_path / "sweep.toml").write_text(sweep)
    port = _free_port()
    addr = f"tcp://127.0.0.1:{port}"
    sched = _start([str(BIN / "dask"), "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"])
    procs = [sched]
    worker_cmd = [str(BIN / "dask"), "worker", addr, "--nthreads", "1", "--nworkers", "1", "--no-dashboard",
                  "--host", "127.0.0.1"]
    try:
        w1 = _start(worker_cmd)
        procs.append(w1)
        out = tmp_path / "out"
        run = subprocess.Popen([str(BIN / "layoutkit"), "sweep", str(tmp_path / "sweep.toml"), "--out", str(out),
                                "--scheduler", addr], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        procs.append(run)
        _wait(lambda: len(_cells(out)) >= 1 if (out / "cells").exists() else False, 90, "a first cell")
        before = {p.name: p.read_bytes() for p in (out / "cells").glob("*.json")}
        _kill(w1)  # the only worker dies while the sweep is running
        assert len(before) < 12  # mid-sweep: cells (json + layout) still missing
        time.sleep(1.0)
        assert run.poll() is None  # the sweep waits for workers instead of failing
        procs.append(_start(worker_cmd))  # a new worker joins the cluster
        so, se = run.communicate(timeout=150)
        assert run.returncode == 0, se
        assert f"cluster {addr}" in se
        cells = _cells(out)
        assert len(cells) == 6 and all(c["status"] == "ok" for c in cells.values())
        for name, data in before.items():  # finished cells were not redone
            assert (out / "cells" / name).read_bytes() == data
        s = json.loads((out / "summary.json").read_text())
        assert s["cells"] == 6 and s["errors"] == 0
    finally:
        for p in procs[::-1]:
            if isinstance(p, subprocess.Popen) and p.args[0] != str(BIN / "layoutkit"):
                _kill(p)
            elif p.poll() is None:
                p.kill()


@pytest.mark.slow
def test_killed_sweep_resumes_with_only_the_missing_cells(tmp_path, small_envelope):
    sweep = _sweep_dir(tmp_path, small_envelope, axes=SLOW_AXES).read_text().replace("time_limit_s = 120", "time_limit_s = 0.7")
    (tmp_path / "sweep.toml").write_text(sweep)
    out = tmp_path / "out"
    cmd = [str(BIN / "layoutkit"), "sweep", str(tmp_path / "sweep.toml"), "--out", str(out), "--scheduler", "synchronous"]
    p = _start(cmd)
    try:
        _wait(lambda: (out / "cells").exists() and len(_cells(out)) >= 2, 90, "two cells")
    finally:
        _kill(p)  # SIGKILL: no clean-up at all
    first = {p.name: p.read_bytes() for p in (out / "cells").glob("*.json")}
    n_first = len(_cells(out))
    assert 2 <= n_first < 6
    assert not list((out / "cells").glob(".*.tmp"))  # atomic writes: no partial file left behind
    r = subprocess.run(cmd + ["--json"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["skipped"] == n_first and s["ran"] == 6 - n_first
    assert set(s["ran_cells"]).isdisjoint({n[:-5] for n in first if not n.endswith(".layout.json")})
    for name, data in first.items():
        assert (out / "cells" / name).read_bytes() == data
    assert len(_cells(out)) == 6


def test_dask_is_imported_only_inside_the_commands():
    """House rule: heavy imports inside command bodies (import check in a fresh interpreter)."""
    code = ("import sys, layoutkit.cli, layoutkit.parallel, layoutkit.workflows.sweep_config, layoutkit.workflows.sweep, "
            "layoutkit.workflows.validate, layoutkit.montecarlo; "
            "print(','.join(m for m in ('dask', 'distributed', 'bokeh') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == ""


@contextlib.contextmanager
def _terminal_sigint():
    """A terminal's SIGINT state for this thread and the children it starts: delivered (unblocked) and
    default-handled; restored after. Blocked and ignored signals are inherited across fork and exec. In
    two full runs (session 11, after a new test file changed the workers' test orders) neither a
    sweep started from the worker nor a raise_signal in the worker itself saw the SIGINT, which fits
    SIGINT blocked or ignored in that worker; each test passes alone."""
    mask = signal.pthread_sigmask(signal.SIG_UNBLOCK, [signal.SIGINT])
    prev = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, prev)
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)


@pytest.mark.slow
def test_ctrl_c_in_a_terminal_ends_a_localcluster_sweep_without_tracebacks(tmp_path, small_envelope):
    """Ctrl-C reaches the whole foreground process group, Dask's nanny and worker processes too:
    they used to die with a KeyboardInterrupt traceback each (printed twice through the nanny)
    while the sweep itself stopped cleanly (issue 29). SIGINT to the group of a real LocalCluster
    sweep: one 'interrupted:' line, no traceback, the finished cells kept."""
    sweep = _sweep_dir(tmp_path, small_envelope, axes=SLOW_AXES).read_text().replace("time_limit_s = 120", "time_limit_s = 3")
    (tmp_path / "sweep.toml").write_text(sweep)
    out = tmp_path / "out"
    with _terminal_sigint():  # the child inherits it
        p = subprocess.Popen([str(BIN / "layoutkit"), "sweep", str(tmp_path / "sweep.toml"), "--out", str(out),
                              "--workers", "2"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             start_new_session=True)
    try:
        _wait(lambda: (out / "cells").exists() and len(_cells(out)) >= 1, 120, "a first cell")
        os.killpg(p.pid, signal.SIGINT)  # what a terminal does on Ctrl-C
        so, se = p.communicate(timeout=60)
    finally:
        _kill(p)
    assert "interrupted:" in se and "Traceback" not in se, se
    assert 1 <= len(_cells(out)) < 6


def test_ctrl_c_during_a_blocking_dask_call_is_delivered_right_after_it():
    """parallel.scheduler._sigint_deferred (around distributed's blocking Client.sync calls): a real
    SIGINT raised inside runs no handler there (the call finishes), then reaches the process's own
    handler (here Python's KeyboardInterrupt) as soon as the block ends; the handler is restored."""
    from layoutkit.parallel.scheduler import _sigint_deferred

    with _terminal_sigint():
        before = signal.getsignal(signal.SIGINT)
        ran = []
        with pytest.raises(KeyboardInterrupt):
            with _sigint_deferred():
                signal.raise_signal(signal.SIGINT)
                ran.append("the blocking call went on")
        assert ran == ["the blocking call went on"] and signal.getsignal(signal.SIGINT) is before
        with _sigint_deferred():  # no signal: nothing delivered
            ran.append("quiet")
        assert ran[-1] == "quiet"
