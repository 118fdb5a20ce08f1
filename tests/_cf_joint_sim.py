"""Simulated Crazyflie set-up for the joint-solve tests and benchmark: a Lighthouse deck (4 sensors,
3 x 1.5 cm) ~3 m from two calibrated LH2 stations, written as the deck's real UART bytes
(:func:`layoutkit.live.protocols.bitcraze.lh2_deck_session`) with a cflib system-config YAML
(:func:`layoutkit.live.protocols.bitcraze.system_config_dict`), and the firmware's crossing-beam
positions computed from the same decoded bytes."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from layoutkit.geometry import rotvec_to_matrix
from layoutkit.layout import load_layout
from layoutkit.lighthouse import StationCalibration, SweepCalibration
from layoutkit.live.protocols.bitcraze import LH2_CYCLE_PERIODS, lh2_deck_session, system_config_dict
from layoutkit.simulate import stations_looking_at

DECK = Path(__file__).resolve().parents[1] / "models" / "crazyflie_lighthouse_deck.layout.json"
TARGET = np.array([0.0, 0.0, 0.5])
STATION_POS = np.array([[-1.6, -1.8, 2.4], [1.9, -1.4, 2.3]])   # ~3.0 m from TARGET
#: the deck's offset quantum: one 6 MHz tick of channel 0's rotor (rad)
Q6 = 2 * np.pi * 4 / LH2_CYCLE_PERIODS[0]


def factory_calibrations(rng):
    """Firmware-convention LH2 calibrations of factory size (phase 0.02-0.06, tilt ~0.01, gib ~0.02 rad)."""
    def sweep():
        return SweepCalibration(phase=float(rng.choice([-1, 1]) * rng.uniform(0.02, 0.06)), tilt=float(rng.normal(0, 0.01)),
                                gibmag=float(rng.choice([-1, 1]) * rng.uniform(0.01, 0.03)),
                                gibphase=float(rng.uniform(0, 2 * np.pi)))
    return {k: StationCalibration((sweep(), sweep()), 100 + k) for k in range(2)}


def static_motion(R0=None, c=TARGET):
    R0 = rotvec_to_matrix([0.05, -0.03, 0.4]) if R0 is None else R0

    def motion(t):
        t = np.atleast_1d(t)
        return np.broadcast_to(R0, (t.size, 3, 3)).copy(), np.broadcast_to(c, (t.size, 3)).copy()
    return motion


def flying_motion(speed=0.5):
    """A Crazyflie-like flight: a Lissajous loop around TARGET (±0.4 / 0.3 / 0.15 m, ~``speed`` m/s)
    with slow yaw and small roll/pitch."""
    w = speed / 0.45

    def motion(t):
        t = np.atleast_1d(np.asarray(t, float))
        c = TARGET + np.column_stack([0.4 * np.sin(w * t), 0.3 * np.sin(1.3 * w * t + 0.5), 0.15 * np.sin(0.7 * w * t)])
        rv = np.column_stack([0.08 * np.sin(1.1 * w * t), 0.08 * np.cos(0.9 * w * t), 0.4 + 0.3 * np.sin(0.3 * w * t)])
        return rotvec_to_matrix(rv), c
    return motion


def scenario(seed=1, *, duration=6.0, sigma=4e-5, motion=None):
    """Stations (true calibrations), the deck's bytes and the truth motion."""
    rng = np.random.default_rng(seed)
    lay = load_layout(DECK)
    cals = factory_calibrations(rng)
    stations = stations_looking_at(STATION_POS, TARGET, kind="lh2",
                                   calibrations=[cals[k].to_calibration("lh2") for k in range(2)])
    motion = static_motion() if motion is None else motion
    data, info = lh2_deck_session(lay.positions, motion, stations, duration=duration, sigma=sigma, rng=rng,
                                  normals=lay.normals)
    return {"layout": lay, "stations": stations, "cals": cals, "motion": motion, "bytes": data, "info": info,
            "sigma": sigma, "sigma_eff": float(np.hypot(sigma, Q6 / np.sqrt(12)))}


def write_capture(sc, folder):
    """capture.bin (+ sidecar: protocol bitcraze-lh2, the deck layout; no stations) and sys.yaml
    (cflib system config: both stations' geometry and calibration)."""
    import yaml

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    cap = folder / "capture.bin"
    cap.write_bytes(sc["bytes"])
    (folder / "capture.bin.json").write_text(json.dumps({"protocol": "bitcraze-lh2", "layout": sc["layout"].to_dict()}))
    ymlp = folder / "sys.yaml"
    geo = {k: st for k, st in enumerate(sc["stations"])}
    ymlp.write_text(yaml.safe_dump(system_config_dict(geo, sc["cals"])))
    return cap, ymlp


def decoded_windows(sc):
    """The deck bytes decoded without pre-correction, paired and windowed as the pipeline does."""
    from layoutkit.live.joint_stream import JointWindower
    from layoutkit.live.pipeline import SweepPairer
    from layoutkit.live.protocols.bitcraze import BitcrazeLh2Decoder

    dec = BitcrazeLh2Decoder(4, calibrate=False)
    pair = SweepPairer(4, 3600.0)
    win = JointWindower(2)
    out = []
    for m in dec.feed(sc["bytes"]) + dec.flush():
        f = pair.push(m)
        if f is not None:
            out += win.push(f)
    return out + win.flush()


def crossing_beam(sc, windows):
    """The firmware's crossing-beam position of every window with both stations: (t (W,), pos (W, 3))."""
    from layoutkit.live.joint_stream import crossing_beam_windows

    # stations by system-config id: the channel's exact rotor period (as load_system_config gives)
    return crossing_beam_windows(windows, sc["stations"], 4)

def truth_position(sc, t):
    """True deck-centre position (mean of the sensors; the deck origin) at the windows' times (the
    mean measurement time of their light planes, :class:`layoutkit.live.joint_stream.JointWindow`)."""
    R, c = sc["motion"](np.asarray(t))
    return c + R @ sc["layout"].positions.mean(0)
