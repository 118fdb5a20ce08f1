"""Benchmark: the camera cross-check on a simulated bench session (issue 16).

One session of ``--duration`` s (default 60) of the tumble, both streams: ``fake-fpga`` writes the
serial capture and renders the bench camera's view (30 fps, 640 x 480) with the truth. Then

1. ``replay --camera-device``: lighthouse vs truth, camera vs truth, lighthouse vs camera
   disagreement vs its predicted size (outside the face-on band), the estimated clock offset and
   the camera ← lighthouse / body ← face rotations against the truth;
2. (unless ``--no-live``) a live session over a real pty with the camera folder played at its
   timing, then ``replay`` of the live capture folder: live figures vs replayed figures, and the
   camera throughput (frames solved per second beside the 120 Hz serial stream on this machine).

Writes ``benchmarks/results/camera_live.json``. Run: ``.venv/bin/python benchmarks/bench_camera_live.py``.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
LAYOUT = ROOT / "models" / "chen_target.layout.json"
OUT = ROOT / "benchmarks" / "results" / "camera_live.json"


def lk(*args, timeout=3600):
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "layoutkit", *map(str, args)], capture_output=True, text=True,
                       timeout=timeout)
    if r.returncode != 0:
        raise SystemExit(f"layoutkit {' '.join(map(str, args))} failed:\n{r.stderr}")
    return r, time.perf_counter() - t


def camera_vs_truth(folder) -> dict:
    """RMS attitude error of the camera solve against the simulator truth (labelling resolved)."""
    from layoutkit.camera.rectangle import resolve_labelling
    from layoutkit.geometry import attitude_error, rotvec_to_matrix
    from layoutkit.io.camera import read_camera_meta
    from layoutkit.live.camera import CameraConfig, process_camera_folder

    meta = read_camera_meta(folder)
    T = meta.truth
    fr, _ = process_camera_folder(folder, CameraConfig(meta.focal_length_px, None, "ippe", meta.aspect_ratio))
    a = fr.arrays()
    ok = a["status"] == "ok"
    return {"a": a, "ok": ok, "T": T}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--tumble-rate-deg-s", type=float, default=5.0)
    ap.add_argument("--no-live", action="store_true")
    args = ap.parse_args(argv)
    from layoutkit.camera.rectangle import resolve_labelling
    from layoutkit.geometry import attitude_error, rotvec_to_matrix
    from layoutkit.live.simulator import load_trajectory

    res = {"duration_s": args.duration, "seed": args.seed, "tumble_rate_deg_s": args.tumble_rate_deg_s,
           "machine": f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}"}
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        common = ["--layout", LAYOUT, "--duration", args.duration, "--seed", args.seed,
                  "--tumble-rate-deg-s", args.tumble_rate_deg_s]
        r, wall = lk("fake-fpga", *common, "--out", d / "cap.lkcap", "--truth", d / "truth.csv",
                     "--camera-out", d / "cam")
        res["fake_fpga_wall_s"] = wall
        res["fake_fpga"] = r.stdout.strip().splitlines()[0]
        r, wall = lk("replay", d / "cap.lkcap", "--truth", d / "truth.csv", "--camera-device", d / "cam",
                     "--motion-compensation", "--report", d / "rep", "--json")
        s = json.loads(r.stdout)
        res["replay_wall_s"] = wall
        res["lighthouse_vs_truth"] = {k: s["truth"][k] for k in ("rms_rot_deg", "predicted_rot_deg", "ratio_rot")}
        cam = s["camera"]
        res["replay_camera"] = cam
        # camera alone against the truth
        info = camera_vs_truth(d / "cam")
        a, ok, T = info["a"], info["ok"], info["T"]
        tr = load_trajectory(d / "truth.csv")
        X = rotvec_to_matrix(T["camera_from_lighthouse_rotvec"])
        Y = rotvec_to_matrix(T["body_from_face_rotvec"])
        R, _ = tr((a["t"][ok] - T["clock_offset_s"]) / (1 + T["clock_drift"]))
        Rt = X @ R @ Y
        e = np.array([attitude_error(resolve_labelling(a["rotation"][ok][k], Rt[k], 2), Rt[k]) for k in range(len(Rt))])
        vf = cam.get("camera_variance_factor") or 1.0
        res["camera_vs_truth"] = {"frames": int(ok.sum()), "rms_deg": float(np.degrees(np.sqrt(np.mean(e ** 2)))),
                                  "predicted_rms_deg": float(np.degrees(np.sqrt(vf * np.mean(a["pred_var"][ok])))),
                                  "max_deg": float(np.degrees(e.max()))}
        if not args.no_live:
            sim_err = open(d / "sim.stderr", "w")
            sim = subprocess.Popen([sys.executable, "-m", "layoutkit", "fake-fpga", *map(str, common)],
                                   stdout=subprocess.PIPE, stderr=sim_err, text=True)
            port = sim.stdout.readline().split()[1]
            t0 = time.perf_counter()
            r = subprocess.run([sys.executable, "-m", "layoutkit", "live", "--port", port, "--layout", str(LAYOUT),
                                "--record", str(d / "live.lkcap"), "--duration", str(args.duration + 10),
                                "--idle-timeout", "2", "--no-dashboard", "--camera-device", str(d / "cam"),
                                "--motion-compensation", "--json"], capture_output=True, text=True)
            live_wall = time.perf_counter() - t0
            sim.wait(timeout=60)
            sim_err.close()
            if r.returncode != 0:
                raise SystemExit(f"live failed (exit {r.returncode}):\n{r.stderr}\nsimulator (exit {sim.returncode}):\n"
                                 f"{(d / 'sim.stderr').read_text()}")
            ls = json.loads(r.stdout)
            lc = ls["camera"]
            rr, _ = lk("replay", d / "live.lkcap", "--motion-compensation", "--json")
            rc = json.loads(rr.stdout)["camera"]
            keys = ("frames", "solved", "clock_offset_s", "disagreement_rms_deg", "predicted_disagreement_rms_deg",
                    "ratio")
            res["live"] = {"wall_s": live_wall, "serial_frames": ls["frames"], "serial_good": ls["good"],
                           "camera": {k: lc.get(k) for k in keys + ("received", "stalls", "backlog")},
                           "replay_of_live_capture": {k: rc.get(k) for k in keys},
                           "max_relative_difference": max(abs(rc[k] - lc[k]) / max(abs(lc[k]), 1e-300)
                                                          for k in keys if lc.get(k) is not None),
                           "camera_frames_solved_per_s": lc["frames"] / max(args.duration, 1e-9)}
    res["peak_rss_mb_this_process"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(res, indent=2, default=float) + "\n")
    c = res["replay_camera"]
    print(f"lighthouse vs truth {res['lighthouse_vs_truth']['rms_rot_deg']:.4f} deg (ratio "
          f"{res['lighthouse_vs_truth']['ratio_rot']:.3f}); camera vs truth {res['camera_vs_truth']['rms_deg']:.4f} deg "
          f"(pred {res['camera_vs_truth']['predicted_rms_deg']:.4f}); LH vs camera {c['disagreement_rms_deg']:.4f} deg "
          f"vs pred {c['predicted_disagreement_rms_deg']:.4f} (ratio {c['ratio']:.3f}); clock error "
          f"{c['truth']['clock_offset_error_s'] * 1e3:.2f} ms (sigma {c['clock']['offset_sigma_s'] * 1e3:.2f} ms)")
    if "live" in res:
        print(f"live: {res['live']['camera']}; replay of the live capture: max rel. difference "
              f"{res['live']['max_relative_difference']:.2e}")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
