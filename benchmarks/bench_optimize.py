"""Layout optimiser benchmark (issue #4): exhaustive agreement and the N = 1000 instance.

    .venv/bin/python benchmarks/bench_optimize.py [--quick]

Part A — small instances (N = 20–22 candidates, k = 6–7, P = 20 poses, rho 0 and 0.8717): the
default pipeline against the exhaustive optimum (every k-subset, vectorised numpy).
Part B — N = 1000 candidates, P = 200 poses, k = 16, rho = 0.8717, 4 lit at every pose: random
feasible (best of 200), random + 1-swap, greedy, plain top-k, relax-round (relaxation + randomised
rounding + repair + 1-swap sweeps: the issue's reference), pipeline (time limit 110 s). Each
method's time includes its own relaxation. Value, gap to the certified bound, wall time.
Instances: `layoutkit.optimize.instances.synthetic_instance` — candidates on a 0.3 × 0.3 × 0.15 m
box (5 faces), poses 1–3 m in front of one station within ±40° of boresight, body +z towards the
station within a 60° cone with random roll; lit = facing the station within the 60° photodiode
half-angle and inside the 120° field of view (the box is convex, so that is the exact occlusion).
--quick: 3 small instances and N = 300, P = 60. Writes benchmarks/results/optimize[_quick].json.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _util import max_rss_bytes, write_result  # noqa: E402

from layoutkit.optimize import optimize_layout  # noqa: E402
from layoutkit.optimize.core import candidate_jacobians  # noqa: E402
from layoutkit.optimize.coverage import minimum_k  # noqa: E402
from layoutkit.optimize.instances import synthetic_instance  # noqa: E402
from layoutkit.optimize.objectives import parse_objective  # noqa: E402
from layoutkit.optimize.problem import build_problem  # noqa: E402
from layoutkit.optimize.relaxation import relax  # noqa: E402
from layoutkit.optimize.search import local_search  # noqa: E402

RHO = 0.8717


def part_a(n_inst):
    rows = []
    seed = 0
    made = 0
    while made < n_inst:
        seed += 1
        N = 20 if made % 2 == 0 else 22
        k = 6 if made % 3 != 2 else 7
        inst = synthetic_instance(N, 20, rng=1000 + seed, cone_deg=45, half_angle_deg=70)
        kmin = minimum_k(inst["visible"], 4)[0]
        if kmin is None or kmin > k:
            continue
        made += 1
        for rho in (0.0, RHO):
            t0 = time.perf_counter()
            ex = optimize_layout(**inst, k=k, rho=rho, method="exhaustive")
            t1 = time.perf_counter()
            pl = optimize_layout(**inst, k=k, rho=rho, rng=seed)
            t2 = time.perf_counter()
            rows.append({"seed": 1000 + seed, "N": N, "k": k, "rho": rho, "exhaustive": ex.value,
                         "pipeline": pl.value, "bound": pl.bound, "ratio": pl.value / ex.value,
                         "bound_ok": bool(pl.bound <= ex.value * (1 + 1e-9)),
                         "exhaustive_s": t1 - t0, "pipeline_s": t2 - t1, "subsets": ex.info.get("n_subsets")})
            print(f"  A seed {1000 + seed} N={N} k={k} rho={rho}: exhaustive {ex.value:.6g} ({t1 - t0:.1f} s)  "
                  f"pipeline {pl.value:.6g} (x{pl.value / ex.value:.5f}, {t2 - t1:.1f} s)  bound {pl.bound:.6g}",
                  flush=True)
    return rows


def part_b(N, P, k, time_limit):
    inst = synthetic_instance(N, P, rng=7)
    out = {"N": N, "P": P, "k": k, "rho": RHO, "min_k": minimum_k(inst["visible"], 4)[0],
           "lit_per_pose_min": int(inst["visible"].sum(1).min())}
    rows = {}

    def run(name, **kw):
        t0 = time.perf_counter()
        r = optimize_layout(**inst, k=k, rho=RHO, rng=0, **kw)
        rows[name] = {"value": r.value, "bound": r.bound, "certified_by": r.certified_by,
                      "time_s": time.perf_counter() - t0, "timings": r.timings, "selected": r.selected.tolist()}
        print(f"  B {name:<14} value {r.value:9.2f}  bound {r.bound:9.2f} ({r.certified_by})  "
              f"{time.perf_counter() - t0:6.1f} s", flush=True)
        return r

    rnd = run("random", method="random")
    # 1-swap local search from the best random feasible layout (the second anchor)
    jac = candidate_jacobians(inst["positions"], inst["rotations"], inst["translations"])
    prob = build_problem(jac, inst["visible"][:, None], RHO, k, 4, parse_objective("worst-adop"))
    t0 = time.perf_counter()
    _, v1, _ = local_search(prob, rnd.selected, two_swap=False)
    rows["random+1swap"] = {"value": v1, "time_s": rows["random"]["time_s"] + time.perf_counter() - t0}
    print(f"  B random+1swap   value {v1:9.2f}  {rows['random+1swap']['time_s']:6.1f} s", flush=True)
    run("greedy", method="greedy")
    run("topk", method="topk")
    run("relax-round", method="relax-round")
    run("pipeline", method="pipeline", time_limit=time_limit)
    bound = max(r.get("bound", 0) or 0 for r in rows.values() if r.get("certified_by") == "relaxation")
    # the design's bound (1 - rho) x (rho = 0 relaxation), for comparison with the GLS bound
    t0 = time.perf_counter()
    plain = relax(prob, use_rho=False)
    out["bound_design_1_minus_rho"] = plain.bound
    out["bound_design_time_s"] = time.perf_counter() - t0
    for r in rows.values():
        r["gap_to_bound"] = r["value"] / bound - 1
    out["bound"] = bound
    out["methods"] = rows
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args()
    t0 = time.perf_counter()
    print("Part A: pipeline vs exhaustive", flush=True)
    A = part_a(3 if a.quick else 10)
    print("Part B: large instance", flush=True)
    B = part_b(300, 60, 12, 40.0) if a.quick else part_b(1000, 200, 16, 110.0)
    ratios = np.array([r["ratio"] for r in A])
    res = {
        "quick": a.quick,
        "part_a": {"instances": len(A) // 2, "runs": len(A), "max_ratio": float(ratios.max()),
                   "within_0.5pct": int((ratios <= 1.005).sum()), "all_bounds_valid": all(r["bound_ok"] for r in A),
                   "rows": A},
        "part_b": B,
        "peak_rss_bytes": max_rss_bytes(),
        "wall_s": time.perf_counter() - t0,
    }
    p = write_result("optimize_quick" if a.quick else "optimize", res)
    print(f"Part A: {res['part_a']['within_0.5pct']}/{len(A)} runs within 0.5 % of exhaustive "
          f"(max ratio {ratios.max():.5f}); bounds valid: {res['part_a']['all_bounds_valid']}")
    print("Part B: bound %.2f (design (1-rho) bound %.2f)" % (B["bound"], B["bound_design_1_minus_rho"]))
    for name, r in B["methods"].items():
        print(f"  {name:<14} {r['value']:9.2f}  gap {100 * r['gap_to_bound']:6.2f} %  {r['time_s']:6.1f} s")
    print(f"-> {p}  ({res['wall_s']:.0f} s, peak RSS {res['peak_rss_bytes'] / 2**20:.0f} MiB)")


if __name__ == "__main__":
    main()
