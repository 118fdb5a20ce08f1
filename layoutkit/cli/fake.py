"""CLI commands (fake-fpga hardware simulator)."""
from __future__ import annotations

import click

from ._common import echo_json, fail
from .options import overwrite_option


@click.command("fake-fpga")
@click.option("--layout", "layout_path", required=True, type=click.Path(dir_okay=False),
              help="Sensor layout JSON.")
@click.option("--out", "out", type=click.Path(dir_okay=False), default=None,
              help="Write a capture file (+ .idx and .json sidecar) instead of streaming on a pty.")
@overwrite_option(what="an existing --out capture")
@click.option("--pty", "use_pty", is_flag=True, help="Stream on a pseudo-terminal (the default without --out).")
@click.option("--link", type=click.Path(dir_okay=False), default=None,
              help="With a pty: also make this symlink point at the device path.")
@click.option("--truth", "truth_path", type=click.Path(dir_okay=False), default=None,
              help="Write the true poses (t,rx,ry,rz,tx,ty,tz; s, rad, m; one row per sweep).")
@click.option("--duration", "duration_s", type=float, default=60.0, show_default=True, help="Simulated seconds.")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--protocol", default="layoutkit", show_default=True, type=click.Choice(["layoutkit", "bitcraze-lh1"]),
              help="Wire protocol to emit.")
@click.option("--motion", default="tumble", show_default=True,
              help="tumble, static, or a trajectory CSV (t,rx,ry,rz,tx,ty,tz).")
@click.option("--dropout", type=float, default=0.0, show_default=True, help="Probability a lit hit is missed.")
@click.option("--frame-loss", type=float, default=0.0, show_default=True, help="Probability a frame is not sent.")
@click.option("--garbage", type=float, default=0.0, show_default=True,
              help="Probability of a random byte burst before a frame.")
@click.option("--sigma-rad", type=float, default=None, help="Angle noise sigma (default: paper 4.014e-5 rad).")
@click.option("--rho", type=float, default=None, help="Same-sweep correlation (default: paper 0.8717).")
@click.option("--realtime/--no-realtime", default=None,
              help="Emit at real timing (default: on for a pty, off for --out).")
@click.option("--speed", type=float, default=1.0, show_default=True, help="Real-time speed factor.")
@click.option("--wait-reader", "wait_reader_s", type=float, default=None,
              help="With a pty: give up when no reader opened it within this many seconds [default: wait].")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
def fake_fpga(layout_path, out, overwrite, use_pty, link, truth_path, duration_s, seed, protocol, motion, dropout,
              frame_loss, garbage, sigma_rad, rho, realtime, speed, wait_reader_s, as_json):
    """Hardware simulator: emit an FPGA board's exact bytes for a layout in motion.

    Without --out a pseudo-terminal is opened and its device path printed (first line,
    "device: /dev/pts/N") so that `layoutkit live --port /dev/pts/N` can read it; streaming starts
    when a reader opens the port. --link keeps a stable path across runs (replug).
    """
    import sys
    from pathlib import Path

    from ..layout import load_layout
    from ..live.capture import station_to_dict
    from ..live.simulator import ReaderGone, load_trajectory, run_fake_fpga, simulate_stream, write_truth
    from ..units import RHO_PAPER, SIGMA_THETA_PAPER

    if out is not None and use_pty:
        fail("--out and --pty: choose one")
    if duration_s <= 0:
        fail(f"--duration: expected > 0 s, got {duration_s}")
    for name, p in (("--dropout", dropout), ("--frame-loss", frame_loss), ("--garbage", garbage)):
        if not 0.0 <= p <= 1.0:
            fail(f"{name}: expected a probability in [0, 1], got {p}")
    try:
        layout = load_layout(layout_path)
        if motion not in ("tumble", "static"):
            if not Path(motion).is_file():
                fail(f"--motion: expected tumble, static or a trajectory CSV file, got {motion!r}")
            motion = load_trajectory(motion)
        sigma = SIGMA_THETA_PAPER if sigma_rad is None else sigma_rad
        rho_v = RHO_PAPER if rho is None else rho
        chunks, sw = simulate_stream(layout, duration=duration_s, seed=seed, protocol=protocol, motion=motion,
                                     dropout=dropout, frame_loss=frame_loss, garbage=garbage, sigma=sigma, rho=rho_v)
    except ValueError as exc:
        fail(str(exc))
    if truth_path:
        write_truth(sw, truth_path)
    sidecar = {
        "source": "fake-fpga",
        "protocol": protocol,
        "protocol_options": ({"n_sensors": layout.n, "rotor_rpm": sw.stations[0].rotor_rpm, "clock_hz": sw.clock_hz}
                             if protocol == "layoutkit" else {"n_sensors": layout.n}),
        "n_sensors": layout.n,
        "layout": layout.to_dict(),
        "stations": [station_to_dict(s) for s in sw.stations],
        "port": {"url": None, "baudrate": None},
        "simulator": {"seed": seed, "duration_s": duration_s, "motion": motion if isinstance(motion, str) else "csv",
                      **sw.info},
    }

    def ready(path):
        click.echo(f"device: {path}")
        sys.stdout.flush()

    try:
        summary = run_fake_fpga(chunks, out=out, realtime=realtime, link=link, on_ready=ready, speed=speed,
                                sidecar=sidecar, wait_reader=wait_reader_s, overwrite=overwrite)
    except (TimeoutError, ReaderGone, ValueError) as exc:
        fail(str(exc))
    except OSError as exc:
        fail(f"cannot emit: {exc}")
    summary.update({"sweeps": int(len(sw.t)), "frames_sent": int(sw.emitted.sum()),
                    "truth": truth_path, "protocol": protocol})
    if as_json:
        echo_json(summary)
    else:
        click.echo(f"sent {summary['frames_sent']} frames ({summary['bytes']} bytes) to {summary['path']} "
                   f"in {summary['wall_s']:.2f} s")


commands: list = [fake_fpga]
