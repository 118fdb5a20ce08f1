"""CLI commands that run on Dask: ``layoutkit sweep`` and ``layoutkit validate``.

Only click is imported here; dask, distributed and numpy are imported inside the command bodies.
"""
from __future__ import annotations

import contextlib

import click

from ._common import bad_input, call_or_fail, echo_json
from .options import (envelope_option, half_angle_option, json_flag, json_out_option, out_dir_option, rho_option,
                      scheduler_option, seed_option, sigma_option, units_option, workers_option)


@contextlib.contextmanager
def executor_from_flags(scheduler, workers, quiet=False):
    """Open the Dask executor the flags ask for; print where it runs (stderr); bad flags: ``error:``."""
    from ..parallel import open_executor

    with contextlib.ExitStack() as stack:
        with bad_input():
            ex = stack.enter_context(open_executor(scheduler, workers))
        if not quiet:
            where = {"synchronous": "in-process (synchronous scheduler)",
                     "local": f"LocalCluster with {ex.n_workers} worker(s) at {ex.address}",
                     "cluster": f"cluster {ex.address} with {ex.n_workers} worker(s)"}[ex.kind]
            click.echo(f"dask: {where}" + (f"; dashboard {ex.dashboard}" if ex.dashboard else ""), err=True)
        yield ex


class _CellProgress:
    """Rich progress bar on stderr: cells done / running / failed."""

    def __init__(self, quiet):
        self.quiet = quiet
        self.p = None

    def __enter__(self):
        if self.quiet:
            return None
        from .progress import progress_bar

        self.p = progress_bar("cells", fields="running {task.fields[running]}  failed {task.fields[failed]}",
                              transient=False)
        self.p.__enter__()
        self.task = None

        def cb(done, running, failed, total):
            if self.task is None:
                self.task = self.p.add_task("cells", total=total, running=0, failed=0)
            self.p.update(self.task, completed=done, running=running, failed=failed)

        return cb

    def __exit__(self, *a):
        if self.p is not None:
            self.p.__exit__(*a)
        return False


@click.command("sweep", short_help="Design sweep: one optimisation per cell, on Dask.")
@click.argument("sweep_path", metavar="SWEEP.toml", type=click.Path(dir_okay=False))
@out_dir_option(out_alias=True, help="Sweep folder (also --out DIR): summary.csv, summary.json, plots, cells/ "
                                     "(re-run to resume).")
@scheduler_option
@workers_option
@json_flag(help="Print the summary as JSON to stdout.")
def sweep_cmd(sweep_path, out_dir, scheduler, workers, as_json):
    """Run every cell of a design sweep (one optimisation each) as a Dask task.

    Each cell is written to DIR/cells/<cell-id>.json (+ .layout.json) when it finishes; running the
    same command again resumes, skipping cells already on disk whose inputs are unchanged. Exits 1
    if a cell failed (its error is in its JSON and in summary.csv).
    """
    from ..workflows.sweep_config import load_sweep
    from ..workflows.sweep import run_sweep

    cfg = call_or_fail(load_sweep, sweep_path)
    echo = lambda m: click.echo(m, err=True)  # noqa: E731
    with executor_from_flags(scheduler, workers, quiet=as_json) as ex:
        try:
            with _CellProgress(as_json) as prog:
                s = run_sweep(cfg, out_dir, ex, progress=prog, echo=echo)
        except KeyboardInterrupt:
            from ..workflows.sweep import read_cells

            n = len(read_cells(out_dir))
            click.secho(f"interrupted: {n} of {len(cfg.cells)} cells are in {out_dir}/cells; run the same "
                        "command again to resume", fg="yellow", err=True)
            raise SystemExit(130)
    if as_json:
        echo_json({k: v for k, v in s.items() if k != "rows"} | {"rows": [
            {k: v for k, v in r.items() if not k.startswith("_")} for r in s["rows"]]})
    else:
        click.echo(f"{s['cells']} cells ({s['ran']} run, {s['skipped']} from disk): {s['feasible']} feasible, "
                   f"{s['errors']} failed; {s['wall_s']:.1f} s")
        for r in s["rows"]:
            if r["status"] == "error":
                click.secho(f"  {r['cell_id']}: {r['_message']}", fg="red", err=True)
        if s["pareto_worst_adop_vs_k"]:
            click.echo("  Pareto front (k: worst ADOP deg/rad): " + ", ".join(
                f"{p['k']}: {p['worst_adop_deg_per_rad']:.5g}" for p in s["pareto_worst_adop_vs_k"]))
        click.echo(f"  summary -> {out_dir}/summary.csv")
    if s["errors"]:
        raise SystemExit(1)


@click.command("validate", short_help="Monte-Carlo a layout over an envelope vs its DOP.")
@click.argument("layout_path", metavar="LAYOUT", type=click.Path(dir_okay=False))
@envelope_option
@click.option("--frames", type=click.IntRange(min=1), required=True, help="Frames to simulate and solve.")
@click.option("--mesh", "mesh_path", type=click.Path(dir_okay=False), default=None,
              help="Mesh for occlusion (default: none — exact for convex bodies).")
@units_option
@half_angle_option
@sigma_option
@rho_option
@seed_option
@click.option("--chunk-frames", type=click.IntRange(min=1), default=20000, show_default=True,
              help="Frames per Dask task (part of the random stream: results depend on it, not on --workers).")
@scheduler_option
@workers_option
@json_flag
@json_out_option
def validate_cmd(layout_path, envelope_path, frames, mesh_path, units, half_angle_deg, sigma, rho, seed,
                 chunk_frames, scheduler, workers, as_json, json_out):
    """Monte-Carlo a LAYOUT over an envelope (simulate + solve) and compare the errors with its DOP.

    Frames are spread evenly over the envelope's (pose, station) pairs with enough lit sensors and
    run as chunked Dask tasks; memory stays flat for any --frames. Exits 1 if nothing could be
    simulated or the errors disagree with the DOP prediction.
    """
    from ..workflows.validate import run_validate

    with executor_from_flags(scheduler, workers, quiet=as_json) as ex:
        from .progress import progress_bar

        with bad_input():
            with progress_bar("frames", quiet=as_json) as prog:
                task = prog.add_task("frames", total=frames)
                res = run_validate(layout_path, envelope_path, frames, executor=ex, sigma=sigma, rho=rho, seed=seed,
                                   mesh=mesh_path, units=units, half_angle_deg=half_angle_deg,
                                   chunk_frames=chunk_frames, progress=lambda n: prog.advance(task, n))
    if json_out:
        echo_json(res, json_out)
    if as_json:
        echo_json(res)
    elif res["success"]:
        o = res["overall"]
        click.echo(f"{o['frames']} frames over {res['pairs']} (pose, station) pairs of {res['poses']} poses "
                   f"({len(res['uncovered_poses'])} poses uncovered)")
        click.echo(f"  attitude: RMS error {o['rms_rot_deg']:.5f} deg, DOP predicts {o['predicted_rms_rot_deg']:.5f} "
                   f"(ratio {o['ratio_rot']:.3f}); p99 |error| {o['abs_error_rot_deg']['p99']:.4g} deg")
        click.echo(f"  position: RMS error {o['rms_trans_m'] * 1e3:.4f} mm, DOP predicts "
                   f"{o['predicted_rms_trans_m'] * 1e3:.4f} (ratio {o['ratio_trans']:.3f}); p99 |error| "
                   f"{o['abs_error_trans_m']['p99'] * 1e3:.4g} mm")
        pr = res["per_pair_ratio"]["rot"]
        if pr:
            click.echo(f"  per-pair RMS/ADOP·σ: p5 {pr['p5']:.3f}  median {pr['p50']:.3f}  p95 {pr['p95']:.3f}")
        click.echo(f"  gross failures {o['gross_failures']}; {res['message']}")
    if not res["success"]:
        click.secho(f"error: {res['status']}: {res['message']}", fg="red", err=True)
        raise SystemExit(1)
    if not res["agrees_with_dop"]:
        raise SystemExit(1)


commands: list = [sweep_cmd, validate_cmd]
