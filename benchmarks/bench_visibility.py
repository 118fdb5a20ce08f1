"""Visibility (FOV + acceptance cone + mesh occlusion) throughput and correctness (issue 3, item 5).

Mesh: the docking target (12,324 faces: dish, wings, boom in the way); sensors: candidate sites at
10 cm spacing; poses: models/docking_envelope.toml (uniform attitudes, 4–10 m).

1. Correctness: every pose–sensor pair that passes the cheap tests in the first poses (≥ 10,000
   pairs, so occlusion decides) is compared with a brute-force float64 segment–triangle test over
   all triangles (``segment_occlusion_reference``, no ray engine). Pairs whose segment passes within
   10 µm of a triangle edge or end (the documented grazing band) are counted and excluded.
   Adversarial set: segments aimed exactly through mesh vertices, same comparison.
2. Speed: pose–sensor evaluations per second of ``visible_sensors`` with embree over all pairs,
   and — on the first 20 poses in the same interleaved rounds — embree vs trimesh's default
   (pure-numpy "triangle") engine. Median of 5 rounds. Peak Python memory (tracemalloc) and max RSS.

    .venv/bin/python benchmarks/bench_visibility.py [--quick]
"""
import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _util import interleaved, max_rss_bytes, peak_python_memory, write_result  # noqa: E402

from layoutkit.candidates import sample_candidates  # noqa: E402
from layoutkit.envelope import load_envelope  # noqa: E402
from layoutkit.shapes import docking_target  # noqa: E402
from layoutkit.visibility import segment_occlusion_reference, visible_sensors  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
TOL = 1e-5


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    mesh = docking_target()
    lay = sample_candidates(mesh, spacing=0.10, rng=np.random.default_rng(0))
    P_, N_ = lay.positions, lay.normals
    R, t = load_envelope(ROOT / "models" / "docking_envelope.toml").poses()
    if args.quick:
        R, t = R[:200], t[:200]
    n_pairs = len(R) * len(P_)
    print(f"mesh {len(mesh.faces)} faces, {len(P_)} sensors, {len(R)} poses -> {n_pairs} pairs", flush=True)

    # ---- 1. correctness against the brute force --------------------------------------------
    want = 3000 if args.quick else 12000
    cheap = visible_sensors(mesh, P_, N_, R, t, occlusion=False)
    k = int(np.searchsorted(np.cumsum(cheap.sum(1)), want)) + 1
    Rk, tk = R[:k], t[:k]
    vis = visible_sensors(mesh, P_, N_, Rk, tk)
    ip, isn = np.nonzero(cheap[:k])
    off = 1e-5 * float(mesh.scale)  # the default surface_offset of visible_sensors
    origins = P_[isn] + off * N_[isn]
    station_body = -np.einsum("pji,pj->pi", Rk, tk)[ip]
    t0 = time.perf_counter()
    occ_ref, amb = segment_occlusion_reference(mesh.triangles, origins, station_body, tol=TOL)
    t_ref = time.perf_counter() - t0
    occ_emb = ~vis[ip, isn]
    mism = (occ_emb != occ_ref) & ~amb
    print(f"correctness: {len(ip)} pairs, {int(occ_ref.sum())} occluded, {int(amb.sum())} grazing, "
          f"{int(mism.sum())} mismatches (reference {t_ref:.1f} s)", flush=True)

    # ---- 1b. adversarial: segments aimed exactly through mesh vertices (edge/vertex grazing) -----
    rng = np.random.default_rng(1)
    n_adv = 500 if args.quick else 2000
    si = rng.integers(0, len(P_), n_adv)
    vi = rng.integers(0, len(mesh.vertices), n_adv)
    o_adv = P_[si] + off * N_[si]
    through = mesh.vertices[vi] - o_adv
    s_adv = o_adv + through * rng.uniform(1.5, 4.0, n_adv)[:, None]  # station beyond the vertex
    L_adv = np.linalg.norm(s_adv - o_adv, axis=1)
    d_adv = (s_adv - o_adv) / L_adv[:, None]
    from layoutkit.visibility import first_hit_distance, ray_engine
    occ_adv_emb = first_hit_distance(mesh, o_adv, d_adv, ray_engine(mesh)) < L_adv
    occ_adv_ref, amb_adv = segment_occlusion_reference(mesh.triangles, o_adv, s_adv, tol=TOL)
    mism_adv = (occ_adv_emb != occ_adv_ref) & ~amb_adv
    print(f"through-vertex segments: {n_adv}, {int(amb_adv.sum())} in the grazing band, "
          f"{int(occ_adv_ref.sum())} robustly occluded, {int(mism_adv.sum())} mismatches outside the band", flush=True)

    # ---- 2. speed -----------------------------------------------------------------------------
    # subset for the slow default engine: the first poses (same for both engines)
    n_sub_poses = 5 if args.quick else 20
    sl = slice(0, n_sub_poses)
    n_sub = int(cheap[sl].sum())
    n_sub_pairs = n_sub_poses * len(P_)
    sub = {}

    def embree_full():
        return visible_sensors(mesh, P_, N_, R, t)

    def cheap_only():
        return visible_sensors(mesh, P_, N_, R, t, occlusion=False)

    def embree_subset():
        sub["embree"] = visible_sensors(mesh, P_, N_, R[sl], t[sl])

    def triangle_subset():
        sub["triangle"] = visible_sensors(mesh, P_, N_, R[sl], t[sl], engine="triangle")

    embree_full()  # warm-up: builds the embree scene once
    times = interleaved({"embree_full": embree_full, "cheap_only": cheap_only, "embree_subset": embree_subset,
                         "triangle_subset": triangle_subset}, rounds=5)
    med = {key: statistics.median(v) for key, v in times.items()}
    rate = n_pairs / med["embree_full"]
    rays_full = int(cheap.sum())
    peak = peak_python_memory(embree_full)
    agree_sub = bool(np.array_equal(sub["embree"], sub["triangle"]))
    print(f"embree: {rate / 1e6:.2f} M pairs/s ({rays_full / med['embree_full'] / 1e6:.2f} M rays/s), "
          f"cheap tests only {n_pairs / med['cheap_only'] / 1e6:.2f} M pairs/s", flush=True)
    print(f"subset ({n_sub_pairs} pairs, {n_sub} rays): embree {med['embree_subset'] * 1e3:.1f} ms, "
          f"triangle {med['triangle_subset'] * 1e3:.0f} ms -> ratio {med['triangle_subset'] / med['embree_subset']:.0f}x, "
          f"same answer: {agree_sub}", flush=True)
    print(f"peak python memory {peak / 2**20:.1f} MiB, max RSS {max_rss_bytes() / 2**20:.0f} MiB")

    write_result("visibility", {
        "command": "benchmarks/bench_visibility.py" + (" --quick" if args.quick else ""),
        "mesh_faces": int(len(mesh.faces)), "sensors": int(len(P_)), "poses": int(len(R)), "pairs": int(n_pairs),
        "correctness": {
            "pairs_compared": int(len(ip)), "poses_used": k, "occluded_reference": int(occ_ref.sum()),
            "occluded_embree": int(occ_emb.sum()), "grazing_excluded": int(amb.sum()), "tolerance_m": TOL,
            "mismatches_outside_tolerance": int(mism.sum()), "reference_seconds": t_ref,
        },
        "through_vertex_segments": {
            "segments": n_adv, "grazing_excluded": int(amb_adv.sum()), "occluded_reference": int(occ_adv_ref.sum()),
            "mismatches_outside_tolerance": int(mism_adv.sum()),
            "note": "segments from a sensor through a random mesh vertex to a point beyond it (no cheap tests)",
        },
        "speed": {
            "median_seconds": med, "rounds": times,
            "embree_pairs_per_second": rate,
            "embree_rays_per_second": rays_full / med["embree_full"],
            "rays_sent_fraction": rays_full / n_pairs,
            "cheap_tests_pairs_per_second": n_pairs / med["cheap_only"],
            "subset_pairs": int(n_sub_pairs), "subset_rays": n_sub,
            "triangle_subset_pairs_per_second": n_sub_pairs / med["triangle_subset"],
            "triangle_subset_rays_per_second": n_sub / med["triangle_subset"],
            "embree_subset_pairs_per_second": n_sub_pairs / med["embree_subset"],
            "triangle_over_embree_time_ratio_subset": med["triangle_subset"] / med["embree_subset"],
            "subset_same_answer": agree_sub,
        },
        "memory": {"peak_python_bytes_embree_full": peak, "max_rss_bytes": max_rss_bytes()},
    })


if __name__ == "__main__":
    main()
