"""Search kernels of the optimiser (issue 13, item 7: the dense loop's local search on 10^4 poses).

Anchor in the same run: the batched-numpy path the search used before (``pose_values_numpy``:
trace scaling, ``np.linalg.cholesky`` condition test, ``np.linalg.inv``, einsums; for moves also the
gather ``A_base - G[:, out] + G[:, in]`` materialised). Measured: ``kernels.pose_values`` and
``kernels.move_values`` (fused per-pose 6 × 6 algebra, numba), on a visor-like problem: 24 selected of
371 candidates, 10,000 poses, 64 one-swap moves confirmed on every pose (what one step of the
worst-case local search does). Interleaved rounds, median of 5; peak memory beside time.

    .venv/bin/python benchmarks/bench_search_kernels.py [--quick]
"""
import argparse
import statistics
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _util import interleaved, max_rss_bytes, peak_python_memory, write_result  # noqa: E402

from layoutkit.optimize.kernels import move_values, pose_values  # noqa: E402
from layoutkit.optimize.problem import pose_values_numpy  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    P, N, C, k, L = (2000 if args.quick else 10000), 371, 2, 24, 64
    rho, w = 0.8717, np.array([1.0, 1, 1, 0, 0, 0])
    U = rng.normal(size=(P, N, C, 6)) * (rng.random((P, N, 1, 1)) < 0.3)
    G = np.einsum("pnci,pncj->pnij", U, U)
    sel = np.sort(rng.choice(N, k, replace=False))
    Ab, bb = G[:, sel].sum(axis=1), U[:, sel].sum(axis=1)
    outs = rng.choice(sel, L)[:, None]
    ins = rng.choice(np.setdiff1d(np.arange(N), sel), L)[:, None]
    allp = np.arange(P)

    def moves_numpy():
        A = Ab[None] - G[:, outs[:, 0]].transpose(1, 0, 2, 3) + G[:, ins[:, 0]].transpose(1, 0, 2, 3)
        b = bb[None] - U[:, outs[:, 0]].transpose(1, 0, 2, 3) + U[:, ins[:, 0]].transpose(1, 0, 2, 3)
        return pose_values_numpy(A, b, rho, w)

    def moves_kernel():
        return move_values(Ab, bb, G, U, allp, outs, ins, rho, w)

    def values_numpy():
        return pose_values_numpy(Ab, bb, rho, w)

    def values_kernel():
        return pose_values(Ab, bb, rho, w)

    # same numbers first (to 1e-6: random information matrices of 4-8 lit rows are ill-conditioned; LU vs
    # Cholesky differ by ~cond x eps), and numba compile / cache load outside the timing
    ref, got = moves_numpy(), moves_kernel()
    f = np.isfinite(ref)
    assert np.array_equal(f, np.isfinite(got)) and np.allclose(got[f], ref[f], rtol=1e-6)
    assert np.allclose(values_kernel(), values_numpy(), rtol=1e-6)
    rounds = 5
    times = interleaved({"moves_numpy": moves_numpy, "moves_kernel": moves_kernel,
                         "values_numpy": values_numpy, "values_kernel": values_kernel}, rounds)
    med = {n: statistics.median(v) for n, v in times.items()}
    res = {"poses": P, "candidates": N, "k": k, "moves": L, "rho": rho, "rounds": rounds,
           "seconds": times, "median_s": med,
           "moves_kernel_vs_numpy": med["moves_numpy"] / med["moves_kernel"],
           "values_kernel_vs_numpy": med["values_numpy"] / med["values_kernel"],
           "move_pose_evals_per_s_kernel": L * P / med["moves_kernel"],
           "move_pose_evals_per_s_numpy": L * P / med["moves_numpy"],
           "peak_python_bytes_moves_numpy": peak_python_memory(moves_numpy),
           "peak_python_bytes_moves_kernel": peak_python_memory(moves_kernel),
           "max_rss_bytes": max_rss_bytes()}
    p = write_result("search_kernels" + ("_quick" if args.quick else ""), res)
    print(f"{L} one-swap moves x {P} poses: kernel {med['moves_kernel'] * 1e3:.1f} ms, numpy {med['moves_numpy'] * 1e3:.1f} ms "
          f"({res['moves_kernel_vs_numpy']:.1f}x; peak {res['peak_python_bytes_moves_kernel'] / 2**20:.1f} vs "
          f"{res['peak_python_bytes_moves_numpy'] / 2**20:.0f} MiB); pose values of one layout: "
          f"{res['values_kernel_vs_numpy']:.1f}x -> {p}")


if __name__ == "__main__":
    main()
