"""CLI command ``calibrate``: bundle adjustment of station poses, calibration and each device's sensor terms."""
from __future__ import annotations

import click

from ._common import call_or_fail, echo_json, fail
from .options import json_flag, layout_option, out_dir_option, seed_option, sigma_option, stations_option


@click.command("calibrate", short_help="Self-calibrate stations and sensors from frame tables.")
@click.argument("frames_paths", nargs=-1, required=True, type=click.Path(dir_okay=False))
@layout_option(multiple=True, help="Layout JSON of the frame table; once per frame table when several devices "
                                   "are given (or once for all).")
@stations_option(required=True, help="Stations JSON: start poses (one world frame), kind, factory calibration.")
# issue 11 keeps `layoutkit calibrate FRAMES ... --out DIR` exact: a silent alias of --out-dir
@out_dir_option(out_alias=True, help="Output folder: stations.json, layout(s), report.json, residuals.png.")
@click.option("--reference", "reference_path", type=click.Path(dir_okay=False), default=None,
              help="Reference pose table (mocap; t,rx,ry,rz,tx,ty,tz; s, rad, m) in the stations' world frame: "
                   "fixes frame and scale (then no station is held fixed). One frame table only.")
@click.option("--sensor-offsets", is_flag=True, help="Also adjust each device's sensor positions (bounded, with a prior).")
@click.option("--sensor-timing", is_flag=True,
              help="Also adjust each sensor's latency (its angles read omega x latency late; prior --timing-prior-ns).")
@click.option("--offset-prior-mm", type=click.FloatRange(min=0.0, min_open=True), default=1.0, show_default=True,
              help="1-sigma of the hand-measured sensor positions, mm: the prior of --sensor-offsets; without "
                   "it, the layout uncertainty every reported sd includes (docs/calibration.md).")
@click.option("--timing-prior-ns", type=click.FloatRange(min=0.0, min_open=True), default=100.0, show_default=True,
              help="1-sigma of each sensor's latency, ns: the prior of --sensor-timing.")
@click.option("--calibration-prior", "calibration_prior", type=click.FloatRange(min=0.0, min_open=True), default=0.1,
              show_default=True, help="1-sigma of each calibration parameter around its starting (factory) value, rad.")
@click.option("--station-prior-deg", type=click.FloatRange(min=0.0, min_open=True), default=None,
              help="1-sigma of the station attitudes around the given ones, deg (with --station-prior-mm; default: "
                   "free). Components the data do not determine are then held (docs/calibration.md).")
@click.option("--station-prior-mm", type=click.FloatRange(min=0.0, min_open=True), default=None,
              help="1-sigma of the station positions around the given ones, mm (with --station-prior-deg).")
@click.option("--station-prior-map", is_flag=True,
              help="With --station-prior-deg/-mm: keep every station term adjusted under the prior (the maximum a "
                   "posteriori estimate, terms the prior dominates reported prior_dominated) instead of holding "
                   "the ones the data do not determine (docs/calibration.md).")
@click.option("--cross-validation/--no-cross-validation", default=True, show_default=True,
              help="Refit leaving each device out (several devices) and on the first half of the windows; a "
                   "calibration that makes a held-out evaluation worse is not written as stations.json.")
@sigma_option(help="Sweep-angle noise 1-sigma, arcsec: the residual scale of the fit (paper: 8.28\").")
@click.option("--max-samples", type=click.IntRange(min=2), default=None,
              help="Use at most this many time windows per device (a random subset, --seed).")
@seed_option
@json_flag(help="Print the report JSON.")
def calibrate_cmd(frames_paths, layout_path, stations_path, out_dir, reference_path, sensor_offsets, sensor_timing,
                  offset_prior_mm, timing_prior_ns, calibration_prior, station_prior_deg, station_prior_mm,
                  station_prior_map, cross_validation, sigma, max_samples, seed, as_json):
    """Bundle-adjust station poses and calibration (and each device's sensor terms) over FRAMES.

    Several frame tables (devices of one recording, one world frame) are adjusted together: the
    stations are shared, each device keeps its own sensor offsets/latency (--sensor-offsets,
    --sensor-timing). Samples: the rows grouped into 20 ms windows (one row per station); a device at
    rest gives one pose per static segment. Gauge: the first station's pose as given, or the
    --reference poses. Unobservable and weakly observable parameters are reported as such and kept at
    their starting values; parameters far from their factory values are flagged suspect. Cross-
    validation reports whether the fitted stations transfer to held-out devices and windows
    (docs/calibration.md).
    """
    from ..units import DEG
    from ..workflows.calibrate import calibrate_files

    if (station_prior_deg is None) != (station_prior_mm is None):
        fail("--station-prior-deg and --station-prior-mm go together")
    if station_prior_map and station_prior_deg is None:
        fail("--station-prior-map needs --station-prior-deg and --station-prior-mm (the prior it keeps)")
    station_prior = None if station_prior_deg is None else (station_prior_deg * DEG, station_prior_mm * 1e-3)
    rep = call_or_fail(calibrate_files, list(frames_paths), list(layout_path), stations_path, out_dir,
                       reference_path=reference_path, sensor_offsets=sensor_offsets,
                       sensor_timing=sensor_timing, sigma=sigma, offset_prior=offset_prior_mm * 1e-3,
                       timing_prior=timing_prior_ns * 1e-9, calibration_prior=calibration_prior,
                       station_prior=station_prior, hold_station_prior=not station_prior_map, max_samples=max_samples, seed=seed,
                       cross_validation=cross_validation)
    if as_json:
        echo_json(rep)
    else:
        _print(rep)
    if not rep["success"]:
        fail("the adjustment did not converge (see report.json)", code=1)


def _print(rep: dict) -> None:
    med = rep["median_sample_residual_rms_rad"]
    fmt = lambda v: "n/a" if v is None else f"{v:.3g}"  # noqa: E731
    click.echo(f"{rep['samples']} samples, {len(rep['stations'])} station(s): {rep['message']}")
    click.echo(f"median per-sample residual RMS: raw {fmt(med['raw'])} rad, start {fmt(med['start'])} rad, "
               f"after {fmt(med['after'])} rad")
    for name, d in rep["devices"].items():
        j = d["joint_residual_median_rad"]
        own = ""
        if rep["sensor_offsets"] or rep["sensor_timing"]:
            own = (f", {fmt(j['calibrated_stations_and_own_layout'])} with its own adjusted terms"
                   + (" (at rest: fitted at this pose only)" if d["at_rest"] else ""))
        click.echo(f"{name}: joint residual {fmt(j['given_stations'])} rad with the given stations, "
                   f"{fmt(j['calibrated_stations'])} calibrated{own}")
    for f in rep["transfer"]["folds"]:
        click.echo(f"held out {f['held_out']}: {fmt(f['factory_rad'])} -> {fmt(f['calibrated_rad'])} rad "
                   f"({f['verdict']})")
    pd = rep.get("prior_dominated") or []
    n_st = sum(1 for n in pd if n.startswith("station"))
    pd = ((f", {len(pd) - n_st} sensor term(s) adjusted but set mostly by their prior" if len(pd) > n_st else "")
          + (f", {n_st} station pose term(s) adjusted but set mostly by the station prior" if n_st else ""))
    click.echo(f"{len(rep['unobservable'])} parameter(s) unobservable, {len(rep['weakly_observable'])} weakly "
               f"observable (held at their start){pd}; wrote {rep['outputs']['stations']} "
               f"({rep['stations_written']}), {rep['outputs']['report']}")
    if rep["transfer"]["status"] == "does_not_transfer":
        click.echo(f"warning: the calibration does not transfer: {rep['transfer']['message']}", err=True)
    if rep["suspect"]:
        click.echo(f"suspect (many sd from the factory value; check the station's model and pose): "
                   f"{', '.join(rep['suspect'])}")


commands = [calibrate_cmd]
