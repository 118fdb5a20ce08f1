"""A design sweep on Dask with 1 and 2 LocalCluster workers: wall time and the workers' CPU split.

    .venv/bin/python benchmarks/bench_sweep.py [--quick]

8 cells (k ∈ {6, 8, 10, 12} × half-angle ∈ {55, 65} deg) on the bundled Chen target, 12 mm
candidate spacing, a 60-pose envelope, the default pipeline with a 4 s budget per cell (2 s quick).
Anchor: the same sweep on 1 worker. Wall time on this shared 2-core machine is load-dependent; the
CPU seconds of each worker process and its children (``getrusage`` inside it) are not: sum/max is
the speed-up the split gives on free cores. Cells that stop at their time budget take that long
whatever the load, so their wall time scales with workers too. Writes benchmarks/results/sweep.json (sweep_quick.json with --quick).
"""
from __future__ import annotations

import argparse
import os
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _util import write_result  # noqa: E402

from layoutkit.parallel import open_executor  # noqa: E402
from layoutkit.workflows.sweep import run_sweep  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def _cpu(ex):
    def f():  # the worker and its reaped children (the optimiser's relaxation runs in a forked child)
        r, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
        return r.ru_utime + r.ru_stime + c.ru_utime + c.ru_stime
    return ex.client.run(f)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_sweep_"))
    shutil.copy(REPO / "models" / "chen_target.stl", tmp / "target.stl")
    (tmp / "env.toml").write_text('count = 60\nseed = 2\nrange_m = [1.0, 3.0]\nboresight_cone_deg = 25.0\n'
                                  '[attitude]\nkind = "cone"\nnominal_rotvec_deg = [180.0, 0.0, 0.0]\n'
                                  'half_angle_deg = 40.0\n')
    (tmp / "sweep.toml").write_text(f"""[base]
mesh = "target.stl"
envelope = "env.toml"
spacing_mm = 12.0
rho = 0.8717
time_limit_s = {2 if a.quick else 4}
[axes]
k = [6, 8, 10, 12]
half_angle_deg = [55.0, 65.0]
""")
    out = {}
    for w in (1, 2):
        with open_executor(None, w) as ex:
            c0 = _cpu(ex)
            t0 = time.perf_counter()
            s = run_sweep(tmp / "sweep.toml", tmp / f"out{w}", ex, echo=lambda m: None)
            dt = time.perf_counter() - t0
            c1 = _cpu(ex)
        cpu = sorted(c1[k] - c0[k] for k in c1)
        out[str(w)] = {"wall_s": dt, "worker_cpu_s": cpu, "cpu_split_speedup": sum(cpu) / max(cpu),
                       "cells": s["cells"], "feasible": s["feasible"], "errors": s["errors"],
                       "cell_wall_s": [r["wall_s"] for r in s["rows"]]}
        print(f"{w} worker(s): {s['cells']} cells in {dt:.1f} s; worker CPU {[round(c, 1) for c in cpu]} s", flush=True)
    shutil.rmtree(tmp, ignore_errors=True)
    p = write_result("sweep_quick" if a.quick else "sweep", {
        "what": "8-cell design sweep (Chen target, pipeline with a per-cell time budget) on a LocalCluster",
        "runs": out, "wall_speedup_2_vs_1": out["1"]["wall_s"] / out["2"]["wall_s"],
        "load_average_at_end": list(os.getloadavg())})
    print("wrote", p)


if __name__ == "__main__":
    main()
