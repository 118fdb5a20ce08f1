"""CLI command ``calibrate``: bundle adjustment of station poses, calibration and sensor offsets."""
from __future__ import annotations

import click

from ._common import echo_json, fail
from .options import json_flag, layout_option, out_dir_option, seed_option, sigma_option, stations_option


@click.command("calibrate", short_help="Self-calibrate stations and sensors from a frame table.")
@click.argument("frames_path", type=click.Path(dir_okay=False))
@layout_option
@stations_option(required=True, help="Stations JSON: start poses (one world frame), kind, factory calibration.")
# issue 11 keeps `layoutkit calibrate FRAMES ... --out DIR` exact: a silent alias of --out-dir
@out_dir_option(out_alias=True, help="Output folder: stations.json, layout.json, report.json, residuals.png.")
@click.option("--reference", "reference_path", type=click.Path(dir_okay=False), default=None,
              help="Reference pose table (mocap; t,rx,ry,rz,tx,ty,tz; s, rad, m) in the stations' world frame: "
                   "fixes frame and scale (then no station is held fixed).")
@click.option("--sensor-offsets", is_flag=True, help="Also adjust each sensor's position (bounded, with a prior).")
@click.option("--offset-prior-mm", type=click.FloatRange(min=0.0, min_open=True), default=1.0, show_default=True,
              help="1-sigma of the hand-measured sensor positions, mm: the prior of --sensor-offsets; without "
                   "it, the layout uncertainty every reported sd includes (docs/calibration.md).")
@click.option("--calibration-prior", "calibration_prior", type=click.FloatRange(min=0.0, min_open=True), default=0.1,
              show_default=True, help="1-sigma of each calibration parameter around its starting (factory) value, rad.")
@sigma_option(help="Sweep-angle noise 1-sigma, arcsec: the residual scale of the fit (paper: 8.28\").")
@click.option("--max-samples", type=click.IntRange(min=2), default=None,
              help="Use at most this many time windows (a random subset, --seed).")
@seed_option
@json_flag(help="Print the report JSON.")
def calibrate_cmd(frames_path, layout_path, stations_path, out_dir, reference_path, sensor_offsets,
                  offset_prior_mm, calibration_prior, sigma, max_samples, seed, as_json):
    """Bundle-adjust station poses and calibration (and, with --sensor-offsets, sensor positions).

    Samples: the frame table's rows grouped into 20 ms windows (one row per station). Gauge: the
    first station's pose as given, or the --reference poses. Unobservable and weakly observable
    parameters are reported as such and kept at their starting values; parameters far from their
    factory values are flagged suspect (docs/calibration.md).
    """
    from ..workflows.calibrate import calibrate_files

    try:
        rep = calibrate_files(frames_path, layout_path, stations_path, out_dir, reference_path=reference_path,
                              sensor_offsets=sensor_offsets, sigma=sigma, offset_prior=offset_prior_mm * 1e-3,
                              calibration_prior=calibration_prior, max_samples=max_samples, seed=seed)
    except ValueError as exc:
        fail(str(exc))
    if as_json:
        echo_json(rep)
        return
    med = rep["median_sample_residual_rms_rad"]
    fmt = lambda v: "n/a" if v is None else f"{v:.3g}"  # noqa: E731
    click.echo(f"{rep['samples']} samples, {len(rep['stations'])} station(s): {rep['message']}")
    click.echo(f"median per-sample residual RMS: raw {fmt(med['raw'])} rad, start {fmt(med['start'])} rad, "
               f"after {fmt(med['after'])} rad")
    click.echo(f"{len(rep['unobservable'])} parameter(s) unobservable, {len(rep['weakly_observable'])} weakly "
               f"observable (held at their start); wrote {rep['outputs']['stations']}, "
               f"{rep['outputs']['layout']}, {rep['outputs']['report']}")
    if rep["suspect"]:
        click.echo(f"suspect (many sd from the factory value; check the station's model and pose): "
                   f"{', '.join(rep['suspect'])}")
    if not rep["success"]:
        fail("the adjustment did not converge (see report.json)", code=1)


commands = [calibrate_cmd]
