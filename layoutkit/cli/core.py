"""CLI commands of the core: dop, simulate, solve, study, demo."""
from __future__ import annotations

import click

from ..units import ARCSEC
from ._common import call_or_fail, echo_json, emit_json, fail
from .options import NONNEGATIVE, POSITIVE, overwrite_option
from .options import (data_dir_option, filter_options, half_angle_option, json_flag, json_out_option, layout_option,
                      out_dir_option, out_file_option, motion_compensation_option, registry_choice, rho_option,
                      seed_option, sigma_option, scheduler_option, solve_mode_option, stations_option,
                      ignore_calibration_option,
                      workers_option)


def _layout(path):
    from ..layout import load_layout

    return call_or_fail(load_layout, path)


@click.command("dop", short_help="ADOP/PDOP and the predicted precision at one pose.")
@layout_option
@click.option("--rotvec-deg", nargs=3, type=float, default=(0.0, 0.0, 0.0), show_default=True,
              help="Body attitude in the lighthouse frame, rotation vector in degrees.")
@click.option("--translation-m", nargs=3, type=float, default=(0.0, 0.0, 2.0), show_default=True,
              help="Body position in the lighthouse frame, metres (z = boresight).")
@click.option("--lit", default="facing", show_default=True,
              help="Sensors used: 'all', 'facing' (normal within --half-angle-deg of the station, in view), "
                   "or comma-separated ids.")
@half_angle_option
@rho_option
@sigma_option
@json_flag
def dop_cmd(layout_path, rotvec_deg, translation_m, lit, half_angle_deg, rho, sigma, as_json):
    """ADOP/PDOP of a layout at one pose and the predicted precision (Chen eqs 18-24)."""
    from ..workflows.precision import pose_precision

    lay = _layout(layout_path)
    out = call_or_fail(pose_precision, lay, rotvec_deg, translation_m, lit=lit, half_angle_deg=half_angle_deg,
                       rho=rho, sigma=sigma)
    under = out["status"] == "underdetermined"
    if as_json:
        echo_json(out)
        if under:
            raise SystemExit(1)
        return
    if not out["success"] and not under:
        lit_ids = ", ".join(out["lit"]) or "none"
        why = ("singular geometry" if out["n_lit"] >= 3 else "fewer than 3 sensors lit; the body may face away "
               "from the station (try another --rotvec-deg, or --lit all)")
        fail(f"DOP undefined at this pose: {why} (lit: {lit_ids})", code=1)
    click.echo(f"lit sensors ({out['n_lit']}): {', '.join(out['lit'])}")
    click.echo(f"ADOP = {out['adop_deg_per_rad']:.2f} deg/rad   PDOP = {out['pdop_m_per_rad']:.3f} m/rad   (rho = {rho})")
    click.echo(f"predicted precision at sigma = {sigma / ARCSEC:.4g}\": {out['predicted_sigma_rot_deg']:.4f} deg, "
               f"{out['predicted_sigma_trans_mm']:.3f} mm")
    if under:
        fail(out["message"], code=1)


@click.command("simulate", short_help="Simulate noisy sweep-angle frames at random poses.")
@layout_option
@click.option("--frames", type=click.IntRange(min=1), default=1000, show_default=True, help="Number of frames.")
@seed_option
@out_file_option(help="Frame file to write (.csv or .npz).")
@rho_option
@sigma_option(allow_zero=True)
@click.option("--no-quantize", is_flag=True, help="Skip the 50 MHz counter quantisation.")
@stations_option(help="Stations JSON (poses in one world frame, kind, calibration): one row per station and pose, "
                      "the angles through each station's forward model (calibrated when it carries a calibration).")
@overwrite_option(what="an existing --out frame table")
@json_flag(help="Print a JSON summary.")
def simulate_cmd(layout_path, frames, seed, out, rho, sigma, no_quantize, stations_path, overwrite, as_json):
    """Simulate noisy sweep-angle frames at random static poses in front of one station.

    Poses: the paper's 3 m × 3 m area in front of the station, uniform attitudes, ≥ 4 sensors lit.
    The file holds the true poses too, so `layoutkit solve` can report errors. With --stations the
    poses are drawn in front of station 0 and every station (each lighting >= 4 sensors) writes a row
    within the same 20 ms window, its angles measure(points, calibration) — the distorted angles a
    station with those factory parameters reports; true poses in each row's station frame.
    """
    from ..workflows.frames import simulate_frame_file
    from ._common import refuse_existing

    refuse_existing(out, overwrite, "the frames and truth of an earlier run")
    lay = _layout(layout_path)
    summary = call_or_fail(simulate_frame_file, lay, frames, out, seed=seed, sigma=sigma, rho=rho,
                           quantize=not no_quantize, stations_path=stations_path)
    if as_json:
        echo_json(summary)
    else:
        click.echo(f"wrote {summary['rows']} frames to {out} (lit sensors: mean {summary['mean_lit']:.1f}, "
                   f"min {summary['min_lit']})")


@click.command("solve", short_help="Solve every frame of a frame file (batched PnP).")
@click.argument("frames_path", type=click.Path(dir_okay=False))
@layout_option
@out_file_option(required=False,
                 help="Write the pose table CSV (t,station,status,rx,ry,rz,tx,ty,tz,residual_rms; rad, m).")
@click.option("--solver", type=registry_choice("layoutkit.pnp:PNP_SOLVERS"), default="lm", show_default=True,
              help="PnP solver (the registry layoutkit.pnp.PNP_SOLVERS).")
@rho_option
@sigma_option(allow_zero=True, help="Sweep-angle noise 1-sigma of the frames, arcsec (0: noise-free, no pose ties; "
                                        "paper: 8.28\" = 4.014e-5 rad).")
@stations_option
@click.option("--static", is_flag=True,
              help="The body is at rest: estimate sigma and rho from the angles and compare the pose scatter "
                   "with the DOP prediction.")
# --calibrated was the opt-in to the stations' calibration; it is the default now (kept so scripts run)
@click.option("--calibrated", is_flag=True, hidden=True)
@ignore_calibration_option
@json_flag(help="Print a JSON summary.")
@filter_options
@solve_mode_option
@motion_compensation_option
def solve_cmd(frames_path, layout_path, out, solver, rho, sigma, stations_path, static, calibrated, ignore_calibration,
              as_json, filter_settings, solve_mode, motion_compensation):
    """Solve the pose of every frame in a frame file (batched PnP); errors vs truth if present.

    Bad frames (too few angles, inf, angles outside (0, pi), all behind) get a status each and the
    batch goes on; exit 0 when the file could be read and at least one pose is good, 1 when no pose
    is (with the most common reason). With --stations the pose table is in the world frame; with
    several stations the default is --solve joint: one pose per 20 ms window from all stations'
    angles through their calibrated forward models (station 'joint'); --solve per-station solves
    each station's frames alone — also through its calibration when the stations file carries one
    (--ignore-calibration: the ideal model, for comparison).

    With --filter ekf the frames (in time order, by their t) also go through the tracking filter
    (X then Y sweep at the frame's t); --out then holds the filtered poses (status 0 ok, 10
    uncertain, 11 lost, -1 before the first start; extras cov_rot_deg_*, cov_pos_m_* = 1-sigma).
    """
    from ..workflows.frames import solve_frame_file

    lay = _layout(layout_path)
    if calibrated and ignore_calibration:
        fail("--calibrated and --ignore-calibration: choose one (calibrated is the default)")
    if solve_mode == "joint" and stations_path is None:
        fail("--solve joint needs --stations (station poses in one world frame)")
    if stations_path is not None and solve_mode != "per-station":
        from ..workflows.calibrate import frame_file_stations, solve_station_file

        several = solve_mode == "joint" or call_or_fail(frame_file_stations, frames_path, stations_path) > 1
    else:
        several = False
    if several:  # joint: one pose per window through every station's calibrated forward model
        summary = call_or_fail(solve_station_file, frames_path, lay, stations_path, out=out, mode="joint",
                               sigma=sigma, rho=rho, ignore_calibration=ignore_calibration,
                               motion_compensation=motion_compensation is not False)
        if as_json:
            echo_json(summary)
        else:
            click.echo(f"{summary['mode']}: solved {summary['solved']} / {summary['poses']} poses from "
                       f"{summary['rows']} rows; statuses {summary['status_counts']}")
            if "predicted_position_sigma_m" in summary:
                click.echo(f"position scatter {summary['position_scatter_m'] * 1e3:.3f} mm; DOP prediction "
                           f"{summary['predicted_position_sigma_m'] * 1e3:.3f} mm")
            if "precision_accuracy" in summary:
                click.echo(f"precision vs accuracy: {summary['precision_accuracy']['message']}")
        if summary["solved"] == 0:
            fail(summary.get("reason", "no pose solved"), code=1)
        return
    summary = call_or_fail(solve_frame_file, frames_path, lay, out=out, sigma=sigma, rho=rho, method=solver,
                           filter_settings=filter_settings, stations_path=stations_path, static=static,
                           ignore_calibration=ignore_calibration)
    if as_json:
        echo_json(summary)
    else:
        _print_solve(summary)
    if summary["solved"] == 0:
        fail(summary["message"], code=1)


def _print_solve(summary: dict) -> None:
    click.echo(f"solved {summary['solved']} / {summary['frames']} frames; statuses {summary['statuses']}")
    if summary["residual_rms_median"] is not None:
        click.echo(f"residual RMS: median {summary['residual_rms_median']:.3g} rad, "
                   f"90 % {summary['residual_rms_p90']:.3g} rad")
    if "rms_rot_deg" in summary:
        click.echo(f"RMS error vs truth: {summary['rms_rot_deg']:.4f} deg, {summary['rms_trans_m'] * 1e3:.3f} mm "
                   f"over the {summary['solved']} frames with status ok; {summary['gross_failures']} of them "
                   "gross failure(s) (> 1 deg)")
        amb = summary.get("ambiguous")
        if amb:
            click.echo(f"{amb['frames']} ambiguous frame(s) (two poses fit equally well; not counted as solved): "
                       f"the truth is within 1 deg of one of the two candidates in {amb['truth_within_1deg_of_a_candidate']}")
        msg = (f"without them: {summary['rms_rot_deg_without_gross']:.4f} deg, "
               f"{summary['rms_trans_m_without_gross'] * 1e3:.3f} mm")
        if "predicted_rms_rot_deg" in summary:
            msg += (f"  (DOP prediction {summary['predicted_rms_rot_deg']:.4f} deg, "
                    f"{summary['predicted_rms_trans_m'] * 1e3:.3f} mm)")
        click.echo(msg)
    f = summary.get("filter")
    if f:
        click.echo(f"filter: ok {f['ok']} / {f['frames']} frames (inits {f['counters']['inits']}, lost "
                   f"{f['counters']['losts']}, angles rejected {f['counters']['angles_rejected']})")
        if "filter_rms_rot_deg" in f:
            click.echo(f"filter RMS error vs truth: {f['filter_rms_rot_deg']:.4f} deg, {f['filter_rms_pos_m'] * 1e3:.3f} mm "
                       f"(own covariance {f['filter_cov_rms_rot_deg']:.4f} deg, {f['filter_cov_rms_pos_m'] * 1e3:.3f} mm; "
                       f"mean NEES {f['filter_mean_nees_6dof']:.2f} of 6)")


@click.group("study", short_help="Reproducible studies of the papers' tables and figures.")
def study_group():
    """Reproducible studies that regenerate the papers' tables and figures."""


@study_group.command("chen2024", short_help="Chen (2024) static precision and dynamic accuracy.")
@click.option("--groups", type=click.IntRange(min=1), default=50, show_default=True, help="Static groups (paper: 50).")
@click.option("--frames", type=click.IntRange(min=2), default=3600, show_default=True, help="Frames per group (paper: 3600).")
@click.option("--chunk-frames", type=click.IntRange(min=1), default=20000, show_default=True,
              help="Frames per Dask task (part of the random stream: results depend on it, not on --workers).")
@seed_option
@click.option("--dynamic-seconds", type=POSITIVE, default=60.0, show_default=True, help="Length of each dynamic run.")
@click.option("--sensor-error-mm", type=NONNEGATIVE, default=0.5, show_default=True,
              help="Systematic sensor-coordinate error for the second dynamic run (0: skip it).")
@out_dir_option(default="out/chen2024", aliases=("--out",), help="Folder for the figure, table and full JSON.")
@json_flag(help="Print the groups JSON to stdout (instead of the text summary).")
@json_out_option(help="Also write the groups JSON to this file.")
@scheduler_option
@workers_option
def study_chen(groups, frames, chunk_frames, seed, dynamic_seconds, sensor_error_mm, out_dir, as_json, json_out,
               scheduler, workers):
    """Chen et al. (2024) static precision (Fig. 5) and dynamic accuracy (Table 2) in simulation.

    The static frames run as chunked Dask tasks (default: a LocalCluster on this machine)."""
    from ..studies.chen2024 import StudyConfig, run_chen2024, write_outputs
    from .distributed import executor_from_flags
    from .progress import progress_bar

    cfg = StudyConfig(groups=groups, frames=frames, seed=seed, dynamic_seconds=dynamic_seconds,
                      sensor_error_mm=sensor_error_mm, chunk_frames=chunk_frames)
    with executor_from_flags(scheduler, workers, quiet=as_json or json_out == "-") as ex, \
            progress_bar("static frames", quiet=as_json or json_out == "-") as prog:
        task = prog.add_task("static frames", total=groups * frames)
        res = run_chen2024(cfg, progress=lambda k: prog.advance(task, k), executor=ex)
    paths = write_outputs(res, out_dir)
    doc = {"summary": res["summary"], "groups": res["groups"],
           "dynamic": [{k: v for k, v in d.items() if not isinstance(v, list)} for d in res["dynamic"]]}
    if emit_json(doc, as_json, json_out):
        return
    s = res["summary"]
    click.echo(f"{s['groups']} groups × {s['frames_per_group']} frames: simulated/predicted median ratio "
               f"{s['median_ratio_rot']:.3f} (attitude), {s['median_ratio_trans']:.3f} (position); "
               f"gross failures {s['gross_failures']} / {s['total_frames']}")
    for d in res["dynamic"]:
        click.echo(f"dynamic (sensor error {d['sensor_error_mm']} mm): RMS {d['rms_rot_deg']:.3f} deg, "
                   f"{d['rms_trans_m'] * 1e3:.2f} mm; max {d['max_rot_deg']:.3f} deg, {d['max_trans_m'] * 1e3:.2f} mm")
    click.echo(f"wrote {paths['fig5']}, {paths['fig7']}, {paths['table']}")


@study_group.command("zhai2014", short_help="Zhai (2014) rectangle-face attitude fly-around.")
@click.option("--quick", is_flag=True, help="Smoke run: 10 s samples, fewer repeats (well under a minute).")
@seed_option(default=2014)
@out_dir_option(default="out/zhai2014", aliases=("--out",), help="Folder for the figures, table.md and results.json.")
@json_flag(help="Print the summary JSON to stdout (instead of progress lines).")
@json_out_option(help="Also write the summary JSON to this file.")
def study_zhai(quick, seed, out_dir, as_json, json_out):
    """Zhai et al. (2014) rectangle-face attitude fly-around (both ground-test cases) with renders."""
    import warnings

    from ..studies.zhai2014 import main as zhai_main

    quiet = as_json or json_out == "-"
    with warnings.catch_warnings():  # pyvista cannot keep trimesh's 'parts' metadata: harmless, noisy
        warnings.filterwarnings("ignore", message="Unable to store metadata key")
        summary = zhai_main(out_dir, quick=quick, seed=seed, progress=(lambda *a, **k: None) if quiet else click.echo)
    emit_json(summary, as_json, json_out)
    if not quiet:
        click.echo(f"wrote figures, table.md and results.json to {out_dir}")


@study_group.command("bitcraze-dataset", short_help="Public Crazyflie Lighthouse logs: firmware vs layoutkit.")
@data_dir_option(help="The dataset's data folder (sets <lh1|lh2>_<crossingBeam|kalman>_<jitter|move|flight>/ with "
                      "logNN, mocapNN.npy, system-config.yaml; bitcraze/positioning_dataset).")
@out_dir_option(default="out/bitcraze_dataset", out_alias=True, help="Folder for table.md, results.json and the figures.")
@json_flag(help="Print the per-set summary JSON to stdout (instead of the table).")
@scheduler_option
@workers_option
def study_bitcraze(data_dir, out_dir, as_json, scheduler, workers):
    """The Crazyflie Lighthouse dataset's own metrics — jitter (static) and error vs motion capture after
    temporal (offset + rate) and rigid (Arun) alignment (moving) — for the firmware's estimates in each
    log (crossing beam, EKF) and for ours (per-station, joint, filter: `replay LOG`), side by side; the
    stations of each set-up refined once from its static logs (OUT/stations/<set-up>.json) and used
    for all its logs.

    One Dask task per log and method (default: a LocalCluster on this machine); says which files it
    could not use and why."""
    from ..studies.bitcraze_dataset import run_study, usable_logs, write_outputs
    from .distributed import executor_from_flags

    quiet = as_json
    call_or_fail(usable_logs, data_dir)       # a folder without any usable log fails before a cluster starts
    with executor_from_flags(scheduler, workers, quiet=quiet) as ex:
        res = call_or_fail(run_study, data_dir, executor=ex, work_dir=out_dir,
                           progress=None if quiet else (lambda msg: click.echo(msg, err=True)))
    paths = write_outputs(res, out_dir)
    if emit_json({"sets": res["sets"], "setups": res["setups"], "skipped": res["skipped"], "outputs": paths}, as_json, None):
        return
    click.echo(open(paths["table"], encoding="utf-8").read())
    click.echo(f"wrote {paths['table']}, {paths['results']} and {len(paths['figures'])} figure(s)")


@click.command("demo", short_help="Optimise a layout on a bundled model, then a Chen study.")
@out_dir_option(default="out/demo", aliases=("--out",), help="Folder for the optimised layout, report and study.")
@seed_option
def demo_cmd(out_dir, seed):
    """The main job on a bundled model: optimise a 12-sensor layout, then a reduced Chen study.

    Optimises a 12-sensor layout on the Chen target (bundled model), then runs a reduced Chen
    precision study of the paper-like layout.
    """
    from pathlib import Path

    out = Path(out_dir)
    try:
        from ..workflows.optimize import run_demo
    except ImportError:  # the optimiser is not installed in this build
        run_demo = None
    if run_demo is not None:
        click.echo("== layoutkit optimize on the Chen target (bundled model) ==")
        summ = run_demo(out / "optimize", quick=True, seed=seed)
        click.echo(f"{summ['message']}\nlayout {out / 'optimize' / 'layout.json'}, report {out / 'optimize' / 'report'}")
        if summ.get("versus_shipped"):
            click.echo(f"against the shipped hand layout, same poses: {summ['versus_shipped']['message']}")
    from ..studies.chen2024 import StudyConfig, run_chen2024, write_outputs

    click.echo("== reduced Chen (2024) precision study ==")
    res = run_chen2024(StudyConfig(groups=10, frames=600, dynamic_seconds=20, seed=seed))
    paths = write_outputs(res, out / "chen2024")
    s = res["summary"]
    click.echo(f"simulated/predicted precision, median over groups: {s['median_ratio_rot']:.3f} (attitude), "
               f"{s['median_ratio_trans']:.3f} (position); figure {paths['fig5']}")


commands = [dop_cmd, simulate_cmd, solve_cmd, study_group, demo_cmd]
