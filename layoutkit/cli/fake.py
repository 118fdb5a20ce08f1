"""CLI commands (fake-fpga hardware simulator)."""
from __future__ import annotations

import click

from ._common import echo_json, fail
from .options import POSITIVE, PROBABILITY, Conflict, Number, flag_rules
from .options import (json_flag, layout_option, overwrite_option, protocol_option, rho_option, seed_option,
                      sigma_option, stations_option)


@click.command("fake-fpga", short_help="Hardware simulator: a board's bytes to a pty or a file.")
@layout_option(help="Sensor layout JSON.")
@click.option("--out", "out", type=click.Path(dir_okay=False), default=None,
              help="Write a capture file (+ .idx and .json sidecar) instead of streaming on a pty.")
@overwrite_option(what="an existing --out capture and --truth file")
@click.option("--pty", "use_pty", is_flag=True, help="Stream on a pseudo-terminal (the default without --out).")
@click.option("--link", type=click.Path(dir_okay=False), default=None,
              help="With a pty: also make this symlink point at the device path.")
@click.option("--truth", "truth_path", type=click.Path(dir_okay=False), default=None,
              help="Write the true poses as a pose table (t,station,status,rx,ry,rz,tx,ty,tz,residual_rms; "
                   "s, rad, m; one row per sweep), ended by a '# layoutkit-run' line naming the byte stream "
                   "(replay --truth checks it against the capture). An existing file is refused unless --overwrite.")
@click.option("--duration", "duration_s", type=POSITIVE, default=60.0, show_default=True,
              help="Simulated seconds.")
@seed_option
@protocol_option(encodable=True, help="Wire protocol to emit (the protocols the simulator can encode).")
@click.option("--motion", default="tumble", show_default=True,
              help="tumble, static, or a trajectory pose table CSV (t,rx,ry,rz,tx,ty,tz at least; s, rad, m).")
@click.option("--dropout", type=PROBABILITY, default=0.0, show_default=True, help="Probability a lit hit is missed.")
@click.option("--frame-loss", type=PROBABILITY, default=0.0, show_default=True,
              help="Probability a frame is not sent.")
@click.option("--garbage", type=PROBABILITY, default=0.0, show_default=True,
              help="Probability of a random byte burst before a frame.")
@sigma_option(allow_zero=True)
@rho_option
@click.option("--realtime/--no-realtime", default=None,
              help="Emit at real timing (default: on for a pty, off for --out).")
@click.option("--speed", type=click.FloatRange(min=0.0, min_open=True), default=1.0, show_default=True,
              help="Real-time speed factor.")
@click.option("--wait-reader", "wait_reader_s", type=Number(0.0, allow_inf=True, what="seconds"), default=60.0,
              show_default=True,
              help="With a pty: give up (exit 2) when no reader opened it within this many seconds ('inf': wait).")
@click.option("--tumble-rate-deg-s", type=click.FloatRange(min=0.0, min_open=True), default=None,
              help="Largest angular rate of --motion tumble, deg/s [default: 0.5, a slow static-like tumble].")
@click.option("--camera-out", "camera_out", type=click.Path(file_okay=False), default=None,
              help="Also render the bench camera's view of the same trajectory into this folder "
                   "(frames + index.csv + camera.json with the truth); the focal length used is printed.")
@click.option("--focal-length-px", "focal_length_px", type=click.FloatRange(min=0.0, min_open=True), default=None,
              help="Bench camera focal length, px [default: the face spans ~1/5 of the image].")
@click.option("--camera-fps", type=click.FloatRange(min=0.0, min_open=True), default=30.0, show_default=True,
              help="Bench camera frame rate, frames per camera second.")
@click.option("--camera-size", default="640x480", show_default=True, metavar="WxH", help="Bench camera image size, px.")
@click.option("--camera-clock-offset-s", type=float, default=0.37, show_default=True,
              help="Camera clock minus device clock at device time 0, s.")
@click.option("--camera-clock-drift-ppm", type=float, default=50.0, show_default=True,
              help="Camera clock rate error, ppm (t_cam = (1 + drift) t_dev + offset).")
@stations_option(help="Stations JSON (poses in the world frame, kind, calibration) [default: one LH1 station at the "
                      "origin]: a station with a calibration emits its distorted angles, measure(points, calibration).")
@json_flag(help="Print the summary as JSON.")
@flag_rules(Conflict("--out", "--link", "--out writes a capture file, --link names a pty"))
def fake_fpga(layout_path, out, overwrite, use_pty, link, truth_path, duration_s, seed, protocol, motion, dropout,
              frame_loss, garbage, sigma, rho, realtime, speed, wait_reader_s, tumble_rate_deg_s, camera_out,
              focal_length_px, camera_fps, camera_size, camera_clock_offset_s, camera_clock_drift_ppm, stations_path,
              as_json):
    """Hardware simulator: emit an FPGA board's exact bytes for a layout in motion.

    Without --out a pseudo-terminal is opened and its device path printed (first line,
    "device: /dev/pts/N") so that `layoutkit live --port /dev/pts/N` can read it; streaming starts
    when a reader opens the port (at most --wait-reader seconds). --link keeps a stable path across
    runs (replug). SIGTERM, SIGHUP and Ctrl-C end it cleanly with a message (the capture closed, the
    link removed; exit 143, 129, 130); the camera rendering stops too (its folder keeps the frames
    made, and is said to be incomplete).
    """
    import sys

    from ..layout import load_layout
    from ..live.simulator import ReaderGone
    from ..workflows.fake import run_fake

    if out is not None and use_pty:
        fail("--out and --pty: choose one")

    def ready(path):
        click.echo(f"device: {path}")
        sys.stdout.flush()

    camera = None
    if camera_out is not None:
        try:
            w, h = (int(v) for v in camera_size.lower().split("x"))
        except ValueError:
            fail(f"--camera-size: expected WxH in pixels, got {camera_size!r}")
        camera = dict(folder=camera_out, focal_length_px=focal_length_px, fps=camera_fps, size=(w, h),
                      clock_offset_s=camera_clock_offset_s, clock_drift=camera_clock_drift_ppm * 1e-6)

    def camera_done(cs):
        click.echo(f"camera: {cs['frames']} frames in {cs['folder']}, focal length {cs['focal_length_px']:g} px, "
                   f"face aspect ratio {cs['aspect_ratio']:.4g}", err=as_json)

    try:
        layout = load_layout(layout_path)
        stations = None
        if stations_path is not None:
            from ..io.stations import read_stations

            stations = list(read_stations(stations_path))
            if not stations:
                fail(f"{stations_path}: no stations")
        summary = run_fake(layout, out=out, link=link, truth_path=truth_path, realtime=realtime, speed=speed,
                           wait_reader_s=None if wait_reader_s == float("inf") else wait_reader_s, overwrite=overwrite, on_ready=ready, duration_s=duration_s, seed=seed,
                           protocol=protocol, motion=motion, dropout=dropout, frame_loss=frame_loss,
                           garbage=garbage, sigma=sigma, rho=rho, tumble_rate_deg_s=tumble_rate_deg_s,
                           camera=camera, on_camera=camera_done, stations=stations)
    except FileExistsError as exc:
        fail(str(exc))
    except (ValueError, TimeoutError, ReaderGone) as exc:
        fail(str(exc))
    except OSError as exc:
        fail(f"{exc.filename}: {exc.strerror or exc}" if exc.filename else f"cannot emit: {exc}")
    if as_json:
        echo_json(summary)
    elif not summary.get("stopped_by"):
        click.echo(f"sent {summary['frames_sent']} frames ({summary['bytes']} bytes) to {summary['path']} "
                   f"in {summary['wall_s']:.2f} s")
    if summary.get("stopped_by"):
        import signal

        cam = summary.get("camera") or {}
        where = (f"while rendering the camera ({cam.get('frames')} frames kept in {cam.get('folder')}, incomplete)"
                 if cam.get("incomplete") else
                 f"while waiting for a reader of {summary['path']}: nothing sent"
                 if out is None and not summary["bytes"] and summary.get("path") else
                 f"after {summary['frames_sent']} of {summary['chunks']} frames ({summary['bytes']:,} bytes) to "
                 f"{summary.get('path') or 'nothing'}" + (" (capture closed)" if out is not None else ""))
        click.echo(f"stopped by {summary['stopped_by']} {where}", err=True)
        sys.exit(128 + int(getattr(signal, summary["stopped_by"])))


commands: list = [fake_fpga]
