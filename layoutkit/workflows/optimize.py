"""Optimisation workflow: a design problem + a spec -> optimised layout JSON + report folder.

Used by ``layoutkit optimize``, ``layoutkit demo`` (:func:`run_demo`) and ``studies/``. The problem
(:class:`layoutkit.optimize.DesignProblem`: mesh, envelope, candidates, visibility) is loaded once by the
caller; the settings are one :class:`layoutkit.optimize.OptimizeSpec`.
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from ..units import RHO_PAPER

__all__ = ["run_optimize", "write_report", "run_demo", "envelope_set_stats"]


def run_optimize(problem, spec, *, out=None, report=None, k_range=None, progress=None, render=True, echo=print,
                 tilt_check=True):
    """Optimise ``spec.k`` sensors on ``problem``; write the layout JSON and a report; return a summary.

    problem : :class:`layoutkit.optimize.DesignProblem` (built for ``spec``:
    :meth:`~layoutkit.optimize.DesignProblem.for_spec`); spec : :class:`layoutkit.optimize.OptimizeSpec`
    (with ``dense``: adaptive pose generation, ``time_limit_s`` the budget of all rounds, reported with
    design-, working-, dense- and held-out-set statistics). Every successful run is scored on fresh poses
    (``summary["heldout"]``, :func:`layoutkit.optimize.heldout.heldout_estimate`); with ``dense`` that
    held-out estimate is the headline ``value`` (``design_value``: the optimiser's own, over its working set)
    and ``bound``/``gap`` come with what they certify (``summary["certificate"]``,
    :func:`layoutkit.optimize.certificate.certificate`). An untilted run also reports what tilt would reach
    (``summary["tilt_estimate"]``, :mod:`layoutkit.optimize.tilt_estimate`; ``tilt_check=False`` skips it).
    out : layout JSON path (it records the spec and
    the problem's provenance, so ``render`` and ``score`` find mesh and envelope from it); report : folder
    for plots, renders and summary.json; k_range : optional (k_min, k_max) — also the best layout for every
    k in the range (DOP vs k); progress : callable ``(stage, fraction, best)``; render : pyvista renders in
    the report; echo : callable for notes. Returns the summary dict (JSON-able). Ctrl-C / SIGTERM: the best
    layout so far and every finished k are written, ``summary["interrupted"]`` names the signal.
    """
    from ..optimize.runcontrol import interruptible

    t0 = time.perf_counter()
    import cvxpy  # noqa: F401 - the relaxation's import (1–2 s) happens before any time budget starts

    problem.check_spec(spec)
    with interruptible():
        res, sweep, interrupted = _solve_all(problem, spec, k_range, progress)
    summary = _summary(problem, spec, res, sweep, interrupted)
    summary["timings_s"] = {**res.timings, "total_s": time.perf_counter() - t0}
    if res.success:
        summary["tilted_sensors"] = int(np.sum(problem.tilt_deg[res.selected] > 0))
        summary["envelope_sets"] = envelope_set_stats(problem, spec, res)
        _headline(problem, spec, res, summary, tilt_check and not interrupted, echo)
    if res.success and out is not None:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        from ..layout import save_layout

        save_layout(problem.layout(res.selected, _layout_metadata(problem, spec, res, summary)), out)
        summary["out"] = str(out)
    if report is not None:
        summary["report"] = write_report(report, problem, res, summary, render=render, echo=echo)
    return summary


def _headline(problem, spec, res, summary, tilt_check, echo):
    """The held-out estimate, the certificate and the tilt estimate into ``summary`` (in place)."""
    from ..optimize.certificate import certificate
    from ..optimize.heldout import heldout_estimate

    heldout = None
    if problem.envelope is not None and problem.envelope.attitude != "trajectory":
        heldout = heldout_estimate(problem, res.selected, objective=spec.objective, weights=spec.weights,
                                   rho=spec.rho, min_visible=spec.min_visible, coverage=spec.coverage)
        summary["heldout"] = heldout
    cert = certificate(problem, spec, res, heldout)
    summary["certificate"] = cert
    summary["design_value"] = res.value
    if spec.dense is not None and heldout is not None:
        summary["value"] = heldout["value"]
        summary["bound"], summary["gap"] = cert["bound"], cert["gap"]
        summary["value_refers_to"] = (
            f"held-out estimate: {spec.objective} over {heldout['poses']} fresh poses of the envelope "
            f"({len(heldout['draws'])} draws; single draws {heldout['draw_value_min']:.5g}–{heldout['draw_value_max']:.5g}), "
            f"{100 * heldout['covered_fraction']:.2f} % covered; with 95 % confidence at most "
            f"{100 * heldout['exceed_fraction_bound_95']:.2f} % of the envelope is worse "
            f"(design_value: the optimiser's own over its working set)")
    else:
        summary["value_refers_to"] = f"{spec.objective} over the {problem.P} design poses"
    summary["gap_refers_to"] = cert["statement"] + (f"; loose: {cert['why']}" if cert["loose"] else "")
    if tilt_check and spec.max_tilt_deg == 0 and heldout is not None and spec.dense is not None:
        from ..optimize.tilt_estimate import tilt_estimate

        est = tilt_estimate(problem, spec, res, heldout)
        if est is not None:
            summary["tilt_estimate"] = est
            if echo is not None and est.get("helps"):
                echo(f"note: {est['note']}")


def _solve_all(problem, spec, k_range, progress):
    """``solve`` for ``spec.k`` and every k of ``k_range``: ``(result, k-sweep rows, interrupted)``."""
    from ..optimize import solve
    from ..optimize.runcontrol import Interrupted

    try:
        res = solve(problem, spec, progress=progress)
    except Interrupted as exc:  # outside the method (coverage analysis): nothing to write
        raise Interrupted(exc.signame) from None
    interrupted = res.info.get("interrupted")
    sweep = []
    if k_range is None:
        return res, sweep, interrupted
    for kk in range(int(k_range[0]), int(k_range[1]) + 1):
        if interrupted:  # every finished k is kept; the rest is not started
            sweep.append({"k": kk, "status": "not run (interrupted)", "value": None, "bound": None,
                          "gap": None, "stats": None, "selected": []})
            continue
        try:
            r = res if kk == spec.k else solve(problem, spec.replace(k=kk), progress=progress)
        except Interrupted as exc:
            interrupted = exc.signame
            sweep.append({"k": kk, "status": "interrupted", "value": None, "bound": None, "gap": None,
                          "stats": None, "selected": []})
            continue
        interrupted = interrupted or r.info.get("interrupted")
        sweep.append({"k": kk, "status": r.status, "value": r.value, "bound": r.bound, "gap": r.gap,
                      "stats": r.stats() if r.success else None, "selected": r.selected.tolist()})
    return res, sweep, interrupted


def _summary(problem, spec, res, sweep, interrupted) -> dict:
    prov = problem.provenance
    env = problem.envelope
    return {
        "mesh": prov.get("mesh") or "(in memory)", "mesh_sha256": prov.get("mesh_sha256"),
        "envelope": prov.get("envelope_file") or (env.name if env is not None else None),
        "candidates": problem.N, "poses": problem.P, "stations": [s.id for s in problem.stations],
        "k": int(spec.k), "objective": res.objective, "rho": spec.rho, "method": spec.method,
        "min_visible": spec.min_visible, "status": res.status, "success": res.success, "message": res.message,
        "value": res.value, "bound": res.bound, "gap": res.gap, "certified_by": res.certified_by,
        "branch_and_bound": res.info.get("branch_and_bound"),
        "min_k": res.min_k, "uncoverable_poses": res.uncoverable.tolist(),
        "selected_ids": [problem.candidates.ids[i] for i in res.selected],
        "stats": res.stats() if res.success else None, "k_sweep": sweep,
        "interrupted": interrupted, "coverage_rule": spec.coverage, "max_tilt_deg": float(spec.max_tilt_deg),
        "tilt_toward": list(spec.tilt_toward) if isinstance(spec.tilt_toward, tuple) else spec.tilt_toward,
        "spec": spec.to_dict(),
    }


def _layout_metadata(problem, spec, res, summary) -> dict:
    """Top-level keys of the optimised layout JSON (docs/layout-format.md)."""
    return {"mesh_sha256": summary["mesh_sha256"], "units_source": problem.provenance.get("units", "m"),
            "objective": res.objective, "rho": spec.rho, "value": summary["value"], "bound": summary["bound"],
            "gap": summary["gap"], "design_value": summary.get("design_value"),
            "value_refers_to": summary.get("value_refers_to"),
            "certified_by": res.certified_by, "method": spec.method, "min_visible": spec.min_visible,
            "candidate_ids": summary["selected_ids"], "dop_stats": summary["stats"],
            "envelope": str(summary["envelope"]), "spec": spec.to_dict(), "provenance": problem.provenance}


def envelope_set_stats(problem, spec, res) -> dict:
    """Design-set, dense-set, working-set and held-out statistics of the chosen layout side by side
    (:func:`layoutkit.optimize.stats.set_stats`); the design set's visibility is the problem's own."""
    from ..envelope import envelope_set
    from ..optimize.stats import pose_stats, set_stats

    def stats(a, p, cov):
        return set_stats(pose_stats(a, p, cov))

    kw = dict(rho=spec.rho, min_visible=spec.min_visible, coverage=spec.coverage)
    out = {"design": stats(*problem.evaluate(res.selected, **kw))}
    dense = res.info.get("dense")
    if dense is not None and "dense_adop" in dense:
        out["dense"] = stats(dense["dense_adop"], dense["dense_pdop"], dense["dense_covered"])
        out["dense"].update({"value": dense["dense_value"], "gap_to_bound": dense["dense_gap"],
                             "working_set_poses": dense["working_set_poses"], "rounds": dense["rounds"]})
        # the poses the layout was finally tuned on (design poses + the loop's additions)
        out["working"] = stats(*problem.evaluate(res.selected, dense["working_rotations"],
                                                 dense["working_translations"], **kw))
        env = problem.envelope
        _, Rh, th = envelope_set(env, count=int(spec.dense.heldout_poses), seed=env.seed + 2)
        out["heldout"] = stats(*problem.evaluate(res.selected, Rh, th, **kw))
        out["heldout"]["seed"] = env.seed + 2
    return out


def write_report(report_dir, problem, res, summary, render=True, echo=print):
    """Plots (DOP over the envelope, CDF, DOP vs k) and renders (if pyvista works) of ``res`` on
    ``problem`` (:class:`layoutkit.optimize.DesignProblem`) into a folder, with summary.json."""
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
        dense = res.info.get("dense") or {}
        # a dense run's per-pose arrays are over its working set (the poses the layout was tuned on)
        t, which = ((dense["working_translations"], "working-set") if len(dense.get("working_translations", ()))
                    == len(res.adop) and "working_translations" in dense else (problem.translations, "envelope"))
        ref = problem.stations[problem.envelope.reference_station if problem.envelope is not None else 0]
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
        save_figure(fig, p, caption=f"{len(rng_m)} {which} poses of the optimised {len(res.selected)}-sensor layout; "
                    "colour: lit sensors; red circle: the worst pose (largest DOP); log scale.")
        files.append(p.name)
        fig, ax = plt.subplots(1, 2, figsize=(11, 4))
        for a, y, lab in ((ax[0], res.adop, "ADOP (deg/rad)"), (ax[1], res.pdop, "PDOP (m/rad)")):
            y = np.sort(y[np.isfinite(y)])
            a.plot(y, np.arange(1, len(y) + 1) / len(y))
            a.set_xlabel(lab)
            a.set_ylabel("fraction of poses")
            a.xaxis.set_major_locator(MaxNLocator(nbins=5))  # five-digit DOPs (a tilted layout's) overlapped at 8
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

            cand = problem.candidates
            pos, nor = cand.positions[res.selected], cand.normals[res.selected]
            lit_frac = problem.visible[:, :, res.selected].any(axis=1).mean(axis=0)
            paths = render_layout_views(problem.mesh, pos, nor, lit_frac, candidates=cand.positions,
                                        out_dir=d, prefix="layout",
                                        title=f"Optimised {len(res.selected)}-sensor layout ({res.objective})")
            files += [Path(p).name for p in paths]
            env = problem.envelope
            q = tracking_quality_map(problem.mesh, pos, nor, distance=float(np.mean(env.range_m)),
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
    from ..optimize import DesignProblem, OptimizeSpec
    from ..resources import model_path

    out_dir = Path(out_dir)
    env = load_envelope(model_path("chen_envelope.toml"))
    if quick:
        env = dataclasses.replace(env, count=min(env.count, 100))
    spec = OptimizeSpec(k=12, objective="worst-adop", rho=RHO_PAPER, time_limit_s=60 if quick else None, seed=seed)
    problem = DesignProblem.for_spec(model_path("chen_target.stl"), env, spec,
                                     spacing=0.008 if quick else 0.005)
    summary = run_optimize(problem, spec, out=out_dir / "layout.json", report=out_dir / "report", progress=progress,
                           echo=echo)
    if (out_dir / "layout.json").is_file():
        summary["versus_shipped"] = versus_layout(out_dir / "layout.json", model_path("chen_target.layout.json"),
                                                  env, model_path("chen_target.stl"), spec.rho)
        if (out_dir / "report").is_dir():
            from ..io.atomic import atomic_write_text
            from ..io.jsonfile import to_jsonable

            atomic_write_text(out_dir / "report" / "versus_shipped.json",
                              json.dumps(to_jsonable(summary["versus_shipped"]), indent=2) + "\n")
    return summary


def versus_layout(layout, other, envelope, mesh, rho: float) -> dict:
    """The optimised ``layout`` beside ``other`` (e.g. the shipped hand layout) over the same envelope
    poses, occlusion by ``mesh``: coverage and worst / median ADOP and worst PDOP of each, and the
    poses each leaves uncovered (a worst ADOP over fewer covered poses is not a better layout)."""
    from .score import score_layout

    r = score_layout(layout, envelope, mesh=mesh, rho=rho, compare=other)
    keys = ("poses", "covered_poses", "coverage_fraction", "worst_adop", "median_adop", "worst_pdop")
    one = {k: r[k] for k in keys}
    two = {k: r["compare"][k] for k in keys}
    def said(name, r):
        if not r["covered_poses"]:
            return f"{name}: covers none of the {r['poses']} poses"
        return f"{name}: {r['covered_poses']}/{r['poses']} poses covered, worst ADOP {r['worst_adop']:.4g} deg/rad"

    lost = two["poses"] - two["covered_poses"]
    return {"optimised": one | {"layout": str(layout)}, "other": two | {"layout": str(other)},
            "message": (said("optimised", one) + "; " + said(Path(str(other)).name, two)
                        + (f" ({lost} poses it cannot track at all)" if 0 < lost else ""))}
