"""Issue 13 study: sensor tilt where the surface normals lean away from the envelope.

    .venv/bin/python studies/tilt/run.py

Instance `layoutkit.optimize.tilt_instance.leaning_instance(n=8, P=20, lo=20, hi=50)`: 8 sites on a cap,
normals leaning 20–50° away from the body +z axis, body +z towards the station within 25°, 60° photodiode
half-angle, k = 5, ≥ 4 lit everywhere, rho 0.8717, worst ADOP. For each max tilt (0–40°, 4 azimuths): the
exhaustive optimum over all k-subsets of (site, orientation) candidates with one orientation per site, and the
pipeline's result. Writes results.json and tilt_worst_adop.png here.
"""
import json
import time
from pathlib import Path

import numpy as np

from layoutkit.optimize.core import candidate_jacobians, optimize_stations
from layoutkit.optimize.instances import cone_visibility
from layoutkit.optimize.tilt import site_conflicts, tilt_orientations
from layoutkit.optimize.tilt_instance import leaning_instance


def main():
    out = Path(__file__).parent
    pos, nor, R, t = leaning_instance(n=8, P=20, lo=20.0, hi=50.0)
    rows = []
    for tilt in (0.0, 10.0, 20.0, 30.0, 40.0):
        p2, a2, site, tl = tilt_orientations(pos, nor, tilt, 4)
        vis = cone_visibility(p2, a2, R, t, half_angle_deg=60)
        jac = candidate_jacobians(p2, R, t)
        C = site_conflicts(site)
        t0 = time.perf_counter()
        ex = optimize_stations(jac, vis[:, None], 5, rho=0.8717, method="exhaustive", conflict=C)
        t1 = time.perf_counter()
        pl = optimize_stations(jac, vis[:, None], 5, rho=0.8717, conflict=C, rng=0)
        rows.append({"max_tilt_deg": tilt, "candidates": int(len(p2)), "exhaustive": ex.value,
                     "exhaustive_s": t1 - t0, "pipeline": pl.value, "pipeline_status": pl.status,
                     "tilted_sensors": int((tl[ex.selected] > 0).sum()) if ex.success else None,
                     "status": ex.status})
        print(rows[-1], flush=True)
    from layoutkit._json import to_jsonable

    (out / "results.json").write_text(json.dumps(to_jsonable(rows), indent=2) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    x = [r["max_tilt_deg"] for r in rows]
    ax.plot(x, [r["exhaustive"] if np.isfinite(r["exhaustive"]) else np.nan for r in rows], "o-",
            label="exhaustive optimum")
    ax.plot(x, [r["pipeline"] if np.isfinite(r["pipeline"]) else np.nan for r in rows], "x--", label="pipeline")
    ax.set_xlabel("max tilt from the surface normal (deg)")
    ax.set_ylabel("worst ADOP (deg/rad)")
    ax.set_yscale("log")
    ax.set_title("normals leaning 20–50° away from the station: k = 5")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "tilt_worst_adop.png", dpi=110)


if __name__ == "__main__":
    main()
