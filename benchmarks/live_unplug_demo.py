"""End-to-end unplug/replug through the CLIs: fake-fpga on a pty → `layoutkit live --record`.

The simulated board streams session A (seed 1) on a pty reached through a symlink, is unplugged
(the pty closes), stays away 1 s, and comes back on a new pty behind the same symlink with
session B (seed 2). `layoutkit live` reads the symlink with the reconnecting source and records.
Check: the recording equals the bytes of A followed by B (regenerated with `fake-fpga --out`),
and the decoder saw every frame. Writes benchmarks/results/live_unplug.json.

    .venv/bin/python benchmarks/live_unplug_demo.py [--duration 8]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXE = [sys.executable, "-m", "layoutkit"]


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=8.0)
    args = ap.parse_args(argv)
    layout = str(ROOT / "tests/data/chen_layout.json")
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        link = d / "fpga"
        ref = []
        for seed in (1, 2):  # the exact bytes of each session
            out = d / f"ref{seed}.lkcap"
            subprocess.run(EXE + ["fake-fpga", "--layout", layout, "--out", str(out), "--duration",
                                  str(args.duration), "--seed", str(seed)], check=True, capture_output=True)
            ref.append(out.read_bytes())
        device = subprocess.Popen(
            ["bash", "-c", " ; ".join(
                [" ".join(EXE + ["fake-fpga", "--layout", layout, "--link", str(link), "--duration",
                                 str(args.duration), "--seed", str(s), "--wait-reader", "60"]) + (" ; sleep 1" if s == 1 else "")
                 for s in (1, 2)])],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        for _ in range(200):
            if link.exists():
                break
            time.sleep(0.05)
        rec = d / "rec.lkcap"
        t0 = time.monotonic()
        live = subprocess.run(EXE + ["live", "--port", str(link), "--layout", layout, "--record", str(rec),
                                     "--no-dashboard", "--idle-timeout", "20"],
                              capture_output=True, text=True, timeout=10 * args.duration + 60)
        wall = time.monotonic() - t0
        try:
            dev_out, _ = device.communicate(timeout=90)
        except subprocess.TimeoutExpired:
            device.kill()
            dev_out, _ = device.communicate()
        got = rec.read_bytes()
        want = ref[0] + ref[1]
        side = json.loads(Path(str(rec) + ".json").read_text())
        res = {
            "what": "unplug/replug: fake-fpga pty sessions A, (1 s away), B → layoutkit live --record",
            "bytes_sent": len(want), "bytes_recorded": len(got), "recording_equals_sent": got == want,
            "wall_s": round(wall, 1), "live_exit_code": live.returncode,
            "live_summary_tail": live.stdout.strip().splitlines()[-6:] + live.stderr.strip().splitlines()[-3:],
            "device_output": dev_out.strip().splitlines(),
            "sidecar_keys": sorted(side),
            "command": "python benchmarks/live_unplug_demo.py --duration %g" % args.duration,
        }
    out = ROOT / "benchmarks/results/live_unplug.json"
    out.write_text(json.dumps(res, indent=2) + "\n")
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
