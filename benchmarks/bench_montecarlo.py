"""Chunked Monte-Carlo of the Chen (2024) static study on Dask: scaling, memory, reproducibility.

    .venv/bin/python benchmarks/bench_montecarlo.py [--quick] [--frames N] [--big-frames M] [--rounds R]

1. Scaling: the static study (50 groups) with ``N`` frames in total on a LocalCluster of 1 and of 2
   worker processes (one thread each), interleaved rounds, median frames/s (cluster start-up not
   timed). The two results must be identical (same seeds, merged in chunk order).
2. Largest run: ``M`` frames on 2 workers; peak RSS of every worker process (``ru_maxrss``) and of
   the client, next to the same at ``N`` frames: flat memory means the peaks do not grow with frames.

Anchor: the 1-worker run of the same code (ratio = 2-worker / 1-worker frames/s). The machine's
two cores are shared with other jobs, so the wall-clock ratio is a floor, not the library's limit;
the CPU seconds each worker spent (``getrusage`` in the worker) are load-independent: frames per
CPU-second, and sum/max of the workers' CPU (the speed-up the split gives when the cores are free).
Writes benchmarks/results/montecarlo.json (montecarlo_quick.json with --quick).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _util import max_rss_bytes, write_result  # noqa: E402

from layoutkit.parallel import open_executor  # noqa: E402
from layoutkit.studies.chen2024 import StudyConfig, static_groups  # noqa: E402

GROUPS = 50
CHUNK = 20000


def _worker_peak_rss(ex) -> list[int]:
    peaks = ex.client.run(lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)
    return sorted(peaks.values())


def _cpu(ex) -> dict:
    def f():
        r = resource.getrusage(resource.RUSAGE_SELF)
        return r.ru_utime + r.ru_stime
    return ex.client.run(f)


def run(frames_total: int, workers: int, seed: int = 0):
    cfg = StudyConfig(groups=GROUPS, frames=max(2, frames_total // GROUPS), seed=seed, chunk_frames=CHUNK)
    with open_executor(None, workers) as ex:
        c0 = _cpu(ex)
        t0 = time.perf_counter()
        groups = static_groups(cfg, executor=ex)
        dt = time.perf_counter() - t0
        c1 = _cpu(ex)
        peaks = _worker_peak_rss(ex)
    frames = cfg.frames * cfg.groups
    cpu = sorted(c1[k] - c0[k] for k in c1)
    # CPU seconds per worker: load-independent; sum/max is the speed-up the split gives on free cores
    return {"frames": frames, "seconds": dt, "frames_per_s": frames / dt, "worker_peak_rss_bytes": peaks,
            "worker_cpu_s": cpu, "frames_per_cpu_s": frames / sum(cpu), "cpu_split_speedup": sum(cpu) / max(cpu),
            "groups": groups}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--frames", type=int, default=None, help="frames of the scaling runs (default 5e5; quick 5e4)")
    ap.add_argument("--big-frames", type=int, default=None, help="frames of the largest run (default 1e7; quick 2e5)")
    ap.add_argument("--rounds", type=int, default=None, help="scaling rounds (default 3; quick 1)")
    a = ap.parse_args()
    n = a.frames or (50_000 if a.quick else 500_000)
    big = a.big_frames or (200_000 if a.quick else 10_000_000)
    rounds = a.rounds or (1 if a.quick else 3)
    times = {1: [], 2: []}
    split = {1: [], 2: []}
    res = {}
    for r in range(rounds):
        for w in (1, 2):
            out = run(n, w)
            times[w].append(out["seconds"])
            split[w].append(out["cpu_split_speedup"])
            res[w] = out
            print(f"round {r}: {w} worker(s): {out['frames']} frames in {out['seconds']:.1f} s "
                  f"({out['frames_per_s']:.0f} frames/s; worker CPU {[round(c, 1) for c in out['worker_cpu_s']]} s)",
                  flush=True)
    identical = json.dumps(res[1]["groups"]) == json.dumps(res[2]["groups"])
    fps = {w: res[w]["frames"] / statistics.median(times[w]) for w in (1, 2)}
    print(f"1 vs 2 workers identical: {identical}; speed-up {fps[2] / fps[1]:.2f}", flush=True)
    t0 = time.perf_counter()
    b = run(big, 2)
    print(f"largest: {b['frames']} frames in {b['seconds']:.0f} s ({b['frames_per_s']:.0f} frames/s); worker "
          f"peak RSS {[round(x / 2**20) for x in b['worker_peak_rss_bytes']]} MiB", flush=True)
    ratios = [g["simulated_sigma_rot_deg"] / g["predicted_sigma_rot_deg"] for g in b["groups"]]
    ratios_t = [g["simulated_sigma_trans_m"] / g["predicted_sigma_trans_m"] for g in b["groups"]]
    p = write_result("montecarlo_quick" if a.quick else "montecarlo", {
        "what": "Chen (2024) static study (50 groups, chunks of 20000 frames) as Dask tasks on a LocalCluster",
        "chunk_frames": CHUNK,
        "scaling": {"frames": res[1]["frames"], "rounds": rounds,
                    "seconds": {str(w): times[w] for w in (1, 2)},
                    "frames_per_s_median": {str(w): fps[w] for w in (1, 2)},
                    "speedup_2_vs_1": fps[2] / fps[1],
                    "worker_cpu_s": {str(w): res[w]["worker_cpu_s"] for w in (1, 2)},
                    "frames_per_cpu_s": {str(w): res[w]["frames_per_cpu_s"] for w in (1, 2)},
                    "cpu_split_speedup_2_workers_median": statistics.median(split[2]),
                    "load_average_at_end": list(os.getloadavg()),
                    "results_identical_1_vs_2_workers": identical,
                    "worker_peak_rss_bytes": {str(w): res[w]["worker_peak_rss_bytes"] for w in (1, 2)}},
        "largest": {"frames": b["frames"], "workers": 2, "seconds": b["seconds"], "frames_per_s": b["frames_per_s"],
                    "worker_cpu_s": b["worker_cpu_s"], "cpu_split_speedup": b["cpu_split_speedup"],
                    "worker_peak_rss_bytes": b["worker_peak_rss_bytes"],
                    "median_ratio_rot": statistics.median(ratios), "median_ratio_trans": statistics.median(ratios_t),
                    "max_abs_rel_dev_rot": max(abs(x - 1) for x in ratios),
                    "gross_failures": sum(g["gross_failures"] for g in b["groups"])},
        "client_peak_rss_bytes": max_rss_bytes(),
        "wall_s_total": time.perf_counter() - t0,
    })
    print("wrote", p)


if __name__ == "__main__":
    main()
