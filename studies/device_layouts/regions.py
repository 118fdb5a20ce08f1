"""Issue 27: where in the envelope does a layout's worst ADOP live? Every held-out pose binned by its view angle —
the angle between the device's front axis and its direction to the station (body frame; 0°: the station sees the
device face-on, 90°: edge-on) — and per band the number of poses, the 99.9th percentile and the worst ADOP of each
layout, over the six 20,000-pose draws (envelope seed + 200 … + 205, the poses both ``run.py`` and
``large_draws.py`` score; self-occlusion, 60° acceptance). Also which band holds each study 2,000-pose draw's
worst.

    .venv/bin/python studies/device_layouts/regions.py [--device wm0_tangent] --layouts refine_az4_p12 refine_p12_p6

Writes ``results/regions_<device>.json``, ``.md`` and ``.png`` (results only; the layouts in ``results/<device>/``).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from devices import device_of_folder, mesh_path
from large_draws import LARGE
from run import FRESH, _scores

BANDS = np.arange(0.0, 120.0 + 1e-9, 10.0)


def view_angle(env, front, R, t):
    """(P,) view angle (deg) of world poses ``R (P, 3, 3), t (P, 3)``: between the body axis ``front`` (3,) and the
    body-frame direction to the envelope's first station."""
    Rs, ts = env.stations[0].world_to_station(R, t)
    to_station = -np.einsum("pji,pj->pi", Rs, ts)  # body frame: Rs^T (0 - ts)
    to_station /= np.linalg.norm(to_station, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip(to_station @ (np.asarray(front, float) / np.linalg.norm(front)), -1.0, 1.0)))


def view_angles(env, front, sets):
    """:func:`view_angle` of every pose of ``sets`` (label, count, seed offset), concatenated in order."""
    from layoutkit.envelope import envelope_set

    return np.concatenate([view_angle(env, front, *envelope_set(env, count=n, seed=env.seed + dseed)[1:])
                           for _, n, dseed in sets])


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="wm0_tangent", help="results folder of the device")
    ap.add_argument("--layouts", nargs="+", required=True)
    ap.add_argument("--need", type=float, default=None,
                    help="ADOP line to draw (default: half the shipped layout's smallest worst over the 2,000-pose draws)")
    a = ap.parse_args()

    from layoutkit.envelope import load_envelope
    from layoutkit.io.atomic import atomic_write_text
    from layoutkit.io.figures import save_figure

    folder = HERE / "results" / a.device
    dev = device_of_folder(a.device)
    env = load_envelope(folder / "env.toml")
    if len(env.stations) != 1:
        raise SystemExit(f"{folder / 'env.toml'}: view angles need one station, the envelope has {len(env.stations)}")
    front = np.asarray(dev.front, float) / np.linalg.norm(dev.front)
    large = [s for s in FRESH + LARGE if s[1] == 20000]
    small = [s for s in FRESH if s[1] == 2000]
    ang_large, ang_small = view_angles(env, front, large), view_angles(env, front, small)
    band_of = np.digitize(ang_large, BANDS) - 1
    res = {"device": a.device, "front_axis_body": front.tolist(), "bands_deg": BANDS.tolist(),
           "poses_per_band": np.bincount(band_of, minlength=len(BANDS) - 1)[:len(BANDS) - 1].tolist(), "layouts": {}}
    for name in ["shipped"] + a.layouts:
        path = folder / ("shipped.json" if name == "shipped" else f"{name}.layout.json")
        sc = _scores(path, str(mesh_path(folder)), env, sets=large + small)
        adop = np.concatenate([sc[lab]["_adop"] for lab, _, _ in large])
        rows = []
        for b in range(len(BANDS) - 1):
            x = adop[(band_of == b) & np.isfinite(adop)]
            rows.append({"p999": float(np.quantile(x, 0.999)) if x.size else None,
                         "worst": float(x.max()) if x.size else None,
                         "untracked": int(np.sum((band_of == b) & ~np.isfinite(adop)))})
        draws, off = [], 0
        for lab, n, _ in small:
            x = sc[lab]["_adop"]
            i = int(np.argmax(np.where(np.isfinite(x), x, -np.inf)))
            draws.append({"set": lab, "worst": float(x[i]), "view_angle_deg": float(ang_small[off + i])})
            off += n
        res["layouts"][name] = {"bands": rows, "draw_worsts": draws}
        print(name, [round(r["worst"]) if r["worst"] else None for r in rows], flush=True)
    need = a.need or 0.5 * min(d["worst"] for d in res["layouts"]["shipped"]["draw_worsts"])
    res["need"] = need

    names = list(res["layouts"])
    lines = [(f"View-angle bands of the {a.device} rows (regions.py): worst ADOP (p99.9) over the six 20,000-pose "
             f"draws per band; the line the tracker's 2,000-pose draws ask for is {need:,.0f}."), "",
             "| view angle | poses | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    for b in range(len(BANDS) - 1):
        cells = []
        for nm in names:
            r = res["layouts"][nm]["bands"][b]
            cells.append("–" if r["worst"] is None else f"{r['worst']:,.0f} ({r['p999']:,.0f})")
        lines.append(f"| {BANDS[b]:.0f}–{BANDS[b + 1]:.0f}° | {res['poses_per_band'][b]:,} | " + " | ".join(cells) + " |")
    lines += ["", "Each 2,000-pose draw's worst pose (ADOP @ view angle):", "",
              "| layout | " + " | ".join(s[0] for s in small) + " |", "|---|" + "---|" * len(small)]
    for nm in names:
        lines.append(f"| {nm} | " + " | ".join(f"{d['worst']:,.0f} @ {d['view_angle_deg']:.0f}°"
                                              for d in res["layouts"][nm]["draw_worsts"]) + " |")
    atomic_write_text(HERE / "results" / f"regions_{a.device}.md", "\n".join(lines) + "\n")
    atomic_write_text(HERE / "results" / f"regions_{a.device}.json", json.dumps(res, indent=1) + "\n")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.4))
    mid = 0.5 * (BANDS[1:] + BANDS[:-1])
    for nm in names:
        w = np.array([np.nan if r["worst"] is None else r["worst"] for r in res["layouts"][nm]["bands"]])
        row = folder / f"{nm}.json"  # a row's record (the shipped layout has none)
        region = (json.loads(row.read_text()).get("spec", {}).get("view_angle_deg")
                  if nm != "shipped" and row.exists() else None)
        if region:  # an ablation (refine.py --view-angle-deg) is drawn over its own region only
            w[(mid < region[0]) | (mid > region[1])] = np.nan
        ax.plot(mid, w, marker="s" if region else "o", ls=":" if region else "-",
                lw=2.2 if nm == "shipped" else 1.2, label=nm + (" (designed for this region only)" if region else ""))
    ax.axhline(need, color="k", ls="--", lw=1, label=f"½ shipped's best 2,000-pose worst ({need:,.0f})")
    ax.set(xlabel="view angle: front axis to station (deg)", ylabel="worst ADOP over 120,000 poses (deg/rad)",
           title=f"{dev.label}: where the worst case lives", yscale="log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    save_figure(fig, HERE / "results" / f"regions_{a.device}.png",
                caption="Worst ADOP per 10° band of view angle over 120,000 held-out poses (six 20,000-pose draws), "
                        "self-occlusion, 60° acceptance. Dashed: what 2x on every study 2,000-pose draw needs.")


if __name__ == "__main__":
    main()
