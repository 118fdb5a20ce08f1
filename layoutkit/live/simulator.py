"""Hardware simulator: the bytes an FPGA timestamp board would send, plus the true poses.

Timing model (LH1, docs/live-io.md): the stations' rotors run at ``rotor_rpm``; sweep slots of
half a rotor turn (8.333 ms at 3600 rpm) cycle through ``(station 0, X), (station 0, Y),
(station 1, X), ...``. Slot k's sync happens at the device counter value
``sync_k = round((t_first + k * slot) * clock_hz)``; its time is ``t_k = sync_k / clock_hz`` —
exactly the decoder's time base (device counter since power-up, the simulator's t = 0).
**Every sweep's angles come from the body pose at that sweep's sync time t_k**, and the truth
holds one row per sweep at the same t_k, so pose and truth are aligned exactly whatever the
pipeline pairs. Noise: :func:`layoutkit.noise.sample_angle_noise` per sweep (rho correlates
same-axis angles within one sweep), then rounding to counter ticks (the quantisation).
A sensor is lit when its normal is within ``cone_deg`` (60°) of the direction to the station
and the point is in the station's field of view; ``dropout`` removes lit hits at random,
``frame_loss`` drops whole frames (the sequence number still advances), ``garbage`` inserts
random bursts between frames.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..geometry import matrix_to_rotvec, random_rotations, rotvec_to_matrix
from ..lighthouse import Station, lh2_sweep_angles, measure, sweep_angles
from ..noise import sample_angle_noise
from ..units import RHO_PAPER, SIGMA_THETA_PAPER

__all__ = [
    "Trajectory",
    "SimulatedSweeps",
    "tumble_trajectory",
    "static_trajectory",
    "load_trajectory",
    "lit_sensors",
    "simulate_sweeps",
    "simulate_stream",
    "write_truth",
    "run_fake_fpga",
    "TRUTH_HEADER",
]

#: Header of TRUTH.csv: the pose table's columns (:data:`layoutkit.io.poses.POSE_COLUMNS`).
TRUTH_HEADER = "t,station,status,rx,ry,rz,tx,ty,tz,residual_rms"
MAX_RATE_RAD_S = np.deg2rad(0.5)  # tumble angular rate bound
MAX_SPEED_M_S = 1e-3  # tumble translation speed bound


@dataclass(frozen=True)
class Trajectory:
    """Body pose in the world frame (station 0's frame in the default set-up) as a function of time.

    times : (P,) s increasing; rotvecs : (P, 3) rad; translations : (P, 3) m. Between samples:
    rotation by spherical linear interpolation, translation linear; held outside the range.
    """

    times: np.ndarray
    rotvecs: np.ndarray
    translations: np.ndarray

    def __call__(self, t) -> tuple[np.ndarray, np.ndarray]:
        """Poses at times ``t`` (K,) → rotation matrices (K, 3, 3), translations (K, 3)."""
        from scipy.spatial.transform import Rotation, Slerp

        t = np.atleast_1d(np.asarray(t, float))
        if len(self.times) == 1:
            R = np.broadcast_to(rotvec_to_matrix(self.rotvecs[0]), (t.size, 3, 3)).copy()
            return R, np.broadcast_to(self.translations[0], (t.size, 3)).copy()
        tc = np.clip(t, self.times[0], self.times[-1])
        R = Slerp(self.times, Rotation.from_rotvec(self.rotvecs))(tc).as_matrix()
        tr = np.stack([np.interp(tc, self.times, self.translations[:, i]) for i in range(3)], -1)
        return R, tr


@dataclass(frozen=True)
class _SineTumble:
    """``R(t) = exp(phi(t)) R0``, ``phi_i = A sin(w_i t + p_i)``; ``c(t) = c0 + B_i sin(v_i t + q_i)``."""

    R0: np.ndarray
    amp: float
    w: np.ndarray
    p: np.ndarray
    c0: np.ndarray
    B: np.ndarray
    v: np.ndarray
    q: np.ndarray

    def __call__(self, t):
        t = np.atleast_1d(np.asarray(t, float))[:, None]
        phi = self.amp * np.sin(self.w * t + self.p)
        R = rotvec_to_matrix(phi) @ self.R0
        return R, self.c0 + self.B * np.sin(self.v * t + self.q)


def lit_sensors(layout, R, t, station: Station | None = None, *, cone_deg: float = 60.0) -> np.ndarray:
    """Which sensors a station sees: (K, n) bool for body poses R (K, 3, 3), t (K, 3) in the world.

    Lit = normal within ``cone_deg`` of the direction from the sensor to the station centre and
    the sensor inside the station's field of view (no self-occlusion model).
    """
    from ..visibility import facing_mask

    station = station or Station()
    Rs, ts = station.world_to_station(R, t)
    return facing_mask(layout.positions, layout.normals, Rs, ts, half_angle_deg=cone_deg, fov_deg=station.fov_deg)


def tumble_trajectory(layout, duration: float, rng: np.random.Generator, *, station: Station | None = None,
                      distance: tuple = (1.5, 3.0), amplitude_deg: float = 25.0, min_lit: int = 4,
                      max_rate: float = MAX_RATE_RAD_S, max_speed: float = MAX_SPEED_M_S):
    """A slow tumble in front of ``station`` with ``min_lit`` sensors lit throughout (when possible).

    Base attitude: the one of 512 random rotations that lights the most sensors (ties: the most
    balanced). Attitude ``exp(phi(t)) R0`` with ``phi_i = A sin(w_i t + p_i)``, rate bound
    ``|phi'| <= max_rate`` (0.5°/s); centre drifting within ``distance`` (1.5-3 m) at
    ``<= max_speed`` (1 mm/s). The amplitude is halved until ``min_lit`` holds on a 1 s grid.
    Returns a callable ``t (K,) -> (R (K,3,3), t (K,3))``.
    """
    station = station or Station()
    dmin, dmax = distance
    d = rng.uniform(dmin + 0.25 * (dmax - dmin), dmax - 0.25 * (dmax - dmin))
    lateral = rng.uniform(-0.15, 0.15, 2) * d
    c_st = np.array([lateral[0], lateral[1], d])
    c0 = station.rotation @ c_st + station.translation
    cands = random_rotations(512, rng)
    lit = lit_sensors(layout, cands, np.broadcast_to(c0, (512, 3)), station)
    score = lit.sum(1) * 1000 - np.abs(lit.sum(1) - layout.n / 2)
    R0 = cands[int(np.argmax(score))]
    B = np.array([0.1 * d, 0.1 * d, 0.2 * (dmax - dmin)])
    w_dir = rng.uniform(0.6, 1.0, 3)
    v_dir = rng.uniform(0.6, 1.0, 3)
    v = v_dir * max_speed / np.linalg.norm(B * v_dir)
    p, q = rng.uniform(0, 2 * np.pi, 3), rng.uniform(0, 2 * np.pi, 3)
    grid = np.arange(0.0, max(duration, 1.0) + 1.0, 1.0)
    amp = np.deg2rad(amplitude_deg)
    for _ in range(6):
        w = w_dir * max_rate / (amp * np.linalg.norm(w_dir))
        motion = _SineTumble(R0, amp, w, p, c0, B, v, q)
        R, t = motion(grid)
        if lit_sensors(layout, R, t, station).sum(1).min() >= min_lit:
            return motion
        amp /= 2
    return motion


def static_trajectory(layout, rng: np.random.Generator, *, station: Station | None = None,
                      distance: tuple = (1.5, 3.0)) -> Trajectory:
    """One fixed pose chosen like the tumble's base pose."""
    m = tumble_trajectory(layout, 1.0, rng, station=station, distance=distance)
    R, t = m(np.zeros(1))
    return Trajectory(np.zeros(1), matrix_to_rotvec(R), t)



def spin_motion(rate_deg_s: float, speed_m_s: float, axis=(0.3, 0.2, 1.0), amplitude_m: float = 0.3):
    """A fast test motion: constant rotation ``rate_deg_s`` about a fixed axis (station frame,
    through the body origin), top face towards the station ~2 m away; translation
    ``amplitude_m sin(f t)`` along a fixed direction with peak speed ``speed_m_s``.
    Returns ``motion(t (K,)) -> (R (K, 3, 3), t (K, 3))`` (body pose in the station frame, m)."""
    ax = np.asarray(axis, float) / np.linalg.norm(axis)
    d = np.array([1.0, 0.3, 0.5]) / np.linalg.norm([1.0, 0.3, 0.5])
    w, f = np.deg2rad(rate_deg_s), speed_m_s / amplitude_m
    R0 = rotvec_to_matrix(np.array([np.pi, 0.0, 0.0]))

    def motion(t):
        t = np.atleast_1d(np.asarray(t, float))
        return rotvec_to_matrix(ax * (w * t)[:, None]) @ R0, np.array([0.1, 0.05, 2.0]) + np.outer(
            amplitude_m * np.sin(f * t), d)

    return motion

def load_trajectory(path) -> Trajectory:
    """Read a pose table (:func:`layoutkit.io.poses.read_poses`: ``t,rx,ry,rz,tx,ty,tz`` at least;
    s, rad — or ``rx_deg`` columns —, m) as a :class:`Trajectory`, sorted by time."""
    from ..io.poses import read_poses

    tb = read_poses(path, min_rows=1)
    order = np.argsort(tb.t, kind="stable")
    return Trajectory(tb.t[order], tb.rotvec[order], tb.translation[order])


@dataclass(frozen=True)
class SimulatedSweeps:
    """Every simulated sweep (K of them), emitted or not.

    t : (K,) s sync time (device time base); station, axis, seq : (K,) int;
    kind : tuple of "lh1"/"lh2" per station; rotvec, translation : (K, 3) true body pose in the
    world frame at t; angles_true : (K, n) rad noise-free (NaN unlit); hits : (K, n) int64 counter
    ticks after sync (layoutkit.NO_HIT = not hit); sync : (K,) int64 unwrapped counter;
    emitted : (K,) bool (False = frame lost); lit : (K, n) bool (before dropout).
    """

    t: np.ndarray
    station: np.ndarray
    axis: np.ndarray
    seq: np.ndarray
    rotvec: np.ndarray
    translation: np.ndarray
    angles_true: np.ndarray
    hits: np.ndarray
    sync: np.ndarray
    emitted: np.ndarray
    lit: np.ndarray
    stations: tuple = ()
    clock_hz: float = 50e6
    info: dict = field(default_factory=dict)

    def measured_angles(self) -> np.ndarray:
        """(K, n) rad: the angles a decoder returns (from the quantised hit ticks), NaN = no hit."""
        from .protocols.layoutkit import NO_HIT

        out = np.full(self.hits.shape, np.nan)
        for s, st in enumerate(self.stations):
            m = self.station == s
            h = self.hits[m].astype(float)
            a = h * (2 * np.pi * st.rotor_rpm / 60.0) / self.clock_hz - (np.pi if st.kind == "lh2" else 0.0)
            out[m] = np.where(self.hits[m] == NO_HIT, np.nan, a)
        return out


def simulate_sweeps(layout, *, duration: float, seed: int = 0, motion="tumble", stations=None,
                    sigma: float = SIGMA_THETA_PAPER, rho: float = RHO_PAPER,
                    clock_hz: float = 50e6, dropout: float = 0.0, frame_loss: float = 0.0,
                    cone_deg: float = 60.0, t_first: float = 0.01) -> SimulatedSweeps:
    """Simulate every sweep of ``duration`` s (see the module docstring for the model).

    layout : :class:`layoutkit.layout.Layout`. motion : "tumble", "static", a :class:`Trajectory`
    or a callable ``t (K,) -> (R (K,3,3), t (K,3))`` giving the body pose in the world frame.
    stations : sequence of :class:`Station` (default one LH1 station at the world origin); a station
    with a calibration reports its forward model's (distorted) angles, :func:`layoutkit.lighthouse.measure`.
    sigma : rad, rho : same-sweep correlation (Chen eq. 19). The hit counters are whole clock
    ticks (the quantisation); ``angles_true`` keeps the exact noise-free angles.
    """
    from .protocols.layoutkit import NO_HIT

    rng = np.random.default_rng(seed)
    stations = tuple(stations) if stations else (Station(clock_hz=clock_hz),)
    if duration <= 0:
        raise ValueError(f"duration: expected > 0 s, got {duration}")
    if not 0 <= dropout <= 1 or not 0 <= frame_loss <= 1:
        raise ValueError("dropout and frame_loss: expected probabilities in [0, 1]")
    if isinstance(motion, str):
        if motion == "tumble":
            motion = tumble_trajectory(layout, duration, rng, station=stations[0], min_lit=4)
        elif motion == "static":
            motion = static_trajectory(layout, rng, station=stations[0])
        else:
            raise ValueError(f"motion: expected 'tumble', 'static', a Trajectory or a callable, got {motion!r}")
    slot = 60.0 / stations[0].rotor_rpm / 2.0
    K = int(np.floor(duration / slot))
    k = np.arange(K)
    S = len(stations)
    sid = (k // 2) % S
    axis = k % 2
    sync = np.round((t_first + k * slot) * clock_hz).astype(np.int64)
    t = sync / clock_hz
    R, tr = motion(t)
    n = layout.n
    angles = np.full((K, n), np.nan)
    lit = np.zeros((K, n), bool)
    for s, st in enumerate(stations):
        m = sid == s
        lit[m] = lit_sensors(layout, R[m], tr[m], st, cone_deg=cone_deg)
        Rs, ts = st.world_to_station(R[m], tr[m])
        p = np.einsum("kij,nj->kni", Rs, layout.positions) + ts[:, None, :]
        if st.calibration is not None:  # the distorted angles a station with these parameters reports
            a = measure(p, st.calibration)
        else:
            a = lh2_sweep_angles(p) if st.kind == "lh2" else sweep_angles(p)
        angles[m] = np.take_along_axis(a, axis[m][:, None, None], -1)[..., 0]
    angles_true = np.where(lit, angles, np.nan)
    noise = sample_angle_noise((K, n), sigma, rho, rng)
    noisy = angles + np.take_along_axis(noise, axis[:, None, None], -1)[..., 0]
    omega = np.array([2 * np.pi * st.rotor_rpm / 60.0 for st in stations])[sid][:, None]
    offset = np.array([np.pi if st.kind == "lh2" else 0.0 for st in stations])[sid][:, None]
    ticks = np.round((noisy + offset) / omega * clock_hz)
    keep = lit & (rng.random((K, n)) >= dropout) & (ticks >= 0) & (ticks < NO_HIT)
    hits = np.where(keep, np.round(ticks), NO_HIT).astype(np.int64)
    emitted = rng.random(K) >= frame_loss
    info = {"slot_s": slot, "sigma": sigma, "rho": rho, "dropout": dropout, "frame_loss": frame_loss,
            "seed": seed, "cone_deg": cone_deg}
    return SimulatedSweeps(t, sid, axis, k & 0xFFFF, matrix_to_rotvec(R), tr, angles_true, hits, sync,
                           emitted, lit, stations, clock_hz, info)


def simulate_stream(layout, *, duration: float, seed: int = 0, protocol: str = "layoutkit",
                    garbage: float = 0.0, **kwargs):
    """Simulated device output: ``(chunks, sweeps)``.

    chunks : list of ``(t_emit, bytes)``, one per emitted frame, ``t_emit`` = end of the sweep's
    slot (s, device time base), in time order; with ``garbage`` > 0 a random burst of 1-48 bytes
    precedes a frame with that probability. sweeps : :class:`SimulatedSweeps` (the truth).
    protocol : a registered protocol with an encoder (:data:`layoutkit.live.protocols.PROTOCOLS`):
    "layoutkit", or "bitcraze-lh1" (the Lighthouse deck stream, <= 4 sensors, 24 MHz
    timestamps: each sweep re-quantised to the deck clock; station 1's sync and angles refer to
    10000 ticks = 0.42 ms after the slot start, while its truth row stays at the slot start).
    Other keyword arguments go to :func:`simulate_sweeps`.
    """
    if not 0 <= garbage <= 1:
        raise ValueError(f"garbage: expected a probability in [0, 1], got {garbage}")
    sw = simulate_sweeps(layout, duration=duration, seed=seed, **kwargs)
    frames = encode_frames(sw, protocol)
    rng = np.random.default_rng([seed, 1])
    slot = sw.info["slot_s"]
    chunks = []
    junk = rng.random(len(frames)) < garbage
    for k in range(len(frames)):
        data = frames[k]
        if data is None:
            continue  # nothing on the wire (a lost layoutkit frame; the deck stream keeps its syncs)
        if junk[k]:
            data = rng.integers(0, 256, int(rng.integers(1, 49)), dtype=np.uint8).tobytes() + data
        chunks.append((float(sw.t[k] + slot), data))
    return chunks, sw


def encode_frames(sw: SimulatedSweeps, protocol: str = "layoutkit") -> list:
    """The wire bytes of every sweep in ``protocol`` (None = nothing sent for that sweep), through
    the protocol's registry entry (:meth:`~layoutkit.live.protocols.ProtocolEntry.encode`)."""
    from .protocols import protocol_entry

    return protocol_entry(protocol).encode(sw)


def write_truth(sw: SimulatedSweeps, path, tie=None) -> None:
    """TRUTH.csv: a pose table (:mod:`layoutkit.io.poses`), one row per sweep (emitted or not) at
    its sync time, ``station`` = the sweeping station, status 0, residual_rms NaN. tie : the
    emitted stream's :class:`layoutkit.io.runtie.StreamTie`, recorded on the file's last line
    (``# layoutkit-run {...}``) so that ``replay --truth`` can tell which capture it belongs to."""
    from ..io.poses import PoseTable
    from ..io.runtie import write_tied_poses

    write_tied_poses(path, PoseTable(sw.t, sw.rotvec, sw.translation, station=sw.station), tie)


def run_fake_fpga(chunks, *, out=None, realtime: bool | None = None, link=None, on_ready=None,
                  drain_timeout: float = 5.0, speed: float = 1.0, sidecar: dict | None = None,
                  wait_reader: float | None = None, overwrite: bool = False, stop=None) -> dict:
    """Emit ``chunks`` ``[(t_emit, bytes), ...]`` into a capture file or a pseudo-terminal.

    out : capture path → written with :class:`CaptureWriter` (index times = t_emit, sidecar
    ``sidecar``; an existing capture is refused unless ``overwrite``), as fast as possible unless ``realtime``. Without ``out``: opens a pty (raw mode),
    calls ``on_ready(slave_path)`` (and makes symlink ``link`` → slave path), waits until a reader
    opens the port (at most ``wait_reader`` s; None = forever; opening a serial port flushes its
    input, so nothing is sent before), then writes each chunk at its time (``realtime`` default
    True; late chunks are sent at once, so nothing is dropped when the reader is slow), waits
    until the reader drained the pty, and closes it (the reader then sees the device vanish).
    stop : a :class:`layoutkit.live.stopping.StopRequest` checked while waiting and between chunks:
    when set, emitting ends there (the capture closed, the pty link removed and the pty closed).
    Returns a summary dict (bytes, chunks, ``chunks_sent``, wall time, path, ``stopped_by``: the
    stop signal's name or None).
    """
    import time

    from .capture import CaptureWriter

    t_wall0 = time.monotonic()
    t0 = chunks[0][0] if chunks else 0.0
    total = 0
    sent = 0

    def stopped() -> bool:
        return stop is not None and stop.requested

    def summary(path) -> dict:
        return {"path": str(path), "bytes": total, "chunks": len(chunks), "chunks_sent": sent,
                "wall_s": time.monotonic() - t_wall0, "stopped_by": stop.name if stopped() else None}

    if out is not None:
        realtime = bool(realtime)
        with CaptureWriter(out, sidecar or {}, overwrite=overwrite) as w:
            for t_emit, data in chunks:
                if realtime:
                    _sleep_until(t_wall0 + (t_emit - t0) / speed, stop)
                if stopped():
                    break
                w.write(data, t_emit)
                total += len(data)
                sent += 1
        return summary(out)

    import os
    import select
    import termios
    import tty

    realtime = True if realtime is None else bool(realtime)
    master, slave = os.openpty()
    tty.setraw(slave)
    # Mark the line settings: a reader that configures the port (pyserial does, then flushes its
    # input) changes VTIME, and the master sees the slave's settings — so we know when it is safe.
    attrs = termios.tcgetattr(slave)
    attrs[6][termios.VTIME] = _VTIME_MARK
    termios.tcsetattr(slave, termios.TCSANOW, attrs)
    path = os.ttyname(slave)
    os.close(slave)  # so that POLLHUP on the master tells whether a reader has the port open
    if link is not None:
        link = Path(link)
        tmp = link.with_name(link.name + ".tmp")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(path)
        os.replace(tmp, link)
    if on_ready is not None:
        on_ready(path)
    poll = select.poll()
    poll.register(master, select.POLLHUP)

    def reader_present(timeout_ms=0):
        return not any(ev & select.POLLHUP for _, ev in poll.poll(timeout_ms))

    try:
        t_wait = time.monotonic()
        while not reader_present(50):  # a reader opening the port flushes its input: wait for it
            if stopped():
                return summary(path)
            if wait_reader is not None and time.monotonic() - t_wait > wait_reader:
                raise TimeoutError(f"no reader opened {path} within {wait_reader:g} s (--wait-reader)")
        t_cfg = time.monotonic()  # wait for the reader to configure the port (at most 2 s: `cat` never does)
        while termios.tcgetattr(master)[6][termios.VTIME] == _VTIME_MARK and time.monotonic() - t_cfg < 2.0:
            time.sleep(0.005)
        time.sleep(0.05)  # pyserial flushes the input right after configuring
        os.set_blocking(master, False)
        t_wall0 = time.monotonic()
        for t_emit, data in chunks:
            if realtime:
                _sleep_until(t_wall0 + (t_emit - t0) / speed, stop)
            if stopped():
                break
            view = memoryview(data)
            away_since = None
            while view:
                try:
                    k = os.write(master, view)
                except BlockingIOError:  # reader slow or away: the pty buffer is full, wait
                    if stopped():  # (a frame already begun is otherwise always finished)
                        break
                    if reader_present():
                        away_since = None
                    elif away_since is None:
                        away_since = time.monotonic()
                    elif time.monotonic() - away_since > READER_GONE_S:
                        raise ReaderGone(f"the reader of {path} closed the port {READER_GONE_S:.0f} s ago "
                                         f"with the buffer full; stopped after {total} bytes") from None
                    time.sleep(0.005)
                    continue
                view = view[k:]
                total += k
            if view:
                break  # stopped with the reader blocked
            sent += 1
        # what was written reaches the reader before the port goes away (a stop: at most 2 s)
        _drain(path, min(drain_timeout, 2.0) if stopped() else drain_timeout)
    finally:
        # Unplugged: the device node goes away first (a reader reconnecting through the link must
        # not reopen this pty's number, which the system may already have given to another pty).
        if link is not None:
            try:
                if os.readlink(link) == path:
                    link.unlink()
            except OSError:
                pass
        os.close(master)
    return summary(path)


_VTIME_MARK = 77  # deciseconds; no reader sets this value
READER_GONE_S = 10.0  # a full pty with no reader for this long: the reader is gone for good


class ReaderGone(RuntimeError):
    """The pty's reader went away and the simulator cannot deliver more bytes."""


def _sleep_until(t_wall: float, stop=None) -> None:
    """Sleep until monotonic time ``t_wall`` (in steps of <= 0.1 s while a ``stop`` may come)."""
    import time

    while True:
        dt = t_wall - time.monotonic()
        if dt <= 0 or (stop is not None and stop.requested):
            return
        time.sleep(dt if stop is None else min(dt, 0.1))


def _drain(path: str, timeout: float) -> None:
    """Wait until the pty's input queue (bytes not yet read by the reader) is empty."""
    import fcntl
    import os
    import struct
    import termios
    import time

    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
    except OSError:
        return
    try:
        end = time.monotonic() + timeout
        quiet = 0
        while time.monotonic() < end and quiet < 3:  # bytes reach the slave asynchronously
            time.sleep(0.05)
            waiting = struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0]
            quiet = quiet + 1 if waiting == 0 else 0
    except OSError:
        pass
    finally:
        os.close(fd)
