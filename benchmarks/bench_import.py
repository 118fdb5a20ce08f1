"""Import + solve speed on the real libsurvive sample (frames/s), with the steps apart.

Anchor: the recording's own rate — the LH1 sample holds ~4 s of frames (two stations, two
devices); the import must run far faster than real time. Same-run stages, median of 5 rounds:
- parse: ``read_recording`` (gzip stream, all lines);
- frames: ``device_frames`` per device (sweep grouping, angle conversion);
- write: the frame table CSV (``io.frames``);
- solve: ``solve_frames`` of the HMD frames (PnP, residuals, per-sensor summary);
- end to end: ``layoutkit import libsurvive`` + ``layoutkit solve`` through the workflows.
Peak memory (tracemalloc) of one end-to-end run. Writes benchmarks/results/import.json.

    .venv/bin/python benchmarks/bench_import.py
"""
from __future__ import annotations

import json
import statistics
import tempfile
import time
import tracemalloc
from pathlib import Path

from layoutkit.importers.libsurvive import device_frames, layout_of, read_recording
from layoutkit.io.frames import write_frame_table
from layoutkit.workflows.frames import read_frames, solve_frames
from layoutkit.workflows.importers import import_libsurvive

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "tests" / "data" / "libsurvive"
ROUNDS = 5


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def one_round(rec_path: Path, tmp: Path) -> dict:
    t_parse, rec = _timed(lambda: read_recording(rec_path))
    frames = {}
    t_frames = 0.0
    for dev in rec.light:
        lay = layout_of(rec, dev)
        dt, (fr, _) = _timed(lambda: device_frames(rec.light[dev], lay.n, lambda g, ch: ch))
        t_frames += dt
        frames[dev] = (lay, fr)
    t_write = sum(_timed(lambda: write_frame_table(fr, tmp / f"{dev}.csv"))[0] for dev, (_, fr) in frames.items())
    dev = "HMD" if "HMD" in frames else next(iter(frames))
    lay, fr = frames[dev]
    t_solve, res = _timed(lambda: solve_frames(fr, lay))
    out = tmp / "e2e"

    def e2e():
        import shutil

        shutil.rmtree(out, ignore_errors=True)
        s = import_libsurvive(rec_path, out)
        n = 0
        for d, info in s["devices"].items():
            if "frames" in info:
                from layoutkit.layout import load_layout

                ly = load_layout(out / d / "layout.json")
                solve_frames(read_frames(out / d / "frames.csv", ly), ly)
                n += info["frames"]
        return n

    t_e2e, n_all = _timed(e2e)
    return {"parse_s": t_parse, "frames_s": t_frames, "write_s": t_write, "solve_s": t_solve, "e2e_s": t_e2e,
            "frames_all": n_all, "frames_solved_device": fr.n_frames, "lines": rec.lines,
            "solved_ok": res["solved"]}


def main() -> dict:
    results = {}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        for name in ("lh1_test_cal_first4s.rec.gz", "lh2_test_cal_first4s.rec.gz"):
            rounds = [one_round(SAMPLES / name, tmp) for _ in range(ROUNDS)]
            med = {k: statistics.median(r[k] for r in rounds) for k in rounds[0]}
            tracemalloc.start()
            one_round(SAMPLES / name, tmp)
            peak = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
            results[name] = {
                "median_of": ROUNDS, **{k: round(v, 5) for k, v in med.items()},
                "parse_lines_per_s": med["lines"] / med["parse_s"],
                "solve_frames_per_s": med["frames_solved_device"] / med["solve_s"],
                "import_plus_solve_frames_per_s": med["frames_all"] / med["e2e_s"],
                "recording_seconds": 4.0,
                "faster_than_real_time": 4.0 / med["e2e_s"],
                "peak_memory_mb": peak / 1e6,
            }
    out = {"benchmark": "bench_import", "anchor": "the recording's real time (4 s per sample)", "results": results}
    path = ROOT / "benchmarks" / "results" / "import.json"
    path.write_text(json.dumps(out, indent=2) + "\n")
    return out


if __name__ == "__main__":
    r = main()
    for name, v in r["results"].items():
        print(f"{name}: import+solve {v['import_plus_solve_frames_per_s']:.0f} frames/s "
              f"({v['faster_than_real_time']:.1f}x real time), solve {v['solve_frames_per_s']:.0f} frames/s, "
              f"parse {v['parse_lines_per_s']:.0f} lines/s, peak {v['peak_memory_mb']:.1f} MB")
