"""Fuzz the layoutkit frame decoder with >= 1e5 random mutations of a valid capture.

Each run damages a 60-frame capture (bit flips, inserted runs — 30 % starting with the frame
magic —, deleted runs, truncation; 1-5 mutations), decodes it in random chunks and checks:
no exception, every intact frame decoded, the first intact frame after each damage decoded
(resynchronisation within one sync period), nothing reported good that is not an original
frame (CRC-32). Writes benchmarks/results/live_fuzz.json.

    .venv/bin/python benchmarks/fuzz_live_decode.py [--mutations 100000] [--seed 0]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from layoutkit.layout import load_layout
from layoutkit.live.protocols.fuzzing import FuzzOutcome, check_layoutkit_decode, mutate
from layoutkit.live.protocols.layoutkit import MAGIC
from layoutkit.live.simulator import encode_frames, simulate_sweeps

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mutations", type=int, default=100_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(ROOT / "benchmarks/results/live_fuzz.json"))
    args = ap.parse_args(argv)
    layout = load_layout(ROOT / "tests/data/chen_layout.json")
    rng = np.random.default_rng(args.seed)
    outcome = FuzzOutcome()
    problems = []
    t0 = time.perf_counter()
    captures = 0
    while outcome.n_mutations < args.mutations:
        # a fresh capture every 200 runs (new poses, dropouts, counter values)
        if outcome.runs % 200 == 0:
            sw = simulate_sweeps(layout, duration=0.5, seed=int(rng.integers(2**31)), dropout=0.05)
            frames = encode_frames(sw)
            data = b"".join(frames)
            meas = sw.measured_angles()
            truth = {int(sw.seq[k]): (float(sw.t[k]), int(sw.station[k]), int(sw.axis[k]), meas[k])
                     for k in range(len(frames))}
            captures += 1
        m = mutate(data, rng, int(rng.integers(1, 6)), magic=MAGIC)
        p = check_layoutkit_decode(data, frames, truth, m, rng, outcome, layout.n)
        if p and len(problems) < 20:
            problems.append({"run": outcome.runs, "problems": p[:5]})
    wall = time.perf_counter() - t0
    res = {"what": "layoutkit decoder mutation fuzzing", "seed": args.seed, "captures": captures,
           "frames_per_capture": len(frames), "wall_s": round(wall, 1), **outcome.as_dict(),
           "all_properties_hold": not problems and outcome.exceptions == 0 and outcome.false_good == 0
           and outcome.intact_decoded == outcome.intact and outcome.resync_next_intact == outcome.damage_events,
           "problems": problems,
           "command": "python benchmarks/fuzz_live_decode.py --mutations %d --seed %d" % (args.mutations, args.seed)}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(res, indent=2) + "\n")
    print(json.dumps({k: v for k, v in res.items() if k != "problems"}, indent=2))


if __name__ == "__main__":
    main()
