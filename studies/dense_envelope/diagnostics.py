"""Session 20 diagnostics of the dense-envelope study (docs/optimize.md, "what the held-out pockets are").

    .venv/bin/python studies/dense_envelope/diagnostics.py polish-all [--time-limit-s 400] [--coverage-poses 40000]
    .venv/bin/python studies/dense_envelope/diagnostics.py pockets [--layout polish_all.json]
    .venv/bin/python studies/dense_envelope/diagnostics.py rays [--results results.json ...]
    .venv/bin/python studies/dense_envelope/diagnostics.py fresh [--results tilt/results.json]

``polish-all``: polish (1- and 2-swaps, kicks) from the committed dense-loop layout (results.json) with the whole
dense set — design + 10,000 dense + ``--coverage-poses`` coverage poses, ~9 GB of search arrays at 40,000 — as
the working set; prints its worst there and on the 2,000 held-out poses, writes ``polish_all.json`` (to
``--out``). ``pockets``: for the five worst held-out poses of a layout (``--layout`` JSON with "selected", default
the committed dense-loop layout) the nearest poses of that dense set by station direction in the body frame:
angle, range, lit sensors, ADOP and ADOP × 3 m / range (the range-dominance check). ``rays`` (session 21): every
layout of the given study results (default the committed results.json) on the 2,000 held-out poses and on their
*rays* — each held-out attitude and bearing over the whole 1–3 m range, by
:func:`layoutkit.optimize.poses.range_sweep_poses` (both ends and both sides of every half-angle crossing of the
layout's sensors: the worst case along each ray) — and on the rays of the 10,000 dense poses; writes ``rays.json``.
``fresh`` (session 22): every layout of one study results file (its device, tilt included) on five more fresh
2,000-pose sets of the envelope (seeds envelope seed + 100 … + 104, never used by any optimiser) and one fresh
20,000-pose set (seed + 200): is the held-out comparison one lucky draw? Writes ``fresh.json`` beside the results.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE))

RHO, K, M = 0.8717, 24, 4


def _setup(n_cov):
    from run import device, envelope

    from layoutkit.optimize import DesignProblem
    from layoutkit.envelope import envelope_set

    hull, cand = device(0.010)
    env = envelope(200, 13)
    prep = DesignProblem.load(hull, env, candidates=cand)
    _, Rd, td = envelope_set(env, count=10000, seed=env.seed + 1)
    _, Rc, tc = envelope_set(env, count=int(n_cov), seed=env.seed + 3)
    _, Rh, th = envelope_set(env, count=2000, seed=env.seed + 2)
    R = np.concatenate([prep.rotations, Rd, Rc])
    t = np.concatenate([prep.translations, td, tc])
    return hull, cand, prep, R, t, Rh, th


def _worst(prep, sel, R, t):
    """A layout's worst ADOP over poses ``R, t`` (∞ if any has < 4 lit), over the tracked ones, and the counts."""

    a, _, cov = prep.evaluate(sel, R, t, rho=RHO, min_visible=M, coverage="any-station")
    return {"poses": int(len(a)), "untracked": int((~cov).sum()),
            "worst_adop": float(a.max()) if cov.all() else float("inf"),
            "worst_adop_over_tracked": float(a[cov].max())}


def _committed():
    r = json.loads((HERE / "results.json").read_text())
    return np.array(r["layouts"]["optimised by the dense loop"]["sensors"])


def polish_all(args):
    from layoutkit.coverage_rule import covered, layout_counts
    from layoutkit.optimize import candidate_jacobians, optimize_stations
    from layoutkit.visibility import envelope_visibility

    hull, cand, prep, R, t, Rh, th = _setup(args.coverage_poses)
    vis = envelope_visibility(hull, cand.positions, cand.normals, R, t, prep.stations, sensor_half_angle_deg=60.0)
    ok = covered(layout_counts(vis, "any-station"), M)
    R, t, vis = R[ok], t[ok], vis[ok]
    sel0 = _committed()
    t0 = time.perf_counter()
    res = optimize_stations(candidate_jacobians(cand.positions, R, t, prep.stations), vis, K, rng=0,
                            time_limit=args.time_limit_s, objective="worst-adop", rho=RHO, min_visible=M,
                            branch_and_bound="off", method="polish",
                            ctx_options={"warm_start": sel0, "patience": 6, "two_swap": True})
    out = {"working_poses": int(len(R)), "time_s": time.perf_counter() - t0, "message": res.message}
    for lab, sel in (("start", sel0), ("polished", res.selected)):
        a, _, cov = prep.evaluate(sel, R, t, rho=RHO, min_visible=M, coverage="any-station")
        ah, _, ch = prep.evaluate(sel, Rh, th, rho=RHO, min_visible=M, coverage="any-station")
        out[lab] = {"working_worst": float(a[cov].max()) if cov.all() else float("inf"),
                    "heldout_worst": float(ah[ch].max()) if ch.all() else float("inf"),
                    "selected": [int(x) for x in sel]}
    print(json.dumps(out, indent=1))
    from layoutkit.io.atomic import atomic_write_text

    atomic_write_text(Path(args.out) / "polish_all.json",
                      json.dumps({**out, "selected": out["polished"]["selected"]}) + "\n")


def pockets(args):
    from layoutkit.optimize.poses import pose_descriptors
    from layoutkit.optimize.design import layout_visibility

    hull, cand, prep, R, t, Rh, th = _setup(args.coverage_poses)
    st = prep.stations
    sel = np.array(json.loads(Path(args.layout).read_text())["selected"]) if args.layout else _committed()
    a, _, _ = prep.evaluate(sel, Rh, th, rho=RHO, min_visible=M, coverage="any-station")
    aw, _, _ = prep.evaluate(sel, R, t, rho=RHO, min_visible=M, coverage="any-station")
    dh, dw = pose_descriptors(Rh, th, st)[:, :3], pose_descriptors(R, t, st)[:, :3]
    rh = np.linalg.norm(th - st[0].translation, axis=1)
    rw = np.linalg.norm(t - st[0].translation, axis=1)
    vh = layout_visibility(hull, cand.positions[sel], cand.normals[sel], Rh, th, st, 60.0)[:, 0]
    vw = layout_visibility(hull, cand.positions[sel], cand.normals[sel], R, t, st, 60.0)[:, 0]
    for i in np.argsort(-a)[:5]:
        ang = np.degrees(np.arccos(np.clip(dw @ dh[i], -1, 1)))
        print(f"held-out {i}: ADOP {a[i]:.0f}, range {rh[i]:.2f} m, lit {np.flatnonzero(vh[i]).tolist()}, "
              f"ADOP x 3/r {a[i] * 3 / rh[i]:.0f}")
        for j in np.argsort(ang)[:5]:
            print(f"    dense {j}: {ang[j]:.2f} deg away, ADOP {aw[j]:.0f}, range {rw[j]:.2f} m, "
                  f"lit {np.flatnonzero(vw[j]).tolist()}, ADOP x 3/r {aw[j] * 3 / rw[j]:.0f}")


def rays(args):
    from layoutkit.optimize.poses import range_sweep_poses
    from layoutkit.envelope import envelope_set

    hull, cand, prep, R, t, Rh, th = _setup(1)
    env = prep.envelope
    _, Rd, td = envelope_set(env, count=10000, seed=env.seed + 1)

    def worst(sel, R_, t_, sweep):
        if sweep:
            R_, t_, _ = range_sweep_poses(env, R_, t_, cand.positions[sel], cand.normals[sel], 60.0)
        return _worst(prep, sel, R_, t_)

    out = {}
    for path in args.results or [str(HERE / "results.json")]:
        for name, row in json.loads(Path(path).read_text())["layouts"].items():
            sel = np.array(row["sensors"])
            key = name if len(args.results or []) <= 1 else f"{Path(path).parent.name}: {name}"
            out[key] = {"heldout": worst(sel, Rh, th, False), "heldout_rays": worst(sel, Rh, th, True),
                        "dense_rays": worst(sel, Rd, td, True)}
            print(f"{key}: " + ", ".join(f"{lab} {v['worst_adop']:.0f} ({v['untracked']} untracked, tracked worst "
                                         f"{v['worst_adop_over_tracked']:.0f})" for lab, v in out[key].items()), flush=True)
    from layoutkit.io.atomic import atomic_write_text

    atomic_write_text(Path(args.out) / "rays.json", json.dumps(out, indent=1) + "\n")


def fresh(args):
    from run import device, envelope

    from layoutkit.optimize import DesignProblem
    from layoutkit.envelope import envelope_set

    path = Path((args.results or [str(HERE / "results.json")])[0])
    res = json.loads(path.read_text())
    dev = res["device"]
    hull, cand = device(dev["spacing_mm"] * 1e-3)
    env = envelope(200, 13)
    prep = DesignProblem.load(hull, env, candidates=cand, max_tilt_deg=dev.get("max_tilt_deg", 0.0),
                           tilt_toward=dev.get("tilt_toward"))
    sets = [(f"seed+{d}", 2000, env.seed + d) for d in range(100, 105)] + [("seed+200", 20000, env.seed + 200)]
    out = {"results": str(path), "sets": {lab: {"poses": n, "seed": sd} for lab, n, sd in sets}, "layouts": {}}
    for lab, n, sd in sets:
        _, R, t = envelope_set(env, count=n, seed=sd)
        for name, row in res["layouts"].items():
            out["layouts"].setdefault(name, {})[lab] = _worst(prep, np.array(row["sensors"]), R, t)
    opt = "optimised by the dense loop"
    hands = [x for x in out["layouts"] if x.startswith("hand")]
    ratio = {}
    for lab, _, _ in sets:
        best = min(out["layouts"][h][lab]["worst_adop"] for h in hands)
        ratio[lab] = best / out["layouts"][opt][lab]["worst_adop"]
        print(f"{lab}: dense loop {out['layouts'][opt][lab]['worst_adop']:.0f}, best hand {best:.0f} "
              f"({ratio[lab]:.2f}x)", flush=True)
    out["best_hand_over_dense_loop"] = ratio
    from layoutkit.io.atomic import atomic_write_text

    atomic_write_text(path.parent / "fresh.json", json.dumps(out, indent=1) + "\n")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mode", choices=("polish-all", "pockets", "rays", "fresh"))
    ap.add_argument("--results", nargs="*", default=None, help="rays: study results.json files (layouts to score)")
    ap.add_argument("--time-limit-s", type=float, default=400.0)
    ap.add_argument("--coverage-poses", type=int, default=40000)
    ap.add_argument("--layout", default=None)
    ap.add_argument("--out", default=str(HERE))
    args = ap.parse_args()
    {"polish-all": polish_all, "pockets": pockets, "rays": rays, "fresh": fresh}[args.mode](args)


if __name__ == "__main__":
    main()
