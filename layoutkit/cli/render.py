"""CLI command ``layoutkit render``: off-screen PNGs of a mesh, layout, coverage and tracking quality."""
from __future__ import annotations

import click

from ._common import echo_json, fail
from .options import (distance_m_option, envelope_option, explicit, half_angle_option, json_flag, layout_option,
                      out_dir_option, rho_option, sigma_option, units_option)


def _size(text: str):
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"expected WIDTHxHEIGHT in pixels, e.g. 1600x1200, got {text!r}") from None
    return w, h


def _views(text: str):
    from ..render import VIEWS

    views = tuple(v.strip() for v in text.split(",") if v.strip())
    bad = [v for v in views if v not in VIEWS]
    if bad or not views:
        raise click.BadParameter(f"unknown view(s) {bad}; choose from {', '.join(VIEWS)}")
    return views


@click.command("render", short_help="Off-screen PNGs: layout, coverage, quality map, views.")
@click.argument("mesh", type=click.Path(dir_okay=False), required=False)
@layout_option(required=False, help="Layout JSON (sensors to draw); one written by `layoutkit optimize` also gives "
                                    "MESH, --envelope and --half-angle-deg when they are left out.")
@click.option("--candidates", "candidates_path", type=click.Path(dir_okay=False),
              help="Candidate sites (layout JSON), drawn as grey points; alone with --envelope: coverage map.")
@envelope_option(required=False, help="Envelope TOML: colour sensors by the fraction of poses in which they are lit.")
@units_option
@out_dir_option(aliases=("--out",), help="Output folder for the PNGs (required).")
@click.option("--size", default="1600x1200", show_default=True, help="Image size WIDTHxHEIGHT, px.")
@click.option("--views", default="iso,front,top,side", show_default=True,
              help="Comma-separated standard views (the names of layoutkit.render.VIEWS; a wrong name lists them).")
@click.option("--quality-map", is_flag=True, help="Also draw the tracking-quality map (ADOP, PDOP, lit count).")
@click.option("--map-kind", type=click.Choice(["mollweide", "sphere", "both"]), default="mollweide", show_default=True,
              help="Quality-map projection.")
@distance_m_option(help="Station range for the quality map, m.")
@rho_option
@click.option("--grid-deg", type=click.FloatRange(min=0.5, max=45.0), default=4.0, show_default=True,
              help="Quality-map cell size, deg.")
@click.option("--roll-samples", type=click.IntRange(min=1), default=6, show_default=True,
              help="Station rolls about the line of sight per direction.")
@sigma_option(default=None, help="Sweep-angle noise 1-sigma, arcsec: adds predicted 1-sigma attitude/position "
                                 "ranges to the map labels (paper: 8.28\").")
@click.option("--station-view-pose", default=None, metavar="RX,RY,RZ,TX,TY,TZ | envelope:K",
              help="Draw the view from the lighthouse: body pose in the station frame (rotation vector deg, "
                   "translation m), or pose K of --envelope.")
@click.option("--view-angle-deg", type=click.FloatRange(0.1, 179.0), default=None,
              help="Station-view vertical view angle, deg (default: fit the target; the lighthouse sees 120).")
@half_angle_option
@json_flag(help="Print a JSON object with the written paths and summaries.")
@click.pass_context
def render_cmd(ctx, mesh, layout_path, candidates_path, envelope_path, units, out_dir, size, views, quality_map, map_kind,
               distance_m, rho, grid_deg, roll_samples, sigma, station_view_pose, view_angle_deg,
               half_angle_deg, as_json):
    """Off-screen PNGs: the mesh with candidates and layout (coloured by envelope coverage), the
    tracking-quality map over all viewing directions, and the view from a lighthouse.

    MESH may be left out with a --layout written by `layoutkit optimize` (it records its mesh and envelope)."""
    try:
        size_px = _size(size)
        view_names = _views(views)
    except click.BadParameter as exc:
        fail(str(exc.message))
    from ..render import RenderingUnavailable
    from ..workflows.render import RenderOptions, parse_pose, render_design

    try:
        pose = parse_pose(station_view_pose) if station_view_pose is not None else None
        opts = RenderOptions(
            size=size_px, views=view_names, quality_map=quality_map,
            map_kinds=("mollweide", "sphere") if map_kind == "both" else (map_kind,),
            distance_m=distance_m, rho=rho, grid_deg=grid_deg, roll_samples=roll_samples, station_view_pose=pose,
            view_angle_deg=view_angle_deg,
            sensor_half_angle_deg=half_angle_deg if explicit(ctx, "half_angle_deg") else None, sigma_theta=sigma)
        res = render_design(mesh, out_dir=out_dir, units=units if explicit(ctx, "units") else None,
                            layout_path=layout_path,
                            candidates_path=candidates_path, envelope_path=envelope_path, options=opts)
    except (ValueError, OSError, RenderingUnavailable) as exc:
        fail(str(exc))
    if as_json:
        echo_json(res)
        return
    for w in res["warnings"]:
        click.secho(f"warning: {w}", fg="yellow", err=True)
    for p in res["paths"]:
        click.echo(p)


commands = [render_cmd]
