"""Chen et al. (2024): accuracy vs precision with systematic errors, and self-calibration.

    .venv/bin/python studies/chen2024_accuracy/run.py            # 400 calibration + 1000 held-out poses
    .venv/bin/python studies/chen2024_accuracy/run.py --quick    # 150 + 300

Chen's set-up in simulation: the 12-sensor 12.5 x 12.5 x 6.25 cm target
(``models/chen_target.layout.json``), one LH1 station, poses in the paper's 3 m x 3 m area,
sigma = 4.014e-5 rad (rho = 0: the same-rotor correlation would only scale both columns). The
true system has the systematic errors the paper blames: sensor positions off by 0.5 mm RMS and a
station calibration of real factory magnitudes (phase ~0.02-0.06 rad, tilt ~0.01, curve ~0.003,
gib magnitude ~0.02). Solving with the nominal model (nominal sensors, no calibration) shows the
accuracy/precision gap of the paper's Table 2. A calibration capture (400 static poses, each with a
motion-capture reference pose, 0.2 mm / 0.02 deg noise) goes through the bundle adjustment
(:func:`layoutkit.calibrate.bundle_adjust`: station calibration + sensor offsets, gauge and scale
from the reference); held-out poses are then solved with the adjusted model. Accuracy = RMS error
against the truth, precision = the DOP prediction sqrt(mean PDOP^2) sigma (Chen eq. 24), per pose set.

Outputs next to this file under ``results/``: ``results.json``, ``results.md`` (the table),
``accuracy.png`` (the figure).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from layoutkit.calibrate import bundle_adjust
from layoutkit.dop import pose_dop
from layoutkit.geometry import attitude_error, rotvec_to_matrix
from layoutkit.joint import solve_joint
from layoutkit.layout import load_layout
from layoutkit.lighthouse import CALIBRATION_PARAMS, Calibration, Station
from layoutkit.simulate import facing_mask, poses_in_front, simulate_station_angles
from layoutkit.units import SIGMA_THETA_PAPER

HERE = Path(__file__).parent
ROOT = HERE.parent.parent


def factory_calibration(rng) -> Calibration:
    """Real factory magnitudes (the libsurvive sample's ranges): phase 0.02-0.06, tilt ~0.01,
    curve ~0.003, gib magnitude ~0.02 rad."""
    p = np.zeros((2, len(CALIBRATION_PARAMS)))
    p[:, 0] = rng.choice([-1, 1], 2) * rng.uniform(0.02, 0.06, 2)
    p[:, 1] = rng.normal(0, 0.01, 2)
    p[:, 2] = rng.normal(0, 0.003, 2)
    p[:, 3] = rng.uniform(-np.pi, np.pi, 2)
    p[:, 4] = rng.uniform(0.005, 0.02, 2)
    return Calibration(p, "lh1", "ideal")


def pose_set(rng, layout, count, station, P_true, sigma):
    R, t = poses_in_front(count * 6, rng)
    vis = facing_mask(layout.positions, layout.normals, R, t)
    keep = np.flatnonzero(vis.sum(1) >= 6)[:count]
    R, t, vis = R[keep], t[keep], vis[keep]
    a = simulate_station_angles(P_true, R, t, [station], sigma=sigma, rho=0.0, rng=rng)
    a[:, 0][~vis] = np.nan
    return R, t, a, vis


def accuracy(res, R, t, P, station, vis, sigma):
    ok = res.success
    e_r = np.degrees(attitude_error(res.rotation[ok], R[ok]))
    e_t = np.linalg.norm(res.translation[ok] - t[ok], axis=1)
    d = pose_dop(P, R[ok], t[ok], stations=[station], visible=vis[ok][:, None])
    fin = np.isfinite(d.pdop)
    return {"poses": int(ok.sum()), "rms_rot_deg": float(np.sqrt(np.mean(e_r ** 2))),
            "rms_pos_mm": float(np.sqrt(np.mean(e_t ** 2)) * 1e3), "max_rot_deg": float(e_r.max()),
            "max_pos_mm": float(e_t.max() * 1e3),
            "precision_rot_deg": float(np.sqrt(np.mean(d.adop[fin] ** 2)) * sigma),
            "precision_pos_mm": float(np.sqrt(np.mean(d.pdop[fin] ** 2)) * sigma * 1e3)}


def run(n_cal, n_test, seed):
    rng = np.random.default_rng(seed)
    layout = load_layout(ROOT / "models" / "chen_target.layout.json")
    sigma = SIGMA_THETA_PAPER
    P = layout.positions
    offsets = rng.normal(0, 0.5e-3 / np.sqrt(3), P.shape)          # 0.5 mm RMS (3-D)
    truth = Station(calibration=factory_calibration(rng))
    nominal = Station()
    out = {"setup": {"sensors": int(layout.n), "sigma_rad": sigma, "sensor_error_rms_mm": float(np.sqrt(np.mean(np.sum(offsets ** 2, 1))) * 1e3),
                     "calibration_truth": truth.calibration.to_dict(), "calibration_poses": n_cal, "test_poses": n_test,
                     "reference_noise": {"rot_deg": 0.02, "pos_mm": 0.2}}}
    # held-out test set
    Rt, tt, at, vt = pose_set(rng, layout, n_test, truth, P + offsets, sigma)
    raw = solve_joint(P, at, stations=[nominal])
    out["nominal_model"] = accuracy(raw, Rt, tt, P, nominal, vt, sigma)
    ideal_a = simulate_station_angles(P, Rt, tt, [nominal], sigma=sigma, rho=0.0, rng=rng)
    ideal_a[:, 0][~vt] = np.nan
    out["no_systematic_errors"] = accuracy(solve_joint(P, ideal_a, stations=[nominal]), Rt, tt, P, nominal, vt, sigma)
    # calibration capture with a mocap reference
    Rc, tc, ac, vc = pose_set(rng, layout, n_cal, truth, P + offsets, sigma)
    n_cal = len(Rc)
    ref_R = rotvec_to_matrix(rng.normal(0, np.radians(0.02) / np.sqrt(3), (n_cal, 3))) @ Rc
    ref_t = tc + rng.normal(0, 0.2e-3 / np.sqrt(3), (n_cal, 3))
    ini = solve_joint(P, ac, stations=[nominal])
    ba = bundle_adjust(P, ac, [nominal], sigma=sigma, initial_poses=(ini.rotation, ini.translation),
                       sensor_offsets=True, offset_prior=1e-3, reference=(ref_R, ref_t, np.ones(n_cal, bool)),
                       reference_sigma=(np.radians(0.02) / np.sqrt(3), 0.2e-3 / np.sqrt(3)))
    out["calibrate"] = {"message": ba.message, "success": bool(ba.success),
                        "median_abs_residual_before_rad": float(np.nanmedian(np.abs(ba.residual_before))),
                        "median_abs_residual_after_rad": float(np.nanmedian(np.abs(ba.residual_after))),
                        "sensor_error_after_rms_mm": float(np.sqrt(np.mean(np.sum((ba.points_body - P - offsets) ** 2, 1))) * 1e3),
                        "parameters": [{"name": p.name, "value": p.value, "std": p.std, "status": p.status}
                                       for p in ba.parameters if "axis" in p.name]}
    cal_st = ba.stations[0]
    after = solve_joint(ba.points_body, at, stations=[cal_st])
    out["calibrated_model"] = accuracy(after, Rt, tt, ba.points_body, cal_st, vt, sigma)
    for k in ("nominal_model", "no_systematic_errors", "calibrated_model"):
        r = out[k]
        r["accuracy_over_precision_rot"] = r["rms_rot_deg"] / r["precision_rot_deg"]
        r["accuracy_over_precision_pos"] = r["rms_pos_mm"] / r["precision_pos_mm"]
    return out


def write(out, folder: Path):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "results.json").write_text(json.dumps(out, indent=2) + "\n")
    rows = [("no systematic errors", out["no_systematic_errors"]), ("nominal model (0.5 mm + factory cal.)", out["nominal_model"]),
            ("after `calibrate`", out["calibrated_model"])]
    md = ["| model | poses | RMS att. (deg) | RMS pos. (mm) | max att. (deg) | max pos. (mm) | precision att. (deg) | "
          "precision pos. (mm) | accuracy/precision att. | accuracy/precision pos. |", "|" + "---|" * 10]
    for name, r in rows:
        md.append(f"| {name} | {r['poses']} | {r['rms_rot_deg']:.4f} | {r['rms_pos_mm']:.3f} | {r['max_rot_deg']:.3f} | "
                  f"{r['max_pos_mm']:.2f} | {r['precision_rot_deg']:.4f} | {r['precision_pos_mm']:.3f} | "
                  f"{r['accuracy_over_precision_rot']:.2f} | {r['accuracy_over_precision_pos']:.2f} |")
    (folder / "results.md").write_text("\n".join(md) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from layoutkit.io.figures import save_figure

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    labels = ["no syst.", "nominal", "calibrated"]
    for ax, (key, pkey, unit) in zip(axes, (("rms_rot_deg", "precision_rot_deg", "deg"), ("rms_pos_mm", "precision_pos_mm", "mm"))):
        acc = [r[key] for _, r in rows]
        pre = [r[pkey] for _, r in rows]
        x = np.arange(3)
        ax.bar(x - 0.2, pre, 0.4, label="precision (DOP sigma)")
        ax.bar(x + 0.2, acc, 0.4, label="accuracy (RMS vs truth)")
        ax.set_xticks(x, labels)
        ax.set_yscale("log")
        ax.set_ylabel(unit)
        ax.set_xlabel("model used to solve the held-out poses")
        ax.set_title("attitude" if unit == "deg" else "position")
        ax.legend(fontsize=7)
    fig.suptitle("Chen set-up: accuracy vs precision, with systematic errors and after calibrate")
    fig.tight_layout(rect=(0, 0.06, 1, 0.93))
    save_figure(fig, folder / "accuracy.png", caption="Held-out poses, one LH1 station, 12-sensor target; truth has "
                                                      "0.5 mm sensor errors and factory-size calibration.")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    res = run(150 if args.quick else 400, 300 if args.quick else 1000, args.seed)
    write(res, HERE / "results")
    for k in ("no_systematic_errors", "nominal_model", "calibrated_model"):
        r = res[k]
        print(f"{k:22s} acc/prec att {r['accuracy_over_precision_rot']:.2f} pos {r['accuracy_over_precision_pos']:.2f} "
              f"(RMS {r['rms_rot_deg']:.4f} deg {r['rms_pos_mm']:.3f} mm)")
    print(res["calibrate"]["message"])
