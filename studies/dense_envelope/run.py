"""Issue 13 study: layouts that hold on poses they were not tuned on (synthetic headset-like device).

    .venv/bin/python studies/dense_envelope/run.py [--quick] [--out studies/dense_envelope]

Device (built like the headset trial of the issue): a convex "visor" — the convex hull of the front
half (z >= -0.03 m) of an ellipsoid with semi-axes 0.095 × 0.06 × 0.05 m — as the mesh, candidate
sites sampled on the hull (``--spacing-mm``, ~10 mm), a ±90° front envelope (body +z towards the
station within 90°, random roll), 1–3 m from one LH1 station, rho 0.8717, 60° photodiode
half-angle, k sensors, ≥ 4 lit everywhere, worst ADOP.
Layouts compared on 2,000 held-out poses (fresh seed):
- hand: k sites spread by farthest-point sampling over the candidates (a sensible even layout);
- optimised on the 200 design poses only;
- optimised with adaptive pose generation against a dense set of 10⁴ more poses (``--dense-poses``).
Two stations (1 m apart, both looking at the envelope): each-station coverage, then an independent
count over the dense set of poses that have no single-station fix (< 4 sensors lit by every station
alone... i.e. by neither station).
Writes results.json, results.md and dense_cdf.png into --out.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def device(spacing):
    import trimesh

    from layoutkit.candidates import sample_candidates

    sph = trimesh.creation.icosphere(subdivisions=4)
    v = sph.vertices * np.array([0.095, 0.06, 0.06])
    v = v[v[:, 2] >= -0.04]
    hull = trimesh.Trimesh(v).convex_hull
    cand = sample_candidates(hull, spacing=spacing, rng=0)
    return hull, cand


def envelope(count, seed, stations=None):
    from layoutkit.envelope import Envelope

    d = {"name": "visor-front-90", "count": count, "seed": seed, "range_m": [1.0, 3.0],
         "boresight_cone_deg": 30.0,
         "attitude": {"kind": "cone", "nominal_rotvec_deg": [180.0, 0.0, 0.0], "half_angle_deg": 90.0}}
    if stations:
        d["station"] = stations
    return Envelope.from_dict(d)


def hand_layout(cand, k):
    """Farthest-point sampling over the candidate sites not on the flat back plate (normal z > -0.5),
    starting from the front-most one: an even spread over the visor."""
    P = cand.positions
    front = cand.normals[:, 2] > -0.5
    sel = [int(np.argmax(P[:, 2]))]
    d = np.where(front, np.linalg.norm(P - P[sel[0]], axis=1), -1.0)
    while len(sel) < k:
        j = int(np.argmax(d))
        sel.append(j)
        d = np.where(front, np.minimum(d, np.linalg.norm(P - P[j], axis=1)), -1.0)
    return np.array(sorted(sel))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--k", type=int, default=24)
    ap.add_argument("--spacing-mm", type=float, default=10.0)
    ap.add_argument("--dense-poses", type=int, default=10000)
    ap.add_argument("--time-limit-s", type=float, default=240.0)
    ap.add_argument("--out", default=str(Path(__file__).parent))
    args = ap.parse_args()
    if args.quick:
        args.spacing_mm, args.dense_poses, args.time_limit_s, args.k = 16.0, 3000, 60.0, 20
    import cvxpy  # noqa: F401

    from layoutkit.coverage_rule import covered, layout_counts
    from layoutkit.layout import Layout
    from layoutkit.optimize import optimize_stations
    from layoutkit.workflows.dense import dense_optimize, evaluate_selection
    from layoutkit.workflows.optimize import prepare_problem
    from layoutkit.workflows.score import envelope_set, layout_visibility, score_arrays

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    hull, cand = device(args.spacing_mm * 1e-3)
    env = envelope(200, 13)
    prep = prepare_problem(hull, env, candidates=cand)
    N = cand.n
    k = args.k
    rho = 0.8717
    _, Rh, th = envelope_set(env, count=2000, seed=env.seed + 2)
    res = {"device": {"candidates": N, "k": k, "mesh": "convex hull of a ellipsoid 0.19 x 0.12 x 0.12 m cut at z = -0.04 m",
                      "envelope": "±90° front, 1–3 m, 200 design poses"}, "layouts": {}}

    def stats(sel, R, t):
        a, p, cov = evaluate_selection(prep, sel, R, t, rho, 4, "any-station")
        x = a[cov]
        return {"poses": int(len(a)), "covered": float(cov.mean()), "worst_adop": float(x.max()) if len(x) else None,
                "median_adop": float(np.median(x)) if len(x) else None,
                "p99_adop": float(np.percentile(x, 99)) if len(x) else None,
                "worst_pdop": float(p[cov].max()) if len(x) else None, "_adop": a, "_cov": cov}

    sets = {}
    hand = hand_layout(cand, k)
    sets["hand"] = hand
    t0 = time.perf_counter()
    kw = dict(objective="worst-adop", rho=rho, min_visible=4, time_limit=args.time_limit_s / 2)
    r_design = optimize_stations(prep["jac"], prep["visible"], k, rng=0, **kw)
    t_design = time.perf_counter() - t0
    print("design-only:", r_design.message, flush=True)
    if r_design.success:
        sets["optimised (200 design poses)"] = r_design.selected
    t0 = time.perf_counter()
    r_dense, info = dense_optimize(prep, k, {x: v for x, v in kw.items() if x != "time_limit"},
                                   dense_poses=args.dense_poses, time_limit=args.time_limit_s, echo=print)
    t_dense = time.perf_counter() - t0
    print("dense:", r_dense.message, info["rounds"], flush=True)
    sets["optimised (dense, adaptive)"] = r_dense.selected
    _, Rd, td = envelope_set(env, count=args.dense_poses, seed=env.seed + 1)
    for name, sel in sets.items():
        row = {"design": stats(sel, prep["rotations"], prep["translations"]), "dense": stats(sel, Rd, td),
               "heldout": stats(sel, Rh, th)}
        res["layouts"][name] = row
    res["dense_run"] = {"rounds": info["rounds"], "note": info["note"],
                        "uncoverable_dense_poses": info["uncoverable_dense_poses"], "working_set_poses": info["working_set_poses"],
                        "bound": r_dense.bound, "dense_gap": info["dense_gap"], "time_s": t_dense}
    res["design_run"] = {"value": r_design.value, "bound": r_design.bound, "gap": r_design.gap, "time_s": t_design}
    H = res["layouts"]["hand"]["heldout"]["worst_adop"]
    O = res["layouts"]["optimised (dense, adaptive)"]
    res["must_show"] = {"heldout_worst_hand": H, "heldout_worst_opt": O["heldout"]["worst_adop"],
                        "improvement_x": H / O["heldout"]["worst_adop"],
                        "heldout_over_design": O["heldout"]["worst_adop"] / O["design"]["worst_adop"]}
    print(res["must_show"], flush=True)

    # two stations, each-station coverage
    st = [{"id": "A", "position_m": [-0.5, 0.0, 0.0], "look_at_m": [0.0, 0.0, 2.0]},
          {"id": "B", "position_m": [0.5, 0.0, 0.0], "look_at_m": [0.0, 0.0, 2.0]}]
    env2 = envelope(200, 21, st)
    prep2 = prepare_problem(hull, env2, candidates=cand)
    r2, info2 = dense_optimize(prep2, k, {x: v for x, v in kw.items() if x != "time_limit"},
                               dense_poses=args.dense_poses, coverage="each-station",
                               time_limit=args.time_limit_s, echo=print)
    _, R2, t2 = envelope_set(env2, count=args.dense_poses, seed=env2.seed + 1)
    two = {"status": r2.status, "message": r2.message}
    if r2.success:
        sel2 = r2.selected
        vis2 = layout_visibility(hull, cand.positions[sel2], cand.normals[sel2], R2, t2, env2.stations, 60.0)
        # independent count: a plain loop over poses and stations
        no_fix = 0
        for p in range(len(R2)):
            if not any(int(vis2[p, s].sum()) >= 4 for s in range(2)):
                no_fix += 1
        any_cov = covered(layout_counts(vis2, "any-station"), 4)
        # the any-station optimum for comparison
        r2a, _ = dense_optimize(prep2, k, {x: v for x, v in kw.items() if x != "time_limit"},
                                dense_poses=args.dense_poses, coverage="any-station",
                                time_limit=args.time_limit_s / 2)
        vis2a = layout_visibility(hull, cand.positions[r2a.selected], cand.normals[r2a.selected], R2, t2,
                                  env2.stations, 60.0)
        no_fix_any = sum(1 for p in range(len(R2)) if not any(int(vis2a[p, s].sum()) >= 4 for s in range(2)))
        two.update({"dense_poses": int(len(R2)), "poses_without_single_station_fix": no_fix,
                    "poses_without_single_station_fix_any_station_layout": no_fix_any,
                    "any_station_covered_fraction": float(any_cov.mean()),
                    "worst_adop_each_station": info2["dense_value"]})
    res["two_stations"] = two
    print("two stations:", two, flush=True)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name, row in res["layouts"].items():
        a = np.sort(row["heldout"]["_adop"][row["heldout"]["_cov"]])
        ax.plot(a, np.arange(1, len(a) + 1) / row["heldout"]["poses"], label=f"{name}: worst {a.max():.0f}")
    ax.set_xscale("log")
    ax.set_xlabel("ADOP (deg/rad) on 2,000 held-out poses")
    ax.set_ylabel("fraction of poses")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "dense_cdf.png", dpi=110)
    for row in res["layouts"].values():
        for v in row.values():
            v.pop("_adop"), v.pop("_cov")
    from layoutkit._json import to_jsonable

    (out / "results.json").write_text(json.dumps(to_jsonable(res), indent=2) + "\n")
    lines = ["| layout | design worst | dense worst | held-out worst | held-out p99 | held-out median |", "|---|---|---|---|---|---|"]
    for name, row in res["layouts"].items():
        lines.append(f"| {name} | {row['design']['worst_adop']:.0f} | {row['dense']['worst_adop']:.0f} | "
                     f"{row['heldout']['worst_adop']:.0f} | {row['heldout']['p99_adop']:.0f} | {row['heldout']['median_adop']:.0f} |")
    (out / "results.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
