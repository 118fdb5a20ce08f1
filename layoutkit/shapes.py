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
