"""Does a station calibration from ``lh1_test_cal`` transfer between its two static devices? (issue 26, must-show 1)

    OPENBLAS_NUM_THREADS=1 nice -n 10 .venv/bin/python studies/libsurvive/transfer.py [--max-windows 200]

``lh1_test_cal``: a Vive HMD and a Vive tracker (T20), both at rest for the whole recording, two LH1
stations with libsurvive's ``LH_POSE`` poses and factory calibration. Each device is one body pose.
Every fit below is :func:`layoutkit.workflows.calibrate_devices.fit_devices` (the ``calibrate`` bundle
adjustment; station 0's pose is the gauge, so station 1's 6 pose terms are the free station geometry),
evaluated by :func:`~layoutkit.workflows.calibrate_devices.joint_residual` (median per-window RMS of the
joint solve, the device's *nominal* layout unless said otherwise).

1. **Station prior sweep** (maximum a posteriori: every station term adjusted with a Gaussian prior
   ``(deg, mm)`` around ``LH_POSE``, ``hold_station_prior=False``; free = no prior): per prior, three
   fits — both devices, HMD only, T20 only — and each device's joint residual through each fit's
   stations. The held-out figures are the HMD through the T20-only fit and the T20 through the
   HMD-only fit.
2. **The prior chosen by a rule stated before the run** (not by the held-out numbers): the factory
   stations are worth what their own residual says — an attitude error of station 1 larger than the
   devices' joint residual with the factory stations would show in that residual, so
   ``sigma_att = median over devices of the factory joint residual`` (rad) and
   ``sigma_pos = sigma_att x`` the median device–station distance. (Cross-validation over the
   folds cannot choose it honestly here: two devices give two folds, both of which are the figures
   to report.)
3. **What one static device determines**: station 1's pose fitted on each device alone (free),
   its change from ``LH_POSE`` and its sd (noise + the layout consider term of ``layout_sigma``);
   whether the two devices' estimates agree within those sds.
   Then station 1's attitude alone (its position held: prior 1e-9 m) and its position alone
   (attitude held), each fitted on both devices and on each alone: does the better-determined
   part transfer where the 6-DoF fit does not?
4. **Each device's sensor offsets as prior-constrained unknowns** (``offset_prior`` = the hardware
   tolerance: two Vive HMDs' factory layouts differ by 0.22 mm RMS), both devices in the fit, station
   prior free and the rule's: each device's joint residual with the nominal layout and with its own
   fitted layout.
5. **Honest data weight** (a second rule stated before the run): the fits above weigh every window
   by the 4" angle noise, but a static device's systematic error (its layout) is the same in each
   window and does not average down; weighing the data by the factory joint residual x sqrt(windows
   per pose) (one independent look per pose) with the section-2 station prior, the calibration terms
   free (prior ``calibration_prior`` 0.1 rad): each fold again.
6. **Calibration terms** (LH1 phase / tilt / curve / gib, both axes): their statuses in the
   two-device fit.

Writes ``studies/libsurvive/results/transfer.json`` and ``transfer.md``. The recording is read from
``~/.cache/layoutkit-realdata/survive/lh1_test_cal.rec.gz`` (imported into a temporary folder with
``layoutkit import libsurvive``; nothing of it is committed).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import numpy as np  # noqa: E402

HERE = Path(__file__).parent
OUT = HERE / "results"
REC = Path.home() / ".cache" / "layoutkit-realdata" / "survive" / "lh1_test_cal.rec.gz"
ARCSEC = np.deg2rad(1.0 / 3600.0)
SIGMA = 4.0 * ARCSEC                       # the angle noise of the note-26 runs
#: station prior sweep, (deg, mm) pairs (about 2.5 mm per mrad: the stations are ~2.5 m away)
PRIORS = [(0.0001, 0.005), (0.0003, 0.015), (0.001, 0.05), (0.003, 0.15), (0.01, 0.5), (0.03, 1.5), (0.1, 5.0), (0.3, 15.0), (1.0, 50.0), None]
HMD_OFFSET_TOLERANCE = 2.2e-4              # m: two Vive HMDs' factory layouts differ by 0.22 mm RMS (note-26)


def load(root: Path):
    from layoutkit.io.stations import read_stations
    from layoutkit.layout import load_layout
    from layoutkit.workflows.calibrate_devices import device_windows
    from layoutkit.workflows.joint_solve import read_station_frames

    stations = list(read_stations(root / "stations.json"))
    devs = []
    for name in ("HMD", "T20"):
        lay = load_layout(root / name / "layout.json")
        devs.append(device_windows(name, read_station_frames(root / name / "frames.csv", lay), lay, stations))
    return stations, devs


def station_change(fitted, given):
    """Station 1's pose change from the given one: rotation angle (deg), position (mm)."""
    from scipy.spatial.transform import Rotation

    a, b = fitted[1], given[1]
    dR = Rotation.from_matrix(a.rotation @ b.rotation.T).magnitude()
    return float(np.rad2deg(dR)), float(1e3 * np.linalg.norm(a.translation - b.translation))


def fit(devs, stations, subset, **kw):
    from layoutkit.workflows.calibrate_devices import NO_FIT, fit_devices, joint_residual

    use = [d for d in devs if d.name in subset]
    t0 = time.time()
    res, parts = fit_devices(use, stations, sigma=SIGMA, **kw)
    out = {"fit_on": list(subset), "status": res.status, "seconds": round(time.time() - t0, 1)}
    if res.status in NO_FIT:
        return out, res, parts
    out["station1_change_deg_mm"] = station_change(res.stations, stations)
    out["joint_rad"] = {d.name: joint_residual(d, res.stations)["median_rad"] for d in devs}
    out["own_layout_rad"] = {d.name: joint_residual(d, res.stations, res.points_body[parts[d.name]["sensors"]])["median_rad"]
                             for d in use}
    st = {p.name: p.status for p in res.parameters if p.name.startswith("station")}
    out["station_terms"] = {s: sum(1 for v in st.values() if v == s) for s in sorted(set(st.values()))}
    return out, res, parts


def sweep(devs, stations, mw):
    rows = []
    for pr in PRIORS:
        kw = dict(max_windows=mw, station_prior=None if pr is None else (np.deg2rad(pr[0]), pr[1] * 1e-3),
                  hold_station_prior=False)
        row = {"prior_deg_mm": pr, "fits": {}}
        for subset in (("HMD", "T20"), ("HMD",), ("T20",)):
            f, _, _ = fit(devs, stations, subset, **kw)
            row["fits"]["+".join(subset)] = f
            print(pr, subset, f.get("joint_rad"), f.get("station1_change_deg_mm"), f["seconds"], flush=True)
        rows.append(row)
    return rows


def rule_prior(devs, stations):
    """Section 2's rule: (rad, m)."""
    from layoutkit.workflows.calibrate_devices import joint_residual

    fac = [joint_residual(d, stations)["median_rad"] for d in devs]
    att = float(np.median(fac))
    dist = []
    for d in devs:
        t = d.start.translation[d.usable]
        for st in stations:
            dist.append(np.median(np.linalg.norm(t - st.translation, axis=1)))
    return att, att * float(np.median(dist)), fac, [float(x) for x in dist]


def determined_alone(devs, stations, mw):
    """Section 3: station 1's 6 terms fitted on each device alone, with their sds."""
    out = {}
    from layoutkit.workflows.calibrate_devices import fit_devices

    for d in devs:
        res, _ = fit_devices([d], stations, sigma=SIGMA, max_windows=mw)
        ps = [p for p in res.parameters if p.name.startswith(f"station {stations[1].id} pose")]
        start = {p.name: p.start for p in ps}
        out[d.name] = {p.name.split()[-1]: {"change": p.value - (start[p.name] if p.unit == "m" else 0.0),
                                            "sd": p.std, "status": p.status, "unit": p.unit} for p in ps}
        out[d.name]["calibration_terms"] = {}
        for p in res.parameters:
            if not p.name.startswith("station") or " pose " in p.name:
                continue
            out[d.name]["calibration_terms"][p.status] = out[d.name]["calibration_terms"].get(p.status, 0) + 1
    a, b = out[devs[0].name], out[devs[1].name]
    out["disagreement_sigmas"] = {k: (a[k]["change"] - b[k]["change"]) / np.hypot(a[k]["sd"] or np.nan, b[k]["sd"] or np.nan)
                                  for k in ("d_rx", "d_ry", "d_rz", "tx", "ty", "tz")}
    return out


def subsets(devs, stations, mw):
    """Section 3, second half: station 1's attitude only / position only (the other held by a 1e-9 prior)."""
    rows = []
    for label, pr in (("attitude only", (np.deg2rad(1.0), 1e-9)), ("position only", (1e-9, 0.05))):
        for subset in (("HMD", "T20"), ("HMD",), ("T20",)):
            f, _, _ = fit(devs, stations, subset, max_windows=mw, station_prior=pr, hold_station_prior=False)
            f["label"] = label
            print(label, f, flush=True)
            rows.append(f)
    return rows


def with_offsets(devs, stations, mw, prior):
    """Section 4: each device's offsets as unknowns (prior: the hardware tolerance), stations free or
    under the rule's prior (MAP), fitted on both devices and on each alone (the held-out device with
    its nominal layout)."""
    rows = []
    for label, sp in (("stations free", None), ("rule prior", prior)):
        for subset in (("HMD", "T20"), ("HMD",), ("T20",)):
            f, res, parts = fit(devs, stations, subset, max_windows=mw, sensor_offsets=True,
                                offset_prior=HMD_OFFSET_TOLERANCE, station_prior=sp, hold_station_prior=False)
            f["median_offset_mm"] = {d.name: float(1e3 * np.median(np.linalg.norm(
                res.points_body[parts[d.name]["sensors"]] - d.layout.positions, axis=1))) for d in devs if d.name in subset}
            f["label"] = label
            f["sensor_terms"] = {}
            for p in res.parameters:
                if not p.name.startswith("station"):
                    f["sensor_terms"][p.status] = f["sensor_terms"].get(p.status, 0) + 1
            f["calibration_fitted"] = [p.name for p in res.parameters if p.name.startswith("station")
                                       and " pose " not in p.name and p.status in ("ok", "suspect")]
            print(label, f, flush=True)
            rows.append(f)
    return rows


def honest_weight(devs, stations, mw, prior, fac):
    """Section 5: sigma = median factory joint residual x sqrt(windows per pose)."""
    global SIGMA
    keep, SIGMA = SIGMA, float(np.median(fac)) * np.sqrt(mw)
    rows = []
    try:
        for subset in (("HMD", "T20"), ("HMD",), ("T20",)):
            f, res, _ = fit(devs, stations, subset, max_windows=mw, station_prior=prior, hold_station_prior=False)
            f["sigma_rad"] = SIGMA
            f["calibration_fitted"] = [p.name for p in res.parameters if p.name.startswith("station")
                                       and " pose " not in p.name and p.status in ("ok", "suspect")]
            print("honest", f, flush=True)
            rows.append(f)
    finally:
        SIGMA = keep
    return rows


def calibration_terms(devs, stations, mw):
    from layoutkit.workflows.calibrate_devices import fit_devices

    res, _ = fit_devices(devs, stations, sigma=SIGMA, max_windows=mw)
    return {p.name: {"status": p.status, "value": p.value, "start": p.start, "sd": p.std}
            for p in res.parameters if p.name.startswith("station") and " pose " not in p.name}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-windows", type=int, default=200, help="windows per device (random subset; static: one pose)")
    ap.add_argument("--markdown-only", action="store_true", help="rewrite transfer.md from transfer.json")
    ap.add_argument("--root", type=Path, default=None, help="an existing `layoutkit import libsurvive` folder")
    a = ap.parse_args()
    if a.markdown_only:
        write_markdown(json.loads((OUT / "transfer.json").read_text()), OUT / "transfer.md")
        return
    with tempfile.TemporaryDirectory() as tmp:
        root = a.root
        if root is None:
            root = Path(tmp) / "L"
            subprocess.run([str(Path(sys.executable).parent / "layoutkit"), "import", "libsurvive", str(REC),
                            "--out-dir", str(root)], check=True)
        stations, devs = load(root)
        att, pos, fac, dist = rule_prior(devs, stations)
        print("rule prior", np.rad2deg(att), pos * 1e3, fac, dist, flush=True)
        result = {"recording": REC.name, "sigma_rad": SIGMA, "max_windows": a.max_windows,
                  "factory_joint_rad": {d.name: f for d, f in zip(devs, fac)},
                  "rule_prior": {"deg": float(np.rad2deg(att)), "mm": pos * 1e3, "distances_m": dist}}
        result["alone"] = determined_alone(devs, stations, a.max_windows)
        print(json.dumps(result["alone"], default=float), flush=True)
        rule = [(float(np.rad2deg(att)), pos * 1e3)]
        result["subsets"] = subsets(devs, stations, a.max_windows)
        global PRIORS
        PRIORS = sorted(PRIORS[:-1] + rule) + [None]
        result["sweep"] = sweep(devs, stations, a.max_windows)
        result["offsets"] = with_offsets(devs, stations, a.max_windows, (att, pos))
        result["honest_weight"] = honest_weight(devs, stations, a.max_windows, (att, pos), fac)
        result["calibration_terms"] = calibration_terms(devs, stations, a.max_windows)
    OUT.mkdir(exist_ok=True)
    from layoutkit.io.jsonfile import to_jsonable

    (OUT / "transfer.json").write_text(json.dumps(to_jsonable(result), indent=2) + "\n")
    write_markdown(result, OUT / "transfer.md")


def _f(v):
    return "–" if v is None else f"{v:.3g}"


def write_markdown(r, path):
    fac = r["factory_joint_rad"]
    L = ["# lh1_test_cal: does a station calibration transfer? (`studies/libsurvive/transfer.py`)", "",
         f"Factory (LH_POSE) stations: joint residual HMD {_f(fac['HMD'])}, T20 {_f(fac['T20'])} rad "
         f"(median per-window RMS; sigma {r['sigma_rad']:.3g} rad; {r['max_windows']} windows per device).",
         f"Rule prior (stated before the run: factory joint residual scale): {r['rule_prior']['deg']:.3g} deg, "
         f"{r['rule_prior']['mm']:.3g} mm.", "",
         "| station prior (deg, mm) | both: HMD | both: T20 | HMD only: HMD | **held-out T20** (fit on HMD) | "
         "T20 only: T20 | **held-out HMD** (fit on T20) | station 1 change, both (deg, mm) | station terms, both |",
         "|---|---|---|---|---|---|---|---|---|"]
    for row in r["sweep"]:
        f = row["fits"]
        b, h, t = f["HMD+T20"], f["HMD"], f["T20"]
        pr = "free" if row["prior_deg_mm"] is None else f"{row['prior_deg_mm'][0]:.3g}, {row['prior_deg_mm'][1]:.3g}"
        jr = lambda x, k: _f(x.get("joint_rad", {}).get(k))  # noqa: E731
        ch = b.get("station1_change_deg_mm")
        L.append(f"| {pr} | {jr(b, 'HMD')} | {jr(b, 'T20')} | {jr(h, 'HMD')} | {jr(h, 'T20')} | {jr(t, 'T20')} | "
                 f"{jr(t, 'HMD')} | {'–' if ch is None else f'{ch[0]:.3g}, {ch[1]:.3g}'} | {b.get('station_terms')} |")
    L += ["", "Station 1 fitted on one device alone (free; change from LH_POSE ± sd incl. the layout consider term):", "",
          "| term | HMD alone | T20 alone | disagreement (sds) |", "|---|---|---|---|"]
    for k in ("d_rx", "d_ry", "d_rz", "tx", "ty", "tz"):
        h, t = r["alone"]["HMD"][k], r["alone"]["T20"][k]
        sc = 1e3 if h["unit"] == "m" else 1e3
        u = "mm" if h["unit"] == "m" else "mrad"
        L.append(f"| {k} ({u}) | {h['change'] * sc:.3g} ± {_f(None if h['sd'] is None else h['sd'] * sc)} | "
                 f"{t['change'] * sc:.3g} ± {_f(None if t['sd'] is None else t['sd'] * sc)} | "
                 f"{_f(r['alone']['disagreement_sigmas'][k])} |")
    L += ["", "Station 1's attitude only (position held) / position only (attitude held), MAP with a 1° / 50 mm prior on "
          "the free part:", "", "| part | fit on | HMD | T20 | station 1 change (deg, mm) |", "|---|---|---|---|---|"]
    for f in r.get("subsets", []):
        j, ch = f.get("joint_rad", {}), f.get("station1_change_deg_mm")
        L.append(f"| {f['label']} | {'+'.join(f['fit_on'])} | {_f(j.get('HMD'))} | {_f(j.get('T20'))} | "
                 f"{'–' if ch is None else f'{ch[0]:.3g}, {ch[1]:.3g}'} |")
    L += ["", f"Each device's sensor offsets as unknowns (prior {HMD_OFFSET_TOLERANCE * 1e3:g} mm per coordinate, "
          "the hardware tolerance), calibration terms free:", "",
          "| stations | fit on | HMD nominal layout | HMD own layout | T20 nominal | T20 own | station 1 change (deg, mm) | "
          "median offset (mm) | sensor terms | calibration terms fitted |", "|---|---|---|---|---|---|---|---|---|---|"]
    for f in r["offsets"]:
        j, o = f.get("joint_rad", {}), f.get("own_layout_rad", {})
        ch = f.get("station1_change_deg_mm")
        L.append(f"| {f['label']} | {'+'.join(f['fit_on'])} | {_f(j.get('HMD'))} | {_f(o.get('HMD'))} | {_f(j.get('T20'))} | "
                 f"{_f(o.get('T20'))} | {'–' if ch is None else f'{ch[0]:.3g}, {ch[1]:.3g}'} | "
                 f"{', '.join(f'{k} {v:.2g}' for k, v in f['median_offset_mm'].items())} | {f['sensor_terms']} | "
                 f"{len(f['calibration_fitted'])} |")
    h = r["honest_weight"]
    L += ["", f"Honest data weight (sigma = factory joint residual x sqrt(windows per pose) = {h[0]['sigma_rad']:.3g} rad), "
          "rule station prior, calibration terms free:", "",
          "| fit on | HMD | T20 | station 1 change (deg, mm) | calibration terms fitted |", "|---|---|---|---|---|"]
    for f in h:
        j, ch = f.get("joint_rad", {}), f.get("station1_change_deg_mm")
        L.append(f"| {'+'.join(f['fit_on'])} | {_f(j.get('HMD'))} | {_f(j.get('T20'))} | "
                 f"{'–' if ch is None else f'{ch[0]:.3g}, {ch[1]:.3g}'} | {len(f['calibration_fitted'])} |")
    L += ["", "(The fitted-term counts of this run are not a determination: the reported sds are rescaled by the "
          "observed residual scale, which undoes the inflated sigma; only the fitted values and folds count.)"]
    for f in r["offsets"]:
        if f["calibration_fitted"]:
            L.append(f"- offsets as unknowns, {f['label']}, fit on {'+'.join(f['fit_on'])}: calibration terms "
                     f"determined: {', '.join(f['calibration_fitted'])}")
    cnt: dict = {}
    for v in r["calibration_terms"].values():
        cnt[v["status"]] = cnt.get(v["status"], 0) + 1
    L += ["", f"Calibration terms in the two-device fit (stations free): {cnt}; determined (ok/suspect): "
          + (", ".join(k for k, v in r["calibration_terms"].items() if v["status"] in ("ok", "suspect")) or "none"), ""]
    path.write_text("\n".join(L) + "\n")


if __name__ == "__main__":
    main()
