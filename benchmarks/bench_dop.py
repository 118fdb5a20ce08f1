"""DOP evaluations per second for 12-sensor layouts (issue 2, item 8).

Anchor in the same run: a Python loop applying eq. (18) literally per pose (explicit 2n×2n
R_theta of eq. 19, numpy matmuls). Interleaved rounds, median of ≥ 5; peak memory beside time.

    .venv/bin/python benchmarks/bench_dop.py [--quick]
"""
import argparse
import statistics
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _util import interleaved, max_rss_bytes, peak_python_memory, write_result  # noqa: E402

from layoutkit.dop import angle_jacobian, pose_dop  # noqa: E402
from layoutkit.geometry import random_rotations  # noqa: E402
from layoutkit.noise import angle_correlation  # noqa: E402
from layoutkit.shapes import chen_target  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    P = chen_target()[1].positions
    n_batch = 20000 if args.quick else 100000
    n_loop = 500 if args.quick else 2000
    R = random_rotations(n_batch, rng)
    t = np.column_stack([rng.uniform(-1, 1, n_batch), rng.uniform(-1, 1, n_batch), rng.uniform(1, 3, n_batch)])
    rho = 0.8717
    Rth = angle_correlation(12, rho)

    def batched():
        # chunked like any long run: bounded memory
        for s in range(0, n_batch, 20000):
            pose_dop(P, R[s:s + 20000], t[s:s + 20000], rho=rho)

    def loop():
        for i in range(n_loop):
            J = angle_jacobian(P @ R[i].T + t[i], P @ R[i].T).reshape(-1, 6)
            G = np.linalg.inv(J.T @ J)
            H = G @ J.T @ Rth @ J @ G
            np.sqrt(np.trace(H[:3, :3])), np.sqrt(np.trace(H[3:, 3:]))

    # same numbers first
    i = 7
    J = angle_jacobian(P @ R[i].T + t[i], P @ R[i].T).reshape(-1, 6)
    G = np.linalg.inv(J.T @ J)
    H = G @ J.T @ Rth @ J @ G
    ref = np.degrees(np.sqrt(np.trace(H[:3, :3])))
    got = float(pose_dop(P, R[i], t[i], rho=rho).adop)
    assert abs(got / ref - 1) < 1e-9, (got, ref)

    rounds = 5
    times = interleaved({"batched": batched, "loop_eq18": loop}, rounds)
    rate_b = n_batch / statistics.median(times["batched"])
    rate_l = n_loop / statistics.median(times["loop_eq18"])
    peak = peak_python_memory(batched)
    res = {
        "sensors": 12, "rho": rho, "rounds": rounds,
        "batched_evals_per_s": rate_b, "loop_eq18_evals_per_s": rate_l, "ratio": rate_b / rate_l,
        "batched_seconds": times["batched"], "loop_seconds": times["loop_eq18"],
        "peak_python_bytes_batched_100k": peak, "max_rss_bytes": max_rss_bytes(),
    }
    p = write_result("dop", res)
    print(f"DOP evaluations/s (12 sensors, rho={rho}): batched {rate_b:,.0f}/s, per-pose eq. (18) loop {rate_l:,.0f}/s, "
          f"ratio {rate_b / rate_l:.0f}x; peak {peak / 2**20:.1f} MiB -> {p}")


if __name__ == "__main__":
    main()
