"""LH2 pulse processing of the Lighthouse deck: deck pulses → rotations (two light planes) per channel.

A deck pulse is one sensor hit by one light plane: ``(sensor, ts, offset, channel)`` with ``ts`` the
deck's 24 MHz timestamp (unwrapped, int ticks), ``offset`` the ticks since the channel's rotor zero
as the FPGA decoded it from the beam's bit stream (24 MHz ticks = 4 × the deck's 6 MHz field; 0 =
none) and ``channel`` None when the FPGA found no channel (the frame's bit 7). A rotation is
``(channel, t0, offsets (n, 2))``: the rotor zero ``t0`` (ticks) and, per sensor and plane, the
ticks from the rotor zero to the light crossing the sensor (NaN = not measured); the plane angles
are ``a0 = off0 2 pi / P - pi + pi/3``, ``a1 = off1 2 pi / P - pi - pi/3`` with ``P`` the channel's
cycle period (:func:`plane_angles`).

Two processors with one interface (``push(pulse) -> list[Rotation]``, ``flush()``, drop reasons
counted in a :class:`~layoutkit.live.frames.DecodeStats`):

:class:`FirmwareLh2` — exactly ``pulse_processor_v2.c`` of crazyflie-firmware at e9ff096 (March
2021, the firmware of the public Lighthouse dataset; read to understand, not copied): pulses within
10000 ticks of the previous one form a workspace of at most 8 pulses (a ninth clears it); on
closing, a pulse without channel takes the channel of the pulse right after it
(``augmentFramesInWorkspace``: one step, skipping the donor); the workspace must hold 4 or 8 pulses,
cut into consecutive blocks of 4 that each hold all four sensors, one channel and exactly one pulse
with an offset (else the whole workspace is dropped); every sensor's offset follows from that
pulse, ``offset_s = offset_ref - (ts_ref - ts_s)``, and the rotor zero is ``t0 = ts_ref -
offset_ref``; per channel the first block is kept until a block whose ``t0`` is within 10 ticks
arrives (the second plane). On the real logs its angles equal the firmware's own ``lhAngle``
events to float32 rounding (:func:`layoutkit.live.cf_events.firmware_angle_check`).

:class:`PhaseLh2` (default) — the same measurements, fewer discarded, checked against each
channel's rotor phase. What it does differently, and why (measured on the public logs, see
docs/real-data.md):

- blocks are cut by channel and sensor, not by position: two channels' blocks in one workspace
  (sweeps within 10000 ticks of each other; the FPGA sends them one after the other) are split
  instead of the workspace being dropped when it does not hold exactly 4 or 8 pulses;
- a block with fewer than 4 sensors gives the angles it has;
- a pulse without channel joins the block of a channel present in its workspace whose pulses are
  within :data:`BLOCK_SPAN` ticks and that lacks its sensor (the FPGA needs a second sensor to
  decode a block's bit stream, so the first pulse of nearly every block has no channel); when no
  pulse of the workspace has a channel, the block is placed by each channel's predicted rotor
  phase (below) if exactly one channel and plane fit the sensors' previous angles;
- each channel's rotor phase (``t0`` and the period in deck ticks) is tracked with an alpha-beta
  filter over the blocks' offsets: a block whose offsets disagree with the phase by more than
  :data:`PHASE_TOL` ticks (a mis-decoded bit stream: 0.1-0.3 % of offsets on the public logs, up to
  ±0.2 turn off) is rejected rather than giving 0.1-3 rad outliers, and a block with a channel but
  no offset takes the predicted ``t0`` (a block whose offset was rejected is dropped: its channel
  came from the same bit stream);
- a rotation with one plane only is still emitted (the other plane NaN): the joint solver uses
  single light-plane angles.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...io.systemconfig import LH2_CYCLE_PERIODS
from ..frames import DecodeStats

__all__ = ["LH2_CYCLE_PERIODS", "Rotation", "FirmwareLh2", "PhaseLh2", "plane_angles", "PROCESSORS", "MAX_TICKS_SENSOR_TO_SENSOR",
           "BLOCK_SPAN", "PHASE_TOL"]

#: pulses further apart than this (ticks) start a new workspace (firmware MAX_TICKS_SENSOR_TO_SENSOR)
MAX_TICKS_SENSOR_TO_SENSOR = 10000
#: firmware e9ff096 MAX_TICKS_BETWEEN_SWEEP_STARTS_TWO_BLOCKS (later firmware: 100)
FIRMWARE_PAIR_TOL = 10
FIRMWARE_WORKSPACE = 8
#: :class:`PhaseLh2`: a pulse without channel joins a block with a pulse within this many ticks
#: (0.031 rad of rotor: the 3 cm deck seen from >= 1 m spans < 0.03 rad)
BLOCK_SPAN = 2400
#: :class:`PhaseLh2`: largest disagreement (ticks) between a block's offsets and the tracked rotor
#: phase (offset quantum 4 ticks; |residual| median 2.5, 99 % < 20 on the public logs)
PHASE_TOL = 40
#: :class:`PhaseLh2`: two blocks are the two planes of one rotation when their t0 agree this well
PAIR_TOL = 40
#: :class:`PhaseLh2`: a predicted phase is used for at most this many rotations after its last update
PHASE_MAX_AGE_ROTATIONS = 25
#: :class:`PhaseLh2`: a block without channel (placed by phase) must match a sensor's previous angle
#: on that channel and plane within this (rad) and that angle must be at most 3 rotations old
PHASE_MATCH_RAD = 0.02


@dataclass(frozen=True)
class Rotation:
    """One rotation of one channel's rotor as the deck saw it.

    channel : LH2 channel 0-15. t0 : int/float deck ticks (unwrapped) of the rotor zero.
    offsets : (n, 2) float, 24 MHz ticks from the rotor zero to the light plane crossing each
    sensor (plane 0, plane 1); NaN where not measured. source : how t0 was found ("offset" or
    "phase").
    """

    channel: int
    t0: float
    offsets: np.ndarray
    source: str = "offset"


def plane_angles(offsets, channel: int) -> np.ndarray:
    """(..., 2) ticks since the rotor zero → the firmware's light-plane angles (rad): ``a0 = off0 2 pi / P
    - pi + pi/3``, ``a1 = off1 2 pi / P - pi - pi/3``, ``P`` = channel's cycle period (24 MHz ticks)."""
    P = LH2_CYCLE_PERIODS[channel]
    off = np.asarray(offsets, float)
    return off * (2 * np.pi / P) - np.pi + np.array([np.pi / 3, -np.pi / 3])


class FirmwareLh2:
    """``pulse_processor_v2.c`` at crazyflie-firmware e9ff096, pulse by pulse (module docstring).

    n_sensors : sensors of the output (the deck's blocks always need all 4). n_channels : channels
    whose blocks are paired (the firmware's PULSE_PROCESSOR_N_BASE_STATIONS was 2; 16 here).
    """

    name = "firmware"

    def __init__(self, n_sensors: int = 4, stats: DecodeStats | None = None, *, n_channels: int = 16):
        self.n = int(n_sensors)
        self.stats = DecodeStats() if stats is None else stats
        self.n_channels = int(n_channels)
        self._ws: list = []
        self._latest = None
        self._prev: dict = {}

    def push(self, sensor: int, ts: int, offset: int, channel) -> list:
        out: list = []
        if self._latest is not None and abs(ts - self._latest) > MAX_TICKS_SENSOR_TO_SENSOR:
            out = self._process()
            self._ws = []
        self._latest = ts
        if len(self._ws) < FIRMWARE_WORKSPACE:
            self._ws.append([sensor, channel, offset, ts])
        else:  # storePulse failed: the firmware clears the workspace (this pulse is lost too)
            self.stats.drop("LH2 workspace of more than 8 pulses (firmware clears it)", len(self._ws) + 1)
            self._ws = []
        return out

    def flush(self) -> list:
        out = self._process()
        self._ws = []
        return out

    def _process(self) -> list:
        ws = [list(p) for p in self._ws]
        if not ws:
            return []
        i = 0
        while i < len(ws) - 1:   # augmentFramesInWorkspace (e9ff096): one step, the donor is skipped
            if ws[i][1] is None and ws[i + 1][1] is not None:
                ws[i][1] = ws[i + 1][1]
                i += 1
            i += 1
        if len(ws) < 4 or len(ws) % 4:
            self.stats.drop("LH2 workspace not 4 or 8 pulses (firmware discards it)", len(ws))
            return []
        blocks = []
        for b in range(len(ws) // 4):
            blk, why = self._block(ws[4 * b:4 * b + 4])
            if blk is None:
                self.stats.drop(f"LH2 workspace with a block {why} (firmware discards it)", len(ws))
                return []
            blocks.append(blk)
        out = []
        for ch, t0, off in blocks:
            if ch >= self.n_channels or ch >= len(LH2_CYCLE_PERIODS):
                continue
            prev = self._prev.get(ch)
            if prev is not None and abs(t0 - prev[0]) <= FIRMWARE_PAIR_TOL:
                offs = np.full((self.n, 2), np.nan)
                for s in range(min(self.n, 4)):
                    offs[s] = prev[1][s], off[s]
                out.append(Rotation(ch, prev[0], offs))    # the stored block stays (as the firmware)
            else:
                if prev is not None:
                    self.stats.drop("LH2 first plane without its second (firmware replaces it)", 4)
                self._prev[ch] = (t0, off)
        return out

    @staticmethod
    def _block(slots):
        if {p[0] for p in slots} != {0, 1, 2, 3}:
            return None, "without all 4 sensors"
        chans = {p[1] for p in slots if p[1] is not None}
        if not chans:
            return None, "without a channel"
        if len(chans) > 1:
            return None, "with several channels"
        ref = [p for p in slots if p[2]]
        if not ref:
            return None, "without an offset"
        if len(ref) > 1:
            return None, "with several offsets"
        _, _, off_ref, ts_ref = ref[0]
        off = {p[0]: (off_ref if p is ref[0] else off_ref - (ts_ref - p[3])) for p in slots}
        return (chans.pop(), ts_ref - off_ref, off), None


class _Phase:
    """One channel's rotor phase: ``t0`` (ticks) and period (ticks), alpha-beta filtered."""

    ALPHA, BETA = 0.3, 0.05

    def __init__(self, t0: float, period: float):
        self.t0 = float(t0)
        self.period = float(period)
        self.nominal = float(period)
        self.n = 1
        self.misses = 0

    def near(self, t0: float) -> float:
        """The tracked rotor zero closest to ``t0``."""
        return self.t0 + round((t0 - self.t0) / self.period) * self.period

    def before(self, ts: float) -> float:
        """The tracked rotor zero at or before ``ts``."""
        return self.t0 + np.floor((ts - self.t0) / self.period) * self.period

    def age(self, ts: float) -> float:
        return (ts - self.t0) / self.period

    def update(self, t0: float) -> bool:
        """Fold a measured rotor zero in; False (and not folded in) when it disagrees by more than
        :data:`PHASE_TOL` (after 3 such in a row the phase restarts from the new one)."""
        k = round((t0 - self.t0) / self.period)
        r = t0 - (self.t0 + k * self.period)
        if abs(r) > PHASE_TOL:
            self.misses += 1
            if self.misses > 3 or self.n < 3:
                self.__init__(t0, self.nominal)
                return True
            return False
        self.misses = 0
        self.n += 1
        self.t0 = self.t0 + k * self.period + self.ALPHA * r
        if k:
            per = self.period + self.BETA * r / k
            if abs(per / self.nominal - 1) < 1e-3:
                self.period = per
        return True


class PhaseLh2:
    """LH2 pulse processing with per-channel rotor phase tracking (module docstring).

    n_sensors : sensors of the layout (pulses of other sensors are dropped). channels : the
    channels that may be present (default all 16; a pulse without channel is placed by phase only
    among channels already seen).
    """

    name = "phase"

    def __init__(self, n_sensors: int = 4, stats: DecodeStats | None = None, *, channels=None):
        self.n = int(n_sensors)
        self.stats = DecodeStats() if stats is None else stats
        self.channels = set(range(len(LH2_CYCLE_PERIODS)) if channels is None else channels)
        self._ws: list = []
        self._latest = None
        self._phase: dict = {}
        self._pending: dict = {}   # channel -> (t0, offsets (n,), source, ts of the block)
        self._last: dict = {}      # (channel, plane) -> (t0, offsets (n,))

    # -- workspaces --------------------------------------------------------------------------
    def push(self, sensor: int, ts: int, offset: int, channel) -> list:
        out: list = []
        if self._latest is not None and abs(ts - self._latest) > MAX_TICKS_SENSOR_TO_SENSOR:
            out = self._process()
        self._latest = ts
        if channel is not None and channel not in self.channels:
            self.stats.drop("LH2 pulse of a channel not in use")
            return out
        self._ws.append((int(sensor), int(ts), int(offset), channel))
        return out

    def flush(self) -> list:
        out = self._process()
        for ch in list(self._pending):
            out += self._emit_pending(ch)
        return out

    def _process(self) -> list:
        ws, self._ws = self._ws, []
        if not ws:
            return []
        blocks: dict = {}          # channel -> list of pulses
        loose = []
        for p in ws:
            (blocks.setdefault(p[3], []) if p[3] is not None else loose).append(p)
        known = dict(blocks)
        for p in loose:
            cands = [ch for ch, b in known.items()
                     if all(q[0] != p[0] for q in b) and min(abs(q[1] - p[1]) for q in b) <= BLOCK_SPAN]
            if len(cands) == 1:
                blocks[cands[0]].append(p)
            elif cands:
                # two channels' blocks both near: the firmware's rule (the next pulse's channel)
                nxt = next((q[3] for q in ws if q[1] > p[1] and q[3] is not None), None)
                if nxt in cands:
                    blocks[nxt].append(p)
                else:
                    self.stats.drop("LH2 pulse without channel near two channels' blocks")
            elif any(q[0] == p[0] and abs(q[1] - p[1]) <= BLOCK_SPAN for b in known.values() for q in b):
                # its sensor already has a decoded pulse in a block right here: a second hit the FPGA
                # could not decode (a reflection; lh2_crossingBeam_jitter/log04's sensor 1, 1.5 mrad early)
                self.stats.drop("LH2 second hit of a sensor without channel beside its decoded one (reflection?)")
            else:
                blocks.setdefault(None, []).append(p)
        out = []
        for ch in sorted(blocks, key=lambda c: min(q[1] for q in blocks[c])):
            b = blocks[ch]
            if ch is None:
                out += self._place_by_phase(b)
            else:
                out += self._block(ch, b)
        return out

    # -- blocks ------------------------------------------------------------------------------
    def _block(self, ch: int, pulses: list, t0_pred: float | None = None) -> list:
        seen: dict = {}
        for p in pulses:
            if p[0] in seen:   # the same sensor twice in one plane crossing: keep neither
                seen[p[0]] = None
            else:
                seen[p[0]] = p
        dup = [s for s, p in seen.items() if p is None]
        if dup:
            self.stats.drop("LH2 sensor hit twice in one block (reflection?)", sum(p[0] in dup for p in pulses))
        pulses = [p for p in seen.values() if p is not None]
        if not pulses:
            return []
        ts_first = min(p[1] for p in pulses)
        ph = self._phase.get(ch)
        t0s = [p[1] - p[2] for p in pulses if p[2]]
        t0, source = None, "offset"
        if t0s:
            t0m = float(np.median(t0s))
            if max(t0s) - min(t0s) > PHASE_TOL:
                # the block's own offsets disagree: keep the one(s) the tracked phase supports
                if ph is not None and ph.age(ts_first) < PHASE_MAX_AGE_ROTATIONS:
                    good = [v for v in t0s if abs(v - ph.near(v)) <= PHASE_TOL]
                    t0m = float(np.median(good)) if good else None
                else:
                    t0m = None
                if t0m is None:
                    self.stats.drop("LH2 block whose offsets disagree (mis-decoded bit stream)", len(pulses))
                    return []
            if ph is None:
                self._phase[ch] = ph = _Phase(t0m, LH2_CYCLE_PERIODS[ch])
                t0 = t0m
            elif ph.update(t0m):
                t0 = t0m
            else:
                self.stats.drop("LH2 block offset disagrees with the rotor phase (mis-decoded bit stream)",
                                len(pulses))
                return []
        if t0 is None:
            if t0_pred is not None:
                t0, source = t0_pred, "phase"
            elif ph is not None and ph.age(ts_first) < PHASE_MAX_AGE_ROTATIONS:
                t0, source = ph.before(ts_first), "phase"
            else:
                self.stats.drop("LH2 block without an offset and no recent rotor phase", len(pulses))
                return []
        offs = np.full(self.n, np.nan)
        for s, ts, _, _ in pulses:
            if s < self.n:
                offs[s] = ts - t0
            else:
                self.stats.drop("LH2 pulse of a sensor outside the layout")
        return self._pair(ch, float(t0), offs, source, ts_first)

    def _place_by_phase(self, pulses: list) -> list:
        """A block without any channel: the one channel whose predicted rotor phase puts each of its
        pulses within :data:`PHASE_MATCH_RAD` of that sensor's previous angle (<= 3 rotations old)."""
        fits = []
        for ch, ph in self._phase.items():
            ts0 = min(p[1] for p in pulses)
            if ph.age(ts0) > PHASE_MAX_AGE_ROTATIONS:
                continue
            t0 = ph.before(ts0)
            f = (ts0 - t0) / ph.period
            plane = 0 if f < 0.5 else 1
            last = self._last.get((ch, plane))
            if last is None or (t0 - last[0]) > 3.5 * ph.period:
                continue
            ok, n = True, 0
            for s, ts, _, _ in pulses:
                if s >= self.n or not np.isfinite(last[1][s]):
                    continue
                a_new = plane_angles(np.array([ts - t0, ts - t0]), ch)[plane]
                a_old = plane_angles(np.array([last[1][s], last[1][s]]), ch)[plane]
                n += 1
                ok &= abs(a_new - a_old) <= PHASE_MATCH_RAD
            if ok and n:
                fits.append((ch, t0))
        if len(fits) != 1:
            self.stats.drop("LH2 block without channel that no single channel's rotor phase explains"
                            if not fits else "LH2 block without channel that several channels' phases explain",
                            len(pulses))
            return []
        return self._block(fits[0][0], pulses, t0_pred=fits[0][1])

    # -- planes → rotations ------------------------------------------------------------------
    def _pair(self, ch: int, t0: float, offs: np.ndarray, source: str, ts: float) -> list:
        """A plane block → a rotation (as the firmware: the first block of a rotor zero waits, the
        next block of the channel with the same rotor zero within :data:`PAIR_TOL`, crossing 0.05-0.62
        turn later (the planes are a third of a turn apart, +/- the elevation), is its second plane). A block left alone is emitted by itself, its plane from where it falls in the rotation
        (:meth:`_lone_plane`). Each plane's offsets stay relative to its own block's ``t0`` (as the
        firmware); the rotation's ``t0`` is plane 0's."""
        pend = self._pending.pop(ch, None)
        P = LH2_CYCLE_PERIODS[ch]
        if pend is not None and abs(t0 - pend[0]) <= PAIR_TOL and 0.05 < (ts - pend[3]) / P < 0.62:
            rot = np.stack([pend[1], offs], -1)
            self._remember(ch, pend[0], rot)
            return [Rotation(ch, pend[0], rot, pend[2] if pend[2] == source else "phase")]
        out = []
        if pend is not None:
            self._pending[ch] = pend
            out += self._emit_pending(ch)
        if (ts - t0) / P > 7 / 12:    # past any plane-0 crossing: plane 1 alone
            out += self._lone(ch, t0, offs, source, 1)
        else:
            self._pending[ch] = (t0, offs, source, ts)
        return out

    def _emit_pending(self, ch: int) -> list:
        t0, offs, source, ts = self._pending.pop(ch)
        plane = self._lone_plane(ch, t0, offs, ts)
        if plane is None:
            self.stats.drop("LH2 lone block that could be either light plane", int(np.isfinite(offs).sum()))
            return []
        return self._lone(ch, t0, offs, source, plane)

    def _lone(self, ch, t0, offs, source, plane) -> list:
        rot = np.full((self.n, 2), np.nan)
        rot[:, plane] = offs
        self._remember(ch, t0, rot)
        return [Rotation(ch, t0, rot, source)]

    def _lone_plane(self, ch, t0, offs, ts):
        """The plane of a block without its pair: plane 0 crosses at 1/12-7/12 of the rotation
        (angles -90°..90°), plane 1 at 5/12-11/12; in the overlap the plane whose previous offsets
        of these sensors are closer (within 1/24 turn), else None."""
        P = LH2_CYCLE_PERIODS[ch]
        f = (ts - t0) / P
        if f < 5 / 12:
            return 0
        if f > 7 / 12:
            return 1
        best, plane = P / 24, None
        for k in (0, 1):
            last = self._last.get((ch, k))
            if last is None:
                continue
            d = np.abs(offs - last[1])
            if np.isfinite(d).any() and np.nanmedian(d) < best:
                best, plane = float(np.nanmedian(d)), k
        return plane

    def _remember(self, ch, t0, rot):
        """The latest offsets of each sensor per channel and plane (for placing blocks by phase)."""
        recent = 3.5 * LH2_CYCLE_PERIODS[ch]
        for k in (0, 1):
            if np.isfinite(rot[:, k]).any():
                prev = self._last.get((ch, k))
                keep = rot[:, k].copy()
                if prev is not None and t0 - prev[0] < recent:
                    keep = np.where(np.isfinite(keep), keep, prev[1])
                self._last[(ch, k)] = (t0, keep)


#: LH2 pulse processors by name (the ``pulse_processor`` option of ``bitcraze-lh2``)
PROCESSORS = {"phase": PhaseLh2, "firmware": FirmwareLh2}
