"""Calibration and joint solving: speed, recovery coverage, joint vs per-station precision.

    python benchmarks/bench_calibrate.py            # all parts (several minutes on 2 cores)
    python benchmarks/bench_calibrate.py --quick    # smaller sizes, same code paths

Parts (results in benchmarks/results/calibrate[_quick].json):

1. ``calibrate_time``: bundle adjustment of 1,000 samples x 2 LH1 stations x 32 sensors (station 1
   pose, both calibrations; medians of rounds; peak Python memory of one run).
2. ``joint_speed``: joint solve of a 4-sensor deck seen by two calibrated LH2 stations, frames/s,
   against the anchor ``solve_pnp`` (fast single-station LM on one station's undistorted angles)
   in the same run (ratio).
3. ``joint_vs_dop``: static deck, two stations, 20,000 frames: joint position RMS / joint PDOP
   sigma, each station alone / its own PDOP sigma, and the ratio of the two predictions.
4. ``recovery``: 100 simulated captures (LH1 and LH2 alternately, 0.5 mm sensor offsets):
   fraction of observable parameters within 3 reported sigma of the truth; accuracy/precision of a
   held-out pose set before (zero calibration, nominal sensors) and after calibrating.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parent.parent / "tests"))

from _calib_sim import capture, observe, z_scores  # noqa: E402
from _util import interleaved, peak_python_memory, write_result  # noqa: E402

from layoutkit.calibrate import bundle_adjust  # noqa: E402
from layoutkit.dop import pose_dop  # noqa: E402
from layoutkit.geometry import look_at_rotation  # noqa: E402
from layoutkit.joint import solve_joint  # noqa: E402
from layoutkit.lighthouse import lh2_to_lh1_angles, undistort  # noqa: E402
from layoutkit.pnp import solve_pnp  # noqa: E402
from layoutkit.simulate import simulate_station_angles, stations_looking_at  # noqa: E402

DECK = np.array([[-0.015, 0.0075, 0.0], [-0.015, -0.0075, 0.0], [0.015, 0.0075, 0.0], [0.015, -0.0075, 0.0]])


def _adjust(cap, **kw):
    ini = solve_joint(cap["P"], cap["angles"], stations=cap["start"])
    return bundle_adjust(cap["P"], cap["angles"], cap["start"], sigma=cap["sigma"],
                         initial_poses=(ini.rotation, ini.translation), **kw)


def calibrate_time(samples, rounds):
    cap = capture(np.random.default_rng(1), kind="lh1", n=32, samples=samples)
    out = {}
    t = interleaved({"calibrate": lambda: out.setdefault("res", _adjust(cap))}, rounds)["calibrate"]
    res = out["res"]
    mem = peak_python_memory(lambda: _adjust(cap))
    return {"samples": samples, "stations": 2, "sensors": 32, "angles": int(np.isfinite(cap["angles"]).sum()),
            "seconds_median": float(np.median(t)), "seconds_all": t, "peak_python_bytes": int(mem),
            "evaluations": res.nfev, "message": res.message,
            "median_abs_residual_after_sigma": float(np.nanmedian(np.abs(res.residual_after)) / cap["sigma"])}


def _deck_setup(rng, F, sigma, rho=0.0):
    from _calib_sim import random_calibration

    sts = stations_looking_at([[-2.0, -1.0, 2.0], [2.0, -1.2, 2.0]], (0, 0, 0), kind="lh2",
                              calibrations=[random_calibration(rng, "lh2"), random_calibration(rng, "lh2", "corrected")])
    R = np.tile(look_at_rotation([0.0, 0.0, 1.0]).T, (F, 1, 1))
    t = np.zeros((F, 3))
    return sts, R, t, simulate_station_angles(DECK, R, t, sts, sigma=sigma, rho=rho, rng=rng)


def joint_speed(F, rounds):
    sts, R, t, a = _deck_setup(np.random.default_rng(2), F, 1e-4)
    ideal = lh2_to_lh1_angles(undistort(a[:, 0], sts[0].calibration, max_iterations=20, tol=1e-9))
    times = interleaved({"joint": lambda: solve_joint(DECK, a, stations=sts),
                         "anchor_solve_pnp_one_station": lambda: solve_pnp(DECK, ideal)}, rounds)
    med = {k: float(np.median(v)) for k, v in times.items()}
    return {"frames": F, "frames_per_s": {k: F / v for k, v in med.items()},
            "joint_over_anchor_time": med["joint"] / med["anchor_solve_pnp_one_station"], "seconds_all": times}


def joint_vs_dop(F, sigma=1e-4):
    sts, R, t, a = _deck_setup(np.random.default_rng(3), F, sigma)
    out = {"frames": F, "sigma_rad": sigma, "rho": 0.0, "layout": "4 sensors, 3 x 1.5 cm (Crazyflie deck)",
           "stations": "2 LH2 at ~3 m, factory-magnitude calibrations"}

    def rms(res):
        e = res.translation[res.success] - t[res.success]
        return float(np.sqrt(np.mean(np.sum(e * e, 1))))

    j = solve_joint(DECK, a, stations=sts)
    pj = float(pose_dop(DECK, R[0], t[0], stations=sts).pdop * sigma)
    out["joint"] = {"ok_fraction": float(j.success.mean()), "position_rms_m": rms(j), "predicted_m": pj,
                    "ratio": rms(j) / pj}
    for k in range(2):
        r = solve_joint(DECK, a[:, k:k + 1], stations=[sts[k]])
        pk = float(pose_dop(DECK, R[0], t[0], stations=[sts[k]]).pdop * sigma)
        out[f"station_{k}"] = {"ok_fraction": float(r.success.mean()), "position_rms_m": rms(r), "predicted_m": pk,
                               "ratio": rms(r) / pk, "prediction_over_joint_prediction": pk / pj}
    return out


def recovery(trials, samples, n):
    ss = np.random.SeedSequence(2024)
    z_all, inside, acc = [], [], []
    for k, child in enumerate(ss.spawn(trials)):
        rng = np.random.default_rng(child)
        kind = "lh1" if k % 2 == 0 else "lh2"
        cap = capture(rng, kind=kind, n=n, samples=samples, offset_rms=0.5e-3)
        res = _adjust(cap, sensor_offsets=True)
        z = z_scores(res, cap, kind)
        z_all.append(z)
        inside.append(float(np.mean(np.abs(z) < 3)))
        # held-out poses: accuracy (vs truth) over precision (DOP sigma), before and after
        hR, ht, ha = observe(cap, rng, 200)
        held = {"R": hR, "t": ht, "angles": ha}
        before = solve_joint(cap["P"], held["angles"], stations=cap["start"])
        after = solve_joint(res.points_body, held["angles"], stations=res.stations)
        acc.append({"kind": kind, "before": _acc_over_prec(before, held, cap, cap["start"]),
                    "after": _acc_over_prec(after, held, cap, res.stations, res.points_body)})
    z = np.concatenate(z_all)
    ratios_b = [a["before"] for a in acc if np.isfinite(a["before"])]
    ratios_a = [a["after"] for a in acc if np.isfinite(a["after"])]
    return {"trials": trials, "samples": samples, "sensors": n, "parameters_checked": int(z.size),
            "fraction_within_3_sigma_all": float(np.mean(np.abs(z) < 3)),
            "trials_with_95pct_within_3_sigma": float(np.mean(np.array(inside) >= 0.95)),
            "median_trial_fraction_within_3_sigma": float(np.median(inside)),
            "fraction_within_1_sigma_all": float(np.mean(np.abs(z) < 1)),
            "position_accuracy_over_precision": {"before_median": float(np.median(ratios_b)),
                                                 "after_median": float(np.median(ratios_a))}}


def _acc_over_prec(res, held, cap, stations, P=None):
    P = cap["P"] if P is None else P
    ok = res.success
    if ok.sum() < 10:
        return float("nan")
    e = res.translation[ok] - held["t"][ok]
    vis = np.all(np.isfinite(held["angles"][ok]), -1)
    d = pose_dop(P, held["R"][ok], held["t"][ok], stations=list(stations), visible=vis)
    fin = np.isfinite(d.pdop)
    pred = np.sqrt(np.mean(d.pdop[fin] ** 2)) * cap["sigma"]
    return float(np.sqrt(np.mean(np.sum(e * e, 1))) / pred)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--parts", default="time,speed,dop,recovery")
    args = ap.parse_args()
    q = args.quick
    parts = args.parts.split(",")
    out = {}
    if "time" in parts:
        out["calibrate_time"] = calibrate_time(200 if q else 1000, 1 if q else 2)
        print("calibrate_time", {k: v for k, v in out["calibrate_time"].items() if k != "seconds_all"}, flush=True)
    if "speed" in parts:
        out["joint_speed"] = joint_speed(2000 if q else 20000, 3)
        print("joint_speed", out["joint_speed"]["frames_per_s"], flush=True)
    if "dop" in parts:
        out["joint_vs_dop"] = joint_vs_dop(3000 if q else 20000)
        print("joint_vs_dop", out["joint_vs_dop"], flush=True)
    if "recovery" in parts:
        out["recovery"] = recovery(10 if q else 100, 60, 16)
        print("recovery", out["recovery"], flush=True)
    name = "calibrate_quick" if q else "calibrate"
    prev = Path(__file__).resolve().parent / "results" / f"{name}.json"
    if prev.exists():  # a subset of --parts keeps the other parts' last figures
        old = json.loads(prev.read_text())
        out = {**{k: v for k, v in old.items() if k not in ("benchmark", "when", "machine")}, **out}
    for k in parts:
        key = {"time": "calibrate_time", "speed": "joint_speed", "dop": "joint_vs_dop"}.get(k, k)
        if isinstance(out.get(key), dict):
            out[key]["measured"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
    p = write_result(name, out)
    print("wrote", p)


if __name__ == "__main__":
    main()
