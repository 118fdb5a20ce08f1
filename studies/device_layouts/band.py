"""Issue 27: where a layout's band near the worst lies on its design poses — by view angle and lit count.

    .venv/bin/python studies/device_layouts/band.py --device wm0_tangent --layout refine_c59_d200k [--poses 50000]

Scores the layout on the design poses (envelope seed + ``--seed-offset``, default + 5000: the refine rows' design
set, never a set the study reports on) at 60° with self-occlusion, and prints, for the poses above ``--level``
(default 3,550: the worst the tracker's hardest 2,000-pose draw allows), their count per 10° band of view angle
(:func:`regions.view_angle`) and per lit count, and how many sensors each band lights. Prints only; nothing written.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from devices import device_of_folder, mesh_path
from regions import view_angle
from run import RHO, SCORE_HALF_ANGLE_DEG, M


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="wm0_tangent")
    ap.add_argument("--layout", required=True, help="row (<row>.layout.json in results/<device>/)")
    ap.add_argument("--poses", type=int, default=50000)
    ap.add_argument("--seed-offset", type=int, default=5000)
    ap.add_argument("--level", type=float, default=3550.0, help="ADOP (deg/rad) that counts as the band")
    a = ap.parse_args()

    from layoutkit.dop_batch import batch_dop
    from layoutkit.envelope import envelope_set, load_envelope
    from layoutkit.layout import load_layout
    from layoutkit.mesh import load_mesh
    from layoutkit.optimize.design import layout_visibility

    folder = HERE / "results" / a.device
    env, dev = load_envelope(folder / "env.toml"), device_of_folder(a.device)
    lay = load_layout(folder / f"{a.layout}.layout.json")
    _, R, t = envelope_set(env, count=a.poses, seed=env.seed + a.seed_offset)
    vis = layout_visibility(load_mesh(str(mesh_path(folder))), lay.positions, lay.normals, R, t, env.stations,
                            SCORE_HALF_ANGLE_DEG)
    d = batch_dop(lay.positions, R, t, rho=RHO, visible=vis, stations=env.stations)
    lit, va = d.n_visible, view_angle(env, dev.front, R, t)
    adop = np.where(lit >= M, d.adop, np.inf)  # the study's rule: a pose with fewer than M lit is untracked
    hi = np.isfinite(adop) & (adop > a.level)
    front = np.degrees(np.arccos(np.clip(lay.normals @ np.asarray(dev.front), -1, 1)))
    print(f"{a.layout}: {a.poses} poses (seed + {a.seed_offset}), {(~np.isfinite(adop)).sum()} untracked, "
          f"{hi.sum()} above {a.level:g}, worst {np.max(adop[np.isfinite(adop)]):.0f} over the tracked; "
          f"sensors within 60° of the front axis: {(front <= 60).sum()}, "
          f"beyond 90°: {(front > 90).sum()}")
    print("view angle | poses | above | lit count of the poses (4, 5, 6, ...)")
    for lo in range(0, 130, 10):
        m = (va >= lo) & (va < lo + 10)
        if m.any():
            print(f"{lo:3d}-{lo + 10:<3d}° | {m.sum():6d} | {(hi & m).sum():5d} | {np.bincount(lit[m], minlength=10)[4:10].tolist()}")
    print("lit count of the poses above:", {k: int((lit[hi] == k).sum()) for k in range(4, 10)})


if __name__ == "__main__":
    main()
