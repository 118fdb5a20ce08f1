"""Optimisation workflow: mesh + candidates + envelope -> optimised layout JSON + report folder.

Used by ``layoutkit optimize``, ``layoutkit demo`` (:func:`run_demo`) and ``studies/``.
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from ..units import RHO_PAPER

__all__ = ["prepare_problem", "mean_station_direction", "run_optimize", "write_report", "run_demo", "evaluate_layout"]


def mean_station_direction(rotations, translations, stations):
    """Mean unit direction (3,) from the body to the stations, body frame, over poses
    ``rotations (P, 3, 3)``, ``translations (P, 3)`` (body-to-world, m) and every station: the axis the
    envelope looks at the body from (for meridional tilts, ``tilt_toward="station"``)."""
    R, t = np.asarray(rotations, float), np.asarray(translations, float)
    d = np.stack([np.einsum("pji,pj->pi", R, st.translation[None, :] - t) for st in stations])
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    m = d.reshape(-1, 3).mean(axis=0)
    return m / np.linalg.norm(m)


def prepare_problem(mesh, envelope, *, candidates=None, spacing=None, keepout=(), units="m",
                    sensor_half_angle_deg=60.0, seed=0, max_candidates=None, max_tilt_deg=0.0,
                    tilt_directions=4, tilt_toward=None):
    """Load/sample everything the optimiser needs.

    mesh : path or ``trimesh.Trimesh`` (m); envelope : path or :class:`layoutkit.envelope.Envelope`;
    candidates : layout JSON path or :class:`Layout` of candidate sites, else ``spacing`` (m) sampling.
    Returns a dict: mesh, envelope, candidates (Layout), rotations (P,3,3), translations (P,3) (world),
    stations, visible (P, S, N) bool, jac (P, S, N, 2, 6), site (N,) site index of each candidate
    and tilt_deg (N,) (``max_tilt_deg > 0``: every site also carries its normal tilted by that angle
    towards ``tilt_directions`` azimuths, or towards and away from the body axis ``tilt_toward`` (3,) if
    given — ``"station"``: :func:`mean_station_direction` over the envelope —,
    :mod:`layoutkit.optimize.tilt`; ids ``<site>~t<j>``, j = 1, 2, ... per site).
    """
    from ..candidates import sample_candidates
    from ..envelope import Envelope, load_envelope
    from ..layout import Layout, load_layout
    from ..mesh import load_mesh
    from ..optimize import candidate_jacobians
    from ..visibility import envelope_visibility

    if isinstance(mesh, (str, Path)):
        mesh = load_mesh(mesh, units)
    env = envelope if isinstance(envelope, Envelope) else load_envelope(envelope)
    if candidates is None:
        if spacing is None:
            spacing = 0.01 * float(np.max(mesh.extents))  # 1 % of the largest extent
        cand = sample_candidates(mesh, spacing=spacing, keepout=keepout, rng=seed, max_count=max_candidates)
    elif isinstance(candidates, Layout):
        cand = candidates
    else:
        cand = load_layout(candidates)
    site = np.arange(cand.n)
    tilt = np.zeros(cand.n)
    R, t = env.poses()
    if max_tilt_deg and max_tilt_deg > 0:
        from ..optimize.tilt import tilt_orientations

        if isinstance(tilt_toward, str):
            if tilt_toward != "station":
                raise ValueError(f"tilt_toward: expected 'station' or a 3-vector, got {tilt_toward!r}")
            tilt_toward = mean_station_direction(R, t, env.stations)
        pos, axes, site, tilt = tilt_orientations(cand.positions, cand.normals, float(max_tilt_deg),
                                                  int(tilt_directions), toward=tilt_toward)
        occ = np.zeros(cand.n, int)
        ids = []
        for s in site:  # the plain sites come first, then each site's tilted orientations in order
            ids.append(cand.ids[s] if occ[s] == 0 else f"{cand.ids[s]}~t{occ[s]}")
            occ[s] += 1
        ids = tuple(ids)
        cand = Layout(pos, axes, ids, dict(cand.metadata),
                      tuple({"x-site": cand.ids[s], "x-tilt-deg": float(tt)} for s, tt in zip(site, tilt)))
    vis = envelope_visibility(mesh, cand.positions, cand.normals, R, t, env.stations,
                              sensor_half_angle_deg=sensor_half_angle_deg)
    jac = candidate_jacobians(cand.positions, R, t, env.stations)
    return {"mesh": mesh, "envelope": env, "candidates": cand, "rotations": R, "translations": t,
            "stations": env.stations, "visible": vis, "jac": jac,
            "sensor_half_angle_deg": sensor_half_angle_deg, "site": site, "tilt_deg": tilt}


def evaluate_layout(prep, positions, normals, rho, min_visible=4):
    """Exact per-pose ADOP/PDOP of an arbitrary layout over the envelope of ``prep``.

    Returns dict with adop (P,), pdop (P,), n_lit (P,), and statistics over the covered poses."""
    from ..dop import dop_from_jacobian
    from ..optimize import candidate_jacobians
    from ..visibility import envelope_visibility

    vis = envelope_visibility(prep["mesh"], positions, normals, prep["rotations"], prep["translations"],
                              prep["stations"], sensor_half_angle_deg=prep["sensor_half_angle_deg"])
    jac = candidate_jacobians(positions, prep["rotations"], prep["translations"], prep["stations"])
    d = dop_from_jacobian(jac, rho, vis)
    n_lit = vis.any(axis=1).sum(axis=1)
    return {"adop": np.asarray(d.adop), "pdop": np.asarray(d.pdop), "n_lit": n_lit,
            "stats": dop_stats(d.adop, d.pdop, n_lit, min_visible)}


def dop_stats(adop, pdop, n_lit, min_visible=4):
    ok = (np.asarray(n_lit) >= min_visible) & np.isfinite(adop) & np.isfinite(pdop)
    out = {"poses": int(len(adop)), "poses_covered": int(ok.sum())}
    for nm, a in (("adop_deg_per_rad", np.asarray(adop)), ("pdop_m_per_rad", np.asarray(pdop))):
        x = a[ok]
        out[nm] = ({"median": float(np.median(x)), "mean": float(np.mean(x)),
                    "p95": float(np.percentile(x, 95)), "max": float(np.max(x))} if len(x) else {})
    return out


def run_optimize(mesh, envelope, k, *, out=None, report=None, objective="worst-adop", rho=RHO_PAPER,
                 method="pipeline", candidates=None, spacing=None, keepout=(), fixed_ids=(),
                 min_visible=4, k_range=None, seed=0, units="m", min_spacing=0.0,
                 coverage_fraction=1.0, time_limit=None, progress=None, sensor_half_angle_deg=60.0,
                 max_candidates=None, render=True, echo=print, coverage="any-station", max_tilt_deg=0.0,
                 tilt_directions=4, tilt_toward=None, dense_poses=None, heldout_poses=2000, dense_rounds=40,
                 dense_coverage_poses=None, branch_and_bound="auto"):
    """Optimise a k-sensor layout on ``mesh`` over ``envelope``; write layout JSON and a report.

    k_range : optional (k_min, k_max) — also the best layout for every k in the range (DOP vs k).
    fixed_ids : candidate ids placed in advance. coverage : coverage rule (:mod:`layoutkit.coverage_rule`).
    max_tilt_deg : sensors may be tilted from the surface normal up to this angle (one orientation
    per site; :mod:`layoutkit.optimize.tilt`); tilt_toward : None (``tilt_directions`` azimuths),
    ``"station"`` or a body axis (3,): meridional tilts only (:func:`prepare_problem`). dense_poses : adaptive pose generation against a
    dense set of the envelope (:mod:`layoutkit.workflows.dense`; ``time_limit`` is then the budget of
    all rounds; coverage also checked on ``dense_coverage_poses`` more poses, default 4 × dense_poses),
    reported with design-set, working-set, dense-set and held-out (``heldout_poses``, fresh seed)
    statistics. branch_and_bound : "auto" | "off" — B&B on the relaxation beside the search
    (:mod:`layoutkit.optimize.bnb`). Returns a summary dict (JSON-able)."""
    from ..layout import Layout, save_layout
    from ..mesh import mesh_hash
    from ..optimize import optimize_stations, spacing_conflicts
    from ..optimize.runcontrol import Interrupted, interruptible

    t0 = time.perf_counter()
    import cvxpy  # noqa: F401 - the relaxation's import (1–2 s) happens before any time budget starts

    prep = prepare_problem(mesh, envelope, candidates=candidates, spacing=spacing, keepout=keepout,
                           units=units, sensor_half_angle_deg=sensor_half_angle_deg, seed=seed,
                           max_candidates=max_candidates, max_tilt_deg=max_tilt_deg,
                           tilt_directions=tilt_directions, tilt_toward=tilt_toward)
    cand = prep["candidates"]
    idmap = {c: i for i, c in enumerate(cand.ids)}
    missing = [f for f in fixed_ids if f not in idmap]
    if missing:
        raise ValueError(f"fixed: unknown candidate id(s) {missing}; ids look like {cand.ids[0]!r}")
    fixed = [idmap[f] for f in fixed_ids]
    conflict = spacing_conflicts(cand.positions, min_spacing)
    if max_tilt_deg and max_tilt_deg > 0:
        from ..optimize.tilt import site_conflicts

        conflict = site_conflicts(prep["site"], conflict)
    kw = dict(objective=objective, rho=rho, min_visible=min_visible, method=method, fixed=fixed,
              conflict=conflict, coverage_fraction=coverage_fraction, time_limit=time_limit, progress=progress,
              branch_and_bound=branch_and_bound)
    interrupted = None
    dense_info = None

    def solve(kk):
        nonlocal dense_info
        if dense_poses:
            from .dense import dense_optimize

            kd = {x: v for x, v in kw.items() if x != "time_limit"}
            ncov = 4 * int(dense_poses) if dense_coverage_poses is None else int(dense_coverage_poses)
            r, inf = dense_optimize(prep, kk, kd, dense_poses=dense_poses, seed=seed, coverage=coverage,
                                    rounds=dense_rounds, coverage_poses=ncov, time_limit=time_limit, echo=None)
            if kk == k:
                dense_info = inf
            return r
        return optimize_stations(prep["jac"], prep["visible"], kk, rng=seed, coverage=coverage, **kw)

    with interruptible():
        try:
            res = solve(k)
        except Interrupted as exc:  # outside the method (coverage analysis): nothing to write
            raise Interrupted(exc.signame) from None
        interrupted = res.info.get("interrupted")
        sweep = []
        if k_range is not None:
            for kk in range(int(k_range[0]), int(k_range[1]) + 1):
                if interrupted:  # every finished k is kept; the rest is not started
                    sweep.append({"k": kk, "status": "not run (interrupted)", "value": None, "bound": None,
                                  "gap": None, "stats": None, "selected": []})
                    continue
                try:
                    r = res if kk == k else solve(kk)
                except Interrupted as exc:
                    interrupted = exc.signame
                    sweep.append({"k": kk, "status": "interrupted", "value": None, "bound": None, "gap": None,
                                  "stats": None, "selected": []})
                    continue
                interrupted = interrupted or r.info.get("interrupted")
                sweep.append({"k": kk, "status": r.status, "value": r.value, "bound": r.bound, "gap": r.gap,
                              "stats": r.stats() if r.success else None, "selected": r.selected.tolist()})
    m = prep["mesh"]
    summary = {
        "mesh": str(mesh) if isinstance(mesh, (str, Path)) else "(in memory)",
        "mesh_sha256": mesh_hash(m), "envelope": envelope if isinstance(envelope, (str, Path)) else prep["envelope"].name,
        "candidates": cand.n, "poses": int(len(prep["rotations"])), "stations": [s.id for s in prep["stations"]],
        "k": int(k), "objective": res.objective, "rho": rho, "method": method, "min_visible": min_visible,
        "status": res.status, "success": res.success, "message": res.message,
        "value": res.value, "bound": res.bound, "gap": res.gap, "certified_by": res.certified_by,
        "branch_and_bound": res.info.get("branch_and_bound"),
        "min_k": res.min_k, "uncoverable_poses": res.uncoverable.tolist(),
        "timings_s": {**res.timings, "total_s": time.perf_counter() - t0},
        "selected_ids": [cand.ids[i] for i in res.selected],
        "stats": res.stats() if res.success else None, "k_sweep": sweep,
        "interrupted": interrupted, "coverage_rule": coverage, "max_tilt_deg": float(max_tilt_deg or 0.0),
        "tilt_toward": tilt_toward if isinstance(tilt_toward, (str, type(None))) else [float(x) for x in tilt_toward],
    }
    if res.success:
        summary["tilted_sensors"] = int(np.sum(prep["tilt_deg"][res.selected] > 0))
        summary["envelope_sets"] = _set_stats(prep, res, rho, min_visible, coverage, dense_info, heldout_poses,
                                              objective)
    if res.success and out is not None:
        lay = Layout(cand.positions[res.selected], cand.normals[res.selected],
                     tuple(f"S{i + 1:02d}" for i in range(len(res.selected))),
                     {"mesh_sha256": summary["mesh_sha256"], "units_source": units, "objective": res.objective,
                      "rho": rho, "value": res.value, "bound": res.bound, "gap": res.gap,
                      "certified_by": res.certified_by, "method": method, "min_visible": min_visible,
                      "candidate_ids": summary["selected_ids"], "dop_stats": summary["stats"],
                      "envelope": summary["envelope"] if isinstance(summary["envelope"], str) else str(summary["envelope"])},
                     tuple({"candidate": cand.ids[i], "x-site": cand.ids[prep["site"][i]],
                            "x-tilt-deg": float(prep["tilt_deg"][i])} for i in res.selected))
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        save_layout(lay, out)
        summary["out"] = str(out)
    if report is not None:
        summary["report"] = write_report(report, prep, res, summary, render=render, echo=echo)
    return summary


def _set_stats(prep, res, rho, min_visible, coverage, dense_info, heldout_poses, objective):
    """Design-set, dense-set and held-out statistics of the chosen layout side by side."""
    from .dense import evaluate_selection
    from .score import envelope_set

    def stats(a, p, cov):
        x, y = a[cov], p[cov]
        ok = len(x) > 0
        return {"poses": int(len(a)), "covered_fraction": float(cov.mean()),
                "worst_adop": float(x.max()) if ok else None, "median_adop": float(np.median(x)) if ok else None,
                "p95_adop": float(np.percentile(x, 95)) if ok else None, "p99_adop": float(np.percentile(x, 99)) if ok else None,
                "worst_pdop": float(y.max()) if ok else None}

    env = prep["envelope"]
    out = {"design": stats(*evaluate_selection(prep, res.selected, prep["rotations"], prep["translations"], rho,
                                               min_visible, coverage))}
    if dense_info is not None:
        out["dense"] = stats(dense_info["dense_adop"], dense_info["dense_pdop"], dense_info["dense_covered"])
        out["dense"].update({"value": dense_info["dense_value"], "gap_to_bound": dense_info["dense_gap"],
                             "working_set_poses": dense_info["working_set_poses"], "rounds": dense_info["rounds"]})
        # the poses the layout was finally tuned on (design poses + the loop's additions)
        out["working"] = stats(*evaluate_selection(prep, res.selected, dense_info["working_rotations"],
                                                   dense_info["working_translations"], rho, min_visible, coverage))
        _, Rh, th = envelope_set(env, count=int(heldout_poses), seed=env.seed + 2)
        out["heldout"] = stats(*evaluate_selection(prep, res.selected, Rh, th, rho, min_visible, coverage))
        out["heldout"]["seed"] = env.seed + 2
    return out


def write_report(report_dir, prep, res, summary, render=True, echo=print):
    """Plots (DOP over the envelope, CDF, DOP vs k) and renders (if pyvista works) into a folder."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    from ..io.atomic import atomic_write_text
    from ..io.figures import integer_ticks, save_figure
    from ..io.jsonfile import to_jsonable

    d = Path(report_dir)
    d.mkdir(parents=True, exist_ok=True)
    files = []
    if res.success:
        t = prep["translations"]
        ref = prep["stations"][prep["envelope"].reference_station]
        rng_m = np.linalg.norm(t - ref.translation, axis=1)
        fig, ax = plt.subplots(1, 2, figsize=(12, 4.6))
        for a, y, lab in ((ax[0], res.adop, "ADOP (deg/rad)"), (ax[1], res.pdop, "PDOP (m/rad)")):
            sc = a.scatter(rng_m, y, c=res.n_lit, s=12, cmap="viridis")
            fin = np.isfinite(y)
            if fin.any():  # the worst pose of the envelope, marked and labelled
                w = int(np.flatnonzero(fin)[np.argmax(y[fin])])
                a.scatter([rng_m[w]], [y[w]], s=140, facecolors="none", edgecolors="r", linewidths=1.6,
                          label=f"worst pose #{w}: {y[w]:.4g} at {rng_m[w]:.2f} m")
                a.legend(fontsize=8, loc="lower right")
            a.set_xlabel("range to station (m)")
            a.set_ylabel(lab)
            a.set_yscale("log")
            a.set_title(lab.split(" ")[0] + " per envelope pose")
            a.xaxis.set_major_locator(MaxNLocator(nbins=6))
            a.grid(alpha=0.3)
        cb = fig.colorbar(sc, ax=ax, label="lit sensors (count)")
        cb.locator = MaxNLocator(integer=True)
        cb.update_ticks()
        fig.suptitle(f"{res.objective} over the envelope: value {res.value:.4g}, bound {res.bound:.4g}, "
                     f"gap {100 * res.gap:.1f} %")
        p = d / "dop_over_envelope.png"
        save_figure(fig, p, caption=f"{len(rng_m)} envelope poses of the optimised {len(res.selected)}-sensor layout; "
                    "colour: lit sensors; red circle: the worst pose (largest DOP); log scale.")
        files.append(p.name)
        fig, ax = plt.subplots(1, 2, figsize=(11, 4))
        for a, y, lab in ((ax[0], res.adop, "ADOP (deg/rad)"), (ax[1], res.pdop, "PDOP (m/rad)")):
            y = np.sort(y[np.isfinite(y)])
            a.plot(y, np.arange(1, len(y) + 1) / len(y))
            a.set_xlabel(lab)
            a.set_ylabel("fraction of poses")
            a.grid(alpha=0.3)
        fig.suptitle("Cumulative distribution of ADOP and PDOP over the envelope")
        p = d / "dop_cdf.png"
        save_figure(fig, p, caption="Fraction of the envelope poses whose DOP is at most the value on the x axis "
                    "(poses with an undefined DOP left out).")
        files.append(p.name)
    sweep = [s for s in summary.get("k_sweep", []) if s["stats"]]
    if sweep:
        fig, ax = plt.subplots(figsize=(6, 4))
        ks = [s["k"] for s in sweep]
        ax.plot(ks, [s["value"] for s in sweep], "o-", label=f"optimised ({summary['objective']})")
        ax.plot(ks, [s["bound"] for s in sweep], "k--", label="certified lower bound")
        if summary["objective"].endswith("adop"):
            ax.plot(ks, [s["stats"]["adop_deg_per_rad"]["median"] for s in sweep], "s-", label="median ADOP")
        ax.set_xlabel("sensors k")
        ax.set_ylabel("ADOP (deg/rad)" if summary["objective"].endswith("adop") else
                      "PDOP (m/rad)" if summary["objective"].endswith("pdop") else "weighted DOP")
        ax.set_xticks(ks)
        integer_ticks(ax, "x")
        infeasible = [s["k"] for s in summary["k_sweep"] if not s["stats"]]
        title = f"Optimised {summary['objective']} against the number of sensors"
        if infeasible:
            title += (f"\ninfeasible (too few sensors for {summary['min_visible']} lit): k = "
                      + ", ".join(map(str, infeasible)))
        ax.set_title(title, fontsize=9)
        ax.set_yscale("log")
        ax.legend()
        ax.grid(alpha=0.3)
        p = d / "dop_vs_k.png"
        save_figure(fig, p, caption="For each k of --k-range: the optimiser's value, the certified lower bound "
                    "(the gap between them is the optimality gap) and, for ADOP objectives, the median ADOP.")
        files.append(p.name)
    if render and res.success:
        try:
            from ..quality import tracking_quality_map
            from ..render import render_layout_views, render_tracking_map

            cand = prep["candidates"]
            pos, nor = cand.positions[res.selected], cand.normals[res.selected]
            lit_frac = prep["visible"][:, :, res.selected].any(axis=1).mean(axis=0)
            paths = render_layout_views(prep["mesh"], pos, nor, lit_frac, candidates=cand.positions,
                                        out_dir=d, prefix="layout",
                                        title=f"Optimised {len(res.selected)}-sensor layout ({res.objective})")
            files += [Path(p).name for p in paths]
            env = prep["envelope"]
            q = tracking_quality_map(prep["mesh"], pos, nor, distance=float(np.mean(env.range_m)),
                                     rho=summary["rho"], grid=(30, 60), roll_samples=3)
            files.append(Path(render_tracking_map(q, out=d / "tracking_map.png")).name)
        except Exception as exc:  # rendering is optional: plots-only report
            echo(f"note: renders skipped ({type(exc).__name__}: {exc}); the report has plots only")
    atomic_write_text(d / "summary.json", json.dumps(to_jsonable(summary), indent=2) + "\n")
    files.append("summary.json")
    return {"dir": str(d), "files": files}


def run_demo(out_dir, quick=True, echo=print, progress=None, seed: int = 0):
    """Optimise 12 sensors on the bundled Chen target over ``models/chen_envelope.toml`` (< 2 min).

    Writes ``out_dir/layout.json`` and the report folder ``out_dir/report``; returns the summary."""
    from ..envelope import load_envelope
    from ..mesh import load_mesh
    from ..resources import model_path

    out_dir = Path(out_dir)
    mesh_path = model_path("chen_target.stl")
    env = load_envelope(model_path("chen_envelope.toml"))
    if quick:
        env = dataclasses.replace(env, count=min(env.count, 100))
    mesh = load_mesh(mesh_path)
    return run_optimize(mesh, env, 12, out=out_dir / "layout.json", report=out_dir / "report",
                        objective="worst-adop", rho=RHO_PAPER, spacing=0.008 if quick else 0.005,
                        seed=seed, time_limit=60 if quick else None, progress=progress,
                        k_range=None, echo=echo)
