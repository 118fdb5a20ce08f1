"""CLI commands of the design flow: mesh-info, candidates, visibility."""
from __future__ import annotations

import click

from ._common import bad_input, call_or_fail, echo_json, emit_json
from .options import (envelope_option, half_angle_option, json_flag, json_out_option, layout_option, length_mm_option,
                      min_visible_option, out_file_option, seed_option, units_option)

_units_option = units_option(what="the mesh file (converted to metres)")


def _warn(msgs):
    for m in msgs:
        click.secho(f"warning: {m}", fg="yellow", err=True)


@click.command("mesh-info", short_help="Size, faces, watertightness and parts of a mesh file.")
@click.argument("mesh", type=click.Path(dir_okay=False))
@_units_option
@json_flag
def mesh_info_cmd(mesh, units, as_json):
    """Size, face count, watertightness, parts and warnings of a mesh file (STL/OBJ/PLY/OFF/GLB/GLTF)."""
    from ..workflows.design import mesh_info

    info = call_or_fail(mesh_info, mesh, units)
    if as_json:
        echo_json(info)
        return
    _warn(info["warnings"])
    ex = info["extents_m"]
    click.echo(f"{info['file']}  (units in file: {units})")
    click.echo(f"  size        {ex[0] * 1000:.1f} x {ex[1] * 1000:.1f} x {ex[2] * 1000:.1f} mm")
    click.echo(f"  faces       {info['faces']}   vertices {info['vertices']}")
    click.echo(f"  area        {info['area_m2']:.4g} m^2")
    click.echo(f"  watertight  {'yes' if info['watertight'] else 'no'}"
               + (f"   volume {info['volume_m3']:.4g} m^3" if info["volume_m3"] is not None else ""))
    if info["parts"]:
        click.echo("  parts       " + ", ".join(f"{k} ({v} faces)" for k, v in info["parts"].items()))
    click.echo(f"  sha256      {info['sha256'][:16]}…")


@click.command("candidates", short_help="Evenly spaced candidate photodiode sites on a mesh.")
@click.argument("mesh", type=click.Path(dir_okay=False))
@_units_option
@length_mm_option("--spacing-mm", "spacing", required=True, help="Minimum distance between candidate sites, mm.")
@click.option("--keepout-box", multiple=True, metavar="X0,Y0,Z0,X1,Y1,Z1",
              help="Axis-aligned keep-out box in the body frame, mm (repeatable).")
@click.option("--keepout-part", multiple=True, metavar="NAME", help="Keep-out named part / face group (repeatable).")
@click.option("--keepout-cone", multiple=True, metavar="DX,DY,DZ,HALF_DEG",
              help="Exclude sites whose normal is within HALF_DEG of (DX,DY,DZ) (repeatable).")
@click.option("--normal-cone", default=None, metavar="DX,DY,DZ,HALF_DEG",
              help="Keep only sites whose normal is within HALF_DEG of (DX,DY,DZ).")
@click.option("--flat-only", is_flag=True, help="Only faces of large coplanar facets (>= (2 x spacing)^2).")
@click.option("--max-count", type=click.IntRange(min=1), default=None, help="Keep at most this many (random subset).")
@seed_option
@out_file_option(help="Candidates file (layout JSON).")
@json_flag(help="Print a JSON summary.")
def candidates_cmd(mesh, units, spacing, keepout_box, keepout_part, keepout_cone, normal_cone, flat_only,
                   max_count, seed, out, as_json):
    """Evenly spaced candidate photodiode sites with outward normals, saved as a layout file."""
    from ..candidates import parse_keepout
    from ..workflows.design import make_candidates

    with bad_input():
        keep = ([parse_keepout("box:" + b) for b in keepout_box] + [parse_keepout("part:" + p) for p in keepout_part]
                + [parse_keepout("cone:" + c) for c in keepout_cone])
        nf = None
        if normal_cone is not None:
            cone = parse_keepout("cone:" + normal_cone)
            nf = (cone.direction, cone.half_angle_deg)
        lay, msgs = make_candidates(mesh, spacing=spacing, units=units, keepout=keep, flat_only=flat_only,
                                    normal_filter=nf, seed=seed, max_count=max_count, out=out)
    parts = {}
    for e in lay.extra:
        if "part" in e:
            parts[e["part"]] = parts.get(e["part"], 0) + 1
    spacing_mm = round(spacing * 1e3, 9)
    summary = {"out": out, "count": lay.n, "spacing_mm": spacing_mm, "parts": parts, "warnings": list(msgs)}
    if as_json:
        echo_json(summary)
        return
    _warn(msgs)
    click.echo(f"{lay.n} candidate sites, spacing >= {spacing_mm:g} mm -> {out}")
    if parts:
        click.echo("  per part: " + ", ".join(f"{k} {v}" for k, v in parts.items()))


@click.command("visibility", short_help="Which sensors are lit over an envelope, per station.")
@click.argument("mesh", type=click.Path(dir_okay=False))
@_units_option
@layout_option
@envelope_option
@half_angle_option
@click.option("--max-range-m", type=click.FloatRange(min=0.0, min_open=True), default=None, help="Maximum range.")
@min_visible_option(help="Sensors one station must see for a pose fix.", aliases=("--min-lit",))
@json_flag(help="Print the full summary as JSON to stdout (instead of the table).")
@json_out_option(help="Also write the full summary as JSON to this file.")
def visibility_cmd(mesh, units, layout_path, envelope_path, half_angle_deg, max_range_m, min_visible, as_json,
                   json_out):
    """Which sensors are lit over the envelope: per-sensor lit fraction, min lit count, poses below --min-visible."""
    from ..workflows.design import visibility_report

    rep = call_or_fail(visibility_report, mesh, layout_path, envelope_path, units=units,
                       sensor_half_angle_deg=half_angle_deg, max_range=max_range_m, min_lit=min_visible)
    if emit_json(rep, as_json, json_out):
        return
    _warn(rep["warnings"])
    st = rep["stations"]
    click.echo(f"{rep['poses']} poses x {len(st)} station(s) x {rep['sensors']} sensors")
    click.echo("  sensor      any  " + "  ".join(f"{s:>5}" for s in st))
    for row in rep["sensor_lit_fraction"]:
        click.echo(f"  {row['id']:<8} {row['any']:5.2f}  " + "  ".join(f"{row[str(s)]:5.2f}" for s in st))
    click.echo(f"  lit by the best station: min {rep['lit_count_min']}, median {rep['lit_count_median']:g}")
    click.echo(f"  poses with < {min_visible} lit: {rep['poses_below_min_lit']} "
               f"({100 * rep['fraction_below_min_lit']:.1f} %)")


commands: list = [mesh_info_cmd, candidates_cmd, visibility_cmd]
