"""Test helpers: a simulated Crazyflie Lighthouse-deck LH2 session written as a real-format
cfusdlog (the encoder side of layoutkit.importers.cfusdlog, written from the public format
description: bitcraze/crazyflie-firmware tools/usdlog/cfusdlog.py)."""
from __future__ import annotations

import struct
import zlib

import numpy as np

from layoutkit.geometry import rotvec_to_matrix, transform_points
from layoutkit.lighthouse import lh2_sweep_angles
from layoutkit.live.protocols.bitcraze import LH2_CYCLE_PERIODS

UART_VARS = [("sensor", "B"), ("basestation", "B"), ("offset", "I"), ("timestampFPGA", "I"), ("timestamp2FPGA", "I")]
ANGLE_VARS = [("sensor", "B"), ("basestation", "B"), ("sweep", "B"), ("angle", "f"), ("correctedAngle", "f")]


def write_cfusdlog(path, events: dict, *, version: int = 2, types: dict | None = None, truncate: int = 0) -> None:
    """events: name → (times_s (N,), [tuple of values per event]) ; types: name → [(var, char)]."""
    types = types or {"lhUartFrame": UART_VARS, "lhAngle": ANGLE_VARS}
    ids = {name: k + 1 for k, name in enumerate(types)}
    out = bytearray([0xBC]) + struct.pack("<HH", version, len(types))
    for name, vars_ in types.items():
        out += struct.pack("<H", ids[name]) + name.encode() + b"\0" + struct.pack("<H", len(vars_))
        for v, c in vars_:
            out += f"{v}({c})".encode() + b"\0"
    stream = []
    for name, (times, rows) in events.items():
        st = struct.Struct("<" + "".join(c for _, c in types[name]))
        for t, row in zip(times, rows):
            head = struct.pack("<HI", ids[name], int(round(t * 1e3))) if version == 1 else \
                struct.pack("<HQ", ids[name], int(round(t * 1e6)))
            stream.append((t, head + st.pack(*row)))
    stream.sort(key=lambda x: x[0])
    for _, b in stream:
        out += b
    out += struct.pack("<I", zlib.crc32(bytes(out)) & 0xFFFFFFFF)
    data = bytes(out[:-truncate] if truncate else out)
    with open(path, "wb") as fh:
        fh.write(data)


def simulate_deck_session(positions, rotations_rv, translations, *, channel: int = 0, t0_ticks: int = 5_000_000,
                          log_offset_s: float = 2712.25, rng=None):
    """One LH2 channel sweeping a 4-sensor deck for R rotations.

    positions (4, 3) body; rotations_rv (R, 3), translations (R, 3) station frame (one pose per
    rotation). Pulses as the real deck sends them: one UART frame per sensor and plane, the sync
    offset on ONE pulse per block only (the FPGA's habit), timestamps in 24 MHz ticks (24-bit),
    offsets in 6 MHz ticks. Returns (events for write_cfusdlog, true plane angles (R, 4, 2), the
    rotation starts in deck seconds (unwrapped), log_offset_s).
    """
    rng = np.random.default_rng(0) if rng is None else rng
    R = len(translations)
    P = LH2_CYCLE_PERIODS[channel]
    Rm = rotvec_to_matrix(np.asarray(rotations_rv, float))
    alpha = lh2_sweep_angles(transform_points(Rm, np.asarray(translations, float), positions))  # (R, 4, 2)
    times, rows, atimes, arows = [], [], [], []
    starts = t0_ticks + P * np.arange(R, dtype=np.int64)
    for r in range(R):
        for plane, shift in ((0, -np.pi / 3), (1, np.pi / 3)):
            ts = [int(starts[r] + round((alpha[r, i, plane] + np.pi + shift) * P / (2 * np.pi))) for i in range(4)]
            order = np.argsort(ts)
            ref = int(order[rng.integers(0, 4)])   # the one pulse of the block that carries the offset
            for i in order:
                off24 = 4 * int(round((ts[i] - starts[r]) / 4)) if i == ref else 0
                t_log = ts[i] / 24e6 + log_offset_s + rng.uniform(0, 2e-4)  # logged a little later
                times.append(t_log)
                rows.append((int(i), channel, off24, ts[i] & 0xFFFFFF, (ts[i] + 5) & 0xFFFFFF))
                atimes.append(t_log)
                arows.append((int(i), channel, plane, float(alpha[r, i, plane]), float(alpha[r, i, plane])))
    events = {"lhUartFrame": (np.array(times), rows), "lhAngle": (np.array(atimes), arows)}
    return events, alpha, starts / 24e6, log_offset_s
