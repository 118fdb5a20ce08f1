"""Simulated Crazyflie microSD logs with known truth, written in the real cfusdlog format
(``cf_helpers.write_cfusdlog``) beside a cflib system-config YAML, with the conventions of the real
logs (``cf_helpers`` docstring):

- :func:`simulate_events`: the firmware's sweep-angle events (``lhAngle``, or the estimator's
  ``estSweepAngle``), LH1 or LH2, logged in bursts when a station completes, sensor by sensor
  (sensor, station, sweep); in crossing-beam mode station 0's angles logged again, bit for bit, in
  station 1's burst; LH1 bursts hold a station's X and Y angles, logged one frame after its Y sweep;
  LH1 logs also carry ``lhUartFrame`` events that all say "no channel" (the deck sends LH1 pulses
  without a channel; the widths that tell sync from sweep pulses are not logged).
- :func:`simulate_uart_log`: LH2 deck pulses (``lhUartFrame``: no channel on each block's first
  pulse, one offset per block, the log clock at -1.094 % and the UART queue) and the firmware's
  ``lhAngle`` bursts of the rotations it accepts (``cf_helpers.simulate_lh2_log``).

The deck (4 sensors, 3 x 1.5 cm) ~3 m from two calibrated stations (``_cf_joint_sim``). Each angle
is the calibrated forward model (:func:`layoutkit.lighthouse.measure`, the true calibration) of the
deck at the time the light crosses it, plus N(0, sigma²) noise, logged as float32 in the firmware's
convention (LH1 ``pi/2 - theta``, LH2 light-plane angles) with the firmware's calibrated angle
(5-step inverse) as ``correctedAngle``. Truth motion is a function of the log clock.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from _cf_joint_sim import DECK, STATION_POS, TARGET, factory_calibrations, static_motion
from cf_helpers import ANGLE_VARS, LOG_RATE, NO_CHANNEL, UART_VARS, simulate_lh2_log, write_cfusdlog

from layoutkit.io.systemconfig import LH2_CYCLE_PERIODS, system_config_dict
from layoutkit.layout import load_layout
from layoutkit.lighthouse import lh2_to_lh1_angles, measure, undistort
from layoutkit.simulate import stations_looking_at

LHANGLE = ANGLE_VARS
ESTSWEEP = [("sensorId", "B"), ("basestationId", "B"), ("sweepId", "B"), ("t", "f"), ("sweepAngle", "f")]
ESTPOS = [("x", "f"), ("y", "f"), ("z", "f")]
FIXED = [("stateEstimate.x", "f"), ("stateEstimate.y", "f"), ("stateEstimate.z", "f")]
LH1_FRAME_S = 1.0 / 120.0


def _setup(kind, rng):
    lay = load_layout(DECK)
    cals = factory_calibrations(rng)
    stations = stations_looking_at(STATION_POS, TARGET, kind=kind,
                                   calibrations=[cals[k].to_calibration(kind) for k in range(2)])
    return lay, cals, stations


def _plane_angles(st, motion, P_body, starts, P):
    """LH2: measured plane angles (R, 4, 2) of rotations starting at ``starts`` (R,) s (log clock),
    period P s; each sensor measured when the plane crosses it (two fixed-point steps)."""
    out = []
    for k, shift in ((0, -np.pi / 3), (1, np.pi / 3)):
        tc = starts[:, None] + np.full((1, 4), (np.pi + shift) / (2 * np.pi) * P)
        for _ in range(2):
            R, c = motion(tc.reshape(-1))
            Rs, ts = st.world_to_station(R, c)
            p = (np.einsum("kij,nj->kni", Rs, P_body) + ts[:, None, :]).reshape(len(starts), 4, 4, 3)
            p = p[:, np.arange(4), np.arange(4)]                  # sensor i at its own time
            a = measure(p, st.calibration)[..., k]                # (R, 4)
            tc = starts[:, None] + (a + np.pi + shift) / (2 * np.pi) * P
        out.append((a, tc))
    return np.stack([out[0][0], out[1][0]], -1), np.stack([out[0][1], out[1][1]], -1)


def _bursts(completions, mode):
    """completions: list of (t_event, station, raw (4, 2), corrected (4, 2), tilt (2,)) in time order →
    event rows sensor by sensor over the stations held (crossing_beam: station 0 held until station 1
    completes or one cycle passes; kalman: none held), and the number of stale frames logged."""
    rows, held, repeats = [], {}, 0
    for te, s, raw, cor, tilt, per in completions:
        held = {c: h for c, h in held.items() if te - h[0] <= h[4]}       # the firmware's stale timeout
        held[s] = (te, raw, cor, tilt, per)
        repeats += len(held) - 1
        t = te
        for i in range(4):
            for c in sorted(held):
                for w in range(2):
                    if np.isfinite(held[c][1][i, w]):
                        rows.append((t, c, i, w, held[c][1][i, w], held[c][2][i, w], held[c][3][w]))
                        t += 1e-5
        if mode == "kalman":
            del held[s]
        elif s == 1:
            held.clear()
    return rows, repeats


def simulate_events(kind="lh2", *, seed=1, duration=4.0, sigma=4e-5, motion=None, latency=3e-4, t0=12.5,
                    mode="crossing_beam"):
    """Returns a dict: stations (true calibrations), cals (firmware convention, for the YAML), layout,
    motion, rows = list of (t_event, station, sensor, sweep, raw angle, corrected angle, tilt) in log
    order, fresh = list of (station, raw (4, 2)) of the new frames in log order, repeats (stale frames
    logged again), kind, sigma, mode. LH2 bursts at the second plane's last crossing + ``latency``;
    LH1 A/B frames of 8.33 ms (A-X, A-Y, B-X, B-Y), bursts one frame after the Y sweep's sync +
    ``latency``."""
    rng = np.random.default_rng(seed)
    lay, cals, stations = _setup(kind, rng)
    P_body = lay.positions
    motion = static_motion() if motion is None else motion
    comp = []
    if kind == "lh2":
        for s, st in enumerate(stations):
            P = LH2_CYCLE_PERIODS[s] / 24e6
            starts = t0 + P * s / 2.7 + P * np.arange(int(duration / P))
            a, tc = _plane_angles(st, motion, P_body, starts, P)
            raw = (a + rng.normal(0, sigma, a.shape)).astype(np.float32).astype(float)
            cor = undistort(raw, st.calibration)
            for r in range(len(starts)):
                comp.append((float(tc[r, :, 1].max() + latency), s, raw[r], cor[r], np.array([-1, 1]) * np.pi / 6, P))
    else:
        nf = int(duration / LH1_FRAME_S)
        order = [(0, 0), (0, 1), (1, 0), (1, 1)]
        held = {}
        for f in range(nf):
            s, ax = order[f % 4]
            ts_ = t0 + f * LH1_FRAME_S
            R, c = motion(np.array([ts_]))
            Rs, tt = stations[s].world_to_station(R, c)
            p = np.einsum("kij,nj->kni", Rs, P_body) + tt[:, None, :]
            th = measure(p, stations[s].calibration)[0]                                  # (4, 2) ours, distorted
            fw = (np.pi / 2 - th[:, ax] + rng.normal(0, sigma, 4)).astype(np.float32).astype(float)
            if ax == 0:
                held[s] = fw
                continue
            if s not in held:
                continue
            raw = np.stack([held.pop(s), fw], -1)
            cor = np.pi / 2 - undistort(np.pi / 2 - raw, stations[s].calibration)
            comp.append((ts_ + LH1_FRAME_S + latency, s, raw, cor, np.zeros(2), 4 * LH1_FRAME_S))
    comp.sort(key=lambda c: c[0])
    rows, repeats = _bursts(comp, mode)
    return {"stations": stations, "cals": cals, "layout": lay, "motion": motion, "rows": rows, "kind": kind,
            "sigma": sigma, "mode": mode, "fresh": [(c[1], c[2]) for c in comp], "repeats": repeats}


def write_event_log(sim, folder, *, event="lhAngle", version=2, firmware=None, name="log00", uart=None):
    """The log (``event``: lhAngle or estSweepAngle) + ``sys.yaml``; firmware : optional
    ``{"estPosition": (t (K,), xyz (K, 3)), "fixedFrequency": (t, xyz)}`` estimate events. uart :
    None = an LH1 log gets ``lhUartFrame`` events as the real LH1 logs (every basestation "no
    channel", no offset; a few per frame), an LH2 log none; False = none."""
    import yaml

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rows = sim["rows"]
    t = np.array([r[0] for r in rows])
    if event == "lhAngle":
        vals = [(r[2], r[1], r[3], r[4], r[5]) for r in rows]
        types = {"lhAngle": LHANGLE}
    else:
        vals = [(r[2], r[1], r[3], r[6], r[4]) for r in rows]
        types = {"estSweepAngle": ESTSWEEP}
    events = {event: (t, vals)}
    if uart is None and sim["kind"] == "lh1":
        # LH1 pulses: sync pulses of the 4 sensors every 8.33 ms (no channel, no offset)
        tu = np.repeat(np.arange(t.min() - 0.05, t.max(), LH1_FRAME_S), 4)
        ticks = (np.round((tu - tu[0]) * 24e6 / LOG_RATE).astype(np.int64) + 4_000_000) + np.tile(np.arange(4), len(tu) // 4)
        events["lhUartFrame"] = (tu + 5.2e-4 * np.tile(np.arange(1, 5), len(tu) // 4),
                                 [(k % 4, NO_CHANNEL, 0, int(x) & 0xFFFFFF, int(x) & 0xFFFFFFFF) for k, x in enumerate(ticks)])
        types["lhUartFrame"] = UART_VARS
    for name_, (tt, p) in (firmware or {}).items():
        types[name_] = ESTPOS if name_ == "estPosition" else FIXED
        events[name_] = (np.asarray(tt), [tuple(map(float, q)) for q in p])
    log = folder / name
    write_cfusdlog(log, events, version=version, types=types)
    yml = folder / "sys.yaml"
    yml.write_text(yaml.safe_dump(system_config_dict(dict(enumerate(sim["stations"])), sim["cals"],
                                                     system_type=1 if sim["kind"] == "lh1" else 2)))
    return log, yml


def simulate_uart_log(folder, *, seed=1, duration=3.0, sigma=4e-5, motion=None, log_offset_s=10.78, mode="kalman",
                      name="log00", extra=None, setup_seed=None, **probabilities):
    """An LH2 log of the deck's pulses (``lhUartFrame``) and the firmware's ``lhAngle`` bursts
    (``cf_helpers.simulate_lh2_log``: no channel on each block's first pulse, one offset per block,
    the log clock at -1.094 % of the deck's, the UART queue) + ``sys.yaml``. The truth motion is a
    function of the log clock; each rotation's rotor zero is on the deck's clock (integer ticks).
    probabilities : ``p_missing``, ``p_two_offsets``, ``p_no_channel``, ``p_garbage`` (see there).
    extra : more events to write, ``{name: (variables [(var, char)], times (K,), rows)}``.
    setup_seed : the calibrations' seed (default ``seed``): logs of one set-up share it.
    Returns ``(log, yml, sim)`` with sim as :func:`simulate_events` plus ``"uart"`` (the
    ``simulate_lh2_log`` result) and ``"alpha"`` / ``"t0"`` per channel (the measured plane angles,
    the rotor zeros in deck ticks)."""
    import yaml

    rng = np.random.default_rng(seed)
    lay, cals, stations = _setup("lh2", rng if setup_seed is None else np.random.default_rng(setup_seed))
    motion = static_motion() if motion is None else motion
    alpha, t0 = {}, {}
    for s, st in enumerate(stations):
        P = LH2_CYCLE_PERIODS[s]
        n = int(duration * 24e6 / P)
        t0[s] = 2_000_000 + int(P * s / 2.7) + P * np.arange(n, dtype=np.int64)
        starts_log = log_offset_s + LOG_RATE * t0[s] / 24e6
        a, _ = _plane_angles(st, motion, lay.positions, starts_log, LOG_RATE * P / 24e6)
        alpha[s] = a + rng.normal(0, sigma, a.shape)
    uart = simulate_lh2_log(alpha, t0, rng=rng, mode=mode, log_offset_s=log_offset_s, **probabilities)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    log = folder / name
    events, types = dict(uart["events"]), dict(uart["types"])
    for ename, (vars_, tt, rows) in (extra or {}).items():
        types[ename] = vars_
        events[ename] = (np.asarray(tt, float), rows)
    write_cfusdlog(log, events, types=types)
    yml = folder / "sys.yaml"
    yml.write_text(yaml.safe_dump(system_config_dict(dict(enumerate(stations)), cals, system_type=2)))
    sim = {"stations": stations, "cals": cals, "layout": lay, "motion": motion, "kind": "lh2", "sigma": sigma,
           "uart": uart, "alpha": alpha, "t0": t0}
    return log, yml, sim


def truth_position(sim, t):
    R, c = sim["motion"](np.asarray(t))
    return c + R @ sim["layout"].positions.mean(0)


def crossing_beam_reference(sim):
    """The firmware's crossing-beam positions on the same angles: per station rotation (LH2) / X+Y
    pair (LH1) the firmware-corrected angles, windows of the two stations' frames closest in time
    (within 20 ms), ``layoutkit.joint.crossing_beam_positions``; times = the frames' times of
    :mod:`layoutkit.live.cf_events` (the same latency model)."""
    from layoutkit.importers.cfusdlog import SweepEvents
    from layoutkit.live.cf_events import event_frames
    from layoutkit.live.joint_stream import JointWindower, crossing_beam_windows

    rows = sim["rows"]
    ev = SweepEvents("lhAngle", np.array([r[0] for r in rows]), np.array([r[1] for r in rows]),
                     np.array([r[2] for r in rows]), np.array([r[3] for r in rows]), np.array([r[4] for r in rows]))
    periods = {k: 60.0 / st.rotor_rpm for k, st in enumerate(sim["stations"])}
    frames = event_frames(ev, sim["kind"], 4, periods=periods)
    win = JointWindower(2)
    ws = []
    for f in frames:
        ws += win.push(f)
    ws += win.flush()
    return crossing_beam_windows(ws, sim["stations"], 4)


__all__ = ["simulate_events", "write_event_log", "simulate_uart_log", "truth_position", "crossing_beam_reference",
           "lh2_to_lh1_angles"]
