"""layoutkit's own serial frame protocol for N-sensor timestamp boards (docs/protocol.md).

One frame per rotor sweep, little-endian::

    offset  size  field
    0       2     magic  0xD7 0x4B
    2       1     version (1)
    3       1     flags: bits 0-3 station (0-15), bit 4 axis (0 = X / plane 0, 1 = Y / plane 1),
                  bit 5 kind (0 = LH1, 1 = LH2), bits 6-7 reserved, must be 0
    4       2     seq, u16, +1 per frame sent (all stations), wraps; 0 after power-up
    6       1     n, sensor count (1-255)
    7       4     sync, u32, device counter at the sweep's sync (zero) in clock ticks, wraps
    11      4 n   hit[i], u32, ticks from sync to sensor i's hit; 0xFFFFFFFF = not hit
    11+4n   4     CRC-32 (zlib.crc32, IEEE 802.3) of bytes 0 .. 10+4n

Timing → angle (Chen eq. 1): LH1 ``theta = omega * hit / clock``; LH2
``alpha = omega * hit / clock - pi`` (the rotor's zero is where the plane points straight
back), ``omega = 2 pi rpm / 60``.
Time base: ``t`` = the device counter unwrapped into seconds (``sync / clock`` plus whole wraps
seen since the first frame); a device reset (seq restarts at 0) continues ``t`` monotonically.
"""
from __future__ import annotations

import struct
import zlib

import numpy as np

from ..frames import DecodeStats, SweepMeasurement

__all__ = [
    "MAGIC",
    "VERSION",
    "NO_HIT",
    "HEADER_SIZE",
    "frame_size",
    "encode_sweep",
    "encode_sweeps",
    "encode_measurement",
    "angles_to_hit_ticks",
    "LayoutkitDecoder",
]

MAGIC = b"\xd7\x4b"
VERSION = 1
NO_HIT = 0xFFFFFFFF
_HEADER = struct.Struct("<2sBBHBI")
HEADER_SIZE = _HEADER.size  # 11
CRC_SIZE = 4
MAX_SENSORS = 255
_KINDS = ("lh1", "lh2")
_WRAP = 1 << 32


def frame_size(n: int) -> int:
    """Bytes in one frame for ``n`` sensors: ``11 + 4 n + 4``."""
    return HEADER_SIZE + 4 * n + CRC_SIZE


def _flags(station: int, axis: int, kind: str) -> int:
    if not 0 <= int(station) <= 15:
        raise ValueError(f"station: expected 0-15, got {station}")
    if int(axis) not in (0, 1):
        raise ValueError(f"axis: expected 0 or 1, got {axis}")
    if kind not in _KINDS:
        raise ValueError(f"kind: expected 'lh1' or 'lh2', got {kind!r}")
    return int(station) | (int(axis) << 4) | (_KINDS.index(kind) << 5)


def encode_sweep(station: int, axis: int, seq: int, sync: int, hits, kind: str = "lh1") -> bytes:
    """Reference encoder: one frame from integer fields.

    station 0-15, axis 0/1, seq (taken mod 2^16), sync counter (ticks, taken mod 2^32),
    hits : (n,) int ticks after sync, ``NO_HIT`` (0xFFFFFFFF) or negative for "not hit".
    """
    h = np.asarray(hits).astype(np.int64).ravel()
    if not 1 <= h.size <= MAX_SENSORS:
        raise ValueError(f"hits: expected 1-{MAX_SENSORS} sensors, got {h.size}")
    h = np.where((h < 0) | (h >= NO_HIT), NO_HIT, h).astype("<u4")
    head = _HEADER.pack(MAGIC, VERSION, _flags(station, axis, kind), int(seq) & 0xFFFF, h.size, int(sync) % _WRAP)
    body = head + h.tobytes()
    return body + struct.pack("<I", zlib.crc32(body))


def encode_sweeps(station, axis, seq, sync, hits, kind: str = "lh1") -> list[bytes]:
    """Vectorised :func:`encode_sweep` for K frames: station/axis/seq/sync (K,), hits (K, n) → K frames."""
    hits = np.asarray(hits).astype(np.int64)
    if hits.ndim != 2 or not 1 <= hits.shape[1] <= MAX_SENSORS:
        raise ValueError(f"hits: expected shape (K, n) with 1 <= n <= {MAX_SENSORS}, got {hits.shape}")
    K, n = hits.shape
    station = np.broadcast_to(np.asarray(station, np.int64), (K,))
    axis = np.broadcast_to(np.asarray(axis, np.int64), (K,))
    if np.any((station < 0) | (station > 15)) or np.any((axis != 0) & (axis != 1)):
        raise ValueError("station: expected 0-15 and axis 0 or 1")
    if kind not in _KINDS:
        raise ValueError(f"kind: expected 'lh1' or 'lh2', got {kind!r}")
    dt = np.dtype([("magic", "S2"), ("version", "u1"), ("flags", "u1"), ("seq", "<u2"), ("n", "u1"),
                   ("sync", "<u4"), ("hits", "<u4", (n,))])
    rec = np.zeros(K, dt)
    rec["magic"] = MAGIC
    rec["version"] = VERSION
    rec["flags"] = station | (axis << 4) | (_KINDS.index(kind) << 5)
    rec["seq"] = np.broadcast_to(np.asarray(seq, np.int64), (K,)) & 0xFFFF
    rec["n"] = n
    rec["sync"] = np.broadcast_to(np.asarray(sync, np.int64), (K,)) % _WRAP
    rec["hits"] = np.where((hits < 0) | (hits >= NO_HIT), NO_HIT, hits)
    raw = rec.tobytes()
    size = dt.itemsize
    return [raw[k * size:(k + 1) * size] + struct.pack("<I", zlib.crc32(raw[k * size:(k + 1) * size]))
            for k in range(K)]


def _omega(rpm: float) -> float:
    return 2.0 * np.pi * rpm / 60.0


def angles_to_hit_ticks(angles, kind: str = "lh1", rotor_rpm: float | None = None,
                        clock_hz: float = 50e6) -> np.ndarray:
    """Sweep angles (rad, NaN = not hit) → integer hit ticks (rounded: the counter's quantisation).

    Inverse of the decoder's conversion. Returns int64 with ``NO_HIT`` for NaN.
    """
    a = np.asarray(angles, dtype=float)
    rpm = rotor_rpm if rotor_rpm is not None else (3600.0 if kind == "lh1" else 3000.0)
    if kind == "lh2":
        a = a + np.pi
    ticks = np.round(np.where(np.isfinite(a), a, 0.0) / _omega(rpm) * clock_hz)
    out = np.where(np.isfinite(a) & (ticks >= 0) & (ticks < NO_HIT), ticks, NO_HIT)
    return out.astype(np.int64)


def encode_measurement(m: SweepMeasurement, *, rotor_rpm: float | None = None, clock_hz: float = 50e6) -> bytes:
    """Encode a :class:`SweepMeasurement` (angles rounded to counter ticks; ``m.t`` → sync counter)."""
    hits = angles_to_hit_ticks(m.angles, m.kind, rotor_rpm, clock_hz)
    return encode_sweep(m.station, m.axis, m.seq or 0, int(round(m.t * clock_hz)), hits, m.kind)


class LayoutkitDecoder:
    """Incremental decoder of the layoutkit frame protocol; never raises on any input bytes.

    n_sensors : int or None — expected sensor count; frames with another count are rejected
        (which also makes resynchronisation faster). None accepts any count.
    rotor_rpm : LH1 rotor speed (3600); lh2_rotor_rpm : LH2 rotor speed (3000 = 50 Hz).
    clock_hz : device counter clock (50 MHz).

    ``feed(data)`` returns the sweeps completed by ``data``; ``stats`` counts bytes, good frames,
    bad candidates (magic found but header or CRC wrong), dropped frames (sequence gaps),
    resyncs (times bytes had to be skipped) and skipped bytes.
    """

    name = "layoutkit"

    def __init__(self, n_sensors: int | None = None, *, rotor_rpm: float = 3600.0,
                 lh2_rotor_rpm: float = 3000.0, clock_hz: float = 50e6):
        if n_sensors is not None and not 1 <= int(n_sensors) <= MAX_SENSORS:
            raise ValueError(f"n_sensors: expected 1-{MAX_SENSORS}, got {n_sensors}")
        self.n_sensors = None if n_sensors is None else int(n_sensors)
        self.clock_hz = float(clock_hz)
        self._scale = {0: _omega(rotor_rpm) / clock_hz, 1: _omega(lh2_rotor_rpm) / clock_hz}
        self.stats = DecodeStats()
        self._buf = b""
        self._in_sync = True
        self._last_seq: int | None = None
        self._last_sync: int | None = None
        self._t = 0.0

    # -- public API -------------------------------------------------------------------------
    def feed(self, data) -> list[SweepMeasurement]:
        """Decode ``data`` (bytes-like, any chunking); returns the completed sweeps, in order."""
        try:
            data = bytes(data)
        except Exception:  # noqa: BLE001 - not bytes-like: nothing to decode
            return []
        self.stats.bytes_in += len(data)
        try:
            return self._decode(self._buf + data)
        except Exception:  # noqa: BLE001 - last line of defence; fuzzing shows it is never reached
            self.stats.errors += 1
            self.stats.skipped_bytes += len(self._buf)
            self._buf = b""
            return []

    def flush(self) -> list[SweepMeasurement]:
        """End of stream: the bytes left cannot form a complete frame; count them as skipped."""
        if self._buf:
            self.stats.skipped_bytes += len(self._buf)
            self._buf = b""
        return []

    # -- internals ---------------------------------------------------------------------------
    def _skip(self, k: int) -> None:
        if k <= 0:
            return
        self.stats.skipped_bytes += k
        if self._in_sync:
            self.stats.resyncs += 1
            self._in_sync = False

    def _decode(self, buf: bytes) -> list[SweepMeasurement]:
        L = len(buf)
        pos = 0
        found = []  # (start, flags, seq, n, sync)
        want_n = self.n_sensors
        crc32 = zlib.crc32
        unpack = _HEADER.unpack_from
        while True:
            i = buf.find(MAGIC, pos)
            if i < 0:
                keep = L - 1 if L > pos and buf[L - 1] == MAGIC[0] else L
                self._skip(keep - pos)
                pos = keep
                break
            self._skip(i - pos)
            pos = i
            if L - pos < HEADER_SIZE:
                break
            _, ver, flags, seq, n, sync = unpack(buf, pos)
            if ver == VERSION and not flags & 0xC0 and n and want_n is not None and n != want_n:
                end = pos + HEADER_SIZE + 4 * n + CRC_SIZE  # a whole frame of another layout? (never waited for)
                if end <= L and crc32(buf[pos:end - CRC_SIZE]) == int.from_bytes(buf[end - CRC_SIZE:end], "little"):
                    self.stats.drop(f"frames of {n} sensors, the layout has {want_n} (another layout's capture?)")
                    self._skip(end - pos)
                    pos = end
                    continue
            if ver != VERSION or flags & 0xC0 or n == 0 or (want_n is not None and n != want_n):
                self.stats.bad += 1
                self._skip(1)
                pos += 1
                continue
            end = pos + HEADER_SIZE + 4 * n + CRC_SIZE
            if end > L:
                break
            if crc32(buf[pos:end - CRC_SIZE]) != int.from_bytes(buf[end - CRC_SIZE:end], "little"):
                self.stats.bad += 1
                self._skip(1)
                pos += 1
                continue
            found.append((pos, flags, seq, n, sync))
            self._in_sync = True
            pos = end
        self._buf = buf[pos:]
        if not found:
            return []
        return self._measurements(buf, found)

    def _measurements(self, buf: bytes, found: list) -> list[SweepMeasurement]:
        arr = np.frombuffer(buf, np.uint8)
        out = []
        by_n: dict[int, list[int]] = {}
        for k, f in enumerate(found):
            by_n.setdefault(f[3], []).append(k)
        angles = [None] * len(found)
        four = np.arange(4)
        for n, ks in by_n.items():
            starts = np.array([found[k][0] for k in ks])
            kinds = np.array([(found[k][1] >> 5) & 1 for k in ks])
            size = frame_size(n)
            if len(ks) == 1 or np.all(np.diff(starts) == size):  # back-to-back frames: a strided view
                hits = np.ndarray((len(ks), n), "<u4", buffer=buf, offset=int(starts[0]) + HEADER_SIZE,
                                  strides=(size, 4))
            else:  # gather the hit counters of scattered frames
                idx = starts[:, None, None] + HEADER_SIZE + 4 * np.arange(n)[None, :, None] + four
                hits = np.ascontiguousarray(arr[idx]).view("<u4")[..., 0]
            scale = np.where(kinds == 1, self._scale[1], self._scale[0])[:, None]
            offset = np.where(kinds == 1, -np.pi, 0.0)[:, None]
            a = np.where(hits == NO_HIT, np.nan, hits * scale + offset)
            for j, k in enumerate(ks):
                angles[k] = a[j]
        for (start, flags, seq, n, sync), a in zip(found, angles):
            if seq == self._last_seq and sync == self._last_sync:
                self.stats.bad += 1  # the same frame twice (a repeated transmission): not new data
                continue
            t = self._advance(seq, sync)
            self.stats.good += 1
            out.append(SweepMeasurement(t, flags & 0x0F, (flags >> 4) & 1, a, seq, _KINDS[(flags >> 5) & 1]))
        return out

    def _advance(self, seq: int, sync: int) -> float:
        """Sequence bookkeeping and the unwrapped time of a good frame."""
        if self._last_seq is None:
            self._t = sync / self.clock_hz
        else:
            gap = (seq - self._last_seq) & 0xFFFF
            reset = gap == 0 or gap > 0x8000 or (seq == 0 and gap != 1)
            if reset:  # device restarted: keep t monotone, restart the counter reference
                self.stats.resets += 1
                self._t += sync / self.clock_hz if sync < self.clock_hz else 0.0
            else:
                self.stats.dropped += gap - 1
                self._t += ((sync - self._last_sync) % _WRAP) / self.clock_hz
        self._last_seq = seq
        self._last_sync = sync
        return self._t


# ------------------------------------------------------------------------------ registry entry

def encode_simulated(sw) -> list:
    """Wire frames of every simulated sweep (:class:`~layoutkit.live.simulator.SimulatedSweeps`):
    one frame per sweep in the sweeping station's kind; None for a lost (not emitted) frame."""
    out = [None] * len(sw.t)
    for kind in _KINDS:
        m = np.array([sw.stations[s].kind == kind for s in sw.station], bool)
        if m.any():
            for i, f in zip(np.flatnonzero(m), encode_sweeps(sw.station[m], sw.axis[m], sw.seq[m], sw.sync[m],
                                                             sw.hits[m], kind)):
                out[i] = f
    return [f if e else None for f, e in zip(out, sw.emitted)]


def station_options(stations, n_sensors=None) -> dict:
    """Rotor speeds and counter clock of the decoder from the station set-up (first of each kind)."""
    out = {}
    lh1 = [s for s in stations if s.kind == "lh1"]
    lh2 = [s for s in stations if s.kind == "lh2"]
    if lh1:
        out.update(rotor_rpm=float(lh1[0].rotor_rpm), clock_hz=float(lh1[0].clock_hz))
    if lh2:
        out["lh2_rotor_rpm"] = float(lh2[0].rotor_rpm)
        out.setdefault("clock_hz", float(lh2[0].clock_hz))
    return out


def _entry():
    from .registry import ProtocolEntry

    return ProtocolEntry("layoutkit", LayoutkitDecoder, encode_simulated, station_options,
                         "layoutkit frame protocol for N-sensor timestamp boards (docs/protocol.md)")


PROTOCOL = _entry()
