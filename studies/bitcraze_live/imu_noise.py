"""The IMU-aided filter's accelerometer noise on a real hand-moved log: 100 ms coverage and the ok
outputs' errors vs motion capture, split by the stations their interval had (issue 25; docs/live.md,
"The IMU on the Crazyflie logs").

    python studies/bitcraze_live/imu_noise.py --data ~/.cache/layoutkit-realdata/bitcraze \\
        --stations OUT/calibration/stations_refined.json --log lh2_crossingBeam_move/log01 --acc-noise 0.1 0.03 0.01

The log is decoded once as ``replay`` decodes it (:func:`layoutkit.workflows.live._decode_all`), then
the filter alone (:class:`layoutkit.filter.imu_tracker.ImuSweepTracker`, defaults but ``acc_noise``)
runs over its sweeps with the log's IMU samples; metrics as run.py's (``coverage``,
``align_to_mocap``, ``ok_errors_by_interval_stations``). Prints one JSON line per noise value.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))


def main():
    from layoutkit.filter import EkfConfig
    from layoutkit.filter.imu_tracker import ImuSweepTracker, ImuTrackerConfig
    from layoutkit.live.pipeline import LiveConfig
    from layoutkit.live.session import calibrated_setup
    from layoutkit.studies.bitcraze_dataset import DECK_LAYOUT, align_to_mocap, coverage, firmware_series
    from layoutkit.workflows.live import _decode_all, _replay_setup
    from run import errors_by_alignment, mm, ok_errors_by_interval_stations

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--stations", required=True, help="stations_refined.json of run.py's calibration step")
    ap.add_argument("--log", default="lh2_crossingBeam_move/log01", help="SET/logNN")
    ap.add_argument("--acc-noise", type=float, nargs="+", default=[0.1], help="m/s²/√Hz")
    a = ap.parse_args()
    data = Path(a.data).expanduser()
    log = data / a.log
    yml = data / a.log.split("/")[0] / "system-config.yaml"
    mocap = data / a.log.split("/")[0] / f"mocap{a.log[-2:]}.npy"
    cfg = LiveConfig()
    cfg = replace(cfg, filter=EkfConfig(sigma_theta=cfg.sigma_theta, rho=cfg.rho))
    setup, usd, _, _ = _replay_setup(log, str(DECK_LAYOUT), protocol=None, options=cfg, stations=a.stations,
                                  system_config=str(yml), solve="joint", cfusdlog_source="auto")
    sweeps = _decode_all(setup, log, usd)[0]
    sts, _, _ = calibrated_setup(setup)
    imu = usd["imu"]
    fw = firmware_series(log)
    on, off = fw["markers"]
    mc = np.load(mocap)
    for an in a.acc_noise:
        ic = ImuTrackerConfig()
        ic = replace(ic, imu=replace(ic.imu, acc_noise=an))
        trk = ImuSweepTracker(setup.layout.positions, sts, cfg.filter, imu.t, imu.gyro, imu.acc, ic)
        c0 = time.process_time()
        outs = [o for o in (trk.push(m) for m in sweeps) if o is not None]
        cpu = time.process_time() - c0
        t = np.array([o.t for o in outs])
        p = np.array([o.translation for o in outs])
        st = np.array([o.status for o in outs])
        sig = np.array([float(np.linalg.norm(o.cov_pos_m)) for o in outs])
        ok = st == "ok"
        al = align_to_mocap(t[ok], p[ok], mc, on, off)
        e = errors_by_alignment(al, mc, on, off, t[ok], p[ok], t[ok], p[ok])
        F = {"t": t, "station": np.array([o.station for o in outs]), "status": st,
             "angles": np.array([o.used + o.rejected for o in outs]), "sigma": sig}
        print(json.dumps({"log": a.log, "acc_noise": an, "coverage_100ms": round(coverage(t[ok], on, off), 4),
                          "rms_mm": mm(al["rms_m"]), "max_mm": mm(al["max_m"]),
                          "ok_by_interval_stations": ok_errors_by_interval_stations(F, e, on, off),
                          "filter_cpu_s": round(cpu, 2), "counters": trk.counters.as_dict()}), flush=True)


if __name__ == "__main__":
    main()
