"""Decode throughput of the live protocols (frames/s), against the pipeline target.

Anchor (issue #5): decode + solve >= 10,000 frames/s, so decoding alone must be far faster.
Compares in the same run, median of 5 interleaved rounds:
- ``layoutkit`` decoder (numpy-gathered per chunk) at chunk sizes 256 B, 4 KiB, 64 KiB,
  on a clean capture and one with 5 % garbage bursts;
- a naive per-frame reference decoder (struct.unpack + per-frame numpy), the obvious way;
- the Bitcraze LH2 deck decoder (pulses/s; the deck sends <= 1920 frames/s at 230400 baud).
Peak memory (tracemalloc) of one 64 KiB-chunk decode. Writes benchmarks/results/live_decode.json.

    .venv/bin/python benchmarks/bench_live_decode.py
"""
from __future__ import annotations

import json
import statistics
import struct
import time
import tracemalloc
import zlib
from pathlib import Path

import numpy as np

from layoutkit.layout import load_layout
from layoutkit.live.frames import SweepMeasurement
from layoutkit.live.protocols import bitcraze as bc
from layoutkit.live.protocols import get_protocol
from layoutkit.live.protocols.layoutkit import MAGIC
from layoutkit.live.simulator import simulate_stream

ROOT = Path(__file__).resolve().parents[1]
TARGET = 10_000.0


def naive_decode(data: bytes, n: int) -> int:
    """Reference: scan for the magic, unpack each frame with struct, convert per frame to the
    same SweepMeasurement output (no sequence bookkeeping)."""
    pos, count, size = 0, 0, 11 + 4 * n + 4
    scale = 2 * np.pi * 60 / 50e6
    while True:
        i = data.find(MAGIC, pos)
        if i < 0 or i + size > len(data):
            return count
        frame = data[i:i + size]
        if zlib.crc32(frame[:-4]) != struct.unpack_from("<I", frame, size - 4)[0]:
            pos = i + 1
            continue
        _, _, flags, seq, _, sync = struct.unpack_from("<2sBBHBI", frame)
        hits = np.array(struct.unpack_from(f"<{n}I", frame, 11), float)
        SweepMeasurement(sync / 50e6, flags & 15, (flags >> 4) & 1,
                         np.where(hits == 0xFFFFFFFF, np.nan, hits * scale), seq, "lh1")
        count += 1
        pos = i + size


def run_decoder(name, data, chunk, **kw):
    dec = get_protocol(name)(**kw)
    n = 0
    for i in range(0, len(data), chunk):
        n += len(dec.feed(data[i:i + chunk]))
    return n + len(dec.flush())


def main():
    layout = load_layout(ROOT / "tests/data/chen_layout.json")
    clean, sw = simulate_stream(layout, duration=60.0, seed=1)
    junk, _ = simulate_stream(layout, duration=60.0, seed=1, garbage=0.05)
    data_clean = b"".join(b for _, b in clean)
    data_junk = b"".join(b for _, b in junk)
    K = len(clean)
    rng = np.random.default_rng(0)
    alpha = rng.uniform(-0.6, 0.6, (3000, 1, 2)) + rng.uniform(-0.01, 0.01, (3000, 4, 2))
    deck, _, pulses = bc.lh2_deck_stream(alpha, channel=0)
    cases = {
        "layoutkit_chunk256": lambda: run_decoder("layoutkit", data_clean, 256, n_sensors=12),
        "layoutkit_chunk4k": lambda: run_decoder("layoutkit", data_clean, 4096, n_sensors=12),
        "layoutkit_chunk64k": lambda: run_decoder("layoutkit", data_clean, 65536, n_sensors=12),
        "layoutkit_garbage5pct_chunk4k": lambda: run_decoder("layoutkit", data_junk, 4096, n_sensors=12),
        "naive_reference": lambda: naive_decode(data_clean, 12),
        "bitcraze_lh2_chunk4k": lambda: run_decoder("bitcraze-lh2", deck, 4096, n_sensors=4),
    }
    units = {k: (len(pulses) if k.startswith("bitcraze") else K) for k in cases}
    times = {k: [] for k in cases}
    for _ in range(5):  # interleaved rounds
        for k, f in cases.items():
            t0 = time.perf_counter()
            got = f()
            times[k].append(time.perf_counter() - t0)
            if not k.startswith("bitcraze"):
                assert got == K, (k, got, K)
    med = {k: statistics.median(v) for k, v in times.items()}
    tracemalloc.start()
    run_decoder("layoutkit", data_clean, 65536, n_sensors=12)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    res = {
        "what": "live decode throughput",
        "frames": K, "sensors": 12, "bytes": len(data_clean), "bitcraze_pulses": len(pulses),
        "anchor_frames_per_s": TARGET,
        "median_s": {k: round(v, 5) for k, v in med.items()},
        "rate_per_s": {k: round(units[k] / v) for k, v in med.items()},
        "ratio_to_anchor": {k: round(units[k] / v / TARGET, 2) for k, v in med.items()},
        "speedup_vs_naive": {k: round(med["naive_reference"] / v, 2) for k, v in med.items()
                             if k.startswith("layoutkit")},
        "peak_memory_mb_layoutkit_chunk64k": round(peak / 1e6, 2),
        "rounds": 5,
        "command": "python benchmarks/bench_live_decode.py",
    }
    out = ROOT / "benchmarks/results/live_decode.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=2) + "\n")
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
