"""Bitcraze Lighthouse deck UART stream (LH1 and LH2) and Crazyflie system-configuration files.

Wire format (public: bitcraze/lighthouse-fpga readme; crazyflie-firmware ``lighthouse_core.c``):
230400 baud, 12-byte little-endian frames, one light pulse per frame::

    byte 0      bits 0-1 sensor id, bit 2 slow (OOTX) bit, bits 3-6 channel, bit 7 = 1: no channel
    bytes 1-2   pulse width, 24 MHz ticks
    bytes 3-5   sync offset, 6 MHz ticks, 17 bits (0 = none); upper 7 bits 0 (padding)
    bytes 6-8   beam word, 17 bits; upper 7 bits 0 (padding)
    bytes 9-11  timestamp, 24 MHz ticks, 24 bits (wraps every 0.699 s)

A sync frame of 12 × 0xFF is sent twice a second. A frame is valid iff
``((b[5] | b[8]) & 0xFE) == 0`` or it is a sync frame; otherwise the receiver waits for the next
sync frame (run of twelve 0xFF bytes) and aligns on its end.

Pulse processing follows the firmware (``pulse_processor_v1.c``, ``pulse_processor_v2.c``):

- **LH1**: sync pulses (1000 < width < 3250 ticks) carry ``code = (width - 1375) // 250``
  (bit 0 axis, bit 1 OOTX data, bit 2 skip); sync pulses of all sensors within 10 ticks are one
  sync event; a sync event 7500-12500 ticks after the previous one is station 1's (A/B mode),
  otherwise station 0's. Sweep pulses (width < 512) after the active (non-skip) sync give
  ``angle = (delta - P/4) * 2 pi / P`` with ``delta`` ticks after that sync and ``P`` the measured
  time between two syncs of the same station and axis (accepted in 395000-405000 ticks).
- **LH2**: :mod:`layoutkit.live.protocols.bitcraze_lh2` turns pulses into rotations, either exactly
  as the firmware of the public dataset does (``pulse_processor="firmware"``) or with each
  channel's rotor phase tracked (``"phase"``, the default: fewer blocks discarded, mis-decoded
  offsets rejected); ``a0 = offset0 * 2 pi / P - pi + pi/3``, ``a1 = offset1 * 2 pi / P - pi - pi/3``
  with ``P`` the channel's cycle period (24 MHz), offsets in 24 MHz ticks since the rotor zero.

Calibration (``lighthouse_calibration.c``) is the firmware's model (implemented in
:mod:`layoutkit.lighthouse` as one case of the internal calibration model), inverted by fixed-point
iteration from the raw angles (we iterate to 1e-10 rad; the firmware stops after a change below
5e-4 rad or 5 steps). Applied: LH1 phase, tilt, curve, gibmag, gibphase; LH2 phase, tilt, gibmag,
gibphase. Not applied (the firmware doesn't either): ogeemag, ogeephase, LH2 curve.

Output angles in layoutkit's conventions (lighthouse frame z = boresight): the Bitcraze
station frame has x forward, so ``x_bc = z, y_bc = x, z_bc = y`` (as in
:func:`layoutkit.lighthouse.lh2_sweep_angles`). LH1: the firmware's ideal angles are
``atan2(y_bc, x_bc)`` and ``atan2(z_bc, x_bc)``; layoutkit's ``theta = pi/2 - firmware angle``.
LH2: the firmware's angles are already the ``lh2_sweep_angles`` light-plane angles
(plane 0: t = -30°, plane 1: t = +30°). ``SweepMeasurement.t`` is the sync (LH1) or rotor-zero
(LH2) time, ``time_offset_s + time_rate * (deck ticks unwrapped / 24 MHz)`` (an imported log's
clock fit, :func:`layoutkit.importers.cfusdlog.fit_deck_clock`; 0 and 1 otherwise); ``station`` is the
LH1 station (0/1) or LH2 channel (0-15).

Length (~650 lines): one module per wire protocol — frame layout, both pulse processors, the
reference encoders belong together and share the frame constants (the system-config YAML is
:mod:`layoutkit.io.systemconfig`'s).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...io.systemconfig import (DECK_CLOCK_HZ, LH2_CYCLE_PERIODS, SystemConfig,  # noqa: F401  (the owner: io)
                                read_system_config, system_config_dict)
from ...lighthouse import (StationCalibration, SweepCalibration, calibrate_lh1, calibrate_lh2,  # noqa: F401
                           lh1_model, lh2_model)
from ..frames import DecodeStats, SweepMeasurement
from .bitcraze_lh2 import PROCESSORS, plane_angles

__all__ = [
    "DECK_CLOCK_HZ",
    "FRAME_SIZE",
    "SYNC_FRAME",
    "LH2_CYCLE_PERIODS",
    "DeckPulse",
    "SweepCalibration",
    "StationCalibration",
    "encode_pulse",
    "parse_frame",
    "lh1_deck_stream",
    "lh1_deck_frames",
    "lh2_deck_stream",
    "lh2_deck_session",
    "system_config_dict",
    "lh1_model",
    "lh2_model",
    "calibrate_lh1",
    "calibrate_lh2",
    "BitcrazeDecoder",
    "BitcrazeLh1Decoder",
    "BitcrazeLh2Decoder",
]

FRAME_SIZE = 12
SYNC_FRAME = b"\xff" * FRAME_SIZE
_TS_MOD = 1 << 24
# LH1 constants (24 MHz ticks), pulse_processor_v1.c
LH1_FRAME_LENGTH = 200000
LH1_SWEEP_MAX_WIDTH = 512
LH1_SYNC_MIN_WIDTH, LH1_SYNC_MAX_WIDTH = 1000, 3250
LH1_SYNC_BASE_WIDTH, LH1_SYNC_DIVIDER = 1375, 250
LH1_SYNC_SEPARATION = 10000
LH1_SYNC_MIN_SEP, LH1_SYNC_MAX_SEP = 7500, 12500
LH1_SENSOR_DISPERSION = 10
LH1_FRAME_WIDTH_MIN, LH1_FRAME_WIDTH_MAX = 395000, 405000
MAX_DECK_SENSORS = 4


# --------------------------------------------------------------------------------------- frames
@dataclass(frozen=True)
class DeckPulse:
    """One deck frame. timestamp, width in 24 MHz ticks; offset in 6 MHz ticks (0 = none);
    channel None when the FPGA found no polynomial."""

    sensor: int
    timestamp: int
    width: int
    offset: int = 0
    beam_word: int = 0
    channel: int | None = None
    slow_bit: int = 0


def encode_pulse(p: DeckPulse) -> bytes:
    """One 12-byte deck frame from a pulse (the public frame layout above)."""
    b0 = (p.sensor & 0x03) | ((p.slow_bit & 1) << 2)
    b0 |= 0x80 if p.channel is None else ((p.channel & 0x0F) << 3)
    return (bytes([b0]) + (p.width & 0xFFFF).to_bytes(2, "little") + (p.offset & 0x1FFFF).to_bytes(3, "little")
            + (p.beam_word & 0x1FFFF).to_bytes(3, "little") + (p.timestamp % _TS_MOD).to_bytes(3, "little"))


def parse_frame(b: bytes) -> DeckPulse | None:
    """A 12-byte frame → :class:`DeckPulse`; None for a sync frame; ValueError when invalid."""
    if b == SYNC_FRAME:
        return None
    if len(b) != FRAME_SIZE or ((b[5] | b[8]) & 0xFE) != 0:
        raise ValueError("deck frame: padding bits set (not synchronised)")
    channel = None if b[0] & 0x80 else (b[0] >> 3) & 0x0F
    return DeckPulse(sensor=b[0] & 0x03, timestamp=int.from_bytes(b[9:12], "little"),
                     width=int.from_bytes(b[1:3], "little"), offset=int.from_bytes(b[3:6], "little"),
                     beam_word=int.from_bytes(b[6:9], "little"), channel=channel, slow_bit=(b[0] >> 2) & 1)


# --------------------------------------------------------------------------------- calibration
# The firmware's calibration records and model live in the core (layoutkit.lighthouse, one
# internal model for both public conventions; docs/calibration.md); re-exported here. The system
# configuration file is read and written by its owner, layoutkit.io.systemconfig.


# ----------------------------------------------------------------------- reference encoders
def lh1_deck_stream(theta, *, stations: int = 1, t0_ticks: int = 1000, sync_every_frames: int = 60,
                    jitter=None, calib: dict | None = None) -> tuple[bytes, np.ndarray, list]:
    """Build an LH1 deck byte stream from layoutkit sweep angles, per the public frame spec.

    theta : (F, n) rad (NaN = not hit), n <= 4: the angle of frame f's active sweep; frame f
    (200000 ticks from ``t0_ticks + 200000 f``) is swept by station ``(f // 2) % stations`` along
    axis ``f % 2``. Each frame carries sync pulses of every station (station 1's 10000 ticks
    later) with width ``1500 + 250 * code`` (code bit 0 axis, bit 2 skip for the idle one),
    then each hit sensor's sweep pulse at ``delta = (a / 2 pi + 1/4) * 400000`` ticks after the
    active sync, ``a = pi/2 - theta`` the firmware angle (``calib``: {station: StationCalibration}
    → distorted with :func:`lh1_model`, needs X and Y of a sensor in consecutive frames).
    A sync frame (12 × 0xFF) every ``sync_every_frames`` frames and first. ``jitter``: a
    Generator adding 0-3 ticks of sensor-to-sensor skew to the sync pulses.
    Returns (bytes, sync times of every frame (F,) in ticks unwrapped, list of DeckPulse);
    :func:`lh1_deck_frames` returns the bytes per frame instead.
    """
    chunks, sync_ts, pulses = lh1_deck_frames(theta, stations=stations, t0_ticks=t0_ticks,
                                              sync_every_frames=sync_every_frames, jitter=jitter, calib=calib)
    return b"".join(chunks), sync_ts, pulses


def lh1_deck_frames(theta, *, stations: int = 1, t0_ticks: int = 1000, sync_every_frames: int = 60,
                    jitter=None, calib: dict | None = None) -> tuple[list, np.ndarray, list]:
    """:func:`lh1_deck_stream` with the bytes split per frame: chunk f holds frame f's pulses
    (preceded by a sync frame where one is due; chunk 0 starts with one)."""
    theta = np.asarray(theta, float)
    F, n = theta.shape
    if n > MAX_DECK_SENSORS:
        raise ValueError(f"theta: the deck has at most {MAX_DECK_SENSORS} sensors, got {n}")
    fw = np.pi / 2 - theta
    if calib:
        fw = fw.copy()
        for f in range(0, F - 1, 2):
            s = (f // 2) % stations
            if s in calib:
                pair = lh1_model(fw[f], fw[f + 1], calib[s])
                fw[f], fw[f + 1] = pair[..., 0], pair[..., 1]
    chunks, pulses = [], []
    sync_ts = np.zeros(F, np.int64)
    for f in range(F):
        out = [SYNC_FRAME] if f % sync_every_frames == 0 else []
        start = t0_ticks + LH1_FRAME_LENGTH * f
        axis = f % 2
        active = (f // 2) % stations
        frame_pulses = []
        for s in range(stations):
            ts = start + s * LH1_SYNC_SEPARATION
            code = axis | (0 if s == active else 4)
            for i in range(n):
                dj = 0 if jitter is None else int(jitter.integers(0, 4))  # sensor-to-sensor skew
                frame_pulses.append(DeckPulse(i, ts + dj, 1500 + 250 * code))
            if s == active:
                sync_ts[f] = ts
        for i in range(n):
            if np.isfinite(fw[f, i]):
                delta = int(round((fw[f, i] / (2 * np.pi) + 0.25) * 2 * LH1_FRAME_LENGTH))
                frame_pulses.append(DeckPulse(i, int(sync_ts[f]) + delta, 200))
        frame_pulses.sort(key=lambda p: p.timestamp)
        pulses += frame_pulses
        out += [encode_pulse(p) for p in frame_pulses]
        chunks.append(b"".join(out))
    return chunks, sync_ts, pulses


def lh2_deck_stream(alpha, *, channel: int = 0, t0_ticks: int = 1000, sync_every: int = 50,
                    calib: StationCalibration | None = None, drop_channel_every: int = 0):
    """Build an LH2 deck byte stream from light-plane angles, per the public frame spec.

    alpha : (R, n, 2) rad (NaN = not hit): rotation r of the channel's rotor starts at
    ``t0_ticks + r P`` (P = ``LH2_CYCLE_PERIODS[channel]``); plane 0 hits at offset
    ``(a0 + pi - pi/3) P / 2 pi``, plane 1 at ``(a1 + pi + pi/3) P / 2 pi`` (24 MHz ticks), sent as
    6 MHz offsets (``round(offset / 4)``) with ``timestamp = start + 4 * offset6``.
    ``calib`` distorts the angles first (:func:`lh2_model`). ``drop_channel_every`` k > 0 marks
    every k-th pulse "no channel found". Returns (bytes, rotation starts (R,) ticks, pulses).
    """
    alpha = np.asarray(alpha, float)
    R, n, _ = alpha.shape
    if n > MAX_DECK_SENSORS:
        raise ValueError(f"alpha: the deck has at most {MAX_DECK_SENSORS} sensors, got {n}")
    if calib is not None:
        alpha = lh2_model(alpha[..., 0], alpha[..., 1], calib)
    P = LH2_CYCLE_PERIODS[channel]
    out, pulses = [SYNC_FRAME], []
    starts = t0_ticks + P * np.arange(R, dtype=np.int64)
    k = 0
    for r in range(R):
        if r and r % sync_every == 0:
            out.append(SYNC_FRAME)
        rot = []
        for plane, shift in ((0, -np.pi / 3), (1, np.pi / 3)):
            for i in range(n):
                a = alpha[r, i, plane]
                if not np.isfinite(a):
                    continue
                off6 = int(round((a + np.pi + shift) * P / (2 * np.pi) / 4))
                k += 1
                ch = None if drop_channel_every and k % drop_channel_every == 0 else channel
                rot.append(DeckPulse(i, int(starts[r]) + 4 * off6, 150, off6, (k * 7919) & 0x1FFFF, ch, 0))
        rot.sort(key=lambda p: p.timestamp)
        pulses += rot
        out += [encode_pulse(p) for p in rot]
    return b"".join(out), starts, pulses


def lh2_deck_session(points_body, motion, stations, *, duration: float, channels=None, sigma: float = 0.0,
                     rng=None, normals=None, cone_deg: float = 80.0, t0_ticks: int = 1000, sync_every: int = 64,
                     phases=None):
    """Deck UART bytes of a body moving in front of several LH2 stations, per the public frame spec.

    points_body : (n <= 4, 3) m; motion : callable ``t (K,) s -> (R (K, 3, 3), t (K, 3))``, the body
    pose in the stations' world frame; stations : LH2 :class:`~layoutkit.lighthouse.Station` s (world
    poses; a station's ``calibration`` distorts its angles through
    :func:`layoutkit.lighthouse.measure` — the true calibration); channels : LH2 channel per station
    (default 0, 1, ...). Channel c's rotor starts rotation r at ``t0_ticks + phase_c + r P_c``
    (24 MHz ticks, ``P_c = LH2_CYCLE_PERIODS[c]``; ``phases`` default ``P_c * c / 2.7``); plane k
    (0: -30°, 1: +30°) of that rotation measures the body at its nominal crossing time
    ``start + (pi -/+ pi/3) / 2 pi * P_c``; each angle gets N(0, sigma²) noise, is quantised to the
    deck's 6 MHz offset and sent as one pulse (offset on every pulse). A sensor is seen when it is in
    front of the station (z > 0) and, with ``normals`` (n, 3), faces it within ``cone_deg``. The
    channels' pulses are merged in time order (blocks of two channels that interleave are lost by
    the decoder, as on the real deck). Returns ``(bytes, info)``: ``info["starts"][c]`` rotation
    starts (s, deck clock), ``info["alpha"][c]`` the noise-free measured angles (R_c, n, 2),
    ``info["plane_times"][c]`` (R_c, 2) s.
    """
    from ...lighthouse import lh2_sweep_angles, measure

    P_body = np.asarray(points_body, float)
    n = P_body.shape[0]
    if n > MAX_DECK_SENSORS:
        raise ValueError(f"points_body: the deck has at most {MAX_DECK_SENSORS} sensors, got {n}")
    stations = list(stations)
    channels = list(range(len(stations))) if channels is None else [int(c) for c in channels]
    rng = np.random.default_rng(0) if rng is None else rng
    pulses, info = [], {"starts": {}, "alpha": {}, "plane_times": {}}
    for s, (st, ch) in enumerate(zip(stations, channels)):
        if st.kind != "lh2":
            raise ValueError(f"stations[{s}]: an LH2 station is required, got {st.kind!r}")
        Pc = LH2_CYCLE_PERIODS[ch]
        ph = int(round(Pc * ch / 2.7)) if phases is None else int(phases[s])
        Rn = int(np.floor((duration * DECK_CLOCK_HZ - ph) / Pc))
        starts = t0_ticks + ph + Pc * np.arange(max(Rn, 0), dtype=np.int64)
        tp = (starts[:, None] + np.array([(np.pi - np.pi / 3), (np.pi + np.pi / 3)]) / (2 * np.pi) * Pc) / DECK_CLOCK_HZ
        R, tr = motion(tp.reshape(-1))
        Rs, ts = st.world_to_station(R, tr)
        p = np.einsum("kij,nj->kni", Rs, P_body) + ts[:, None, :]            # (2 Rn, n, 3)
        a = measure(p, st.calibration) if st.calibration is not None else lh2_sweep_angles(p)
        a = a.reshape(Rn, 2, n, 2)
        alpha = np.stack([a[:, 0, :, 0], a[:, 1, :, 1]], -1)                  # plane k at its own time
        seen = p[..., 2] > 0
        if normals is not None:
            nw = np.einsum("kij,nj->kni", Rs, np.asarray(normals, float))
            cosang = -np.sum(nw * p, -1) / np.maximum(np.linalg.norm(p, axis=-1), 1e-300)
            seen &= cosang >= np.cos(np.deg2rad(cone_deg))
        seen = seen.reshape(Rn, 2, n).transpose(0, 2, 1)
        alpha_n = np.where(seen, alpha + (rng.normal(0.0, sigma, alpha.shape) if sigma > 0 else 0.0), np.nan)
        info["starts"][ch], info["alpha"][ch], info["plane_times"][ch] = starts / DECK_CLOCK_HZ, alpha, tp
        for r in range(Rn):
            for plane, shift in ((0, -np.pi / 3), (1, np.pi / 3)):
                for i in range(n):
                    v = alpha_n[r, i, plane]
                    if not np.isfinite(v):
                        continue
                    off6 = int(round((v + np.pi + shift) * Pc / (2 * np.pi) / 4))
                    pulses.append(DeckPulse(i, int(starts[r]) + 4 * off6, 150, off6, 0, ch, 0))
    pulses.sort(key=lambda q: q.timestamp)
    out = []
    for k, q in enumerate(pulses):
        if k % sync_every == 0:
            out.append(SYNC_FRAME)
        out.append(encode_pulse(q))
    return b"".join(out), info


# ------------------------------------------------------------------------------------ decoder
class BitcrazeDecoder:
    """Incremental decoder of the Lighthouse deck UART stream; never raises on any bytes.

    mode : "lh1" or "lh2". n_sensors : 1-4 (angles of sensors 0..n-1). system_config : path,
    dict or :class:`SystemConfig`; its calibrations are applied (``calibrate=True``).
    time_offset_s, time_rate : every sweep time is ``time_offset_s + time_rate * deck s`` (deck s =
    unwrapped 24 MHz ticks / 24e6). pulse_processor : LH2 only, "phase" (default) or "firmware"
    (:data:`layoutkit.live.protocols.bitcraze_lh2.PROCESSORS`).
    stats: good = sweeps emitted, bad = invalid frames (padding set), resyncs, skipped bytes,
    dropped = sweeps discarded by the pulse processor (incomplete/ambiguous).
    ``pulses`` counts valid pulse frames.
    """

    name = "bitcraze"

    def __init__(self, n_sensors: int | None = 4, *, mode: str = "lh2", system_config=None,
                 calibrate: bool = True, time_offset_s: float = 0.0, time_rate: float = 1.0,
                 pulse_processor: str = "phase"):
        if mode not in ("lh1", "lh2"):
            raise ValueError(f"mode: expected 'lh1' or 'lh2', got {mode!r}")
        if pulse_processor not in PROCESSORS:
            raise ValueError(f"pulse_processor: expected one of {sorted(PROCESSORS)}, got {pulse_processor!r}")
        if not (np.isfinite(time_rate) and 0.5 < float(time_rate) < 2.0):
            raise ValueError(f"time_rate: expected a clock rate near 1, got {time_rate!r}")
        n = 4 if n_sensors is None else int(n_sensors)
        if not 1 <= n <= MAX_DECK_SENSORS:
            raise ValueError(f"n_sensors: the Lighthouse deck has 1-{MAX_DECK_SENSORS} sensors, got {n_sensors}")
        self.mode = mode
        self.n = n
        # added to every emitted t: an imported log puts the deck clock onto its own event clock
        self.time_offset_s = float(time_offset_s)
        self.time_rate = float(time_rate)
        cfg = system_config
        if cfg is not None and not isinstance(cfg, SystemConfig):
            cfg = read_system_config(cfg)
        self.config = cfg
        self.calibs = dict(cfg.calibs) if (cfg is not None and calibrate) else {}
        self.stats = DecodeStats()
        self.pulses = 0
        self._buf = b""
        self._synced = False
        self._ff_run = 0
        self._last_ts = None
        self._abs = 0
        # LH1 state
        self._sync_abs = None  # last sync event (abs ticks)
        self._last_sync_by = {}  # (station, axis) → abs ticks
        self._active = None  # (station, axis, sync_abs, period)
        self._hits: dict = {}
        self._held = {}  # station → held X sweep (for calibration pairing)
        # LH2 state
        self.pulse_processor = pulse_processor
        self._lh2p = PROCESSORS[pulse_processor](n, self.stats)

    # -- bytes → frames ------------------------------------------------------------------------
    def feed(self, data) -> list[SweepMeasurement]:
        try:
            data = bytes(data)
        except Exception:  # noqa: BLE001
            return []
        self.stats.bytes_in += len(data)
        out: list = []
        try:
            self._frames(self._buf + data, out)
        except Exception:  # noqa: BLE001 - last line of defence; fuzzing shows it is never reached
            self.stats.errors += 1
            self._buf = b""
            self._synced = False
        return out

    def flush(self) -> list[SweepMeasurement]:
        out: list = []
        try:
            if self.mode == "lh1":
                self._finish_lh1_sweep(out)
            else:
                for rot in self._lh2p.flush():
                    self._rotation(rot, out)
        except Exception:  # noqa: BLE001
            self.stats.errors += 1
        if self._buf:
            self.stats.skipped_bytes += len(self._buf)
            self._buf = b""
        return out

    def _frames(self, buf: bytes, out: list) -> None:
        pos, L = 0, len(buf)
        while True:
            if not self._synced:
                # look for twelve 0xFF in a row; align on the end of the run
                while pos < L:
                    if buf[pos] == 0xFF:
                        self._ff_run += 1
                    else:
                        if self._ff_run >= FRAME_SIZE:
                            self._synced = True
                            self._ff_run = 0
                            break
                        self._ff_run = 0
                    self.stats.skipped_bytes += 1
                    pos += 1
                if not self._synced:
                    break
                # the run's 12 last bytes were the sync frame (counted as skipped above)
            if L - pos < FRAME_SIZE:
                break
            fr = buf[pos:pos + FRAME_SIZE]
            if fr == SYNC_FRAME:
                pos += FRAME_SIZE
                continue
            if (fr[5] | fr[8]) & 0xFE:
                self.stats.bad += 1
                self.stats.resyncs += 1
                self._synced = False
                self._ff_run = 0
                continue  # rescan from this frame's first byte
            pos += FRAME_SIZE
            self.pulses += 1
            self._pulse(fr, out)
        self._buf = buf[pos:]

    def _unwrap(self, ts: int) -> int:
        if self._last_ts is None:
            self._abs = ts
        else:
            d = (ts - self._last_ts) % _TS_MOD
            if d >= _TS_MOD // 2:
                d -= _TS_MOD  # slightly out of order (the FPGA may swap close pulses)
            self._abs += d
        self._last_ts = ts
        return self._abs

    def _pulse(self, fr: bytes, out: list) -> None:
        sensor = fr[0] & 0x03
        ts = self._unwrap(int.from_bytes(fr[9:12], "little"))
        width = int.from_bytes(fr[1:3], "little")
        if self.mode == "lh1":
            self._lh1(sensor, ts, width, out)
        else:
            channel = None if fr[0] & 0x80 else (fr[0] >> 3) & 0x0F
            offset = int.from_bytes(fr[3:6], "little") * 4
            self._lh2(sensor, ts, offset, channel, out)

    # -- LH1 -----------------------------------------------------------------------------------
    def _lh1(self, sensor: int, ts: int, width: int, out: list) -> None:
        if LH1_SYNC_MIN_WIDTH < width < LH1_SYNC_MAX_WIDTH:
            if self._sync_abs is not None and abs(ts - self._sync_abs) <= LH1_SENSOR_DISPERSION:
                return  # the same sync seen by another sensor
            since = None if self._sync_abs is None else ts - self._sync_abs
            station = 1 if since is not None and LH1_SYNC_MIN_SEP < since < LH1_SYNC_MAX_SEP else 0
            self._sync_abs = ts
            code = int((width - LH1_SYNC_BASE_WIDTH) / LH1_SYNC_DIVIDER)  # C truncation
            axis = code & 1
            skip = bool(code & 4)  # the other station sweeps this frame
            if self._hits or not skip:  # a skipping sync right after the active one ends nothing
                self._finish_lh1_sweep(out)
            prev = self._last_sync_by.get((station, axis))
            self._last_sync_by[(station, axis)] = ts
            if skip:
                return
            period = None if prev is None else ts - prev
            self._active = (station, axis, ts, period)
            self._hits = {}
        elif width < LH1_SWEEP_MAX_WIDTH and self._active is not None:
            if sensor < self.n:
                self._hits[sensor] = None if sensor in self._hits else ts  # two hits → error

    def _finish_lh1_sweep(self, out: list) -> None:
        if self._active is None:
            return
        station, axis, sync, period = self._active
        self._active = None
        hits, self._hits = self._hits, {}
        if period is None or not LH1_FRAME_WIDTH_MIN <= period <= LH1_FRAME_WIDTH_MAX:
            self.stats.drop("LH1 sweep without a measured period (first sync of its station and axis, "
                            "or a period outside 395000-405000 ticks)")
            return
        a = np.full(self.n, np.nan)
        for s, ts in hits.items():
            if ts is not None and 0 <= ts - sync < LH1_FRAME_LENGTH:
                a[s] = (ts - sync - period / 4.0) * 2 * np.pi / period
        t = sync / DECK_CLOCK_HZ
        cal = self.calibs.get(station)
        if cal is None:
            self._emit(out, t, station, axis, np.pi / 2 - a, "lh1")
            return
        if axis == 0:
            if station in self._held:
                self.stats.drop("LH1 X sweep without its Y sweep (calibration needs both)")
            self._held[station] = (t, a)
            return
        if station not in self._held:
            self.stats.drop("LH1 Y sweep without its X sweep (calibration needs both)")
            return
        tx, ax = self._held.pop(station)
        ideal = calibrate_lh1(np.stack([ax, a], -1), cal)  # NaN where either axis is missing
        self._emit(out, tx, station, 0, np.pi / 2 - ideal[:, 0], "lh1")
        self._emit(out, t, station, 1, np.pi / 2 - ideal[:, 1], "lh1")

    def _emit(self, out, t, station, axis, angles, kind):
        self.stats.good += 1
        out.append(SweepMeasurement(self.time_offset_s + self.time_rate * float(t), int(station), int(axis),
                                    np.asarray(angles, float), None, kind))

    # -- LH2 -----------------------------------------------------------------------------------
    def _lh2(self, sensor: int, ts: int, offset: int, channel, out: list) -> None:
        for rot in self._lh2p.push(sensor, ts, offset, channel):
            self._rotation(rot, out)

    def _rotation(self, rot, out: list) -> None:
        """A rotation's offsets → both planes' angles (calibrated when the channel has a calibration),
        emitted at the rotor zero."""
        raw = plane_angles(rot.offsets, rot.channel)
        cal = self.calibs.get(rot.channel)
        ang = calibrate_lh2(raw, cal) if cal is not None else raw
        t = rot.t0 / DECK_CLOCK_HZ
        self._emit(out, t, rot.channel, 0, ang[:, 0], "lh2")
        self._emit(out, t, rot.channel, 1, ang[:, 1], "lh2")


class BitcrazeLh1Decoder(BitcrazeDecoder):
    """:class:`BitcrazeDecoder` in LH1 mode (registry name ``bitcraze-lh1``)."""

    name = "bitcraze-lh1"

    def __init__(self, n_sensors: int | None = 4, *, system_config=None, calibrate: bool = True):
        super().__init__(n_sensors, mode="lh1", system_config=system_config, calibrate=calibrate)


class BitcrazeLh2Decoder(BitcrazeDecoder):
    """:class:`BitcrazeDecoder` in LH2 mode (registry name ``bitcraze-lh2``)."""

    name = "bitcraze-lh2"

    def __init__(self, n_sensors: int | None = 4, *, system_config=None, calibrate: bool = True,
                 time_offset_s: float = 0.0, time_rate: float = 1.0, pulse_processor: str = "phase"):
        super().__init__(n_sensors, mode="lh2", system_config=system_config, calibrate=calibrate,
                         time_offset_s=time_offset_s, time_rate=time_rate, pulse_processor=pulse_processor)


# ------------------------------------------------------------------------------ registry entries

def encode_simulated_lh1(sw) -> list:
    """The deck's LH1 stream for simulated sweeps (:class:`~layoutkit.live.simulator.SimulatedSweeps`):
    bytes per sweep, re-quantised to the 24 MHz deck clock; <= 4 sensors, one or two LH1 stations
    at 3600 rpm (A/B mode)."""
    n = sw.hits.shape[1]
    if n > MAX_DECK_SENSORS:
        raise ValueError(f"protocol bitcraze-lh1: the Lighthouse deck has at most {MAX_DECK_SENSORS} "
                         f"sensors, the layout has {n}")
    if any(st.kind != "lh1" or st.rotor_rpm != 3600.0 for st in sw.stations) or len(sw.stations) > 2:
        raise ValueError("protocol bitcraze-lh1: needs one or two LH1 stations at 3600 rpm")
    theta = np.where(sw.emitted[:, None], sw.measured_angles(), np.nan)
    chunks, _, _ = lh1_deck_frames(theta, stations=len(sw.stations), t0_ticks=int(round(sw.t[0] * DECK_CLOCK_HZ)))
    return chunks


def _entries():
    from .registry import ProtocolEntry

    return (ProtocolEntry("bitcraze-lh1", BitcrazeLh1Decoder, encode_simulated_lh1, None,
                          "Bitcraze Lighthouse deck UART stream, LH1 stations (docs/live-io.md)"),
            ProtocolEntry("bitcraze-lh2", BitcrazeLh2Decoder, None, None,
                          "Bitcraze Lighthouse deck UART stream, LH2 stations (decode only)"))


LH1_PROTOCOL, LH2_PROTOCOL = _entries()
