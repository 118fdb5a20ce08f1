"""Rectangle-attitude solves per second and detector/render time per frame (issue 6, optional).

Anchors in the same run: a Python loop calling ``rectangle_attitude`` per item (the vectorised
batch must beat it), and OpenCV IPPE (``cv2.solvePnPGeneric``) per item. Interleaved rounds,
median of ≥ 5; peak Python memory beside time. Also the study's per-frame costs: a 128 × 128
8×-supersampled render window and the sub-pixel detector on it.

    .venv/bin/python benchmarks/bench_camera.py [--quick]
"""
import argparse
import statistics
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _util import interleaved, max_rss_bytes, peak_python_memory, write_result  # noqa: E402

from layoutkit.camera import rectangle_attitude, rectangle_corners, solve_rectangle  # noqa: E402
from layoutkit.camera.conventions import project_paper  # noqa: E402
from layoutkit.geometry import attitude_error, random_rotations  # noqa: E402


def _poses(n, rng):
    R, out = random_rotations(4 * n, rng), []
    for Rk in R:
        if Rk[0, 0] > 0.3:  # face x_t towards the camera
            out.append(Rk)
        if len(out) == n:
            break
    return np.array(out)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    f = 2133.3
    n_batch, n_loop = (20000, 1000) if args.quick else (100000, 3000)
    R = _poses(n_batch, rng)
    uv = project_paper(np.einsum("tij,nj->tni", R, rectangle_corners(3, 3, 3)) + [-30.0, 0, 0], f)
    uv += rng.normal(0, 0.1, uv.shape)

    # same numbers first: batch == loop, and both near the truth
    assert np.array_equal(rectangle_attitude(uv[:50], f), np.array([rectangle_attitude(q, f) for q in uv[:50]]))
    med_err = float(np.degrees(np.median(attitude_error(rectangle_attitude(uv, f), R))))

    funcs = {
        "zhai_batch": lambda: rectangle_attitude(uv, f),
        "homography_batch": lambda: solve_rectangle(uv, f, "homography"),
        "zhai_loop": lambda: [rectangle_attitude(q, f) for q in uv[:n_loop]],
        "ippe_loop": lambda: solve_rectangle(uv[:n_loop], f, "ippe", aspect_ratio=1.0),
    }
    times = interleaved(funcs, rounds=5)
    n_items = {"zhai_batch": n_batch, "homography_batch": n_batch, "zhai_loop": n_loop, "ippe_loop": n_loop}
    rate = {k: n_items[k] / statistics.median(v) for k, v in times.items()}
    mem = {k: peak_python_memory(funcs[k]) for k in ("zhai_batch", "homography_batch")}

    # per-frame costs of the study (render window + detector)
    from layoutkit.camera.conventions import pose_paper_to_cv
    from layoutkit.camera.corners import detect_quadrilateral
    from layoutkit.camera.synthetic import SyntheticCamera
    from layoutkit.shapes import zhai_target
    from layoutkit.studies.zhai2014 import camera_and_crop, case_truth, target_colors

    full, crop, _ = camera_and_crop()
    mesh = zhai_target()
    _, Rt = case_truth("case1", np.arange(0.0, 50.0, 5.0))
    imgs = []
    with SyntheticCamera(mesh, crop, face_colors=target_colors(mesh), supersample=8) as sc:
        render_t = interleaved({"render": lambda: imgs.append(sc.render(*pose_paper_to_cv(Rt[len(imgs) % 10],
                                                                                          np.array([-100.0, 0, 0]))))},
                               rounds=7)["render"]
    det_t = interleaved({"detect": lambda: detect_quadrilateral(imgs[0], threshold=80.0)}, rounds=7)["detect"]

    out = {
        "quick": args.quick,
        "solves_per_s": rate,
        "ratio_zhai_batch_over_loop": rate["zhai_batch"] / rate["zhai_loop"],
        "ratio_zhai_batch_over_ippe_loop": rate["zhai_batch"] / rate["ippe_loop"],
        "median_attitude_error_deg_at_0.1px_30m": med_err,
        "peak_python_memory_bytes": mem,
        "max_rss_bytes": max_rss_bytes(),
        "render_128px_8x_ms_median": 1e3 * statistics.median(render_t),
        "detect_128px_ms_median": 1e3 * statistics.median(det_t),
        "n_batch": n_batch, "n_loop": n_loop,
    }
    p = write_result("camera_quick" if args.quick else "camera", out)
    for k, v in out.items():
        print(f"{k}: {v}")
    print(f"wrote {p}")


if __name__ == "__main__":
    main()
