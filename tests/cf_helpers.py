"""Test helpers: Crazyflie microSD logs (cfusdlog) written in the real format, with the conventions
found on the public Lighthouse dataset's logs (bitcraze/positioning_dataset, firmware e9ff096; see
layoutkit.importers.cfusdlog and layoutkit.live.cf_events):

- ``lhUartFrame.basestation`` = :data:`NO_CHANNEL` (2, the firmware's number of base stations) when
  the FPGA found no channel; the first pulse of nearly every block has none (the FPGA needs a second
  sensor to decode the bit stream); such a pulse never carries an offset; one pulse per block
  carries the sync offset (sometimes two);
- the log clock runs :data:`LOG_RATE` (-1.094 %) against the deck's 24 MHz clock, and every frame is
  logged after it crossed the 230400-baud UART, queued behind the frames before it;
- ``lhAngle`` events are logged in bursts when a station's rotation completes, sensor by sensor
  (sensor, station, sweep), with every station the firmware still holds: in crossing-beam mode
  station 0's angles again, bit for bit, in station 1's burst; in Kalman mode no repeats.

The encoder side of layoutkit.importers.cfusdlog, written from the public format description
(bitcraze/crazyflie-firmware tools/usdlog/cfusdlog.py) and from what the real logs hold.
"""
from __future__ import annotations

import struct
import zlib

import numpy as np

from layoutkit.geometry import rotvec_to_matrix, transform_points
from layoutkit.io.systemconfig import LH2_CYCLE_PERIODS
from layoutkit.lighthouse import lh2_sweep_angles

UART_VARS = [("sensor", "B"), ("basestation", "B"), ("offset", "I"), ("timestampFPGA", "I"), ("timestamp2FPGA", "I")]
ANGLE_VARS = [("sensor", "B"), ("basestation", "B"), ("sweep", "B"), ("angle", "f"), ("correctedAngle", "f")]
MARKER_VARS = [("mode", "B")]
#: lhUartFrame.basestation for "no channel found" (firmware e9ff096: PULSE_PROCESSOR_N_BASE_STATIONS)
NO_CHANNEL = 2
#: log seconds per deck second (the public logs: 1 - 10926e-6 .. 1 - 10978e-6)
LOG_RATE = 1 - 10940e-6
#: one 12-byte frame on the deck's 230400-baud UART
UART_FRAME_S = 12 * 10 / 230400


def write_cfusdlog(path, events: dict, *, version: int = 2, types: dict | None = None, truncate: int = 0) -> None:
    """events: name → (times_s (N,), [tuple of values per event]) ; types: name → [(var, char)].
    Events are written in time order (stable: equal times keep their given order)."""
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
            stream.append((t, len(stream), head + st.pack(*row)))
    stream.sort(key=lambda x: (x[0], x[1]))
    for _, _, b in stream:
        out += b
    out += struct.pack("<I", zlib.crc32(bytes(out)) & 0xFFFFFFFF)
    data = bytes(out[:-truncate] if truncate else out)
    with open(path, "wb") as fh:
        fh.write(data)


def _fw_angle(off, plane: int, period: int) -> np.float32:
    """The firmware's float32 light-plane angle of an offset (pulse_processor_v2.c calculateAngles)."""
    pi = np.float32(np.pi)
    a = np.float32(np.float32(off * 2) * pi) / np.float32(period)
    return np.float32(a - pi + pi / np.float32(3)) if plane == 0 else np.float32(a - pi - pi / np.float32(3))


def simulate_lh2_log(alpha: dict, t0: dict, *, rng, mode: str = "crossing_beam", log_offset_s: float = 10.78,
                     p_missing: float = 0.0, p_two_offsets: float = 0.0, p_no_channel: float = 0.0,
                     p_garbage: float = 0.0, p_stray: float = 0.0, log_rate: float = LOG_RATE) -> dict:
    """The deck's pulses and the firmware's lhAngle bursts of LH2 channels, as a Crazyflie logs them.

    alpha : channel → (R, 4, 2) measured light-plane angles (rad, NaN = sensor not hit); t0 :
    channel → (R,) int deck ticks of each rotation's rotor zero (unwrapped; the 24-bit counter is
    what is logged). Plane k of sensor i is hit at ``t0 + round((alpha + pi -/+ pi/3) P / 2 pi)``.
    Per block (one plane crossing): the first pulse has no channel (:data:`NO_CHANNEL`) and no
    offset; one later pulse carries its offset, quantised to the deck's 6 MHz (``4 * round((ts -
    t0) / 4)``). With probabilities: ``p_missing`` one sensor of the block lost, ``p_two_offsets`` a
    second pulse carries its offset, ``p_no_channel`` no pulse of the block has a channel or an
    offset, ``p_garbage`` the offset is mis-decoded (wrong by 5000-100000 ticks, channel still given),
    ``p_stray`` a sensor (not the block's first) is hit a second time 113 ticks (1.5 mrad) early
    without channel or offset (lh2_crossingBeam_jitter/log04's sensor 1: a reflection).

    Log times: a pulse is logged when its frame has crossed the UART (queued behind earlier ones),
    ``t_log = log_offset_s + log_rate * (deck s) + U(0, 50 us)``. The firmware's lhAngle bursts
    (module docstring): a rotation is logged when both its blocks are clean (4 sensors, one offset,
    a channel, not garbage), no other channel's pulse is within 10000 ticks (the firmware's
    workspace) and their rotor zeros agree within 10 ticks; the burst is logged when the next pulse
    closes the workspace. ``mode`` "crossing_beam" (station 0's angles repeated in station 1's
    bursts, both cleared after it) or "kalman" (each station's angles logged once).

    Returns ``{"events", "types", "pulses" (list of (ch, r, plane, sensor, ts)), "fw_frames" (list of
    (ch, r, (4, 2) float32 angles) fresh firmware frames in log order), "repeats" (stale frames
    logged), "garbage" (blocks with a mis-decoded offset), "no_channel_blocks", "log_offset_s",
    "log_rate"}``.
    """
    blocks = []          # (first ts, ch, r, plane, pulses [(sensor, ts, offset, channel)], clean, t0_est)
    pulses_truth = []
    n_garbage = n_nochan = 0
    for ch, A in alpha.items():
        P = LH2_CYCLE_PERIODS[ch]
        for r in range(A.shape[0]):
            for k, shift in ((0, -np.pi / 3), (1, np.pi / 3)):
                hit = [(i, int(t0[ch][r] + round((A[r, i, k] + np.pi + shift) * P / (2 * np.pi))))
                       for i in range(A.shape[1]) if np.isfinite(A[r, i, k])]
                if hit and rng.random() < p_missing:
                    hit.pop(int(rng.integers(len(hit))))
                if not hit:
                    continue
                hit.sort(key=lambda x: x[1])
                for i, ts in hit:
                    pulses_truth.append((ch, r, k, i, ts))
                nochan = rng.random() < p_no_channel
                garbage = (not nochan) and rng.random() < p_garbage
                n_garbage += garbage
                n_nochan += nochan
                refs = set()
                if not nochan and len(hit) > 1:
                    refs.add(int(rng.integers(1, len(hit))))
                    if rng.random() < p_two_offsets and len(hit) > 2:
                        refs.add(int(rng.integers(1, len(hit))))
                ps = []
                for j, (i, ts) in enumerate(hit):
                    off = 4 * int(round((ts - t0[ch][r]) / 4)) if j in refs else 0
                    if off and garbage:
                        off += int(rng.choice([-1, 1]) * rng.integers(5000, 100000))
                    ps.append((i, ts, off, None if (nochan or j == 0) else ch))
                ref = min(refs) if refs else None
                t0e = hit[ref][1] - ps[ref][2] if ref is not None else None
                clean = len(hit) == 4 and len(refs) == 1 and not garbage
                if len(hit) > 2 and rng.random() < p_stray:
                    j = int(rng.integers(2, len(hit)))
                    if hit[j][1] - 113 > hit[0][1]:
                        ps.append((hit[j][0], hit[j][1] - 113, 0, None))
                        ps.sort(key=lambda q: q[1])
                        clean = False          # five pulses: the firmware drops the workspace
                blocks.append((hit[0][1], ch, r, k, ps, clean, t0e))
    blocks.sort(key=lambda b: b[0])
    stream = sorted(((ts, s, off, c, bi) for bi, b in enumerate(blocks) for s, ts, off, c in b[4]),
                    key=lambda x: x[0])
    # UART queue: a frame leaves the deck when the pulse is over and the UART is free
    t_log, free = [], -np.inf
    for ts, *_ in stream:
        d = max(ts / 24e6, free) + UART_FRAME_S
        free = d
        t_log.append(log_offset_s + log_rate * d + rng.uniform(0, 5e-5))
    t_log = np.array(t_log)
    uart_rows = [(s, NO_CHANNEL if c is None else c, off, ts & 0xFFFFFF, ts & 0xFFFFFFFF)
                 for ts, s, off, c, _ in stream]
    # the firmware's accepted rotations and when they are processed
    ts_all = np.array([x[0] for x in stream])
    ch_all = np.array([-1 if x[3] is None else x[3] for x in stream])
    blk_all = np.array([x[4] for x in stream])
    pend, accepted = {}, []
    for bi, b in enumerate(blocks):
        _, ch, r, k, ps, clean, t0e = b
        idx = np.flatnonzero(blk_all == bi)
        lo, hi = ts_all[idx].min(), ts_all[idx].max()
        near = (np.abs(ts_all - lo) <= 10000) | (np.abs(ts_all - hi) <= 10000) | ((ts_all > lo) & (ts_all < hi))
        isolated = not np.any(near & (blk_all != bi))
        ok = clean and isolated
        if k == 0:
            pend[ch] = (r, t0e, ps) if ok else None
            continue
        pr = pend.pop(ch, None)
        if ok and pr is not None and pr[0] == r and abs(pr[1] - t0e) <= 10:
            nxt = np.flatnonzero(ts_all > hi + 10000)
            if nxt.size == 0:
                continue
            P = LH2_CYCLE_PERIODS[ch]
            vals = np.zeros((4, 2), np.float32)
            for plane, (t0p, pl) in enumerate(((pr[1], pr[2]), (t0e, ps))):
                for s, ts, _, _ in pl:
                    vals[s, plane] = _fw_angle(ts - t0p, plane, P)
            accepted.append((int(nxt[0]), ch, r, vals))
    accepted.sort(key=lambda a: a[0])
    held, a_t, a_rows, fw_frames, repeats = {}, [], [], [], 0
    for k_close, ch, r, vals in accepted:
        now = ts_all[k_close]
        held = {c: h for c, h in held.items() if now - h[0] <= LH2_CYCLE_PERIODS[c]}  # the firmware's stale timeout
        held[ch] = (now, vals)
        fw_frames.append((ch, r, vals))
        repeats += len(held) - 1
        te = t_log[k_close] + 1e-5
        for s in range(4):
            for c in sorted(held):
                for w in range(2):
                    a_t.append(te)
                    a_rows.append((s, c, w, float(held[c][1][s, w]), float(held[c][1][s, w])))
                    te += 1e-5
        if mode == "kalman":
            del held[ch]                # used by the estimator at once
        elif ch == 1:
            held.clear()                # the crossing beam uses both stations when station 1 completes
    events = {"lhUartFrame": (t_log, uart_rows), "lhAngle": (np.array(a_t), a_rows)}
    return {"events": events, "types": {"lhUartFrame": UART_VARS, "lhAngle": ANGLE_VARS}, "pulses": pulses_truth,
            "fw_frames": fw_frames, "repeats": repeats, "garbage": n_garbage, "no_channel_blocks": n_nochan,
            "log_offset_s": log_offset_s, "log_rate": log_rate}


def simulate_deck_session(positions, rotations_rv, translations, *, channel: int = 0, t0_ticks: int = 5_000_000,
                          log_offset_s: float = 2712.25, rng=None):
    """One LH2 channel sweeping a 4-sensor deck for R rotations (the log clock at the deck's rate:
    ``t_log = log_offset_s + deck s + UART delay``; :func:`simulate_lh2_log` has the real -1.1 %).

    positions (4, 3) body; rotations_rv (R, 3), translations (R, 3) station frame (one pose per
    rotation). Pulses as the real deck sends them (:func:`simulate_lh2_log`: no channel on each
    block's first pulse, the sync offset on one pulse per block). Returns (events for
    write_cfusdlog, true plane angles (R, 4, 2), the rotation starts in deck seconds (unwrapped),
    log_offset_s).
    """
    rng = np.random.default_rng(0) if rng is None else rng
    R = len(translations)
    P = LH2_CYCLE_PERIODS[channel]
    Rm = rotvec_to_matrix(np.asarray(rotations_rv, float))
    alpha = lh2_sweep_angles(transform_points(Rm, np.asarray(translations, float), positions))  # (R, 4, 2)
    starts = t0_ticks + P * np.arange(R, dtype=np.int64)
    sim = simulate_lh2_log({channel: alpha}, {channel: starts}, rng=rng, mode="kalman", log_offset_s=log_offset_s,
                           log_rate=1.0)
    return sim["events"], alpha, starts / 24e6, log_offset_s
