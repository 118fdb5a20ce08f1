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
6 MHz field; 0 = none), ``timestampFPGA`` (24 MHz, 24 bits) and ``timestamp2FPGA`` (the same
counter extended to 32 bits with the Crazyflie's millisecond clock). Conventions found on the
public logs (crazyflie-firmware e9ff096, ``lighthouse_core.c``; :func:`uart_frames`):

- ``basestation`` is the channel when the FPGA found one, else the firmware's number of base
  stations (2 with two LH2 stations; every frame of an LH1 log) — "no channel" (the frame's bit 7).
  Such a pulse never carries an offset: the offset comes from the decoded bit stream.
- the deck's clock and the log's clock differ in rate by about -1.1 % (the log clock runs slow);
  each frame is logged after it crossed the 230400-baud UART (0.52 ms per queued frame):
  :func:`fit_deck_clock`.

The pulse width, the beam word and the slow bit are not logged:
``layoutkit.workflows.importers.deck_bytes`` re-encodes each event as the deck's 12-byte frame
with width 0, beam word 0 and slow bit 0, which is what the firmware's LH2 angle path uses of
them (nothing: it reads sensor, channel, offset and timestamp only). LH1 needs the sync pulse
widths, so an LH1 session cannot be replayed from ``lhUartFrame`` events (its ``lhAngle`` events
can: :mod:`layoutkit.live.cf_events`).
"""
from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..io.systemconfig import DECK_CLOCK_HZ

__all__ = ["MAGIC", "UsdLog", "read_cfusdlog", "SWEEP_EVENTS", "SweepEvents", "sweep_events", "firmware_positions",
           "UartFrames", "uart_frames", "no_channel_value", "DeckClock", "fit_deck_clock",
           "UART_FRAME_S"]

MAGIC = 0xBC


@dataclass
class UsdLog:
    """A decoded log: ``events[name][var]`` arrays and ``events[name]["t"]`` (s, log clock; a
    variable itself named ``t`` is stored as ``t_var``);
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
        # a variable named "t" (estSweepAngle's plane tilt) is kept as "t_var": "t" is the event time
        ev = {("t_var" if v == "t" else v): np.asarray(c) for (v, _), c in zip(vars_, cols)}
        ev["t"] = np.asarray(times[name], float)
        log.events[name] = ev
    return log


# ------------------------------------------------------------------ sweep-angle and estimate events
#
# What the firmware's lighthouse code can write to the card (docs/real-data.md, "Crazyflie"):
#   lhAngle      (sensor u8, basestation u8, sweep u8, angle f32, correctedAngle f32): one angle of one
#                sensor and sweep as the pulse processor measured it (``angle``: raw, the firmware's
#                own convention; ``correctedAngle``: after its calibration inverse). The public
#                Lighthouse dataset's logs (Taffanel et al. 2021) carry it.
#   estSweepAngle (sensorId u8, basestationId|baseStationId u8, sweepId u8, t f32, sweepAngle f32):
#                the sweep-angle measurement the Kalman filter gets (``estimator.c``); ``t`` is the
#                light plane's tilt (LH1: 0, LH2: -/+ pi/6), ``sweepAngle`` the raw measured angle.
#   estPosition  (x, y, z f32 in old firmware; ``source`` u8 + the log variables the config names
#                in newer firmware, e.g. lighthouse.x/y/z): the crossing-beam position pushed to the
#                estimator (lighthouse.method = 0).
#   any event (e.g. ``fixedFrequency``) with the log variables stateEstimate.x/y/z (the state
#                estimate) or lighthouse.x/y/z (the last crossing-beam position).

#: sweep-angle event types this reader understands, in order of preference: name → variables
#: (sensor, station, sweep, angle) — alternatives separated by "|".
SWEEP_EVENTS = {
    "lhAngle": ("sensor", "basestation", "sweep", "angle"),
    "estSweepAngle": ("sensorId", "basestationId|baseStationId", "sweepId", "sweepAngle"),
}


@dataclass(frozen=True)
class SweepEvents:
    """Sweep-angle events of a log, one row per sensor and sweep, in log order.

    source : the event type read (``lhAngle`` / ``estSweepAngle``). t : (N,) s, log clock (when the
    firmware logged the angle). station : (N,) base-station index (LH1 0/1, LH2 channel 0-15).
    sensor : (N,) deck sensor 0-3. sweep : (N,) 0/1 (LH1 X/Y rotor, LH2 light plane -30°/+30°).
    angle : (N,) rad, the raw measured angle in the firmware's convention, float32 as logged.
    corrected : (N,) rad, the firmware's calibrated angle (``lhAngle`` only) or None.
    kind : "lh1"/"lh2" when the events tell (``estSweepAngle``'s plane tilt), else None.
    """

    source: str
    t: np.ndarray
    station: np.ndarray
    sensor: np.ndarray
    sweep: np.ndarray
    angle: np.ndarray
    corrected: np.ndarray | None = None
    kind: str | None = None


def _var(ev: dict, spec: str):
    for name in spec.split("|"):
        if name in ev:
            return ev[name]
    return None


def sweep_events(log: UsdLog) -> SweepEvents | None:
    """The log's sweep-angle events (``lhAngle`` preferred, else ``estSweepAngle``), or None when it
    has neither (or none logged). ValueError naming the file and the variables it has when such
    an event type lacks a variable."""
    for name, spec in SWEEP_EVENTS.items():
        ev = log.events.get(name)
        if ev is None or len(ev["t"]) == 0:
            continue
        cols = [_var(ev, s) for s in spec]
        miss = [s for s, c in zip(spec, cols) if c is None]
        if miss:
            raise ValueError(f"{log.path}: {name} events lack variable(s) {miss} "
                             f"(have {sorted(k for k in ev if k != 't')})")
        sensor, station, sweep, angle = (np.asarray(c) for c in cols)
        kind = None
        if name == "estSweepAngle" and "t_var" in ev:
            tilt = np.asarray(ev["t_var"], float)
            kind = "lh2" if np.nanmedian(np.abs(tilt)) > 0.1 else "lh1"
            if kind == "lh2":  # the plane from the tilt's sign (some firmware leaves sweepId unset)
                sweep = (tilt > 0).astype(int)
        corrected = np.asarray(ev["correctedAngle"], float) if "correctedAngle" in ev else None
        return SweepEvents(name, np.asarray(ev["t"], float), station.astype(int), sensor.astype(int),
                           sweep.astype(int), angle.astype(np.float32).astype(float), corrected, kind)
    return None


#: firmware position estimates: (label, event or None = any event, x/y/z variable names)
_ESTIMATE_SOURCES = (
    ("crossing_beam", None, ("lighthouse.x", "lighthouse.y", "lighthouse.z")),
    ("crossing_beam", "lhCrossingBeam", ("x", "y", "z")),
    ("crossing_beam", "estPosition", ("x", "y", "z")),
    ("state_estimate", None, ("stateEstimate.x", "stateEstimate.y", "stateEstimate.z")),
)


def firmware_positions(log: UsdLog) -> dict:
    """The firmware's own position estimates in the log: label → ``{"event", "t" (K,) s, "position"
    (K, 3) m}`` (world frame = the system config's). ``crossing_beam``: the two-station
    crossing-beam positions (``lighthouse.x/y/z`` log variables, ``lhCrossingBeam`` or old
    ``estPosition`` x/y/z events); ``state_estimate``: ``stateEstimate.x/y/z`` (the Kalman filter's
    state, fed by the crossing beam or the sweeps). Rows that are exactly 0 (the variable is 0
    until the method writes it) and non-finite rows are left out. The first event type that has
    a source's variables wins."""
    out = {}
    for label, event, names in _ESTIMATE_SOURCES:
        if label in out:
            continue
        for ename, ev in log.events.items():
            if event is not None and ename != event:
                continue
            if not all(k in ev for k in names) or len(ev["t"]) == 0:
                continue
            p = np.column_stack([np.asarray(ev[k], float) for k in names])
            keep = np.all(np.isfinite(p), 1) & np.any(p != 0, 1)
            if keep.any():
                out[label] = {"event": ename, "variables": list(names), "t": np.asarray(ev["t"], float)[keep],
                              "position": p[keep]}
                break
    return out


# ------------------------------------------------------------------------------ deck UART frames
#: time one 12-byte deck frame takes on the 230400-baud UART (10 bits per byte)
UART_FRAME_S = 12 * 10 / 230400
#: a frame is "isolated" (logged with an empty UART queue) when the previous one is this much older
_ISOLATED_GAP_S = 3e-3


@dataclass(frozen=True)
class UartFrames:
    """A log's ``lhUartFrame`` events, one row per deck pulse, in log order.

    t : (N,) s, log clock. sensor : (N,) 0-3. channel : (N,) LH2 channel, -1 = no channel found.
    offset : (N,) 24 MHz ticks since the rotor zero (0 = none). timestamp : (N,) the deck's 24-bit
    counter. ticks : (N,) int64, the counter unwrapped (origin: the first frame's 24-bit value;
    unwrapped through ``timestamp2FPGA`` when the log has it, so gaps of any length are safe).
    no_channel : the ``basestation`` value that meant "no channel" in this log (None: none seen).
    """

    t: np.ndarray
    sensor: np.ndarray
    channel: np.ndarray
    offset: np.ndarray
    timestamp: np.ndarray
    ticks: np.ndarray
    no_channel: int | None

    @property
    def deck_s(self) -> np.ndarray:
        """(N,) s, the deck clock (unwrapped ticks / 24 MHz)."""
        return self.ticks / DECK_CLOCK_HZ


def no_channel_value(basestation, offset) -> int | None:
    """The ``basestation`` value of a log's ``lhUartFrame`` events that means "no channel found".

    The firmware writes its number of base stations there (2 at the dataset's firmware, more in
    later builds); a value >= 16 is never a channel. Rule: the largest value seen, if none of its
    frames carries an offset (a decoded channel carries one on ~1 pulse in 4; every frame of an
    LH1 log has the no-channel value), else None (every value is a channel)."""
    bs = np.asarray(basestation, np.int64)
    off = np.asarray(offset, np.int64)
    if bs.size == 0:
        return None
    top = int(bs.max())
    if top >= 16 or not np.any(off[bs == top] != 0):
        return top
    return None


def _unwrap(ts, bits: int) -> np.ndarray:
    ts = np.asarray(ts, np.int64) & ((1 << bits) - 1)
    if ts.size == 0:
        return ts
    d = np.diff(ts) % (1 << bits)
    d = np.where(d >= (1 << (bits - 1)), d - (1 << bits), d)
    return np.concatenate([[0], np.cumsum(d)])


def uart_frames(log: UsdLog) -> UartFrames | None:
    """The log's ``lhUartFrame`` events as :class:`UartFrames` (None when it has none); ValueError
    naming the file and the variables found when a needed variable is missing."""
    ev = log.events.get("lhUartFrame")
    if ev is None or len(ev["t"]) == 0:
        return None
    need = ("sensor", "basestation", "offset", "timestampFPGA")
    miss = [k for k in need if k not in ev]
    if miss:
        raise ValueError(f"{log.path}: lhUartFrame events lack variable(s) {miss} "
                         f"(have {sorted(k for k in ev if k != 't')})")
    bs = np.asarray(ev["basestation"], np.int64)
    off = np.asarray(ev["offset"], np.int64)
    ts = np.asarray(ev["timestampFPGA"], np.int64) & 0xFFFFFF
    nc = no_channel_value(bs, off)
    ch = np.where(bs == nc, -1, bs) if nc is not None else bs.copy()
    rel = _unwrap(ts, 24)
    if "timestamp2FPGA" in ev:
        ts2 = np.asarray(ev["timestamp2FPGA"], np.int64)
        if np.all((ts2 & 0xFFFFFF) == ts):     # the 32-bit extension of the same counter
            rel = _unwrap(ts2, 32)
    return UartFrames(np.asarray(ev["t"], float), np.asarray(ev["sensor"], np.int64) & 3, ch, off, ts,
                      int(ts[0]) + rel, nc)


@dataclass(frozen=True)
class DeckClock:
    """``t_log = offset_s + rate * t_deck``: the log time of the light hitting a sensor at deck time
    ``t_deck`` (s, unwrapped ticks / 24 MHz, origin as :attr:`UartFrames.ticks`).

    Fitted on the frames logged with an empty UART queue (the previous frame >= 3 ms earlier), by
    least squares with 5-MAD trimming, minus one frame's UART time (:data:`UART_FRAME_S`).
    rate_ppm : (rate - 1) * 1e6. rms_s : RMS residual of the frames used. frames_used / frames.
    queue_s : the median extra delay per frame queued before (the UART: ~0.52 ms). status :
    "ok", or "inaccurate" (fewer than 20 isolated frames, or residual RMS > 1 ms). message : why.
    """

    offset_s: float
    rate: float
    rms_s: float
    frames_used: int
    frames: int
    queue_s: float
    status: str = "ok"
    message: str = ""

    @property
    def rate_ppm(self) -> float:
        return (self.rate - 1.0) * 1e6

    @property
    def success(self) -> bool:
        return self.status == "ok"

    def to_log(self, deck_s):
        """Deck seconds → log seconds."""
        return self.offset_s + self.rate * np.asarray(deck_s, float)

    def as_dict(self) -> dict:
        return {"offset_s": self.offset_s, "rate": self.rate, "rate_ppm": self.rate_ppm, "rms_s": self.rms_s,
                "frames_used": self.frames_used, "frames": self.frames, "uart_queue_s_per_frame": self.queue_s,
                "status": self.status, "message": self.message,
                "model": "t_log = offset_s + rate * t_deck (light time; isolated frames minus one UART frame)"}


def fit_deck_clock(deck_s, t_log) -> DeckClock:
    """Fit :class:`DeckClock` to frames' deck times (N,) s and log times (N,) s (see there)."""
    x = np.asarray(deck_s, float)
    y = np.asarray(t_log, float)
    n = x.size
    if n < 2:
        off = float(y[0] - x[0]) if n else 0.0
        return DeckClock(off, 1.0, float("nan"), n, n, float("nan"), "inaccurate",
                         f"{n} UART frame(s): offset only, rate 1")
    gap = np.concatenate([[np.inf], np.diff(x)])
    iso = gap >= _ISOLATED_GAP_S
    if iso.sum() < 20:
        iso = np.ones(n, bool)
    x0 = x[0]
    A = np.column_stack([np.ones(n), x - x0])
    use = iso.copy()
    for _ in range(4):
        c, *_ = np.linalg.lstsq(A[use], y[use], rcond=None)
        r = y - A @ c
        med = np.median(r[iso])
        mad = np.median(np.abs(r[iso] - med))
        new = iso & (np.abs(r - med) <= 5 * 1.4826 * mad + 1e-5)
        if np.array_equal(new, use):
            break
        use = new
    c, *_ = np.linalg.lstsq(A[use], y[use], rcond=None)
    r = y - A @ c
    rms = float(np.sqrt(np.mean(r[use] ** 2)))
    # extra delay of the frame right after another (queued behind it on the UART)
    queued = (~iso) & np.concatenate([[False], iso[:-1]])
    q = float(np.median(r[queued] - np.median(r[use]))) if queued.any() else float("nan")
    rate = float(c[1])
    offset = float(c[0] - rate * x0 - UART_FRAME_S)
    status, msg = "ok", f"rate {1e6 * (rate - 1):+.0f} ppm from {int(use.sum())} isolated frames, residual RMS {1e3 * rms:.3f} ms"
    if use.sum() < 20 or rms > 1e-3:
        status, msg = "inaccurate", msg + " (fewer than 20 frames or RMS > 1 ms)"
    return DeckClock(offset, rate, rms, int(use.sum()), n, q, status, msg)


# ------------------------------------------------------------------------------ IMU samples
#: the Crazyflie's IMU log variables (``sensors`` log group, crazyflie-firmware ``sensors_bmi088_*.c``:
#: ``gyro.x/y/z`` deg/s and ``acc.x/y/z`` g, body frame x forward, y left, z up, bias-corrected by the
#: firmware), in the order gyro xyz, acc xyz
IMU_VARIABLES = ("gyro.x", "gyro.y", "gyro.z", "acc.x", "acc.y", "acc.z")


#: s, how much later than the motion the Crazyflie's logged IMU samples are stamped (the firmware's
#: gyro / accelerometer low-pass filters and the logging): measured on lh2_crossingBeam_move/log00
#: by the lag that best matches the gyro to the lighthouse attitude rates (-4 ms) and the
#: accelerometer to the motion capture's second differences (-5 ms); imu_samples moves them back
IMU_DELAY_S = 0.005


def imu_samples(log: UsdLog):
    """The log's IMU samples as :class:`layoutkit.io.imu.ImuSamples` (SI: rad/s, m/s² specific force,
    body frame; ``t`` the log's event clock — the clock the replay maps the deck's timestamps onto),
    or None when no event type carries all of :data:`IMU_VARIABLES` (e.g. a log without
    ``fixedFrequency`` sensor logging). The first event type with the most samples wins (the
    dataset's logs: ``fixedFrequency`` at ~100 Hz). Rows with a non-finite value are dropped;
    time-sorted (stable); ``t`` is the event time minus :data:`IMU_DELAY_S` (the motion's time)."""
    from ..io.imu import ImuSamples
    from ..units import DEG_PER_S, STANDARD_GRAVITY

    best = None
    for name, ev in log.events.items():
        if all(k in ev for k in IMU_VARIABLES) and len(ev["t"]) > 0:
            if best is None or len(ev["t"]) > len(log.events[best]["t"]):
                best = name
    if best is None:
        return None
    ev = log.events[best]
    raw = np.column_stack([np.asarray(ev[k], float) for k in IMU_VARIABLES])
    t = np.asarray(ev["t"], float)
    keep = np.all(np.isfinite(raw), 1) & np.isfinite(t)
    raw, t = raw[keep], t[keep]
    order = np.argsort(t, kind="stable")
    return ImuSamples(t[order] - IMU_DELAY_S, raw[order, 0:3] * DEG_PER_S, raw[order, 3:6] * STANDARD_GRAVITY,
                      f"{log.path}: {best} events gyro.x/y/z (deg/s), acc.x/y/z (g), time - {IMU_DELAY_S} s")
