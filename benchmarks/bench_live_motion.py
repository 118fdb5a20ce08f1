"""Motion compensation of the live pipeline: RMS pose error vs truth / DOP prediction, with and
without ``LiveConfig.motion_compensation``, at several tumble rates (docs/live.md "Motion
compensation").

    .venv/bin/python benchmarks/bench_live_motion.py [--seconds 30] [--seeds 3]

Simulator sweeps (paper noise, 50 MHz quantisation, Chen target reconstruction, one LH1 station)
fed straight into the pipeline (no byte encoding), chunks of 2048 frames as in ``replay``.
Cases: constant rotation at 0, 5, 20, 60 °/s about a fixed tilted axis plus a 0.3 m sine
translation with 0.2 m/s peak speed (0.13 m/s² peak acceleration); a static target; the simulator's
default tumble (≤ 0.5°/s); and a ±20° sine tumble at ≤ 18°/s (the case quoted in docs/live.md
"Frame time"). Ratios = RMS error over good frames after a 0.5 s warm-up / (sqrt(mean DOP²)·σθ);
seeds pooled. Also decode-free solve throughput with and without. Writes
benchmarks/results/live_motion.json.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _util import write_result  # noqa: E402

WARM_UP_S = 0.5




def sweeps_of(sw):
    from layoutkit.live.frames import SweepMeasurement

    ang = sw.measured_angles()
    return [SweepMeasurement(float(sw.t[k]), int(sw.station[k]), int(sw.axis[k]), ang[k], int(sw.seq[k]))
            for k in range(sw.t.size) if sw.emitted[k]]


def solve(layout, sweeps, on: bool):
    from layoutkit.live.pipeline import LiveConfig, PosePipeline

    pipe = PosePipeline(layout.positions, LiveConfig(n_sensors=layout.n, chunk_frames=2048,
                                                         chunk_seconds=float("inf"), motion_compensation=on))
    chunks = pipe.feed(sweeps) + pipe.flush(end_of_stream=True)
    return {k: np.concatenate([getattr(c, k) for c in chunks])
            for k in ("t", "rotation", "translation", "status", "adop", "pdop")}


def errors(sw, c):
    """Squared errors and squared predictions (attitude deg², position m²) of the evaluated frames."""
    from layoutkit.dop import pose_errors
    from layoutkit.geometry import rotvec_to_matrix
    from layoutkit.status import OK as STATUS_OK
    from layoutkit.units import SIGMA_THETA_PAPER

    x = sw.axis == 0
    i = np.searchsorted(sw.t[x], c["t"])
    g = (c["status"] == STATUS_OK) & (c["t"] >= WARM_UP_S)
    e_r, e_t = pose_errors(c["rotation"][g], c["translation"][g], rotvec_to_matrix(sw.rotvec[x][i[g]]),
                           sw.translation[x][i[g]])
    return (np.degrees(e_r) ** 2, e_t ** 2, (c["adop"][g] * SIGMA_THETA_PAPER) ** 2,
            (c["pdop"][g] * SIGMA_THETA_PAPER) ** 2, int(g.sum()), int(c["t"].size))


def case(layout, name, make_motion, seconds, seeds):
    from layoutkit.live.simulator import simulate_sweeps

    acc = {False: [], True: []}
    for seed in range(seeds):
        sw = simulate_sweeps(layout, duration=seconds, seed=100 + seed, motion=make_motion(seed))
        sweeps = sweeps_of(sw)
        for on in (False, True):
            acc[on].append(errors(sw, solve(layout, sweeps, on)))
    out = {"case": name}
    for on, key in ((False, "off"), (True, "on")):
        er, et, pr, pt, good, frames = (np.concatenate([a[k] for a in acc[on]]) if k < 4 else
                                        sum(a[k] for a in acc[on]) for k in range(6))
        out[key] = {"attitude_ratio": round(float(np.sqrt(er.mean() / pr.mean())), 3),
                    "position_ratio": round(float(np.sqrt(et.mean() / pt.mean())), 3),
                    "rms_attitude_deg": round(float(np.sqrt(er.mean())), 4),
                    "rms_position_mm": round(float(1e3 * np.sqrt(et.mean())), 3),
                    "good_frames": good, "frames": frames}
    print(f"{name:32s} off {out['off']['attitude_ratio']:.3f} / {out['off']['position_ratio']:.3f}   "
          f"on {out['on']['attitude_ratio']:.3f} / {out['on']['position_ratio']:.3f}   "
          f"good {out['off']['good_frames']}/{out['on']['good_frames']} of {out['on']['frames']}", flush=True)
    return out


def throughput(layout, seconds=60.0, rounds=3):
    """Solve-only frames/s (chunks of 2048) on the default tumble, off and on, interleaved rounds."""
    from layoutkit.live.simulator import simulate_sweeps

    sw = simulate_sweeps(layout, duration=seconds, seed=1)
    sweeps = sweeps_of(sw)
    n = int(sw.emitted.sum()) // 2
    times = {False: [], True: []}
    for _ in range(rounds):
        for on in (False, True):
            t0 = time.perf_counter()
            solve(layout, sweeps, on)
            times[on].append(time.perf_counter() - t0)
    return {"frames": n, "frames_per_s_off": round(n / statistics.median(times[False])),
            "frames_per_s_on": round(n / statistics.median(times[True]))}


def main(argv=None):
    from layoutkit.live.simulator import spin_motion, tumble_trajectory
    from layoutkit.shapes import chen_target

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=30.0, help="simulated seconds per seed and case")
    ap.add_argument("--seeds", type=int, default=3)
    args = ap.parse_args(argv)
    layout = chen_target()[1]
    t0 = time.perf_counter()
    cases = [case(layout, "static", lambda s: spin_motion(0.0, 0.0), args.seconds, args.seeds)]
    for rate in (0.0, 5.0, 20.0, 60.0):
        cases.append(case(layout, f"spin {rate:g} deg/s + 0.2 m/s", lambda s, r=rate: spin_motion(r, 0.2),
                          args.seconds, args.seeds))
    cases.append(case(layout, "default tumble (<= 0.5 deg/s)", lambda s: "tumble", args.seconds, args.seeds))
    cases.append(case(layout, "sine tumble +-20 deg, <= 18 deg/s",
                      lambda s: tumble_trajectory(layout, args.seconds, np.random.default_rng(200 + s),
                                                  amplitude_deg=20.0, max_rate=np.deg2rad(18.0)),
                      args.seconds, args.seeds))
    tp = throughput(layout)
    print(f"throughput (solve only, 2048-frame chunks): off {tp['frames_per_s_off']} frames/s, "
          f"on {tp['frames_per_s_on']} frames/s")
    p = write_result("live_motion", {
        "command": "python benchmarks/bench_live_motion.py" + ("" if argv is None else " " + " ".join(argv)),
        "seconds_per_seed": args.seconds, "seeds": args.seeds, "warm_up_s": WARM_UP_S,
        "cases": cases, "throughput": tp, "wall_s": round(time.perf_counter() - t0, 1)})
    print(f"wrote {p}")


if __name__ == "__main__":
    main()
