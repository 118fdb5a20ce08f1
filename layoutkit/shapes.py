"""Parametric target geometries built from trimesh primitives (the sources of ``models/``).

Each builder returns a :class:`trimesh.Trimesh` in metres, body frame; builders that come
with a sensor layout return ``(mesh, Layout)``.
"""
from __future__ import annotations

import numpy as np

from .layout import Layout

__all__ = ["chen_target", "zhai_target", "cubesat_3u", "docking_target", "assemble_parts"]


def chen_target():
    """The 12-sensor target of Chen et al. (2024), reconstructed: ``(mesh, layout)``.

    The paper gives only its size (12.5 × 12.5 × 6.25 cm, a convex polyhedron) and a photo
    (Fig. 2b). This is a plausible reconstruction, not the authors' drawing: a 12.5 cm square
    base with 3.125 cm vertical walls, four 45° chamfers rising to a 6.25 cm square top at
    6.25 cm. Sensors: 4 on the top face near its corners, one on each chamfer and one on each
    wall (offset alternately sideways to break the 4-fold symmetry), 12 in all, each on its
    facet's centre plane with the facet's outward normal. Origin at the bounding-box centre.
    """
    import trimesh

    a, c, h, w = 0.0625, 0.03125, 0.0625, 0.03125  # half base, half top, height, wall height
    base = [(sx * a, sy * a, 0.0) for sx in (-1, 1) for sy in (-1, 1)]
    wall = [(sx * a, sy * a, w) for sx in (-1, 1) for sy in (-1, 1)]
    top = [(sx * c, sy * c, h) for sx in (-1, 1) for sy in (-1, 1)]
    shift = np.array([0.0, 0.0, -h / 2])
    mesh = trimesh.convex.convex_hull(np.asarray(base + wall + top) + shift)

    pos, nor = [], []
    for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1)):  # top face, near the corners
        pos.append((sx * 0.6 * c, sy * 0.6 * c, h))
        nor.append((0.0, 0.0, 1.0))
    s2 = np.sqrt(0.5)
    mid_ch = (a + c) / 2  # chamfer centre line (x = z offset)
    for k, (ux, uy) in enumerate(((1, 0), (0, 1), (-1, 0), (0, -1))):
        off = 0.015 * (1 if k % 2 == 0 else -1)
        vx, vy = -uy, ux  # in-plane sideways direction
        pos.append((ux * mid_ch + vx * off, uy * mid_ch + vy * off, w + (a - mid_ch)))
        nor.append((ux * s2, uy * s2, s2))
        pos.append((ux * a - vx * off, uy * a - vy * off, w / 2))
        nor.append((ux, uy, 0.0))
    order = [0, 1, 2, 3, 4, 6, 8, 10, 5, 7, 9, 11]  # top, chamfers, walls
    P = np.asarray(pos)[order] + shift
    N = np.asarray(nor)[order]
    ids = [f"T{i + 1}" for i in range(4)] + [f"C{i + 1}" for i in range(4)] + [f"W{i + 1}" for i in range(4)]
    layout = Layout(P, N, tuple(ids), {
        "name": "chen2024-target",
        "note": "Reconstruction of Chen et al. (2024) Fig. 2b: size from the paper, facet/sensor arrangement plausible, not the authors' drawing.",
    })
    return mesh, layout


def assemble_parts(parts: dict):
    """Concatenate named meshes into one :class:`trimesh.Trimesh`, keeping the part names.

    parts : ``{name: Trimesh}`` in the body frame (m). Returns one mesh whose
    ``metadata["parts"]`` maps each name to the int array of its face indices
    (the faces keep the order of ``parts``). Vertices are not merged across parts.
    """
    import trimesh

    names = list(parts)
    mesh = trimesh.util.concatenate([parts[k] for k in names])
    groups, start = {}, 0
    for k in names:
        nf = len(parts[k].faces)
        groups[k] = np.arange(start, start + nf)
        start += nf
    mesh.metadata["parts"] = groups
    return mesh


def _box(extents, center):
    import trimesh

    return trimesh.creation.box(extents=extents, transform=trimesh.transformations.translation_matrix(center))


def zhai_target(cube: float = 3.0, wing_length: float = 10.0, wing_width: float = 3.0,
                wing_thickness: float = 0.05):
    """Zhai et al. (2014) ground-test target: a 3 m cube with two 10 m × 3 m solar wings.

    Body frame at the cube centre (metres). The cube spans ``[-1.5, 1.5]^3``; its +x face
    (``x = cube/2``) is the rectangle the camera observes (Zhai's ``x_t = H/2`` face, corners
    ``(H/2, ±L/2, ±W/2)``). The wings are thin plates in the y–z plane (normal ±x, thickness
    ``wing_thickness`` centred on x = 0), attached to the ±y faces and reaching out to
    ``y = ±(cube/2 + wing_length)``, ``wing_width`` tall in z. Parts: ``bus``, ``wing+y``, ``wing-y``.
    Returns a :class:`trimesh.Trimesh` with ``metadata["parts"]`` (face indices per part).
    """
    h = cube / 2
    yc = h + wing_length / 2
    parts = {
        "bus": _box((cube, cube, cube), (0.0, 0.0, 0.0)),
        "wing+y": _box((wing_thickness, wing_length, wing_width), (0.0, yc, 0.0)),
        "wing-y": _box((wing_thickness, wing_length, wing_width), (0.0, -yc, 0.0)),
    }
    mesh = assemble_parts(parts)
    mesh.metadata["name"] = "zhai2014-target"
    return mesh


def cubesat_3u(panel_length: float = 0.30, panel_thickness: float = 0.002):
    """A 3U CubeSat (10 × 10 × 34 cm bus along z) with four deployed solar panels.

    Body frame at the bus centre (metres); the bus spans ``[-0.05, 0.05]² × [-0.17, 0.17]``.
    Four 10 cm wide panels of ``panel_length`` are hinged at the +z end and deployed flat in the
    plane just below the top face (normal ±z), reaching out along +x, -x, +y, -y (a "cross"),
    1 mm clear of the bus (so that every part stays a closed 2-manifold).
    Parts: ``bus``, ``panel+x``, ``panel-x``, ``panel+y``, ``panel-y``.
    """
    a, hz, w, gap = 0.05, 0.17, 0.10, 0.001
    zc = hz - panel_thickness / 2
    rc = a + gap + panel_length / 2
    parts = {
        "bus": _box((2 * a, 2 * a, 2 * hz), (0.0, 0.0, 0.0)),
        "panel+x": _box((panel_length, w, panel_thickness), (rc, 0.0, zc)),
        "panel-x": _box((panel_length, w, panel_thickness), (-rc, 0.0, zc)),
        "panel+y": _box((w, panel_length, panel_thickness), (0.0, rc, zc)),
        "panel-y": _box((w, panel_length, panel_thickness), (0.0, -rc, zc)),
    }
    mesh = assemble_parts(parts)
    mesh.metadata["name"] = "cubesat-3u"
    return mesh


def docking_target(sections: int = 96, dish_rings: int = 26):
    """A docking target with real self-occlusion; ≥ 10,000 faces at the defaults.

    Body frame at the bus centre (metres). Parts:

    - ``bus``: box 1.2 (x) × 1.2 (y) × 1.6 (z) m;
    - ``docking_port``: ring (outer radius 0.35 m, inner 0.25 m, 0.15 m tall) on the +z face;
    - ``dish``: a 1.0 m diameter parabolic shell (focal length 0.4 m, 2 cm thick, revolved with
      ``sections`` × ``dish_rings`` facets) on a 0.3 m mast, facing +x, centred in front of the +x face;
    - ``wing+y`` / ``wing-y``: 3.0 × 1.0 m solar panels (normal ±x, 3 cm thick) on 0.5 m yokes
      off the ±y faces;
    - ``boom``: a 2.0 m boom (radius 2.5 cm) along -z with a 0.15 m radius sensor sphere at its tip.

    The dish shadows the +x face, the wings shadow the ±y faces at grazing views, the boom and its
    sphere shadow the -z face: sensors placed anywhere but the docking face see real occlusion.
    """
    import trimesh

    hx, hy, hz = 0.6, 0.6, 0.8
    parts = {"bus": _box((2 * hx, 2 * hy, 2 * hz), (0.0, 0.0, 0.0))}

    ring = trimesh.creation.annulus(r_min=0.25, r_max=0.35, height=0.15, sections=sections)
    ring.apply_translation((0.0, 0.0, hz + 0.075))
    parts["docking_port"] = ring

    # Parabolic dish: profile (radius, height) of a closed shell, revolved about the local z axis.
    R, f, th = 0.5, 0.4, 0.02
    r = np.linspace(0.0, R, dish_rings)
    z = r ** 2 / (4 * f)
    profile = np.vstack([np.column_stack([r, z]), np.column_stack([r[::-1], z[::-1] - th])])
    dish = trimesh.creation.revolve(profile, sections=sections)
    if dish.volume < 0:  # the profile's orientation decides the winding; make normals point out
        dish.invert()
    mast_len = 0.3
    mast = trimesh.creation.cylinder(radius=0.03, height=mast_len, sections=32)
    mast.apply_translation((0.0, 0.0, -mast_len / 2 - th))
    to_x = trimesh.transformations.rotation_matrix(np.pi / 2, (0.0, 1.0, 0.0))  # local z → body +x
    dish_all = trimesh.util.concatenate([dish, mast])
    dish_all.apply_transform(to_x)
    dish_all.apply_translation((hx + mast_len + th, 0.0, 0.0))
    parts["dish"] = dish_all

    yoke_len, wl, ww, wt = 0.5, 3.0, 1.0, 0.03
    for s, name in ((1, "wing+y"), (-1, "wing-y")):
        yoke = trimesh.creation.cylinder(radius=0.03, height=yoke_len, sections=32)
        yoke.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1.0, 0.0, 0.0)))
        yoke.apply_translation((0.0, s * (hy + yoke_len / 2), 0.0))
        panel = _box((wt, wl, ww), (0.0, s * (hy + yoke_len + wl / 2), 0.0))
        parts[name] = trimesh.util.concatenate([yoke, panel])

    boom_len = 2.0
    boom = trimesh.creation.cylinder(radius=0.025, height=boom_len, sections=64)
    boom.apply_translation((0.0, 0.0, -hz - boom_len / 2))
    tip = trimesh.creation.icosphere(subdivisions=3, radius=0.15)
    tip.apply_translation((0.0, 0.0, -hz - boom_len - 0.15))
    parts["boom"] = trimesh.util.concatenate([boom, tip])

    mesh = assemble_parts(parts)
    mesh.metadata["name"] = "docking-target"
    return mesh
