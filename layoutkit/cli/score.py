"""CLI command ``layoutkit score``: a fixed layout over an envelope (issue 13, item 4)."""
from __future__ import annotations

import click

from ._common import bad_input, echo_json
from .options import (coverage_option, envelope_option, explicit, half_angle_option, json_flag, min_visible_option,
                      report_option, rho_option, seed_option, units_option)


@click.command("score", short_help="Score a layout over an envelope: DOP, coverage, usage.")
@click.argument("layout", type=click.Path(dir_okay=False))
@envelope_option(required=False, help="Operating envelope TOML (docs/envelope.md); default: the one the layout "
                                      "records (layouts written by `layoutkit optimize`).")
@click.option("--mesh", "mesh_path", default=None, type=click.Path(dir_okay=False),
              help="Mesh for self-occlusion (default: the one the layout records; without either: acceptance "
                   "cone and field of view only).")
@units_option
@rho_option
@half_angle_option
@coverage_option
@min_visible_option
@click.option("--poses", "n_poses", type=click.IntRange(min=1), default=None,
              help="Number of envelope poses (overrides the envelope's count, e.g. a dense set).")
@seed_option(default=None)
@click.option("--draws", type=click.IntRange(min=0), default=0, show_default=True,
              help="Score on this many fresh draws of the envelope (--poses each, default 2000; the held-out draws "
                   "of `layoutkit optimize`) instead of its own pose set: statistics over all, worst per draw.")
@click.option("--compare", "compare_path", default=None, type=click.Path(dir_okay=False),
              help="Second layout scored over the same poses: side-by-side table (and CDF with --report).")
@report_option
@json_flag
@click.pass_context
def score_cmd(ctx, layout, envelope_path, mesh_path, units, rho, half_angle_deg, coverage, min_visible, n_poses,
              seed, draws, compare_path, report_dir, as_json):
    """Score LAYOUT over the envelope: DOP distribution, coverage by rule, per-sensor usage.

    --seed replaces the envelope's pose seed (a held-out pose set). ADOP in deg/rad, PDOP in m/rad;
    statistics over the covered poses. Exit 1 if no pose is covered. A layout written by `layoutkit
    optimize` records its envelope, mesh and settings: what is not given here is taken from it
    (the JSON's "sources" says what came from where).
    """
    from ..workflows.score import FROM_LAYOUT, score_layout

    def given(name, value):
        return value if explicit(ctx, name) else None

    from .progress import progress_bar

    with bad_input():
        with progress_bar("poses", quiet=as_json or not n_poses) as bar:
            task = bar.add_task("poses", total=n_poses)
            res = score_layout(layout, envelope_path, mesh=mesh_path if mesh_path is not None else FROM_LAYOUT,
                               units=given("units", units), rho=given("rho", rho),
                               half_angle_deg=given("half_angle_deg", half_angle_deg),
                               min_visible=given("min_visible", min_visible), coverage=given("coverage", coverage),
                               poses=n_poses, seed=seed, compare=compare_path, report=report_dir, draws=draws,
                               progress=lambda n: bar.advance(task, n))
    out = {k: v for k, v in res.items() if not k.startswith("_")}
    if as_json:
        echo_json(out)
    else:
        _print(out)
    if not res["success"]:
        raise SystemExit(1)


def _fmt(v):
    return "-" if v is None else f"{v:.5g}" if isinstance(v, float) else str(v)


def _print(r):
    from ..workflows.score import COMPARISON_ROWS

    c = r.get("compare")
    click.echo(f"{r['layout']} over {r['envelope']} ({r['coverage_rule']}, >= {r['min_visible']} lit, rho {r['rho']}, "
               f"occlusion: {r['occlusion']})" + (f", {len(r['draws'])} fresh draws" if r.get("draws") else ""))
    rows = r["comparison"] if c else [{"quantity": lab, "layout": r[k]} for lab, k in COMPARISON_ROWS]
    if not c:
        rows += [{"quantity": f"draw {i} (seed {d['seed']}) ADOP worst", "layout": d["worst_adop"]}
                 for i, d in enumerate(r.get("draws", []))]
    click.echo(f"{'':<34}{'layout':>14}" + (f"{'compare':>14}{'ratio':>9}" if c else ""))
    for row in rows:
        line = f"{row['quantity']:<34}{_fmt(row['layout']):>14}"
        if c:
            line += f"{_fmt(row['compare']):>14}{_fmt(row['ratio']) if row['ratio'] is not None else '':>9}"
        click.echo(line)
    used = sorted(r["per_sensor"], key=lambda u: u["lit_fraction"])
    click.echo("least used sensors: " + ", ".join(f"{u['id']} {100 * u['lit_fraction']:.0f} %" for u in used[:5]))
    click.echo(r["message"])
    if r.get("report"):
        click.echo(f"report -> {r['report']['dir']}")


commands: list = [score_cmd]
