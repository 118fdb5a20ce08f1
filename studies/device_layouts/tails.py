"""Issue 27: what are a layout's rare bad attitudes (its held-out tails)? For the worst poses of a layout on
the large 20,000-pose draws: how many sensors are lit, at what angle to their axes (near the 60° edge of the
acceptance cone?), how many face the station but are occluded by the hull, how many sit just outside the cone,
the range, the attitude's angle from the envelope's nominal, and what the pose's ADOP would be with a wider
(65°) or narrower (55°) acceptance cone (a lit-set edge: the ADOP jumps when one sensor crosses the cone).

    .venv/bin/python studies/device_layouts/tails.py [--layout tilt_az4_spare1_s1] [--seeds 204 205] [--top 8]

Writes ``results/tails_<layout>.json`` and ``results/tails_<layout>.md`` (results only; the layout and hull in
``results/<device>/``)."""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from layoutkit.envelope import envelope_set, load_envelope

from devices import mesh_path
from run import RHO, M


def pose_angles(lay, R, t, station):
    """(P, n) angle (deg) between each sensor's axis and its direction to ``station``; (P,) range (m)."""
    Rs, ts = station.world_to_station(R, t)
    p = np.einsum("pij,nj->pni", Rs, lay.positions) + ts[:, None, :]
    n = np.einsum("pij,nj->pni", Rs, lay.normals)
    to = -p / np.linalg.norm(p, axis=-1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.sum(n * to, -1), -1, 1))), np.linalg.norm(ts, axis=-1)


def diagnose(folder: Path, layout: str, seeds, top: int):
    from layoutkit.dop_batch import batch_dop
    from layoutkit.layout import load_layout
    from layoutkit.mesh import load_mesh
    from layoutkit.optimize.design import layout_visibility

    env = load_envelope(folder / "env.toml")
    lay = load_layout(folder / ("shipped.json" if layout == "shipped" else f"{layout}.layout.json"))
    mesh = load_mesh(mesh_path(folder), "m")
    st = env.stations[0]
    from layoutkit.geometry import rotvec_to_matrix

    R0 = rotvec_to_matrix(np.deg2rad(env.nominal_rotvec_deg))[None]  # the attitude cone's axis
    out = []
    for s in seeds:
        _, R, t = envelope_set(env, count=20000, seed=env.seed + s)
        vis = layout_visibility(mesh, lay.positions, lay.normals, R, t, env.stations, 60.0)
        d = batch_dop(lay.positions, R, t, rho=RHO, visible=vis, stations=env.stations)
        lit = vis.sum(axis=(1, 2))
        adop = np.where(lit >= M, d.adop, np.inf)
        order = np.argsort(-adop)[:top]
        ang, rng = pose_angles(lay, R[order], t[order], st)
        alt = {}
        for ha in (55.0, 65.0):
            v2 = layout_visibility(mesh, lay.positions, lay.normals, R[order], t[order], env.stations, ha)
            d2 = batch_dop(lay.positions, R[order], t[order], rho=RHO, visible=v2, stations=env.stations)
            alt[ha] = (np.where(v2.sum(axis=(1, 2)) >= M, d2.adop, np.inf), v2.sum(axis=(1, 2)))
        facing = layout_visibility(None, lay.positions, lay.normals, R[order], t[order], env.stations, 60.0)
        for j, i in enumerate(order):
            a_lit = np.sort(ang[j][vis[i, 0]])
            out.append({
                "set": f"20k seed+{s}", "pose": int(i), "adop": float(adop[i]),
                "rank_in_set": j + 1, "median_adop_of_set": float(np.median(adop[np.isfinite(adop)])),
                "lit": int(lit[i]), "lit_angles_deg": [round(float(x), 1) for x in a_lit],
                "lit_within_5deg_of_edge": int((a_lit > 55.0).sum()),
                "facing_but_occluded": int(facing[j, 0].sum() - vis[i, 0].sum()),
                "outside_by_lt_5deg": int(((ang[j] > 60.0) & (ang[j] <= 65.0)).sum()),
                "range_m": float(rng[j]),
                "attitude_off_nominal_deg": float(np.degrees(np.arccos(np.clip(
                    (np.trace(R0[0].T @ R[i]) - 1) / 2, -1, 1)))),
                "adop_if_55deg": float(alt[55.0][0][j]), "lit_if_55deg": int(alt[55.0][1][j]),
                "adop_if_65deg": float(alt[65.0][0][j]), "lit_if_65deg": int(alt[65.0][1][j])})
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="hmd")
    ap.add_argument("--folder", default=None)
    ap.add_argument("--layout", default="tilt_az4_spare1_s1")
    ap.add_argument("--seeds", nargs="*", type=int, default=[204, 205])
    ap.add_argument("--top", type=int, default=8)
    a = ap.parse_args()
    folder = Path(a.folder) if a.folder else HERE / "results" / a.device
    rows = diagnose(folder, a.layout, a.seeds, a.top)
    res = HERE / "results"
    (res / f"tails_{a.layout}.json").write_text(json.dumps(rows, indent=1) + "\n")
    f = lambda x: "∞" if not math.isfinite(x) else f"{x:,.0f}"
    lines = [f"Worst poses of `{a.layout}` on 20,000-pose draws (self-occlusion by the hull, 60° cone; "
             f"`python studies/device_layouts/tails.py --layout {a.layout}`). Angles: each lit sensor's axis to the "
             "station, sorted. 'occl.': facing within 60° but hidden by the hull; '60–65°': just outside the cone; "
             "attitude: rotation angle from the envelope's nominal (cone half-angle 90°).", "",
             "| set | rank | ADOP | set median | lit | lit angles (deg) | > 55° | occl. | 60–65° | range m | attitude ° "
             "| ADOP at 55° (lit) | ADOP at 65° (lit) |", "|---|" + "---|" * 12]
    for r in rows:
        lines.append(f"| {r['set']} | {r['rank_in_set']} | {f(r['adop'])} | {f(r['median_adop_of_set'])} | {r['lit']} | "
                     f"{', '.join(str(x) for x in r['lit_angles_deg'])} | {r['lit_within_5deg_of_edge']} | "
                     f"{r['facing_but_occluded']} | {r['outside_by_lt_5deg']} | {r['range_m']:.2f} | "
                     f"{r['attitude_off_nominal_deg']:.1f} | {f(r['adop_if_55deg'])} ({r['lit_if_55deg']}) | "
                     f"{f(r['adop_if_65deg'])} ({r['lit_if_65deg']}) |")
    (res / f"tails_{a.layout}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
