"""Certified gap against wall time on the issue's instance (issue 13, item 6).

    .venv/bin/python benchmarks/bench_certificate.py [--limits 60,120,300] [--off-limits 120]
    .venv/bin/python benchmarks/bench_certificate.py --seeds 5 [--first-seed 101] [--limits 60,120,300]

``--seeds N`` (issue 30, item 2): the family — N more instances drawn the same way with seeds
``first_seed … first_seed + N - 1`` (none of them the tuned-on seed 7), one run per seed and limit, a
per-seed table and, per limit, the median and worst gap; writes benchmarks/results/certificate_seeds.json
(the single-instance file is left alone).

Instance: ``benchmarks/bench_optimize.py`` part B — ``synthetic_instance(1000, 200, rng=7)``,
k = 16, rho = 0.8717 (RHO_PAPER), worst ADOP, 4 lit at every pose. One ``pipeline`` run per time
limit (the limit includes the relaxation and the branch-and-bound of :mod:`layoutkit.optimize.bnb`,
which runs in a second process beside the search and, once the search is done, gets node
relaxations solved by the parent too), and one run per ``--off-limits`` entry with
``branch_and_bound="off"`` (relaxation bound only) as the same-run anchor. Value, certified bound,
gap, who certified it, B&B node count, why B&B stopped and its bound history, wall and CPU time of each;
the load average before and after each run (the machine has 2 cores: figures measured under load say so). Writes
benchmarks/results/certificate.json.
"""
from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _util import max_rss_bytes, write_result  # noqa: E402

from layoutkit.optimize import optimize_layout  # noqa: E402
from layoutkit.optimize.instances import synthetic_instance  # noqa: E402
from layoutkit.units import RHO_PAPER  # noqa: E402


def _run(inst, tl, bnb):
    load = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), os.times()
    r = optimize_layout(**inst, k=16, rho=RHO_PAPER, time_limit=tl, rng=0, branch_and_bound=bnb)
    wall, c1 = time.perf_counter() - t0, os.times()
    b = r.info.get("branch_and_bound", {})
    row = {"time_limit_s": tl, "branch_and_bound": bnb, "wall_s": wall, "value": r.value, "bound": r.bound,
           "gap": r.gap, "certified_by": r.certified_by, "root_bound": b.get("root_bound"),
           "bnb_nodes": b.get("nodes"), "bnb_open_nodes": b.get("open_nodes"),
           "bnb_nodes_solved_by_parent": b.get("served_by_parent"), "search_s": r.info.get("search_s"),
           "relaxation_s": r.timings.get("relaxation_s"), "bnb_stopped": b.get("stopped"),
           "bnb_stopped_at_s": b.get("stopped_at_s"), "bnb_history": b.get("history"),
           # CPU seconds this run got (parent; forked relaxation / B&B / node-server children): on a shared
           # machine the wall-clock limit buys fewer node relaxations than on a quiet one
           "cpu_parent_s": (c1.user - c0.user) + (c1.system - c0.system),
           "cpu_children_s": (c1.children_user - c0.children_user) + (c1.children_system - c0.children_system),
           "load_avg_1min_before": load, "load_avg_1min_after": os.getloadavg()[0],
           "status": r.status, "message": r.message}
    print(f"limit {tl:.0f} s, B&B {bnb}: wall {wall:.1f} s, value {r.value:.2f}, bound {r.bound:.2f} "
          f"({r.certified_by}, {b.get('nodes', 0)} nodes), gap {100 * r.gap:.2f} %, load {load:.1f}; "
          f"B&B stopped: {b.get('stopped')}", flush=True)
    return row


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--limits", default="60,120,300")
    ap.add_argument("--off-limits", default="120", help="time limits also run with branch_and_bound='off'")
    ap.add_argument("--seeds", type=int, default=0, help="instances of the family (0: the issue's instance only)")
    ap.add_argument("--first-seed", type=int, default=101)
    ap.add_argument("--result-name", default="certificate_seeds",
                    help="--seeds: results/<name>.json (e.g. a held-out family of seeds beside the must-show's)")
    args = ap.parse_args()
    import cvxpy  # noqa: F401 - import outside the timed runs

    if args.seeds:
        return _family(args)

    inst = synthetic_instance(1000, 200, rng=7)
    rows = [_run(inst, float(x), "auto") for x in args.limits.split(",") if x]
    rows += [_run(inst, float(x), "off") for x in args.off_limits.split(",") if x]
    child = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024
    p = write_result("certificate", {"instance": "synthetic_instance(1000, 200, rng=7), k=16, rho=0.8717, worst-adop",
                                     "cpus": os.cpu_count(), "runs": rows, "max_rss_bytes": max_rss_bytes(),
                                     "max_rss_children_bytes": child})
    print("->", p)


def _family(args):
    """One run per (seed, limit) on instances drawn like the issue's; median/worst gap per limit."""
    import numpy as np

    limits = [float(x) for x in args.limits.split(",") if x]
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    rows = []
    for sd in seeds:
        inst = synthetic_instance(1000, 200, rng=sd)
        for tl in limits:
            rows.append({"seed": sd, **_run(inst, tl, "auto")})
    summary = {}
    for tl in limits:
        g = [r["gap"] for r in rows if r["time_limit_s"] == tl]
        early = [{"seed": r["seed"], "wall_s": r["wall_s"], "bnb_stopped": r["bnb_stopped"]} for r in rows
                 if r["time_limit_s"] == tl and r["wall_s"] < 0.9 * tl]
        summary[f"{tl:g}"] = {"median_gap": float(np.median(g)), "worst_gap": float(np.max(g)), "seeds": len(g),
                              "ended_before_90pct_of_limit": early}
        print(f"limit {tl:g} s: median gap {100 * np.median(g):.2f} %, worst {100 * np.max(g):.2f} % over {len(g)} seeds")
    print("| seed | " + " | ".join(f"gap at {tl:g} s" for tl in limits) + " |")
    for sd in seeds:
        print(f"| {sd} | " + " | ".join(f"{100 * r['gap']:.2f} %" for tl in limits for r in rows
                                       if r["seed"] == sd and r["time_limit_s"] == tl) + " |")
    p = write_result(args.result_name, {
        "instance": "synthetic_instance(1000, 200, rng=seed), k=16, rho=0.8717, worst-adop", "seeds": seeds,
        "cpus": os.cpu_count(), "runs": rows, "per_limit": summary, "max_rss_bytes": max_rss_bytes(),
        "max_rss_children_bytes": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024})
    print("->", p)


if __name__ == "__main__":
    main()
