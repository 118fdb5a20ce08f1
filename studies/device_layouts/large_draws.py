"""Issue 27: is the headset's per-draw ratio a small-sample effect? The best tilted layouts and the
shipped one on five more fresh draws of 20,000 poses each (envelope seed + 201 … + 205) besides the
study's sets, self-occlusion by the hull, worst ADOP per draw and the ratio shipped / ours.

    .venv/bin/python studies/device_layouts/large_draws.py [--layouts tilt_az4_spare1_s1 tilt_spare1_s1]

A worst case over 2,000 poses estimates the supremum over the envelope poorly for a layout with rare
bad attitudes: the shipped layout's worst over 2,000 poses ranged 5,506–10,051 across five draws. Writes
``results/large_draws.json`` and ``results/large_draws.md`` (results only; uses the layouts and hull in
``results/hmd/``)."""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from layoutkit.envelope import load_envelope

from devices import mesh_path
from run import FRESH, _scores

LARGE = [(f"fresh 20k seed+{s}", 20000, s) for s in range(201, 206)]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="hmd")
    ap.add_argument("--folder", default=None, help="layouts folder (default results/<device>)")
    ap.add_argument("--layouts", nargs="*", default=["tilt_az4_spare1_s1", "tilt_spare1_s1", "tilt_az4_spare1_s1_h55"])
    ap.add_argument("--chunks", type=int, default=10,
                    help="also split each 20,000-pose set into this many disjoint draws (2,000 poses each): the "
                         "per-draw ratio over many fresh small draws, on the same poses for every layout")
    a = ap.parse_args()
    folder = Path(a.folder) if a.folder else HERE / "results" / a.device
    env = load_envelope(folder / "env.toml")
    sets = FRESH + LARGE
    t0 = time.time()
    rows, chunked, adops = {}, {}, {}
    for name in ["shipped"] + a.layouts:
        path = folder / ("shipped.json" if name == "shipped" else f"{name}.layout.json")
        sc = _scores(path, str(mesh_path(folder)), env, sets=sets)
        rows[name] = {lab: sc[lab]["worst_adop"] for lab, _, _ in sets}
        rows[name]["_covered"] = {lab: sc[lab]["covered_fraction"] for lab, _, _ in sets}
        adops[name] = {lab: sc[lab]["_adop"] for lab, _, _ in sets}
        chunked[name] = np.concatenate([np.max(np.array_split(sc[lab]["_adop"], a.chunks), axis=1)
                                        for lab, n, _ in sets if n == 20000])
        print(name, {k: round(v) if math.isfinite(v) else v for k, v in rows[name].items() if k[0] != "_"}, flush=True)
    def common_worst(x, y):
        """worst of x and of y over the poses both track (finite in both)"""
        both = np.isfinite(x) & np.isfinite(y)
        return float(np.max(x[both])), float(np.max(y[both]))

    common, common_chunks = {}, {}
    for name in a.layouts:
        common[name] = {}
        for lab, _, _ in sets:
            sw, ow = common_worst(adops["shipped"][lab], adops[name][lab])
            common[name][lab] = sw / ow
        common_chunks[name] = np.array([np.divide(*common_worst(xs, ys)) for lab, n, _ in sets if n == 20000
                                        for xs, ys in zip(np.array_split(adops["shipped"][lab], a.chunks),
                                                          np.array_split(adops[name][lab], a.chunks))])
    partial = any(v < 1.0 for r in rows.values() for v in r["_covered"].values())
    draws2k = {}
    for name in a.layouts:
        r = chunked["shipped"] / chunked[name]
        draws2k[name] = {"draws": len(r), "worst_adop_min_median_max": [float(np.min(chunked[name])),
                       float(np.median(chunked[name])), float(np.max(chunked[name]))],
                       "x_shipped_min_median_max": [float(np.min(r)), float(np.median(r)), float(np.max(r))],
                       "draws_at_least_2x": int((r >= 2.0).sum()),
                       "x_shipped_on_poses_both_track_min_median_max": [float(np.min(common_chunks[name])),
                       float(np.median(common_chunks[name])), float(np.max(common_chunks[name]))],
                       "draws_at_least_2x_on_poses_both_track": int((common_chunks[name] >= 2.0).sum())}
    sh = chunked["shipped"]
    out = {"device": a.device, "folder": str(folder), "sets": [lab for lab, _, _ in sets], "worst_adop": rows,
           "x_shipped_on_poses_both_track": common,
           "chunked_2000_pose_draws": {"chunks_per_20k_set": a.chunks, "shipped_worst_adop_min_median_max":
                                       [float(np.min(sh)), float(np.median(sh)), float(np.max(sh))], "layouts": draws2k},
           "wall_s": time.time() - t0, "loadavg": os.getloadavg()}
    stem = "large_draws" if folder.name == "hmd" else f"large_draws_{folder.name}"
    (HERE / "results" / f"{stem}.json").write_text(json.dumps(out, indent=1, default=str) + "\n")
    lines = ["Worst ADOP (deg/rad), self-occlusion by the mesh (∞: a pose with fewer than 4 lit); ×shipped = shipped worst / this worst on the same set "
             f"(`python studies/device_layouts/large_draws.py --device {a.device} --layouts {' '.join(a.layouts)}`; "
             f"mesh `{mesh_path(folder).relative_to(HERE / 'results')}`).", "",
             "| layout | " + " | ".join(lab.replace("fresh ", "") for lab, _, _ in sets) + " | min ×shipped, 2,000-pose draws | min ×shipped, 20,000-pose sets |",
             "|---|" + "---|" * (len(sets) + 2)]
    ship = rows["shipped"]
    for name, r in rows.items():
        cells = [f"{r[lab]:,.0f}" if math.isfinite(r[lab]) else "∞" for lab, _, _ in sets]
        if name == "shipped":
            lines.append(f"| {name} | " + " | ".join(cells) + " | – | – |")
            continue
        ratio = {lab: ship[lab] / r[lab] for lab, _, _ in sets}
        small = min(ratio[lab] for lab, n, _ in sets if n == 2000)
        large = min(ratio[lab] for lab, n, _ in sets if n == 20000)
        lines.append(f"| {name} | " + " | ".join(f"{c} ({ratio[lab]:.2f}×)" for c, (lab, _, _) in zip(cells, sets))
                     + f" | {small:.2f} | {large:.2f} |")
    if partial:
        lines += ["", "Some layout leaves poses untracked: coverage per set (min) and ×shipped on the poses both track "
                  "(min over the 2,000-pose draws / over the 20,000-pose sets): " + "; ".join(
                      f"{name} covered ≥ {100 * min(rows[name]['_covered'].values()):.2f} %"
                      + ("" if name == "shipped" else
                         f", ×shipped {min(common[name][lab] for lab, n, _ in sets if n == 2000):.2f} / "
                         f"{min(common[name][lab] for lab, n, _ in sets if n == 20000):.2f}")
                      for name in rows) + "."]
    k = len(chunked["shipped"])
    lines += ["", f"The six 20,000-pose sets split into {k} disjoint draws of {20000 // a.chunks:,} poses (fresh draws of the "
              f"small size, the same poses for every layout): the shipped layout's worst per draw ranges "
              f"{np.min(sh):,.0f} (median {np.median(sh):,.0f}) to {np.max(sh):,.0f}.", "",
              "| layout | worst per draw: min / median / max | ×shipped per draw: min / median / max | draws ≥ 2× |",
              "|---|---|---|---|"]
    for name, v in draws2k.items():
        w, r = v["worst_adop_min_median_max"], v["x_shipped_min_median_max"]
        if partial:
            lines.append(f"| {name} | {w[0]:,.0f} / {w[1]:,.0f} / {w[2]:,.0f} | – (poses untracked: below) | – |")
            continue
        lines.append(f"| {name} | {w[0]:,.0f} / {w[1]:,.0f} / {w[2]:,.0f} | {r[0]:.2f} / {r[1]:.2f} / {r[2]:.2f} | "
                     f"{v['draws_at_least_2x']} of {v['draws']} |")
    if partial:
        lines += ["", "On the poses both track, per 2,000-pose draw: " + "; ".join(
            f"{name} {v['x_shipped_on_poses_both_track_min_median_max'][0]:.2f} / "
            f"{v['x_shipped_on_poses_both_track_min_median_max'][1]:.2f} / "
            f"{v['x_shipped_on_poses_both_track_min_median_max'][2]:.2f}× (min / median / max), ≥ 2× on "
            f"{v['draws_at_least_2x_on_poses_both_track']} of {v['draws']}" for name, v in draws2k.items()) + "."]
    (HERE / "results" / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
