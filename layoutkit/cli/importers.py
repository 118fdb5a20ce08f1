"""CLI: ``layoutkit import`` — foreign recordings and device files into layoutkit's own files."""
from __future__ import annotations

import click

from ._common import call_or_fail, echo_json
from .options import (Requires, flag_rules, json_flag, overwrite_option, out_dir_option, out_file_option, stations_option,
                      system_config_option, units_option)


@click.group("import", short_help="Import real recordings and device files.")
def import_group():
    """Bring in the field's formats: each writes layoutkit's own files (layout JSON, frame table,
    pose table, stations JSON, capture + sidecar) that every other command reads."""


@import_group.command("vive-config", short_help="Vive/Index device JSON to a layout.")
@click.argument("file", type=click.Path(dir_okay=False))
@out_file_option(help="Layout JSON to write.")
@json_flag(help="Print a JSON summary.")
def vive_config_cmd(file, out, as_json):
    """A Vive / Index device calibration JSON (lighthouse_config.modelPoints / modelNormals,
    metres, device frame) → layout JSON with ids, positions and normals."""
    from ..workflows.importers import import_vive_config

    s = call_or_fail(import_vive_config, file, out)
    if as_json:
        echo_json(s)
    else:
        click.echo(f"wrote {s['sensors']} sensors to {out}")


@import_group.command("libsurvive", short_help="libsurvive recording to frames.")
@click.argument("recording", type=click.Path(dir_okay=False))
@out_dir_option(out_alias=True, help="Output folder: <device>/layout.json, <device>/frames.csv, stations.json, ... "
                                     "(--out DIR works too).")
@click.option("--device", default=None, metavar="NAME", help="Only this device (libsurvive code name: HMD, T20, WM0, ...).")
@click.option("--config", "config", type=click.Path(dir_okay=False), default=None, metavar="JSON",
              help="libsurvive lighthouse config (default: <recording>.json beside it).")
@click.option("--imu-filter", "imu_filter", is_flag=True,
              help="Also run the IMU-aided filter (gyro/accelerometer 'i' lines + every sweep) on each device with "
                   "IMU lines: <device>/imu_filter_poses.csv, one pose per sweep (docs/real-data.md).")
@stations_option(help="Stations JSON for --imu-filter (e.g. calibrate's stations.json) [default: the recording's].")
@json_flag(help="Print the JSON summary.")
@flag_rules(Requires("--stations", "--imu-filter", "the import itself writes the recording's stations"))
def libsurvive_cmd(recording, out_dir, device, config, imu_filter, stations_path, as_json):
    """A libsurvive .rec / .rec.gz recording → per-device layout, frame table and reference poses,
    and the stations (poses + factory calibration) from the recording's .json.

    Angles are converted to layoutkit's convention (theta = pi/2 + libsurvive angle; station frame
    = libsurvive lighthouse frame turned by diag(1, -1, -1); docs/real-data.md). A truncated .gz
    imports what is there and says where it ended.
    """
    from ..workflows.importers import import_libsurvive

    out = out_dir
    s = call_or_fail(import_libsurvive, recording, out, device=device, config=config, imu_filter=imu_filter,
             filter_stations=stations_path)
    if as_json:
        echo_json(s)
        return
    if s["ended"]:
        click.echo(f"warning: {s['ended']}", err=True)
    for dev, info in s["devices"].items():
        if "frames" in info:
            click.echo(f"{dev}: {info['frames']} frames ({info['frames_with_4_lit']} with >= 4 sensors on both axes), "
                       f"{info['sensors']} sensors -> {out}/{dev}/")
        else:
            click.echo(f"{dev}: " + ", ".join(f"{k}" for k in info) + f" -> {out}/{dev}/")
    if "stations" in s:
        st = s["stations"]
        click.echo(f"stations: {st['count']} ({st['with_pose']} with pose, {st['with_calibration']} with calibration) "
                   f"-> {st['file']}")
    for dev, f in s.get("imu_filter", {}).items():
        if "skipped" in f:
            click.echo(f"{dev}: IMU filter skipped: {f['skipped']}")
            continue
        c = f["sweeps"]
        med = f["residual_before_update_median_rad"]
        click.echo(f"{dev}: IMU filter: {c['accepted']} of {c['sweeps']} sweeps accepted, {c['rejected']} rejected, "
                   f"{c['restarts']} restart(s); residual before each sweep's update "
                   f"{'n/a' if med is None else f'{med:.3g} rad'} (median) -> {f['file']}")


@import_group.command("cfusdlog", short_help="Crazyflie microSD log to a capture.")
@click.argument("log", type=click.Path(dir_okay=False))
@out_dir_option(out_alias=True, help="Output folder: capture.bin (+ .json sidecar), firmware_angles.csv "
                                     "(--out DIR works too).")
@system_config_option
@json_flag(help="Print the JSON summary.")
def cfusdlog_cmd(log, out_dir, system_config, as_json):
    """A Crazyflie microSD event log (cfusdlog) → a deck capture + sidecar for `layoutkit replay`
    (lhUartFrame events), a frame table for `solve` / `calibrate` (sweep-angle events lhAngle /
    estSweepAngle, LH1 or LH2), the firmware's own angles and position estimates as tables."""
    from ..workflows.importers import import_cfusdlog

    s = call_or_fail(import_cfusdlog, log, out_dir, system_config=system_config)
    if as_json:
        echo_json(s)
        return
    if s.get("ended"):
        click.echo(f"warning: {s['ended']}", err=True)
    if s.get("capture"):
        click.echo(f"{s['uart_frames']} lhUartFrame events -> {s['capture']}")
    if s.get("clock"):
        c = s["clock"]
        click.echo(f"clock: log t = {c['offset_s']:.6f} s + deck t x (1 {c['rate_ppm']:+.1f} ppm); residual RMS "
                   f"{1e3 * c['rms_s']:.3f} ms over {c['frames_used']} frames ({c['status']})")
    if s.get("frames_file"):
        click.echo(f"{s['sweep_events']} {s['sweep_event_type']} events ({s['kind']}) -> {s['frames']} frames in "
                   f"{s['frames_file']}")
    elif s.get("frames_error"):
        click.echo(f"note: {s['frames_error']}")
    click.echo(f"{s['angle_rows']} lhAngle rows -> {s['firmware_angles']}")
    for label, f in (s.get("firmware_estimates") or {}).items():
        click.echo(f"firmware {label} ({f['event']}): {f['rows']} rows -> {f['file']}")
    for note in s.get("notes", []):
        click.echo(f"note: {note}")


@import_group.command("reference", short_help="Mocap reference to a pose table.")
@click.argument("file", type=click.Path(dir_okay=False))
@out_file_option(help="Pose table (CSV) to write.")
@units_option(what="the positions in FILE")
@overwrite_option(what="an existing --out pose table")
@json_flag(help="Print a JSON summary.")
def reference_cmd(file, out, units, overwrite, as_json):
    """A motion-capture reference (CSV or .npy): t plus attitude and position, or position only
    (t,x,y,z) → a pose table (status 0; position-only rows have empty rotation)."""
    from ..workflows.importers import import_reference
    from ._common import refuse_existing

    refuse_existing(out, overwrite, "a reference of an earlier import")

    s = call_or_fail(import_reference, file, out, units=units)
    if as_json:
        echo_json(s)
    else:
        click.echo(f"wrote {s['rows']} reference poses ({'position only' if s['position_only'] else 'pose'}) to {out}")
    if s["dropped_rows"]:
        lines = s["dropped_lines"]
        where = (f" (line{'s' if len(lines) > 1 else ''} {', '.join(map(str, lines[:10]))}"
                 f"{', ...' if len(lines) > 10 else ''})" if lines else "")
        click.echo(f"note: {s['dropped_rows']} row(s) of {file} left out: a time or value is NaN or empty{where}",
                   err=True)


commands = [import_group]
