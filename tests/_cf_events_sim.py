"""Simulated Crazyflie microSD logs with the firmware's sweep-angle events (``lhAngle``, or the
estimator's ``estSweepAngle``), LH1 or LH2, with known truth — written in the real cfusdlog format
(``cf_helpers.write_cfusdlog``) beside a cflib system-config YAML.

The deck (4 sensors, 3 x 1.5 cm) ~3 m from two calibrated stations (``_cf_joint_sim``). Each angle
is the calibrated forward model (:func:`layoutkit.lighthouse.measure`, the true calibration) of the
deck at the time the light crosses it, plus N(0, sigma²) noise, logged as float32 in the firmware's
convention (LH1 ``pi/2 - theta``, LH2 light-plane angles) with the firmware's calibrated angle
(5-step inverse) as ``correctedAngle``. Event times: LH2 each plane's crossing + ``latency``;
LH1 the sweep's sync + one 8.33 ms frame (processed at the next sync) + ``latency``.
LH1 A/B mode: frames of 8.33 ms, sweeps A-X, A-Y, B-X, B-Y.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from _cf_joint_sim import DECK, STATION_POS, TARGET, factory_calibrations, static_motion
from cf_helpers import write_cfusdlog

from layoutkit.layout import load_layout
from layoutkit.lighthouse import lh2_to_lh1_angles, measure, undistort
from layoutkit.live.protocols.bitcraze import LH2_CYCLE_PERIODS, system_config_dict
from layoutkit.simulate import stations_looking_at

LHANGLE = [("sensor", "B"), ("basestation", "B"), ("sweep", "B"), ("angle", "f"), ("correctedAngle", "f")]
ESTSWEEP = [("sensorId", "B"), ("basestationId", "B"), ("sweepId", "B"), ("t", "f"), ("sweepAngle", "f")]
ESTPOS = [("x", "f"), ("y", "f"), ("z", "f")]
FIXED = [("stateEstimate.x", "f"), ("stateEstimate.y", "f"), ("stateEstimate.z", "f")]


def _angles(st, motion, t, P_body):
    R, c = motion(t)
    Rs, ts = st.world_to_station(R, c)
    p = np.einsum("kij,nj->kni", Rs, P_body) + ts[:, None, :]
    return measure(p, st.calibration) if st.calibration is not None else None


def simulate_events(kind="lh2", *, seed=1, duration=4.0, sigma=4e-5, motion=None, latency=3e-4, t0=12.5):
    """Returns a dict: stations (true calibrations), cals (firmware convention, for the YAML), layout,
    motion, rows = list of (t_event, station, sensor, sweep, raw angle, corrected angle, tilt)."""
    rng = np.random.default_rng(seed)
    lay = load_layout(DECK)
    P_body = lay.positions
    motion = static_motion() if motion is None else motion
    cals = factory_calibrations(rng)
    stations = stations_looking_at(STATION_POS, TARGET, kind=kind,
                                   calibrations=[cals[k].to_calibration(kind) for k in range(2)])
    rows = []
    if kind == "lh2":
        for s, st in enumerate(stations):
            P = LH2_CYCLE_PERIODS[s] / 24e6
            starts = t0 + P * s / 2.7 + P * np.arange(int(duration / P))
            for k, shift in ((0, -np.pi / 3), (1, np.pi / 3)):
                tc = starts[:, None] + np.full((1, 4), (np.pi + shift) / (2 * np.pi) * P)
                for _ in range(2):  # each sensor measured when the plane crosses it
                    R, c = motion(tc.reshape(-1))
                    Rs, ts = st.world_to_station(R, c)
                    p = (np.einsum("kij,nj->kni", Rs, P_body) + ts[:, None, :]).reshape(len(starts), 4, 4, 3)
                    p = p[:, np.arange(4), np.arange(4)]                  # sensor i at its own time
                    a = measure(p, st.calibration)[..., k]                # (R, 4)
                    tc = starts[:, None] + (a + np.pi + shift) / (2 * np.pi) * P
                if k == 0:
                    a0, tc0 = a, tc
                else:
                    raw = np.stack([a0, a], -1) + rng.normal(0, sigma, (len(starts), 4, 2))
                    raw = raw.astype(np.float32).astype(float)
                    cor = undistort(raw, st.calibration)
                    for r in range(len(starts)):
                        for kk, tcx in ((0, tc0), (1, tc)):
                            te = float(tcx[r].max() + latency)
                            for i in range(4):
                                rows.append((te, s, i, kk, raw[r, i, kk], cor[r, i, kk], (2 * kk - 1) * np.pi / 6))
    else:
        frame = 1.0 / 120.0
        nf = int(duration / frame)
        order = [(0, 0), (0, 1), (1, 0), (1, 1)]
        for f in range(nf):
            s, ax = order[f % 4]
            st = stations[s]
            ts_ = t0 + f * frame
            th = _angles(st, motion, np.array([ts_]), P_body)[0]          # (4, 2) ours, distorted
            raw = (np.pi / 2 - th[:, ax] + rng.normal(0, sigma, 4)).astype(np.float32).astype(float)
            rows.append((ts_, s, ax, raw))
        # corrected angles need both axes of a station: pair each X with its following Y
        out, held = [], {}
        for ts_, s, ax, raw in rows:
            if ax == 0:
                held[s] = (ts_, raw)
                continue
            if s not in held:
                continue
            tx, rx = held.pop(s)
            th = np.stack([np.pi / 2 - rx, np.pi / 2 - raw], -1)
            cor = np.pi / 2 - undistort(th, stations[s].calibration)
            for kk, (tt, rr) in enumerate(((tx, rx), (ts_, raw))):
                for i in range(4):
                    out.append((tt + frame + latency, s, i, kk, rr[i], cor[i, kk], 0.0))
        rows = out
    rows.sort(key=lambda r: r[0])
    return {"stations": stations, "cals": cals, "layout": lay, "motion": motion, "rows": rows, "kind": kind,
            "sigma": sigma}


def write_event_log(sim, folder, *, event="lhAngle", version=2, firmware=None, name="log00"):
    """The log (``event``: lhAngle or estSweepAngle) + ``sys.yaml``; firmware : optional
    ``{"estPosition": (t (K,), xyz (K, 3)), "fixedFrequency": (t, xyz)}`` estimate events."""
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
    for name_, (tt, p) in (firmware or {}).items():
        types[name_] = ESTPOS if name_ == "estPosition" else FIXED
        events[name_] = (np.asarray(tt), [tuple(map(float, q)) for q in p])
    log = folder / name
    write_cfusdlog(log, events, version=version, types=types)
    yml = folder / "sys.yaml"
    yml.write_text(yaml.safe_dump(system_config_dict(dict(enumerate(sim["stations"])), sim["cals"],
                                                     system_type=1 if sim["kind"] == "lh1" else 2)))
    return log, yml


def truth_position(sim, t):
    R, c = sim["motion"](np.asarray(t))
    return c + R @ sim["layout"].positions.mean(0)


def crossing_beam_reference(sim):
    """The firmware's crossing-beam positions on the same angles: per station rotation (LH2) / X+Y
    pair (LH1) the firmware-corrected angles, windows of the two stations' frames closest in time
    (within 20 ms), ``layoutkit.joint.crossing_beam_positions``; times = mean of the two frames'
    event times minus the latency model of :mod:`layoutkit.live.cf_events`."""
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

__all__ = ["simulate_events", "write_event_log", "truth_position", "crossing_beam_reference", "lh2_to_lh1_angles"]
