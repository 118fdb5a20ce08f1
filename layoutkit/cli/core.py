"""CLI commands of the core: dop, simulate, solve, study, demo."""
from __future__ import annotations

import click

from ..units import ARCSEC
from ._common import echo_json, fail
from .options import filter_options


def _layout(path):
    from ..layout import load_layout

    try:
        return load_layout(path)
    except ValueError as exc:
        fail(str(exc))


def _noise_options(f):
    f = click.option("--rho", type=click.FloatRange(0.0, 1.0), default=0.8717, show_default=True,
                     help="Same-rotor correlation of angle noise (Chen eq. 19).")(f)
    f = click.option("--sigma-arcsec", type=click.FloatRange(min=0.0), default=8.2795, show_default=True,
                     help="Angle noise 1-sigma in arcsec (paper: 4.014e-5 rad).")(f)
    return f


@click.command("dop")
@click.option("--layout", "layout_path", required=True, type=click.Path(dir_okay=False), help="Layout JSON.")
@click.option("--rotvec-deg", nargs=3, type=float, default=(0.0, 0.0, 0.0), show_default=True,
              help="Body attitude in the lighthouse frame, rotation vector in degrees.")
@click.option("--translation-m", nargs=3, type=float, default=(0.0, 0.0, 2.0), show_default=True,
              help="Body position in the lighthouse frame, metres (z = boresight).")
@click.option("--lit", default="facing", show_default=True,
              help="Sensors used: 'all', 'facing' (normal within --half-angle-deg of the station, in view), or comma-separated ids.")
@click.option("--half-angle-deg", type=float, default=60.0, show_default=True, help="Sensor acceptance half-angle.")
@_noise_options
@click.option("--json", "json_out", is_flag=True, help="Print JSON.")
def dop_cmd(layout_path, rotvec_deg, translation_m, lit, half_angle_deg, rho, sigma_arcsec, json_out):
    """ADOP/PDOP of a layout at one pose and the predicted precision (Chen eqs 18–24)."""
    import numpy as np

    from ..dop import pose_dop
    from ..geometry import rotvec_to_matrix
    from ..visibility import facing_mask

    lay = _layout(layout_path)
    R = rotvec_to_matrix(np.radians(rotvec_deg))
    t = np.asarray(translation_m, float)
    if lit == "all":
        v = np.ones(lay.n, bool)
    elif lit == "facing":
        v = facing_mask(lay.positions, lay.normals, R[None], t[None], half_angle_deg=half_angle_deg)[0]
    else:
        want = [s.strip() for s in lit.split(",") if s.strip()]
        unknown = [s for s in want if s not in lay.ids]
        if unknown:
            fail(f"--lit: unknown sensor ids {unknown}; the layout has {list(lay.ids)}")
        v = np.isin(lay.ids, want)
    r = pose_dop(lay.positions, R, t, rho=rho, visible=v)
    sigma = sigma_arcsec * ARCSEC
    out = {"lit": [i for i, b in zip(lay.ids, v) if b], "n_lit": int(v.sum()), "rho": rho,
           "status": int(r.status), "message": r.message,
           "adop_deg_per_rad": float(r.adop), "pdop_m_per_rad": float(r.pdop),
           "predicted_sigma_rot_deg": float(r.adop * sigma), "predicted_sigma_trans_mm": float(r.pdop * sigma * 1e3)}
    if json_out:
        echo_json(out)
        return
    if not r.success:
        lit_ids = ", ".join(out["lit"]) or "none"
        why = ("singular geometry" if out["n_lit"] >= 3 else "fewer than 3 sensors lit; the body may face away "
               "from the station (try another --rotvec-deg, or --lit all)")
        fail(f"DOP undefined at this pose: {why} (lit: {lit_ids})", code=1)
    click.echo(f"lit sensors ({out['n_lit']}): {', '.join(out['lit'])}")
    click.echo(f"ADOP = {out['adop_deg_per_rad']:.2f} deg/rad   PDOP = {out['pdop_m_per_rad']:.3f} m/rad   (rho = {rho})")
    click.echo(f"predicted precision at sigma = {sigma_arcsec}\": {out['predicted_sigma_rot_deg']:.4f} deg, "
               f"{out['predicted_sigma_trans_mm']:.3f} mm")


@click.command("simulate")
@click.option("--layout", "layout_path", required=True, type=click.Path(dir_okay=False), help="Layout JSON.")
@click.option("--frames", type=click.IntRange(min=1), default=1000, show_default=True, help="Number of frames.")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--out", required=True, type=click.Path(dir_okay=False), help="Frame file to write (.csv or .npz).")
@_noise_options
@click.option("--no-quantize", is_flag=True, help="Skip the 50 MHz counter quantisation.")
@click.option("--json", "json_out", is_flag=True, help="Print a JSON summary.")
def simulate_cmd(layout_path, frames, seed, out, rho, sigma_arcsec, no_quantize, json_out):
    """Simulate noisy sweep-angle frames at random static poses in front of one station.

    Poses: the paper's 3 m × 3 m area in front of the station, uniform attitudes, ≥ 4 sensors lit.
    The file holds the true poses too, so `layoutkit solve` can report errors.
    """
    import numpy as np

    from ..workflows.frames import simulate_frames, write_frames

    lay = _layout(layout_path)
    fr = simulate_frames(lay, frames, seed=seed, sigma=sigma_arcsec * ARCSEC, rho=rho, quantize=not no_quantize)
    write_frames(fr, out)
    lit = np.all(np.isfinite(fr.angles), -1).sum(1)
    summary = {"out": out, "frames": frames, "mean_lit": float(lit.mean()), "min_lit": int(lit.min())}
    echo_json(summary) if json_out else click.echo(f"wrote {frames} frames to {out} (lit sensors: mean {lit.mean():.1f}, min {lit.min()})")


@click.command("solve")
@click.argument("frames_path", type=click.Path(dir_okay=False))
@click.option("--layout", "layout_path", required=True, type=click.Path(dir_okay=False), help="Layout JSON.")
@click.option("--out", type=click.Path(dir_okay=False),
              help="Write the pose table CSV (t,station,status,rx,ry,rz,tx,ty,tz,residual_rms; rad, m).")
@_noise_options
@click.option("--json", "json_out", is_flag=True, help="Print a JSON summary.")
@filter_options
def solve_cmd(frames_path, layout_path, out, rho, sigma_arcsec, json_out, filter_settings):
    """Solve the pose of every frame in a frame file (batched PnP); errors vs truth if present.

    With --filter ekf the frames (in time order, by their t) also go through the tracking filter
    (X then Y sweep at the frame's t); --out then holds the filtered poses (status 0 ok, 10
    uncertain, 11 lost, -1 before the first start; extras cov_rot_deg_*, cov_pos_m_* = 1-sigma).
    """
    from ..io.poses import write_poses
    from ..workflows.frames import read_frames, solution_table, solve_frames

    lay = _layout(layout_path)
    try:
        fr = read_frames(frames_path, lay)
    except (ValueError, OSError) as exc:
        fail(str(exc))
    res = solve_frames(fr, lay, sigma=sigma_arcsec * ARCSEC, rho=rho)
    fres = None
    if filter_settings is not None:
        from ..workflows.filter import filter_config, filter_frames, filter_table

        try:
            fres = filter_frames(fr, lay, filter_config(filter_settings, sigma_arcsec * ARCSEC, rho))
        except ValueError as exc:
            fail(f"{frames_path}: {exc}")
    if out:
        write_poses(out, solution_table(res) if fres is None else filter_table(fres))
    summary = {k: v for k, v in res.items()
               if k not in ("t", "rotvec", "translation", "success", "status", "residual_rms")}
    if fres is not None:
        summary["filter"] = {k: v for k, v in fres.items()
                             if k not in ("t", "rotvec", "translation", "status", "cov_rot_deg", "cov_pos_m")}
    if json_out:
        echo_json(summary)
        return
    click.echo(f"solved {summary['solved']} / {summary['frames']} frames; statuses {summary['status_counts']}")
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


@click.group("study")
def study_group():
    """Reproducible studies that regenerate the papers' tables and figures."""


@study_group.command("chen2024")
@click.option("--groups", type=click.IntRange(min=1), default=50, show_default=True, help="Static groups (paper: 50).")
@click.option("--frames", type=click.IntRange(min=2), default=3600, show_default=True, help="Frames per group (paper: 3600).")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--dynamic-seconds", type=float, default=60.0, show_default=True, help="Length of each dynamic run.")
@click.option("--sensor-error-mm", type=float, default=0.5, show_default=True,
              help="Systematic sensor-coordinate error for the second dynamic run (0: skip it).")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default="out/chen2024", show_default=True,
              help="Folder for the figure, table and full JSON.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), help="Write the groups JSON here ('-' = stdout).")
def study_chen(groups, frames, seed, dynamic_seconds, sensor_error_mm, out_dir, json_path):
    """Chen et al. (2024) static precision (Fig. 5) and dynamic accuracy (Table 2) in simulation."""
    from rich.progress import Progress

    from ..workflows.chen import StudyConfig, run_chen2024, write_outputs

    cfg = StudyConfig(groups=groups, frames=frames, seed=seed, dynamic_seconds=dynamic_seconds,
                      sensor_error_mm=sensor_error_mm)
    with Progress(transient=True) as prog:
        task = prog.add_task("static groups", total=groups)
        res = run_chen2024(cfg, progress=lambda k: prog.advance(task, k))
    paths = write_outputs(res, out_dir)
    if json_path:
        echo_json({"summary": res["summary"], "groups": res["groups"],
                   "dynamic": [{k: v for k, v in d.items() if not isinstance(v, list)} for d in res["dynamic"]]},
                  json_path)
    if json_path != "-":
        s = res["summary"]
        click.echo(f"{s['groups']} groups × {s['frames_per_group']} frames: simulated/predicted median ratio "
                   f"{s['median_ratio_rot']:.3f} (attitude), {s['median_ratio_trans']:.3f} (position); "
                   f"gross failures {s['gross_failures']} / {s['total_frames']}")
        for d in res["dynamic"]:
            click.echo(f"dynamic (sensor error {d['sensor_error_mm']} mm): RMS {d['rms_rot_deg']:.3f} deg, "
                       f"{d['rms_trans_m'] * 1e3:.2f} mm; max {d['max_rot_deg']:.3f} deg, {d['max_trans_m'] * 1e3:.2f} mm")
        click.echo(f"wrote {paths['fig5']}, {paths['fig7']}, {paths['table']}")


@study_group.command("zhai2014")
@click.option("--quick", is_flag=True, help="Smoke run: 5 s samples, fewer repeats (well under a minute).")
@click.option("--seed", type=int, default=2014, show_default=True)
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default="out/zhai2014", show_default=True,
              help="Folder for the figures, table.md and results.json.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), help="Write the summary JSON here ('-' = stdout).")
def study_zhai(quick, seed, out_dir, json_path):
    """Zhai et al. (2014) rectangle-face attitude fly-around (both ground-test cases) with renders."""
    import warnings

    from ..workflows.camera import main as zhai_main

    with warnings.catch_warnings():  # pyvista cannot keep trimesh's 'parts' metadata: harmless, noisy
        warnings.filterwarnings("ignore", message="Unable to store metadata key")
        summary = zhai_main(out_dir, quick=quick, seed=seed,
                            progress=(lambda *a, **k: None) if json_path == "-" else click.echo)
    if json_path:
        echo_json(summary, json_path)
    if json_path != "-":
        click.echo(f"wrote figures, table.md and results.json to {out_dir}")


@click.command("demo")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default="out/demo", show_default=True)
def demo_cmd(out_dir):
    """The main job on a bundled model: optimise a 12-sensor layout on the Chen target, then a
    reduced Chen precision study of the paper-like layout."""
    from pathlib import Path

    out = Path(out_dir)
    try:
        from ..workflows.optimize import run_demo
    except ImportError:  # the optimiser is not installed in this build
        run_demo = None
    if run_demo is not None:
        click.echo("== layoutkit optimize on the Chen target (bundled model) ==")
        summ = run_demo(out / "optimize", quick=True)
        click.echo(f"{summ['message']}\nlayout {out / 'optimize' / 'layout.json'}, report {out / 'optimize' / 'report'}")
    from ..workflows.chen import StudyConfig, run_chen2024, write_outputs

    click.echo("== reduced Chen (2024) precision study ==")
    res = run_chen2024(StudyConfig(groups=10, frames=600, dynamic_seconds=20))
    paths = write_outputs(res, out / "chen2024")
    s = res["summary"]
    click.echo(f"simulated/predicted precision, median over groups: {s['median_ratio_rot']:.3f} (attitude), "
               f"{s['median_ratio_trans']:.3f} (position); figure {paths['fig5']}")


commands = [dop_cmd, simulate_cmd, solve_cmd, study_group, demo_cmd]
