"""Live-mode benchmark (issue #5 "must show"): replay speed, decode + solve throughput, flat
memory, and simulator → pty → `layoutkit live` for 10 minutes of simulated time.

    .venv/bin/python benchmarks/bench_live.py [--quick] [--skip-pty] [--pty-seconds 600] [--speed 10]

Anchors (the issue's numbers, checked in the same run): replay >= 50x real time, decode + solve
>= 10,000 frames/s, pty run with no frame lost and RMS error vs TRUTH within 5 % of the DOP
prediction. Writes benchmarks/results/live.json (replay/throughput/memory) and
benchmarks/results/live_pty.json (pty run).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _util import interleaved, max_rss_bytes, write_result  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def make_capture(layout, seconds: float, path: Path, seed: int = 1):
    from layoutkit.live.capture import station_to_dict
    from layoutkit.live.simulator import run_fake_fpga, simulate_stream, write_truth

    chunks, sw = simulate_stream(layout, duration=seconds, seed=seed)
    run_fake_fpga(chunks, out=path, sidecar={"protocol": "layoutkit", "layout": layout.to_dict(),
                                             "stations": [station_to_dict(s) for s in sw.stations]})
    truth = path.with_suffix(".truth.csv")
    write_truth(sw, truth)
    return truth, int(sw.emitted.sum())


def decode_and_solve(layout, data: bytes, chunk_frames: int = 2048) -> int:
    """Decoder + pose pipeline only (no JSON/CSV sinks): returns frames solved."""
    from layoutkit.live.pipeline import LiveConfig, PosePipeline
    from layoutkit.live.protocols import get_protocol

    dec = get_protocol("layoutkit")(n_sensors=layout.n)
    pipe = PosePipeline(layout.positions, LiveConfig(n_sensors=layout.n, chunk_frames=chunk_frames,
                                                         chunk_seconds=float("inf")))
    step = 1 << 16
    for i in range(0, len(data), step):
        pipe.feed(dec.feed(data[i:i + step]))
    pipe.feed(dec.flush())
    pipe.flush(end_of_stream=True)
    return pipe.counters.frames


def bench_replay(layout, tmp: Path, seconds: float, rounds: int) -> dict:
    from layoutkit.workflows.live import replay_capture

    cap = tmp / "bench.lkcap"
    truth, sweeps = make_capture(layout, seconds, cap)
    data = cap.read_bytes()
    frames = {}

    def replay():
        frames["replay"] = replay_capture(cap, layout)["frames"]

    def dsolve():
        frames["decode_solve"] = decode_and_solve(layout, data)

    decode_and_solve(layout, data[:200000])  # warm imports
    times = interleaved({"replay": replay, "decode_solve": dsolve}, rounds)
    med = {k: statistics.median(v) for k, v in times.items()}
    # memory: peak Python/numpy allocation (tracemalloc) during one replay of the long capture,
    # sampled as the stream goes: flat memory = the peak after the first tenth of the stream is
    # already the peak of the whole run (and the live allocation does not grow)
    import tracemalloc

    marks = []

    def progress(s):
        cur, peak = tracemalloc.get_traced_memory()
        marks.append((s.decoder.stats.bytes_in / len(data), cur, peak))

    tracemalloc.start()
    try:
        replay_capture(cap, layout, on_progress=progress)
    finally:
        tracemalloc.stop()
    m = np.array(marks)
    tenth = m[: max(1, int(np.sum(m[:, 0] <= 0.1)))]
    peak_tenth, peak_all = float(tenth[-1, 2]), float(m[-1, 2])
    cur_tenth, cur_end = float(tenth[:, 1].max()), float(m[m[:, 0] >= 0.9][:, 1].max())
    with_truth = replay_capture(cap, layout, truth=truth)
    return {
        "stream_seconds": seconds, "sweeps": sweeps, "frames": frames["replay"], "capture_bytes": len(data),
        "rounds": rounds, "seconds": times, "median_s": med,
        "replay_x_realtime": seconds / med["replay"],
        "replay_frames_per_s": frames["replay"] / med["replay"],
        "decode_solve_frames_per_s": frames["decode_solve"] / med["decode_solve"],
        "anchor_replay_x_realtime": 50.0, "anchor_frames_per_s": 10000.0,
        "ratio_replay_vs_anchor": (seconds / med["replay"]) / 50.0,
        "ratio_decode_solve_vs_anchor": (frames["decode_solve"] / med["decode_solve"]) / 10000.0,
        "memory_tracemalloc_bytes": {
            "peak_first_tenth": peak_tenth, "peak_whole_run": peak_all, "peak_ratio": peak_all / peak_tenth,
            "live_max_first_tenth": cur_tenth, "live_max_last_tenth": cur_end,
            "note": "peak includes one chunk's PnP temporaries (2048 frames); live = allocated between chunks"},
        "max_rss_bytes": max_rss_bytes(),
        "accuracy_vs_truth": with_truth["truth"],
    }


def bench_pty(layout_path: Path, tmp: Path, seconds: float, speed: float, seed: int = 1) -> dict:
    """fake-fpga on a pty (accelerated ``speed`` x) and `layoutkit live` as two processes."""
    exe = [sys.executable, "-m", "layoutkit"]
    link = tmp / "port"
    truth = tmp / "TRUTH.csv"
    cap = tmp / "live.lkcap"
    rep = tmp / "report"
    fake = subprocess.Popen(exe + ["fake-fpga", "--layout", str(layout_path), "--truth", str(truth), "--duration",
                                   str(seconds), "--seed", str(seed), "--speed", str(speed), "--link", str(link),
                                   "--wait-reader", "60", "--json"], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    t0 = time.monotonic()
    while not (link.exists() and truth.exists()):
        if fake.poll() is not None or time.monotonic() - t0 > 120:
            raise RuntimeError("fake-fpga did not start")
        time.sleep(0.1)
    time.sleep(0.5)  # truth file fully written before the pty appears (it is written first)
    t_live = time.monotonic()
    live = subprocess.run(exe + ["live", "--port", str(link), "--layout", str(layout_path), "--record", str(cap),
                                 "--truth", str(truth), "--report", str(rep), "--idle-timeout", "3", "--no-dashboard",
                                 "--json"], capture_output=True, text=True, cwd=ROOT)
    wall = time.monotonic() - t_live
    out, _ = fake.communicate(timeout=60)
    if live.returncode:
        raise RuntimeError(live.stderr)
    s = json.loads(live.stdout)
    fk = json.loads(out[out.index("{"):])
    n_truth = sum(1 for ln in open(truth) if not ln.startswith("#")) - 1  # the last line is the run tie
    # regenerate the simulator's bytes (deterministic in the seed) and compare with the capture
    from layoutkit.layout import load_layout
    from layoutkit.live.simulator import simulate_stream

    chunks, _ = simulate_stream(load_layout(layout_path), duration=seconds, seed=seed)
    sent = hashlib.sha256(b"".join(c for _, c in chunks)).hexdigest()
    got = hashlib.sha256(cap.read_bytes()).hexdigest()
    e = s["truth"]
    return {
        "simulated_seconds": seconds, "speed": speed, "live_wall_s": wall,
        "command_fake": f"layoutkit fake-fpga --layout L.json --truth TRUTH.csv --duration {seconds:g} --seed {seed} "
                        f"--speed {speed:g} --link PORT --wait-reader 60",
        "command_live": "layoutkit live --port PORT --layout L.json --record live.lkcap --truth TRUTH.csv "
                        "--report report --idle-timeout 3 --no-dashboard --json",
        "truth_rows": n_truth, "frames_expected": n_truth // 2, "frames": s["frames"], "good": s["good"],
        "bad": s["bad"], "unpaired_sweeps": s["unpaired_sweeps"], "decode": s["decode"],
        "bytes_sent": fk.get("bytes"), "capture_bytes": cap.stat().st_size,
        "capture_identical_to_sent": sent == got,
        "no_frame_lost": bool(s["frames"] == n_truth // 2 and s["decode"]["dropped"] == 0 and s["decode"]["bad"] == 0
                              and s["unpaired_sweeps"] == 0 and sent == got),
        "rms_rot_deg": e["rms_rot_deg"], "predicted_rot_deg": e["predicted_rot_deg"], "ratio_rot": e["ratio_rot"],
        "rms_trans_m": e["rms_trans_m"], "predicted_trans_m": e["predicted_trans_m"], "ratio_trans": e["ratio_trans"],
        "within_5_percent": bool(abs(e["ratio_rot"] - 1) <= 0.05 and abs(e["ratio_trans"] - 1) <= 0.05),
        "max_rot_deg": e["max_rot_deg"], "max_trans_m": e["max_trans_m"],
        "static_groups": len(s.get("static_groups") or []),
        "source": s.get("source"),
    }


def static_steps_csv(layout, path: Path, groups: int, hold: float, move: float, rng) -> None:
    """A trajectory CSV (TRUTH format) holding ``groups`` static poses for ``hold`` s each, with
    ``move`` s transitions: positions 1.5-3 m in front of the station, attitudes with >= 5 of the
    layout's sensors lit (like Chen's 50 static groups)."""
    from layoutkit.geometry import matrix_to_rotvec
    from layoutkit.simulate import poses_in_front
    from layoutkit.visibility import facing_mask

    rows, t = [], 0.0
    while len(rows) < 2 * groups:
        R, tr = poses_in_front(200, rng, z_range=(1.5, 3.0))
        ok = facing_mask(layout.positions, layout.normals, R, tr).sum(1) >= 5
        for Ri, ti in zip(R[ok], tr[ok]):
            if len(rows) >= 2 * groups:
                break
            rv = matrix_to_rotvec(Ri)
            rows += [[t, *rv, *ti], [t + hold, *rv, *ti]]
            t += hold + move
    np.savetxt(path, np.array(rows), delimiter=",", header="t,rx,ry,rz,tx,ty,tz", comments="")


def figures(directory: Path, tmp: Path) -> dict:
    """Report figures for docs: static groups (Fig. 5 style) and the default tumble (Fig. 7 style)."""
    exe = [sys.executable, "-m", "layoutkit"]
    from layoutkit.layout import save_layout
    from layoutkit.shapes import chen_target

    layout = chen_target()[1]
    lay = tmp / "chen.json"
    save_layout(layout, lay)
    steps = tmp / "steps.csv"
    static_steps_csv(layout, steps, 20, 20.0, 3.0, np.random.default_rng(7))
    out = {}
    for name, motion, secs in (("static", str(steps), 20 * 23.0), ("tumble", "tumble", 300.0)):
        cap, truth = tmp / f"{name}.lkcap", tmp / f"{name}.csv"
        subprocess.run(exe + ["fake-fpga", "--layout", str(lay), "--out", str(cap), "--truth", str(truth),
                              "--duration", str(secs), "--seed", "11", "--motion", motion], check=True, cwd=ROOT,
                       capture_output=True)
        rep = directory / name
        r = subprocess.run(exe + ["replay", str(cap), "--layout", str(lay), "--truth", str(truth), "--report",
                                  str(rep), "--json"], check=True, cwd=ROOT, capture_output=True, text=True)
        s = json.loads(r.stdout)
        (rep / "poses.csv").unlink(missing_ok=True)  # large; regenerate with the commands in docs/live.md
        g = s.get("static_groups") or []
        out[name] = {"frames": s["frames"], "truth": s["truth"], "static_groups": len(g),
                     "group_ratio_rot": [x["sigma_rot_deg"] / x["predicted_rot_deg"] for x in g],
                     "group_ratio_trans": [x["sigma_trans_m"] / x["predicted_trans_m"] for x in g]}
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="60 s stream, 3 rounds, 60 s pty run")
    ap.add_argument("--skip-pty", action="store_true")
    ap.add_argument("--only-pty", action="store_true")
    ap.add_argument("--pty-seconds", type=float, default=None, help="simulated seconds over the pty [600]")
    ap.add_argument("--speed", type=float, default=10.0, help="pty stream speed-up over real time [10]")
    ap.add_argument("--figures", type=Path, default=None, help="also write report figures into this directory")
    args = ap.parse_args()
    from layoutkit.layout import save_layout
    from layoutkit.shapes import chen_target

    layout = chen_target()[1]
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        lay = tmp / "chen.json"
        save_layout(layout, lay)
        if args.figures is not None:
            f = figures(args.figures, tmp)
            write_result("live_figures", {"directory": str(args.figures), **f})
            print("figures:", {k: (v["static_groups"], v["truth"]["ratio_rot"]) for k, v in f.items()})
            return
        if not args.only_pty:
            seconds = 60.0 if args.quick else 600.0
            r = bench_replay(layout, tmp, seconds, 3 if args.quick else 5)
            p = write_result("live_quick" if args.quick else "live", {
                "command": "python benchmarks/bench_live.py" + (" --quick" if args.quick else ""),
                "layout": "chen2024 reconstruction (12 sensors)", **r})
            print(f"replay {r['replay_x_realtime']:.0f}x real time ({r['replay_frames_per_s']:.0f} frames/s), "
                  f"decode+solve {r['decode_solve_frames_per_s']:.0f} frames/s, peak memory whole run / first tenth "
                  f"{r['memory_tracemalloc_bytes']['peak_ratio']:.2f} -> {p}")
        if not args.skip_pty:
            secs = args.pty_seconds or (60.0 if args.quick else 600.0)
            (tmp / "pty").mkdir()
            r = bench_pty(lay, tmp / "pty", secs, args.speed)
            p = write_result("live_pty_quick" if args.quick else "live_pty", r)
            print(f"pty {secs:.0f} s simulated at {args.speed:g}x: frames {r['frames']}/{r['frames_expected']}, "
                  f"no frame lost {r['no_frame_lost']}, ratio rot {r['ratio_rot']:.3f} trans {r['ratio_trans']:.3f} "
                  f"-> {p}")


if __name__ == "__main__":
    main()
