"""CLI commands (camera): ``camera calibrate`` / ``camera attitude`` (real cameras: lens distortion,
calibration, photographs) and ``camera-attitude`` (rectangle-face attitude streams from images,
videos or corner tables with a pinhole camera)."""
from __future__ import annotations

import click

from ._common import bad_input, call_or_fail, echo_json, fail
from .options import POSITIVE, Conflict, Number, Requires, flag_rules
from .options import camera_model_option, corner_sigma_option, json_flag, registry_choice


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
    Prints Euler angles Z→Y→X (deg) of R_ct in the paper's camera convention per frame; exits 1
    when no frame was solved. For a real camera with lens distortion use `layoutkit camera attitude IMAGE --camera CAM.yml`.
    """
    if focal_length_px <= 0:
        fail(f"--focal-length-px must be positive, got {focal_length_px}")
    from ..workflows.attitude import camera_attitude as run

    out = call_or_fail(run, input, focal_length_px, principal_point=principal_point, method=method,
                       aspect_ratio=aspect_ratio, fps=fps, max_frames=max_frames, threshold=threshold)
    if as_json:
        echo_json(out)
    else:
        click.echo(f"{out['source']}: {out['n_solved']}/{out['n_frames']} frames solved ({method})")
        click.echo(f"{'t_s':>10} {'status':>16} {'theta1_deg':>11} {'theta2_deg':>11} {'theta3_deg':>11}")
        for fr in out["frames"]:
            th = fr["euler_zyx_deg"]
            vals = " ".join(f"{v:11.4f}" for v in th) if th is not None else " ".join(["        nan"] * 3)
            click.echo(f"{fr['t_s']:10.3f} {fr['status']:>16} {vals}")
    if not out["n_solved"]:  # a run that produced nothing says why and exits non-zero
        from collections import Counter

        why = Counter(fr["status"] for fr in out["frames"]).most_common(1)
        fail(f"no frame of {out['n_frames']} solved" + (f" (most common status: {why[0][0]}, {why[0][1]} frames)"
                                                        if why else f": no frame read from {input}"), code=1)


@click.group("camera", short_help="Real camera: calibrate its lens; face attitude in photos.")
def camera_group():
    """A real camera: its intrinsics and lens distortion from pattern photos (calibrate), and the
    attitude of a rectangular face in a photograph through that lens (attitude)."""


def _inner(ctx, param, value):
    from ..camera.calibration import parse_inner

    try:
        return parse_inner(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None


@camera_group.command("calibrate", short_help="Intrinsics + lens distortion from pattern photos.")
@click.argument("images", nargs=-1, required=True, type=click.Path(exists=True))
@click.option("--pattern", type=click.Choice(("chessboard", "charuco")), default="chessboard", show_default=True,
              help="Calibration pattern.")
@click.option("--inner", "inner", default="9x6", show_default=True, callback=_inner, metavar="WxH",
              help="Inner chessboard corners per row x per column (a ChArUco board has (W+1) x (H+1) squares).")
@click.option("--square-mm", "square_mm", type=POSITIVE, default=25.0,
              show_default=True, help="Side of one square, mm.")
@click.option("--marker-mm", "marker_mm", type=POSITIVE, default=None,
              help="ChArUco marker side, mm (--pattern charuco).")
@click.option("--dictionary", default="DICT_5X5_100", show_default=True,
              help="ChArUco marker dictionary (a cv2.aruco name).")
@click.option("--distortion-model", "model", type=registry_choice("layoutkit.camera.calibration:DISTORTION_MODELS"),
              default="standard", show_default=True,
              help="standard: k1 k2 p1 p2 k3; rational: + k4 k5 k6; thin-prism: + s1..s4.")
@click.option("--drop-outliers", is_flag=True, help="Calibrate again without the outlier images (named either way).")
@click.option("--out", "out", type=click.Path(dir_okay=False), required=True, metavar="CAM.yml",
              help="Camera model file to write (.yml/.yaml/.xml: OpenCV FileStorage; .json: ours).")
@click.option("--figure", type=click.Path(dir_okay=False), default=None, metavar="PNG",
              help="Residual figure [default: <CAM>_residuals.png beside --out].")
@json_flag
@flag_rules(Requires("--marker-mm", "--pattern=charuco", "markers are a ChArUco thing"),
            Requires("--dictionary", "--pattern=charuco", "markers are a ChArUco thing"))
def calibrate_cmd(images, pattern, inner, square_mm, marker_mm, dictionary, model, drop_outliers, out, figure, as_json):
    """Calibrate a camera from IMAGES (files or folders) of a planar pattern (OpenCV).

    Prints the camera matrix, the distortion, their standard deviations and each image's RMS
    reprojection error; names the outlier images and those where the pattern was not found.
    Exits 1 when the pattern is found in fewer than 3 images (nothing written).
    """
    from ..workflows.camera import calibrate_images

    if pattern == "charuco" and marker_mm is None:
        fail("--marker-mm: required with --pattern charuco")
    res = call_or_fail(calibrate_images, images, out, pattern=pattern, inner=inner, square_mm=square_mm, model=model,
                       drop_outliers=drop_outliers, figure=figure, marker_mm=marker_mm, dictionary=dictionary)
    if as_json:
        echo_json(res)
    else:
        _print_calibration(res)
    if not res["success"]:
        if not as_json:
            click.secho(f"error: {res['message']}", fg="red", err=True)
        raise SystemExit(1)


def _print_calibration(res):
    import numpy as np

    click.echo(f"{res['status']}: {res['message']}")
    K = np.asarray(res["camera_matrix"])
    sd = res["std_dev"]
    for name, val in (("fx", K[0, 0]), ("fy", K[1, 1]), ("cx", K[0, 2]), ("cy", K[1, 2])):
        click.echo(f"  {name:<3} {val:12.4f} px  ± {sd.get(name, float('nan')):.4f}")
    names = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4")
    for name, val in zip(names, np.asarray(res["distortion"]).ravel()):
        click.echo(f"  {name:<3} {val:12.6f}     ± {sd.get(name, float('nan')):.6f}")
    click.echo(f"{'image':<24} {'points':>6} {'rms_px':>8}")
    for v in res["views"]:
        click.echo(f"{v['image']:<24} {v['points']:>6} {v['rms_px']:8.3f}" + ("  OUTLIER" if v["outlier"] else ""))
    for name, why in res["not_found"].items():
        click.echo(f"{name:<24} {'-':>6} {'-':>8}  {why}")
    click.echo(f"wrote {res['out']} and {res['figure']}")


@camera_group.command("attitude", short_help="Rectangular-face attitude in one photo (real lens).")
@click.argument("image", type=click.Path(exists=True, dir_okay=False))
@camera_model_option(flags=("--camera",), required=True)
@click.option("--corners", default=None, metavar="x,y;x,y;x,y;x,y",
              help="The face's four corners in pixels (any order round the face) instead of detecting them.")
@click.option("--detect", type=click.Choice(("face", "chessboard")), default="face", show_default=True,
              help="face: a bright (or dark) rectangle against clutter; chessboard: the board's 4 extreme inner corners.")
@click.option("--inner", "inner", default="9x6", show_default=True, callback=_inner, metavar="WxH",
              help="Inner corners of the chessboard (--detect chessboard).")
@click.option("--method", type=registry_choice("layoutkit.camera.rectangle:RECTANGLE_SOLVERS"), default="zhai",
              show_default=True, help="Rectangle solver (zhai, homography: size-free; ippe: with --aspect-ratio).")
@click.option("--aspect-ratio", type=POSITIVE, default=None,
              help="Face L/W for --method ippe [default: the chessboard's, else 1].")
@corner_sigma_option(help="Corner noise per coordinate, px, for the predicted sigma [default: the detector's "
                          "line fits (face) or the grid's homography residuals (chessboard)].")
@click.option("--polarity", type=click.Choice(("auto", "bright", "dark")), default="auto", show_default=True,
              help="Face brighter or darker than its surround (--detect face).")
@click.option("--picture", type=click.Path(dir_okay=False), default=None, metavar="PNG",
              help="Picture with the corners drawn [default: <IMAGE stem>_attitude.png in the current folder].")
@click.option("--no-picture", is_flag=True, help="Write no picture.")
@json_flag
@flag_rules(Conflict("--corners", "--detect", "given corners are not detected"),
            Requires("--inner", "--detect=chessboard"),
            Requires("--polarity", "--detect=face"),
            Requires("--aspect-ratio", "--method=ippe", "zhai and homography are size-free"),
            Conflict("--picture", "--no-picture"))
def attitude_cmd(image, camera_model, corners, detect, inner, method, aspect_ratio, corner_sigma_px, polarity,
                 picture, no_picture, as_json):
    """Attitude of a rectangular face in IMAGE seen through the camera of --camera (lens distortion
    removed before the solve) and its predicted 1-sigma error.

    JSON: rotvec (rad, Zhai's R_ct: paper camera frame <- face frame), rotvec_cv (the same in
    OpenCV's camera frame), status, sigma_deg, corners_px (P1..P4), aspect_ratio, position_over_width
    (face centre / face width W), tilt_deg. Exits 1 when no face was found or solved.
    """
    from pathlib import Path

    import numpy as np

    from ..workflows.camera import image_attitude, parse_corners

    with bad_input():
        c = parse_corners(corners) if corners is not None else None
        pic = None if no_picture else (picture or f"{Path(image).stem}_attitude.png")
        out = image_attitude(image, camera_model, corners=c, detect=detect, inner=inner, method=method,
                             aspect_ratio=aspect_ratio, corner_sigma_px=corner_sigma_px, polarity=polarity,
                             picture=pic)
    if as_json:
        echo_json(out)
    elif out["success"]:
        rv = np.degrees(np.asarray(out["rotvec"]))
        sig = out["sigma_deg"]
        click.echo(f"{out['status']}: {out['message']}")
        click.echo(f"rotvec_deg {rv[0]:.3f} {rv[1]:.3f} {rv[2]:.3f}  sigma_deg "
                   + (f"{sig:.3f}" if sig is not None else f"unknown ({out['sigma_deg_per_px']:.3f} per px of corner noise)"))
        click.echo(f"tilt_deg {out['tilt_deg']:.2f}  aspect_ratio {out['aspect_ratio']:.4f}  position/W "
                   + " ".join(f"{v:.3f}" for v in out["position_over_width"]))
        click.echo("corners_px " + "; ".join(f"{x:.2f},{y:.2f}" for x, y in out["corners_px"]))
        if out.get("picture"):
            click.echo(f"wrote {out['picture']}")
    if not out["success"]:
        if not as_json:
            click.secho(f"error: {out['message']}", fg="red", err=True)
        raise SystemExit(1)


commands = [camera_attitude, camera_group]
