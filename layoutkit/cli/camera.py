"""CLI commands (camera): rectangle-face attitude from images, videos or corner tables."""
from __future__ import annotations

import click

from ._common import echo_json, fail
from .options import Number, POSITIVE, Requires, flag_rules
from .options import json_flag, registry_choice


@click.command("camera-attitude", short_help="Rectangle-face attitude from images or video (Zhai).")
@click.argument("input", metavar="INPUT")
@click.option("--focal-length-px", "focal_length_px", type=POSITIVE, required=True, help="Focal length (pixels).")
@click.option("--principal-point-px", "principal_point", type=(float, float), default=None,
              help="Principal point cx cy (pixels); default the image centre (images) or 0 0 (CSV).")
@click.option("--method", type=registry_choice("layoutkit.camera.rectangle:RECTANGLE_SOLVERS"), default="zhai",
              show_default=True,
              help="Rectangle solver (zhai and homography are size-free; ippe needs --aspect-ratio).")
@click.option("--aspect-ratio", type=POSITIVE, default=None, help="Face L/W for --method ippe (default 1).")
@click.option("--fps", type=POSITIVE, default=None, help="Frame rate for an image folder (timestamps).")
@click.option("--max-frames", type=click.IntRange(min=1), default=None, help="Stop after this many frames.")
@click.option("--threshold", type=Number(0.0, 255.0, what="a grey level"), default=None, help="Grey level of the face (default: Otsu).")
@json_flag
@flag_rules(Requires("--aspect-ratio", "--method=ippe", "zhai and homography are size-free"))
def camera_attitude(input, focal_length_px, principal_point, method, aspect_ratio, fps, max_frames, threshold,
                    as_json):
    """Attitude of a rectangular face from INPUT (Zhai et al, 2014).

    INPUT: an image, a folder of images, a video file, a capture device index (0, 1, ...) or a
    corners CSV (t,u1,v1,...,u4,v4 in paper (u, v) pixels, v up; or t,x1,y1,...,x4,y4 pixels).
    Prints Euler angles Z→Y→X (deg) of R_ct in the paper's camera convention per frame.
    """
    if focal_length_px <= 0:
        fail(f"--focal-length-px must be positive, got {focal_length_px}")
    from ..workflows.attitude import camera_attitude as run

    try:
        out = run(input, focal_length_px, principal_point=principal_point, method=method,
                  aspect_ratio=aspect_ratio, fps=fps, max_frames=max_frames, threshold=threshold)
    except ValueError as e:
        fail(str(e))
    if as_json:
        echo_json(out)
        return
    click.echo(f"{out['source']}: {out['n_solved']}/{out['n_frames']} frames solved ({method})")
    click.echo(f"{'t_s':>10} {'status':>16} {'theta1_deg':>11} {'theta2_deg':>11} {'theta3_deg':>11}")
    for fr in out["frames"]:
        th = fr["euler_zyx_deg"]
        vals = " ".join(f"{v:11.4f}" for v in th) if th is not None else " ".join(["        nan"] * 3)
        click.echo(f"{fr['t_s']:10.3f} {fr['status']:>16} {vals}")


commands = [camera_attitude]
