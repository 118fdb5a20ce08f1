"""Design sweeps on Dask: every cell of a sweep file is one optimisation, run as a task.

``run_sweep(sweep_toml, out_dir, executor)``:

1. cells already in ``out_dir/cells/<cell-id>.json`` with the same ``input_hash`` and a status other
   than ``error`` are skipped (resume); the others are queued;
2. one :func:`prepare_task` per distinct problem (mesh × units × envelope × candidates/spacing ×
   half-angle × tilt × seed) loads the mesh and computes visibility ONCE, on a worker: a
   :class:`layoutkit.optimize.DesignProblem`, which Dask moves to the cells that need it (no cell
   re-reads a mesh);
3. each :func:`cell_task` runs :func:`layoutkit.optimize.solve` on it with the cell's
   :class:`layoutkit.optimize.OptimizeSpec` (what ``layoutkit optimize`` runs; the Jacobians are
   computed on first use, in the cell);
4. as each cell finishes the client writes ``cells/<id>.json`` (and ``cells/<id>.layout.json`` for
   a feasible layout) atomically; a cell that raised records ``status = "error"`` and its message
   and the sweep goes on;
5. at the end: ``summary.csv`` (one row per cell: the axes, status, value, bound, gap, wall_s, ...),
   ``summary.json`` (the same rows, the Pareto front, counts) and plots (objective vs each axis;
   worst ADOP vs k with its Pareto front).
"""
from __future__ import annotations

import csv
import json
import math
import time
import warnings
from pathlib import Path

import numpy as np

from ..io.atomic import atomic_write, atomic_write_text
from .sweep_config import PREP_KEYS, SweepConfig, load_sweep

__all__ = ["run_sweep", "prepare_task", "cell_task", "read_cells", "SUMMARY_COLUMNS"]

#: Columns of summary.csv after the axis columns.
SUMMARY_COLUMNS = ("status", "value", "bound", "gap", "wall_s", "worst_adop_deg_per_rad",
                   "worst_pdop_m_per_rad", "certified_by", "cell_id")


def prepare_task(opts: dict):
    """Worker task: load mesh, candidates, envelope and visibility once: a
    :class:`layoutkit.optimize.DesignProblem` (its mesh, arrays and provenance; Dask moves it to the cells).

    opts : the cell options (only :data:`layoutkit.workflows.sweep_config.PREP_KEYS` are used). Warnings
    raised while loading (other than a refused odd size) are in ``problem.provenance["warnings"]``.
    """
    from ..candidates import parse_keepout
    from ..mesh import MeshUnitsWarning
    from ..optimize import DesignProblem

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if not opts.get("allow_odd_size"):
            warnings.simplefilter("error", MeshUnitsWarning)
        keep = [parse_keepout("box:" + ",".join(b.split())) for b in opts.get("keepout_box", ())]
        sp = opts.get("spacing_mm")
        problem = DesignProblem.load(opts["mesh"], opts["envelope"], candidates=opts.get("candidates"),
                                     spacing=None if sp is None else sp * 1e-3, keepout=keep,
                                     units=opts.get("units", "m"), half_angle_deg=opts["half_angle_deg"],
                                     seed=opts["seed"], max_candidates=opts.get("max_candidates"),
                                     max_tilt_deg=opts.get("max_tilt_deg") or 0.0)
    problem.provenance["warnings"] = [str(w.message) for w in caught]
    return problem


def cell_task(problem, opts: dict) -> dict:
    """Worker task: one optimisation on a prepared problem (:func:`prepare_task`) with the cell's spec
    (:func:`layoutkit.workflows.sweep_config.cell_spec`).

    Returns a JSON-able dict: status, success, message, value, bound, gap, certified_by, min_k,
    selected_ids, stats, wall_s (s, this optimisation only), layout (layout JSON dict or None).
    """
    from ..io.jsonfile import to_jsonable
    from ..optimize import solve
    from ..parallel.scheduler import allow_child_processes
    from .sweep_config import cell_spec

    t0 = time.perf_counter()
    spec = cell_spec(opts)
    ids = problem.candidates.ids
    with allow_child_processes():  # the relaxation may run in a forked child (time limit)
        res = solve(problem, spec)
    wall = time.perf_counter() - t0
    sel = [int(i) for i in res.selected]
    layout = None
    if res.success:
        layout = problem.layout(sel, {"mesh_sha256": problem.provenance.get("mesh_sha256"),
                                      "objective": res.objective, "rho": opts["rho"], "value": res.value,
                                      "bound": res.bound, "gap": res.gap, "certified_by": res.certified_by,
                                      "method": opts["method"], "min_visible": opts["min_visible"],
                                      "candidate_ids": [ids[i] for i in sel], "envelope": opts["envelope"],
                                      "spec": spec.to_dict(), "provenance": problem.provenance}).to_dict()
    return to_jsonable({
        "status": res.status, "success": bool(res.success), "message": res.message,
        "value": res.value, "bound": res.bound, "gap": res.gap, "certified_by": res.certified_by,
        "min_k": res.min_k, "selected_ids": [ids[i] for i in sel],
        "stats": res.stats() if res.success else None, "candidates": len(ids),
        "poses": problem.P, "wall_s": wall, "timings_s": res.timings,
        "prepare_warnings": problem.provenance.get("warnings", []), "layout": layout,
    })


def _cell_path(cells_dir: Path, cell_id: str) -> Path:
    return cells_dir / f"{cell_id}.json"


def read_cells(out_dir) -> dict:
    """``{cell_id: record}`` of every readable cell JSON under ``out_dir/cells``."""
    out = {}
    for p in sorted((Path(out_dir) / "cells").glob("*.json")):
        if p.name.endswith(".layout.json"):
            continue
        try:
            rec = json.loads(p.read_text())
        except (OSError, ValueError):
            continue
        out[rec.get("cell_id", p.stem)] = rec
    return out


def run_sweep(sweep, out_dir, executor, *, progress=None, echo=print) -> dict:
    """Run (or resume) a sweep; returns the summary dict also written to ``out_dir/summary.json``.

    sweep : sweep TOML path or :class:`SweepConfig`; executor : from
    :func:`layoutkit.parallel.open_executor`; progress : ``callable(done, running, failed, total)``.
    """
    from ..io.jsonfile import to_jsonable

    cfg = sweep if isinstance(sweep, SweepConfig) else load_sweep(sweep)
    out = Path(out_dir)
    cells_dir = out / "cells"
    cells_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    done, todo, stale = {}, [], []
    for c in cfg.cells:
        p = _cell_path(cells_dir, c.cell_id)
        rec = None
        if p.exists():
            try:
                rec = json.loads(p.read_text())
            except (OSError, ValueError):
                rec = None
        if rec is not None and rec.get("input_hash") == c.input_hash and rec.get("status") != "error":
            done[c.cell_id] = rec
            continue
        if rec is not None and rec.get("input_hash") != c.input_hash:
            stale.append(c.cell_id)
        todo.append(c)
    total = len(cfg.cells)
    n_done, n_failed = len(done), 0
    if done or stale:
        echo(f"resuming: {len(done)} of {total} cells already in {cells_dir} (inputs unchanged); "
             f"{len(todo)} to run" + (f" ({len(stale)} with changed inputs)" if stale else ""))
    preps, handles = {}, {}
    for c in todo:
        key = c.prep_key()
        if key not in preps:
            preps[key] = executor.submit(prepare_task, {k: c.opts.get(k) for k in PREP_KEYS}, key="prepare")
        h = executor.submit(cell_task, preps[key], c.opts, key=f"cell-{c.cell_id}")
        handles[h.key] = (h, c)
    pending = {k: h for k, (h, _) in handles.items()}

    def tick():
        if progress is not None:
            progress(n_done, executor.running(list(pending.values())), n_failed, total)

    tick()
    ran = []
    try:
        for h, ok, value in executor.completed([h for h, _ in handles.values()], tick=tick):
            _, c = handles[h.key]
            pending.pop(h.key, None)
            rec = {"cell_id": c.cell_id, "index": c.index, "axes": dict(c.axes), "input_hash": c.input_hash,
                   "options": dict(c.options), "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
            if ok:
                lay = value.pop("layout")
                rec.update(value)
                if lay is not None:
                    lp = cells_dir / f"{c.cell_id}.layout.json"
                    atomic_write_text(lp, json.dumps(lay, indent=2) + "\n")
                    rec["layout"] = lp.name
            else:
                rec.update(status="error", success=False, message=f"{type(value).__name__}: {value}",
                           value=None, bound=None, gap=None, wall_s=None)
                n_failed += 1
            atomic_write_text(_cell_path(cells_dir, c.cell_id), json.dumps(to_jsonable(rec), indent=2) + "\n")
            done[c.cell_id] = rec
            ran.append(c.cell_id)
            n_done += 1
            tick()
    except BaseException:
        executor.cancel(list(pending.values()))
        raise
    finally:
        preps.clear()
    rows = [_row(cfg, c, done[c.cell_id]) for c in cfg.cells]
    summary = {
        "sweep": cfg.path, "name": cfg.name, "axes": {a: list(v) for a, v in cfg.axes},
        "cells": total, "ran": len(ran), "skipped": total - len(ran),
        "errors": sum(r["status"] == "error" for r in rows),
        "feasible": sum(r["status"] in ("ok", "optimal") for r in rows),
        "scheduler": getattr(executor, "kind", "?"), "wall_s": time.perf_counter() - t0,
        "ran_cells": ran, "pareto_worst_adop_vs_k": _pareto(rows), "rows": rows,
    }
    _write_summary_csv(out / "summary.csv", cfg, rows)
    summary["plots"] = _plots(out, cfg, rows, summary["pareto_worst_adop_vs_k"], echo)
    atomic_write_text(out / "summary.json", json.dumps(to_jsonable(summary), indent=2) + "\n")
    return summary


def _row(cfg: SweepConfig, cell, rec: dict) -> dict:
    st = rec.get("stats") or {}
    row = dict(cell.axes)
    row.update(status=rec.get("status"), value=rec.get("value"), bound=rec.get("bound"), gap=rec.get("gap"),
               wall_s=rec.get("wall_s"),
               worst_adop_deg_per_rad=(st.get("adop_deg_per_rad") or {}).get("max"),
               worst_pdop_m_per_rad=(st.get("pdop_m_per_rad") or {}).get("max"),
               certified_by=rec.get("certified_by"), cell_id=cell.cell_id, k=cell.opts["k"])
    row["_message"] = rec.get("message")
    return row


def _fmt(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ""
    if isinstance(v, (list, tuple)):
        return " ".join(map(str, v))
    return str(v)


def _write_summary_csv(path: Path, cfg: SweepConfig, rows) -> None:
    cols = list(cfg.axis_names) + [c for c in SUMMARY_COLUMNS if c not in cfg.axis_names]
    with atomic_write(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for r in rows:
            w.writerow([_fmt(r.get(c)) for c in cols])


def _pareto(rows) -> list[dict]:
    """Cells not dominated in (k smaller, worst ADOP smaller), by increasing k."""
    pts = sorted(((r["k"], r["worst_adop_deg_per_rad"], r["cell_id"]) for r in rows
                  if r["status"] in ("ok", "optimal") and r["worst_adop_deg_per_rad"] is not None),
                 key=lambda p: (p[0], p[1]))
    front, best = [], math.inf
    for k, a, cid in pts:
        if a < best:
            front.append({"k": k, "worst_adop_deg_per_rad": a, "cell_id": cid})
            best = a
    return front


def _objective_label(cfg) -> str:
    from ..optimize.objectives import objective_unit

    names = sorted({str(dict(c.options).get("objective")) for c in cfg.cells})
    if len(names) == 1:
        unit = objective_unit(names[0])
        return f"{names[0]} ({unit})" if unit else names[0]
    return "objective value (ADOP deg/rad, PDOP m/rad)"


def _plots(out: Path, cfg: SweepConfig, rows, front, echo) -> list[str]:
    """objective_vs_axes.png (one panel per axis; cells without a layout drawn as red crosses on top)
    and pareto_worst_adop_vs_k.png."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io.figures import save_figure

    ok = [r for r in rows if r["status"] in ("ok", "optimal") and r["value"] is not None]
    failed = [r for r in rows if r not in ok]
    files = []
    if not ok:
        echo("note: no feasible cell; no plots")
        return files
    names = cfg.axis_names or ("k",)
    fig, axs = plt.subplots(1, len(names), figsize=(4.5 * len(names), 3.8), squeeze=False)
    top = max(r["value"] for r in ok) * 2.0
    for ax, name in zip(axs[0], names):
        vals = [r.get(name, r["k"]) for r in ok + failed]
        numeric = all(isinstance(v, (int, float)) for v in vals)
        levels = sorted(set(vals)) if numeric else list(dict.fromkeys(vals))
        x_all = np.array([v if numeric else levels.index(v) for v in vals], float)
        x, xf = x_all[:len(ok)], x_all[len(ok):]
        y = np.array([r["value"] for r in ok])
        ax.scatter(x, y, s=18, alpha=0.7, label="cells")
        lx = np.array([lv if numeric else i for i, lv in enumerate(levels)], float)
        best = [y[x == v].min() if np.any(x == v) else np.nan for v in lx]
        ax.plot(lx, best, "k.-", lw=1, label="best at this value")
        if len(xf):
            ax.scatter(xf, np.full(len(xf), top), marker="x", s=40, c="C3", label="infeasible / failed (no value)")
        if not numeric:
            ax.set_xticks(lx, [Path(str(v)).stem for v in levels], rotation=20)
        ax.set_xlabel(name)
        ax.set_ylabel(_objective_label(cfg))
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
    axs[0][0].legend(fontsize=8)
    fig.suptitle(f"sweep {cfg.name}: objective of each cell against each axis")
    fig.tight_layout()
    save_figure(fig, out / "objective_vs_axes.png",
                caption=f"{len(ok)} cells with a layout (dots; black: the best at each axis value)"
                        + (f", {len(failed)} without one (red crosses drawn above the rest: infeasible or failed, "
                           "see summary.csv)" if failed else "") + "; log scale.")
    files.append("objective_vs_axes.png")
    pts = [(r["k"], r["worst_adop_deg_per_rad"]) for r in ok if r["worst_adop_deg_per_rad"] is not None]
    if pts:
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.scatter(*zip(*pts), s=18, c="0.6", label="cells")
        ax.plot([p["k"] for p in front], [p["worst_adop_deg_per_rad"] for p in front], "o-", c="C3",
                label="Pareto front")
        ax.set_xlabel("sensors k")
        ax.set_ylabel("worst ADOP over the envelope (deg/rad)")
        ax.set_yscale("log")
        ax.set_title(f"sweep {cfg.name}: worst ADOP against the sensor count")
        ax.grid(alpha=0.3)
        ax.legend()
        fig.tight_layout()
        save_figure(fig, out / "pareto_worst_adop_vs_k.png",
                    caption="Worst ADOP over the envelope of every cell with a layout (grey) and the cells no other "
                            "cell beats with as few sensors (red).")
        files.append("pareto_worst_adop_vs_k.png")
    return files

