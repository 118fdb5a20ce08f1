"""CLI command ``layoutkit optimize`` (the demo is wired by the core CLI to workflows.optimize.run_demo)."""
from __future__ import annotations

import math

import click

from ._common import bad_input, echo_json, fail
from .options import Conflict, flag_rules
from .options import (allow_odd_size_option, coverage_option, envelope_option, half_angle_option, json_flag, min_visible_option,
                      out_file_option, registry_choice, report_option, rho_option, seed_option, time_limit_option,
                      units_option)


def _k_range(ctx, param, value):
    if value is None:
        return None
    try:
        a, b = (int(x) for x in value.split(":"))
    except ValueError:
        raise click.BadParameter(f"expected KMIN:KMAX (e.g. 8:16), got {value!r}") from None
    if not 1 <= a <= b:
        raise click.BadParameter(f"expected 1 <= KMIN <= KMAX, got {value!r}")
    return a, b


def _tilt_toward(ctx, param, value):
    if value is None or value == "station":
        return value
    try:
        v = [float(x) for x in value.split(",")]
    except ValueError:
        v = []
    if len(v) != 3 or not all(map(math.isfinite, v)) or not any(v):
        raise click.BadParameter(f"expected 'station' or a non-zero body axis X,Y,Z (e.g. 0,0,1), got {value!r}")
    return v


@click.command("optimize", short_help="Choose K photodiode sites minimising DOP (certified gap).")
@click.argument("mesh", type=click.Path(dir_okay=False))
@click.option("--sensors", "-k", "k", type=click.IntRange(min=1), required=True, help="Number of photodiodes.")
@envelope_option(help="Operating envelope TOML (poses x stations; docs/envelope.md).")
@click.option("--objective", default="worst-adop", show_default=True,
              help="<worst|mean|pNN>-<adop|pdop|weighted>, e.g. worst-adop, mean-pdop, p95-adop.")
@click.option("--weights", default=None, metavar="A,B",
              help="For *-weighted: weights of ADOP^2 (deg^2) and PDOP^2 (m^2).")
@rho_option
@out_file_option(help="Output layout JSON.")
@report_option(help="Report folder (plots, renders, summary.json).")
@click.option("--method", type=registry_choice("layoutkit.optimize:METHODS"), default="pipeline", show_default=True,
              help="Search method (the registry layoutkit.optimize.METHODS).")
@click.option("--candidates", "candidates_path", default=None, type=click.Path(dir_okay=False),
              help="Candidate sites (layout JSON from `layoutkit candidates`).")
@click.option("--spacing-mm", type=click.FloatRange(min=0.0, min_open=True), default=None,
              help="Sample candidate sites this far apart, mm (default 1 % of the mesh size, coarser if that "
                   "would give more than ~25 sites per sensor, at most 1500).")
@click.option("--keepout-box", multiple=True, metavar="X0,Y0,Z0,X1,Y1,Z1",
              help="Keep-out box in the body frame, mm (repeatable; with --spacing-mm sampling).")
@click.option("--fixed", default="", metavar="ID,...", help="Candidate ids placed in advance.")
@min_visible_option(help="Lit sensors needed at every pose.")
@click.option("--coverage-fraction", type=click.FloatRange(0.0, 1.0, min_open=True), default=1.0,
              show_default=True, help="Share of poses that must have --min-visible lit.")
@click.option("--min-spacing-mm", type=click.FloatRange(min=0.0), default=0.0, show_default=True,
              help="Minimum distance between chosen sensors, mm.")
@half_angle_option
@click.option("--k-range", default=None, callback=_k_range, metavar="KMIN:KMAX",
              help="Also optimise every k in the range (DOP vs sensor count).")
@time_limit_option(help="Wall-time budget per optimisation, s.")
@seed_option
@units_option
@allow_odd_size_option
@click.option("--no-render", is_flag=True, help="Plots only, no pyvista renders.")
@json_flag(help="Print the summary as JSON.")
@coverage_option
@click.option("--max-tilt-deg", type=click.FloatRange(0.0, 90.0, max_open=True), default=0.0, show_default=True,
              help="Sensors may be tilted from the surface normal up to this angle (one orientation per site).")
@click.option("--tilt-toward", default=None, callback=_tilt_toward, metavar="station|X,Y,Z",
              help="With --max-tilt-deg: tilt only in the plane of the normal and this body axis, towards it and "
                   "away from it ('station': the mean body-frame direction to the stations over the envelope); "
                   "default: 4 azimuths about the normal.")
@click.option("--dense-poses", type=click.IntRange(min=0), default=None, metavar="N",
              help="Adaptive pose generation against N extra envelope poses (dense set); the reported value is "
                   "then the held-out estimate over fresh poses. Default: on, N chosen from the time limit "
                   "(--time-limit-s is the budget of all rounds, default 300 s); 0: the design poses only.")
@click.option("--branch-and-bound/--no-branch-and-bound", "bnb", default=True, show_default=True,
              help="Tighten the certified bound by branch-and-bound in a second process beside the search "
                   "(worst-case objectives with a time limit; docs/optimize.md).")
@flag_rules(Conflict("--candidates", "--spacing-mm", "the candidates file already fixes the sites"),
            Conflict("--candidates", "--keepout-box", "keep-out boxes filter sampled sites; filter the file instead"))
def optimize_cmd(mesh, k, envelope_path, objective, weights, rho, out, report_dir, method, candidates_path,
                 spacing_mm, keepout_box, fixed, min_visible, coverage_fraction, min_spacing_mm,
                 half_angle_deg, k_range, time_limit_s, seed, units, allow_odd_size, no_render, as_json,
                 coverage, max_tilt_deg, tilt_toward, dense_poses, bnb):
    """Choose K photodiode sites on MESH minimising DOP over the envelope, with a certified gap."""
    import warnings

    from ..mesh import MeshUnitsWarning

    with warnings.catch_warnings():  # mesh warnings (wrong --units, not watertight) as one line each
        warnings.showwarning = lambda msg, *a, **k: click.secho(f"warning: {msg}", fg="yellow", err=True)
        if not allow_odd_size:  # an optimisation at the wrong scale is minutes of nonsense: stop now
            warnings.simplefilter("error", MeshUnitsWarning)
        else:  # asked for: one warning line (the command group makes odd sizes errors by default)
            warnings.simplefilter("default", MeshUnitsWarning)
        try:
            spec = _spec(k, objective, weights, rho, method, fixed, min_visible, coverage_fraction, min_spacing_mm,
                         half_angle_deg, time_limit_s, seed, coverage, max_tilt_deg, tilt_toward, dense_poses, bnb)
            s = _optimize(mesh, envelope_path, spec, dict(candidates=candidates_path, units=units,
                                                          spacing=None if spacing_mm is None else spacing_mm * 1e-3,
                                                          keepout=_keepout(keepout_box)),
                          out, report_dir, k_range, no_render, as_json, auto_dense=dense_poses is None)
        except MeshUnitsWarning as exc:
            fail(f"{exc} (as --units {units}); give the right --units, or --allow-odd-size to go on")
    if as_json:
        echo_json(s)
    else:
        _print_summary(s)
    if s.get("interrupted"):  # outputs written; the conventional 128 + signal number
        click.secho(f"interrupted by {s['interrupted']}: wrote the best layout so far and every finished k",
                    fg="yellow", err=True)
        raise SystemExit(143 if s["interrupted"] == "SIGTERM" else 130)
    if not s["success"]:
        raise SystemExit(1)


def _keepout(keepout_box):
    from ..candidates import parse_keepout

    with bad_input():
        return [parse_keepout("box:" + b) for b in keepout_box]


def _spec(k, objective, weights, rho, method, fixed, min_visible, coverage_fraction, min_spacing_mm,
          half_angle_deg, time_limit_s, seed, coverage, max_tilt_deg, tilt_toward, dense_poses, bnb):
    """The :class:`layoutkit.optimize.OptimizeSpec` of the command's options (errors: exit 2 with the field)."""
    from ..optimize import DenseSpec, OptimizeSpec

    if weights and not objective.strip().lower().endswith("weighted"):
        fail(f"--weights is for the *-weighted objectives; --objective {objective} would ignore it")
    if objective.strip().lower().endswith("weighted") and not weights:
        fail(f"--objective {objective}: needs --weights A,B (weights of ADOP² in deg² and PDOP² in m²); "
             "no silent default")
    with bad_input():
        w = tuple(float(x) for x in weights.split(",")) if weights else None
        return OptimizeSpec(k=k, objective=objective, weights=w, rho=rho, min_visible=min_visible, coverage=coverage,
                            coverage_fraction=coverage_fraction, min_spacing_m=min_spacing_mm * 1e-3,
                            half_angle_deg=half_angle_deg, max_tilt_deg=max_tilt_deg,
                            tilt_toward=tuple(tilt_toward) if isinstance(tilt_toward, list) else tilt_toward,
                            method=method, time_limit_s=time_limit_s, seed=seed,
                            branch_and_bound="auto" if bnb else "off",
                            fixed=tuple(f.strip() for f in fixed.split(",") if f.strip()),
                            dense=DenseSpec(poses=dense_poses) if dense_poses else None)


def _optimize(mesh, envelope_path, spec, sources, out, report_dir, k_range, no_render, as_json, auto_dense):
    """Load the problem once, run the workflow; a ValueError is a clear error (exit 2). ``auto_dense``: no
    --dense-poses given, the dense loop's size and budget come from the envelope and the time limit."""
    from ..optimize import DesignProblem
    from ..optimize.dense import default_dense
    from ..optimize.runcontrol import Interrupted
    from ..workflows.optimize import run_optimize

    with bad_input():
        problem = DesignProblem.for_spec(mesh, envelope_path, spec, **sources)
        if auto_dense:
            dense, budget, note = default_dense(problem.envelope, spec.time_limit_s)
            if dense is not None:
                spec = spec.replace(dense=dense, time_limit_s=budget)
            click.echo(f"note: {note} (--dense-poses 0: the design poses only)", err=True)
        with _progress(as_json) as prog:
            try:
                return run_optimize(problem, spec, out=out, report=report_dir, k_range=k_range, progress=prog,
                                    render=not no_render, echo=lambda m: click.echo(m, err=True))
            except Interrupted as exc:
                click.secho(f"error: interrupted by {exc.signame} before any layout was found; nothing written",
                            fg="red", err=True)
                raise SystemExit(143 if exc.signame == "SIGTERM" else 130)


def _print_summary(s):
    if not s["success"]:
        click.secho(f"error: {s['status']}: {s['message']}", fg="red", err=True)
        return
    st = s["stats"]
    a, p = st["adop_deg_per_rad"], st["pdop_m_per_rad"]
    click.echo(f"{s['k']} of {s['candidates']} candidate sites over {s['poses']} poses ({s['method']}, rho {s['rho']})")
    click.echo(f"  {s['objective']} = {s['value']:.5g}   ({s.get('value_refers_to', 'design poses')})")
    if s.get("design_value") is not None and s["design_value"] != s["value"]:
        click.echo(f"  the optimiser's own value over its working set: {s['design_value']:.5g}")
    cert = s.get("certificate") or {}
    if s["certified_by"] == "none" or s["bound"] is None or s["bound"] != s["bound"]:
        click.echo(f"  bound: none ({s['message'].split('bound: none')[-1].strip(' ;')})")
    else:
        gap = s["gap"]
        gtxt = "none" if gap is None else f"{100 * gap:.2f} %"
        click.echo(f"  certified bound {s['bound']:.5g} ({s['certified_by']})   gap {gtxt}"
                   + (f"   [{cert['verdict']}]" if cert.get("verdict") else ""))
        if cert.get("statement"):
            click.echo(f"    {cert['statement']}")
    if cert.get("loose") and cert.get("why"):
        click.echo(f"    {'loose' if cert.get('bound') is not None else 'why'}: {cert['why']}")
    if s.get("branch_and_bound"):
        b = s["branch_and_bound"]
        click.echo(f"  branch-and-bound: {b['nodes']} node relaxations, bound {b['root_bound']:.5g} (relaxation)"
                   f" -> {b['bound']:.5g}")
    h = s.get("heldout")
    if h and h["uncovered"]:
        click.secho(f"  warning: {h['uncovered']} of {h['poses']} fresh poses have fewer than {s['min_visible']} lit "
                    "sensors (the value is over the covered ones)", fg="yellow")
    if h:
        click.echo(f"  held-out ({h['poses']} fresh poses, {len(h['draws'])} draws): worst ADOP {h['worst_adop']:.5g}, "
                   f"p99 {h['p99_adop']:.5g}, covered {100 * h['covered_fraction']:.2f} % "
                   f"(uncovered share <= {100 * h['uncovered_fraction_bound_95']:.2f} % at 95 %)")
    where = "working set" if "dense" in (s.get("envelope_sets") or {}) else "design poses"
    click.echo(f"  {where}: ADOP deg/rad  median {a['median']:.5g}  p95 {a['p95']:.5g}  max {a['max']:.5g}")
    click.echo(f"  {where}: PDOP m/rad    median {p['median']:.5g}  p95 {p['p95']:.5g}  max {p['max']:.5g}")
    for row in s["k_sweep"]:
        gap = row["gap"]
        gtxt = f"{100 * gap:.1f} %" if isinstance(gap, float) and gap == gap else "none"
        click.echo(f"  k={row['k']:>3}  {row['status']:<10} value {row['value']:.5g}  gap {gtxt}"
                   if row["stats"] else f"  k={row['k']:>3}  {row['status']}")
    click.echo(f"  layout -> {s.get('out')}" + (f"   report -> {s['report']['dir']}" if s.get("report") else ""))
    sets = s.get("envelope_sets") or {}
    if "dense" in sets:
        click.echo("  worst/median ADOP by pose set (deg/rad):  " + "   ".join(
            f"{nm} ({v['poses']} poses) {v['worst_adop']:.5g} / {v['median_adop']:.5g}"
            for nm, v in sets.items() if v.get("worst_adop") is not None))
    if s.get("tilt_estimate") and s["tilt_estimate"].get("note"):
        click.echo(f"  tilt: {s['tilt_estimate']['note']}")
    click.echo(f"  {s['timings_s']['total_s']:.1f} s")


class _progress:
    """Rich progress bar fed by the optimiser's ``progress(stage, fraction, best)`` callback."""

    def __init__(self, quiet):
        self.quiet = quiet

    def __enter__(self):
        if self.quiet:
            return None
        from rich.console import Console
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        # on stderr: stdout keeps only the summary (no stray blank line when it is redirected)
        self.p = Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.fields[best]}"),
                          TimeElapsedColumn(), transient=True, console=Console(stderr=True))
        self.p.__enter__()
        self.task = self.p.add_task("preparing", total=1.0, best="")

        def cb(stage, fraction=None, best=None):
            b = "" if best is None or best == float("inf") else f"best {best:.5g}"
            self.p.update(self.task, description=stage, completed=fraction or 0.0, best=b)

        return cb

    def __exit__(self, *a):
        if not self.quiet:
            self.p.__exit__(*a)
        return False


commands: list = [optimize_cmd]
