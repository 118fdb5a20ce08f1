"""Certified gap against wall time on the issue's instance (issue 13, item 6).

    .venv/bin/python benchmarks/bench_certificate.py [--limits 60,120,300]

Instance: ``benchmarks/bench_optimize.py`` part B — ``synthetic_instance(1000, 200, rng=7)``,
k = 16, rho = 0.8717, worst ADOP, 4 lit at every pose. One ``pipeline`` run per time limit
(time limit includes the relaxation); value, certified bound, gap and wall time of each.
Writes benchmarks/results/certificate.json.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _util import max_rss_bytes, write_result  # noqa: E402

from layoutkit.optimize import optimize_layout  # noqa: E402
from layoutkit.optimize.instances import synthetic_instance  # noqa: E402
from layoutkit.units import RHO_PAPER  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--limits", default="60,120,300")
    args = ap.parse_args()
    import cvxpy  # noqa: F401 - import outside the timed runs

    inst = synthetic_instance(1000, 200, rng=7)
    rows = []
    for tl in [float(x) for x in args.limits.split(",")]:
        t0 = time.perf_counter()
        r = optimize_layout(**inst, k=16, rho=RHO_PAPER, time_limit=tl, rng=0)
        wall = time.perf_counter() - t0
        rows.append({"time_limit_s": tl, "wall_s": wall, "value": r.value, "bound": r.bound, "gap": r.gap,
                     "certified_by": r.certified_by, "status": r.status, "message": r.message})
        print(f"limit {tl:.0f} s: wall {wall:.1f} s, value {r.value:.2f}, bound {r.bound:.2f} ({r.certified_by}), "
              f"gap {100 * r.gap:.2f} %", flush=True)
    p = write_result("certificate", {"instance": "synthetic_instance(1000, 200, rng=7), k=16, rho=0.8717",
                                     "runs": rows, "max_rss_bytes": max_rss_bytes()})
    print("->", p)


if __name__ == "__main__":
    main()
