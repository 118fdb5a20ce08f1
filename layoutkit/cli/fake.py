"""CLI commands (fake-fpga hardware simulator)."""
from __future__ import annotations

import click

from ._common import echo_json, fail
from .options import (json_flag, layout_option, overwrite_option, protocol_option, rho_option, seed_option,
                      sigma_option)


@click.command("fake-fpga", short_help="Hardware simulator: a board's bytes to a pty or a file.")
@layout_option(help="Sensor layout JSON.")
@click.option("--out", "out", type=click.Path(dir_okay=False), default=None,
              help="Write a capture file (+ .idx and .json sidecar) instead of streaming on a pty.")
@overwrite_option(what="an existing --out capture")
@click.option("--pty", "use_pty", is_flag=True, help="Stream on a pseudo-terminal (the default without --out).")
@click.option("--link", type=click.Path(dir_okay=False), default=None,
              help="With a pty: also make this symlink point at the device path.")
@click.option("--truth", "truth_path", type=click.Path(dir_okay=False), default=None,
              help="Write the true poses as a pose table (t,station,status,rx,ry,rz,tx,ty,tz,residual_rms; "
                   "s, rad, m; one row per sweep).")
@click.option("--duration", "duration_s", type=float, default=60.0, show_default=True,
              help="Simulated seconds.")
@seed_option
@protocol_option(encodable=True, help="Wire protocol to emit (the protocols the simulator can encode).")
@click.option("--motion", default="tumble", show_default=True,
              help="tumble, static, or a trajectory pose table CSV (t,rx,ry,rz,tx,ty,tz at least; s, rad, m).")
@click.option("--dropout", type=float, default=0.0, show_default=True, help="Probability a lit hit is missed.")
@click.option("--frame-loss", type=float, default=0.0, show_default=True,
              help="Probability a frame is not sent.")
@click.option("--garbage", type=float, default=0.0, show_default=True,
              help="Probability of a random byte burst before a frame.")
@sigma_option(allow_zero=True)
@rho_option
@click.option("--realtime/--no-realtime", default=None,
              help="Emit at real timing (default: on for a pty, off for --out).")
@click.option("--speed", type=click.FloatRange(min=0.0, min_open=True), default=1.0, show_default=True,
              help="Real-time speed factor.")
@click.option("--wait-reader", "wait_reader_s", type=float, default=None,
              help="With a pty: give up when no reader opened it within this many seconds [default: wait].")
@json_flag(help="Print the summary as JSON.")
def fake_fpga(layout_path, out, overwrite, use_pty, link, truth_path, duration_s, seed, protocol, motion, dropout,
              frame_loss, garbage, sigma, rho, realtime, speed, wait_reader_s, as_json):
    """Hardware simulator: emit an FPGA board's exact bytes for a layout in motion.

    Without --out a pseudo-terminal is opened and its device path printed (first line,
    "device: /dev/pts/N") so that `layoutkit live --port /dev/pts/N` can read it; streaming starts
    when a reader opens the port. --link keeps a stable path across runs (replug).
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

    try:
        layout = load_layout(layout_path)
        summary = run_fake(layout, out=out, link=link, truth_path=truth_path, realtime=realtime, speed=speed,
                           wait_reader_s=wait_reader_s, overwrite=overwrite, on_ready=ready, duration_s=duration_s, seed=seed,
                           protocol=protocol, motion=motion, dropout=dropout, frame_loss=frame_loss,
                           garbage=garbage, sigma=sigma, rho=rho)
    except (ValueError, TimeoutError, ReaderGone) as exc:
        fail(str(exc))
    except OSError as exc:
        fail(f"{exc.filename}: {exc.strerror or exc}" if exc.filename else f"cannot emit: {exc}")
    if as_json:
        echo_json(summary)
    else:
        click.echo(f"sent {summary['frames_sent']} frames ({summary['bytes']} bytes) to {summary['path']} "
                   f"in {summary['wall_s']:.2f} s")


commands: list = [fake_fpga]
