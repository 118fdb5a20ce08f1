"""Crazyflie microSD event logs (cfusdlog), and the deck UART frames inside them.

Format (bitcraze/crazyflie-firmware ``tools/usdlog/cfusdlog.py``, read and re-implemented):

- byte 0: magic ``0xBC``; ``<u16 version>`` (1 or 2), ``<u16 number of event types>``;
- per event type: ``<u16 id>``, its name (null-terminated), ``<u16 number of variables>``, then per
  variable a null-terminated ``name(T)`` with ``T`` a :mod:`struct` type character;
- events until the last 4 bytes: ``<u16 id>`` then ``<u32 ms>`` (version 1) or ``<u64 µs>``
  (version 2), then the variables packed little-endian;
- trailer: CRC-32 (zlib) of everything before it, ``<u32>``.

A log cut short (the card pulled, power lost) reads up to its last complete event; ``ended`` says
where and why. Event times are returned in seconds on the log's own clock.

``lhUartFrame`` events carry what the Lighthouse deck's FPGA sent for one pulse: ``sensor``,
``basestation`` (the channel), ``offset`` (24 MHz ticks, the firmware's value = 4 × the deck's
6 MHz field; 0 = none) and ``timestampFPGA`` (24 MHz, 24 bits). The pulse width, the beam word and
the slow bit are not logged: ``layoutkit.workflows.importers.deck_bytes`` re-encodes each event as the deck's 12-byte frame
with width 0, beam word 0 and slow bit 0, which is what the firmware's LH2 angle path uses of
them (nothing: it reads sensor, channel, offset and timestamp only). LH1 needs the sync pulse
widths, so an LH1 session cannot be replayed from ``lhUartFrame`` events.
"""
from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["MAGIC", "UsdLog", "read_cfusdlog"]

MAGIC = 0xBC


@dataclass
class UsdLog:
    """A decoded log: ``events[name][var]`` arrays and ``events[name]["t"]`` (s, log clock);
    version; crc_ok (None when the trailer is missing); ended (None or where it stopped)."""

    path: str
    version: int
    events: dict = field(default_factory=dict)
    types: dict = field(default_factory=dict)   # name → [(var, struct char)]
    crc_ok: bool | None = None
    ended: str | None = None


def _cstr(data: bytes, i: int, path, what: str) -> tuple[str, int]:
    j = data.find(b"\x00", i)
    if j < 0:
        raise ValueError(f"{path}: header ends inside {what} (no terminating NUL)")
    try:
        return data[i:j].decode("utf-8"), j + 1
    except UnicodeDecodeError:
        raise ValueError(f"{path}: {what} at byte {i} is not text") from None


def read_cfusdlog(path) -> UsdLog:
    """Read a cfusdlog file; ``ValueError`` naming the file for anything that is not one."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise ValueError(f"{path}: no such log file") from None
    if len(data) < 5 or data[0] != MAGIC:
        raise ValueError(f"{path}: not a Crazyflie microSD log (first byte {data[:1].hex() or 'missing'}, "
                         "expected 0xbc)")
    version, n_types = struct.unpack_from("<HH", data, 1)
    if version not in (1, 2):
        raise ValueError(f"{path}: cfusdlog version {version} is not supported (1 or 2)")
    i = 5
    types, by_id = {}, {}
    for _ in range(n_types):
        if i + 2 > len(data):
            raise ValueError(f"{path}: header cut short at byte {i}")
        (eid,) = struct.unpack_from("<H", data, i)
        name, i = _cstr(data, i + 2, path, "an event name")
        if i + 2 > len(data):
            raise ValueError(f"{path}: header cut short at byte {i}")
        (nv,) = struct.unpack_from("<H", data, i)
        i += 2
        vars_ = []
        for _ in range(nv):
            s, i = _cstr(data, i, path, f"a variable of {name}")
            if len(s) < 4 or s[-1] != ")" or s[-3] != "(":
                raise ValueError(f"{path}: event {name}: variable {s!r} is not 'name(T)'")
            vars_.append((s[:-3], s[-2]))
        fmt = "<" + "".join(c for _, c in vars_)
        try:
            size = struct.calcsize(fmt)
        except struct.error:
            raise ValueError(f"{path}: event {name}: unknown variable type in {fmt[1:]!r}") from None
        types[name] = vars_
        by_id[eid] = (name, struct.Struct(fmt), [v for v, _ in vars_])
    log = UsdLog(str(path), version, types=types)
    rows = {name: [] for name in types}
    times = {name: [] for name in types}
    head = struct.Struct("<HI" if version == 1 else "<HQ")
    end = len(data) - 4
    crc_present = True
    while i < end:
        if i + head.size > end:
            break
        eid, ts = head.unpack_from(data, i)
        if eid not in by_id:
            # either a truncated log (the trailer is not a trailer) or corruption
            log.ended = f"{path}: unknown event id {eid} at byte {i}; read the events before it"
            crc_present = False
            break
        name, st, _ = by_id[eid]
        if i + head.size + st.size > len(data):
            log.ended = f"{path}: the log ends inside an event at byte {i} (truncated); read the events before it"
            crc_present = False
            break
        rows[name].append(st.unpack_from(data, i + head.size))
        times[name].append(ts / 1000.0 if version == 1 else ts / 1e6)
        i += head.size + st.size
    if crc_present and i == end:
        (crc,) = struct.unpack_from("<I", data, end)
        log.crc_ok = crc == (zlib.crc32(data[:end]) & 0xFFFFFFFF)
        if not log.crc_ok:
            log.ended = f"{path}: CRC-32 does not match (the log is damaged; events read as they are)"
    elif log.ended is None:
        log.ended = f"{path}: the log ends inside an event at byte {i} (truncated); read the events before it"
    for name, (vars_) in types.items():
        cols = list(zip(*rows[name])) if rows[name] else [[] for _ in vars_]
        ev = {v: np.asarray(c) for (v, _), c in zip(vars_, cols)}
        ev["t"] = np.asarray(times[name], float)
        log.events[name] = ev
    return log
