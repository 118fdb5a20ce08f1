"""DOP evaluations per second for 12-sensor layouts (issue 2, item 8; issue 13, item 7).

Anchors in the same run: a Python loop applying eq. (18) literally per pose (explicit 2n×2n
R_theta of eq. 19, numpy matmuls), and a plain batched einsum (J from ``angle_jacobian``,
``A = einsum(J, J)``, ``np.linalg.inv``, ``H = A^-1 J^T R J A^-1`` by einsum) over the same 10^5
poses. Measured: ``pose_dop`` (batched), the fused kernel ``layoutkit.dop_batch.batch_dop`` and
the einsum anchor. Interleaved rounds, median of ≥ 5; peak memory beside time.

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
from layoutkit.dop_batch import batch_dop  # noqa: E402
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

    def fused():
        batch_dop(P, R, t, rho=rho)

    def einsum_plain():
        for s in range(0, n_batch, 20000):
            Rc, tc = R[s:s + 20000], t[s:s + 20000]
            lever = np.einsum("pij,nj->pni", Rc, P)
            J = angle_jacobian(lever + tc[:, None], lever).reshape(len(Rc), -1, 6)
            A = np.einsum("pki,pkj->pij", J, J, optimize=True)
            Ai = np.linalg.inv(A)
            JAi = np.einsum("pki,pij->pkj", J, Ai, optimize=True)
            H = np.einsum("pki,kl,plj->pij", JAi, Rth, JAi, optimize=True)
            np.sqrt(np.trace(H[:, :3, :3], axis1=1, axis2=2)), np.sqrt(np.trace(H[:, 3:, 3:], axis1=1, axis2=2))

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
    got_f = float(batch_dop(P, R[i:i + 1], t[i:i + 1], rho=rho).adop[0])
    assert abs(got_f / ref - 1) < 1e-9, (got_f, ref)
    batch_dop(P, R[:10], t[:10], rho=rho)  # numba compile / cache load outside the timing

    rounds = 5
    times = interleaved({"batched": batched, "fused": fused, "einsum": einsum_plain, "loop_eq18": loop}, rounds)
    rate_b = n_batch / statistics.median(times["batched"])
    rate_f = n_batch / statistics.median(times["fused"])
    rate_e = n_batch / statistics.median(times["einsum"])
    rate_l = n_loop / statistics.median(times["loop_eq18"])
    peak = peak_python_memory(batched)
    peak_f = peak_python_memory(fused)
    peak_e = peak_python_memory(einsum_plain)
    res = {
        "sensors": 12, "rho": rho, "rounds": rounds, "poses": n_batch,
        "batched_evals_per_s": rate_b, "loop_eq18_evals_per_s": rate_l, "ratio": rate_b / rate_l,
        "fused_evals_per_s": rate_f, "einsum_evals_per_s": rate_e,
        "fused_vs_einsum": rate_f / rate_e, "pose_dop_vs_einsum": rate_b / rate_e,
        "fused_seconds_per_100k": 1e5 / rate_f,
        "batched_seconds": times["batched"], "fused_seconds": times["fused"], "einsum_seconds": times["einsum"],
        "loop_seconds": times["loop_eq18"],
        "peak_python_bytes_batched_100k": peak, "peak_python_bytes_fused": peak_f,
        "peak_python_bytes_einsum": peak_e, "max_rss_bytes": max_rss_bytes(),
    }
    p = write_result("dop" + ("_quick" if args.quick else ""), res)
    print(f"DOP evaluations/s (12 sensors, rho={rho}, {n_batch} poses): fused {rate_f:,.0f}/s "
          f"({1e5 / rate_f * 1e3:.1f} ms per 1e5 poses), pose_dop {rate_b:,.0f}/s, plain einsum {rate_e:,.0f}/s "
          f"(fused/einsum {rate_f / rate_e:.1f}x, pose_dop/einsum {rate_b / rate_e:.2f}x), per-pose eq. (18) loop "
          f"{rate_l:,.0f}/s; peak fused {peak_f / 2**20:.1f} MiB, einsum {peak_e / 2**20:.1f} MiB -> {p}")


if __name__ == "__main__":
    main()
