"""A housing stand-in that does not occlude a device's own sensors where the device is convex: the
tangent-cell housing of a layout.

The convex hull of a layout's positions is a poor stand-in for a housing whose sensors look sideways: a sensor
on a hull vertex whose normal is 54° (the Vive tracker's median) off the hull's face normals has a quarter of its
acceptance cone inside the hull, and the occlusion test then hides it from stations it sees on the real device.
The rule used here is fixed by the layout alone (positions p_i and normals n_i, nothing tuned to a score):

    housing = ⋃_i ( hull ∩ Vor_i ∩ {x : n_i·(x − p_i) ≤ 0} )

— each sensor owns the part of the hull nearer to it than to any other sensor (its Voronoi cell Vor_i), cut by
its tangent plane. Nothing of a sensor's own cell is then in front of it. Where the tangent plane cuts the cell,
the sensor sits on a face whose outward normal is its own normal; where it only touches the cell at the sensor (the
hull around the sensor already lies behind it: 12 of the Vive tracker's 22 sensors, 16 of the headset's 32), the
sensor stays on a vertex of the hull whose normal cone holds its normal, with no face of its own (the tracker's:
9–41° from the nearest face there); where the layout is convex (every sensor behind every other sensor's tangent plane) the
housing is ⋂_i of the tangent half-spaces with the hull, the brief's convex rule, and no sensor is occluded at all
within a cone of less than 90°. Where neighbouring tangent planes disagree (a ridge with sensors on its flanks)
the cells meet in steps, and a sensor beside a taller neighbour cell may still be occluded by it — real geometry of
a non-convex device, roughly. Each piece is a convex polytope (``scipy.spatial.HalfspaceIntersection``); the mesh
is their boundary with the walls two pieces share removed (exact convex clipping in the wall's plane), wound
outwards. It is closed but has T-junctions where a lower cell's wall meets a higher one, so ``trimesh`` calls it
not watertight (``layoutkit`` warns and treats it as a surface, which is what the occlusion test needs).

    .venv/bin/python studies/device_layouts/housing.py [--devices WM0 HMD]   # checks: volume, shipped coverage
"""
from __future__ import annotations

import numpy as np

TOL = 1e-9


def cell_halfspaces(P, N, i, hull_eq):
    """(K, 4) rows [a, b] with a·x + b ≤ 0 of sensor ``i``'s piece, and (K,) labels: ('hull', f), ('wall', k)
    or ('tangent', i). P, N (n, 3) positions (m) and unit normals; hull_eq (F, 4) the hull's facet equations."""
    n = len(P)
    o = np.array([k for k in range(n) if k != i])
    wall = np.c_[P[o] - P[i], -(np.sum(P[o] ** 2, 1) - np.sum(P[i] ** 2)) / 2]
    tang = np.r_[N[i], -N[i] @ P[i]][None]
    rows = np.vstack([hull_eq, wall, tang])
    labels = [("hull", f) for f in range(len(hull_eq))] + [("wall", int(k)) for k in o] + [("tangent", i)]
    return rows, labels


def cell_vertices(rows):
    """Vertices (V, 3) of the polytope {a·x + b ≤ 0} (None if it has no interior)."""
    from scipy.optimize import linprog
    from scipy.spatial import HalfspaceIntersection

    A, b = rows[:, :3], rows[:, 3]
    nrm = np.linalg.norm(A, axis=1)
    res = linprog(np.r_[0, 0, 0, -1], A_ub=np.c_[A, nrm], b_ub=-b, bounds=[(None, None)] * 3 + [(0, None)])
    if res.status != 0 or res.x[3] < 1e-7:
        return None
    return HalfspaceIntersection(rows, res.x[:3]).intersections


def _facet_polygon(V, row):
    """The vertices of ``V`` on the plane of ``row`` (unit-normalised), as a CCW polygon in 2-D coordinates of
    that plane seen from outside: (origin (3,), u (3,), v (3,), poly (m, 2)) or None if degenerate."""
    from scipy.spatial import ConvexHull

    a = row[:3] / np.linalg.norm(row[:3])
    d = row[3] / np.linalg.norm(row[:3])
    on = V[np.abs(V @ a + d) < 1e-7]
    if len(on) < 3:
        return None
    u = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(a, u)  # (u, v, a) right-handed: CCW in (u, v) is outward winding
    o = on.mean(axis=0)
    q = np.c_[(on - o) @ u, (on - o) @ v]
    try:
        h = ConvexHull(q)
    except Exception:  # noqa: BLE001 - a degenerate (zero-area) facet
        return None
    if h.volume < 1e-12:
        return None
    return o, u, v, q[h.vertices]


def _clip(poly, a, b, keep_left=True):
    """Sutherland–Hodgman: the part of convex ``poly`` (m, 2) left of (or right of) the directed line a→b."""
    def side(p):
        s = (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])
        return s if keep_left else -s
    out = []
    for j in range(len(poly)):
        p, q = poly[j], poly[(j + 1) % len(poly)]
        sp, sq = side(p), side(q)
        if sp >= 0:
            out.append(p)
        if (sp >= 0) != (sq >= 0):
            out.append(p + (q - p) * (sp / (sp - sq)))
    return np.array(out) if len(out) >= 3 else None


def _difference(poly, cut):
    """Convex pieces of convex ``poly`` minus convex CCW ``cut`` (both (m, 2))."""
    pieces, rest = [], poly
    for j in range(len(cut)):
        if rest is None:
            break
        a, b = cut[j], cut[(j + 1) % len(cut)]
        outside = _clip(rest, a, b, keep_left=False)
        if outside is not None and _area(outside) > 1e-12:
            pieces.append(outside)
        rest = _clip(rest, a, b, keep_left=True)
    return pieces


def _area(p):
    x, y = p[:, 0], p[:, 1]
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def tangent_cell_housing(positions, normals):
    """The tangent-cell housing of a layout (module docstring): a ``trimesh.Trimesh`` (m, outward winding) and
    a per-sensor record (piece volume m³, whether the piece exists)."""
    import trimesh
    from scipy.spatial import ConvexHull

    P = np.asarray(positions, float)
    N = np.asarray(normals, float)
    N = N / np.linalg.norm(N, axis=1, keepdims=True)
    hull_eq = ConvexHull(P).equations
    cells = []
    for i in range(len(P)):
        rows, labels = cell_halfspaces(P, N, i, hull_eq)
        V = cell_vertices(rows)
        cells.append((rows, labels, V))
    verts, faces = [], []

    def emit(o, u, v, poly):
        base = sum(len(x) for x in verts)
        verts.append(o + poly[:, :1] * u + poly[:, 1:] * v)
        faces.extend([base, base + j, base + j + 1] for j in range(1, len(poly) - 1))

    for i, (rows, labels, V) in enumerate(cells):
        if V is None:
            continue
        for row, (kind, k) in zip(rows, labels):
            f = _facet_polygon(V, row)
            if f is None:
                continue
            o, u, v, poly = f
            if kind != "wall" or cells[k][2] is None:
                emit(o, u, v, poly)
                continue
            # the neighbour's facet on the same wall plane (its row for sensor i), in these coordinates
            rk, lk, Vk = cells[k]
            jk = lk.index(("wall", i))
            g = _facet_polygon(Vk, rk[jk])
            if g is None:
                emit(o, u, v, poly)
                continue
            ok, _, _, polyk = g
            ptsk = ok + polyk[:, :1] * g[1] + polyk[:, 1:] * g[2]
            qk = np.c_[(ptsk - o) @ u, (ptsk - o) @ v]
            from scipy.spatial import ConvexHull as CH
            qk = qk[CH(qk).vertices]  # CCW in this facet's (u, v)
            for piece in _difference(poly, qk):
                emit(o, u, v, piece)
    mesh = trimesh.Trimesh(np.vstack(verts), np.asarray(faces), process=True)
    mesh.merge_vertices()
    record = [{"sensor": i, "piece": c[2] is not None,
               "piece_volume_m3": float(trimesh.convex.convex_hull(c[2]).volume) if c[2] is not None else 0.0,
               # the tangent plane (the piece's last row) cuts a face of positive area: the sensor's own face
               "own_face": c[2] is not None and _facet_polygon(c[2], c[0][-1]) is not None}
              for i, c in enumerate(cells)]
    return mesh, record


def main():
    import argparse
    import sys
    from pathlib import Path

    here = Path(__file__).resolve().parent
    sys.path.insert(0, str(here))
    from layoutkit.envelope import envelope_set
    from layoutkit.optimize.design import layout_visibility

    from devices import DEVICES, front_envelope, load_device

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--devices", nargs="*", default=["WM0", "HMD"])
    a = ap.parse_args()
    for name in a.devices:
        label, rec, dn = next(d for d in DEVICES if d[2] == name)
        dev = load_device(label, rec, dn)
        mesh, rec_ = tangent_cell_housing(dev.layout.positions, dev.layout.normals)
        env = front_envelope(dev)
        _, R, t = envelope_set(env, count=2000, seed=env.seed + 100)
        P, N = dev.layout.positions, dev.layout.normals
        v0 = layout_visibility(None, P, N, R, t, env.stations, 60.0)
        print(f"{dn}: hull {dev.hull.volume * 1e6:.1f} cm³, housing {sum(r['piece_volume_m3'] for r in rec_) * 1e6:.1f} "
              f"cm³ (mesh {mesh.volume * 1e6:.1f}), {len(mesh.faces)} faces, watertight {mesh.is_watertight}")
        for lab, m in (("hull", dev.hull), ("tangent-cell housing", mesh), ("no occlusion", None)):
            v = layout_visibility(m, P, N, R, t, env.stations, 60.0)
            print(f"  shipped on 2,000 poses, {lab}: covered {(v.sum((1, 2)) >= 4).mean():.4f}, "
                  f"lit pairs lost to the mesh {(v0 & ~v).sum() / v0.sum():.4f}")
        own = np.array([r["own_face"] for r in rec_])
        off = hull_face_angles(P, N)
        print(f"  sensors on a face of their own normal: {int(own.sum())} of {len(P)}; the others' normals are "
              f"{off[~own].min():.0f}–{off[~own].max():.0f}° from the nearest hull face at the sensor")
        _figure(dev, mesh, here / "results" / f"housing_{dn.lower()}.png")


def hull_face_angles(positions, normals):
    """Each sensor's angle (deg, (n,)) between its normal and the nearest facet of the hull of ``positions``
    through it (NaN if no facet passes through it)."""
    from scipy.spatial import ConvexHull

    P = np.asarray(positions, float)
    N = np.asarray(normals, float)
    N = N / np.linalg.norm(N, axis=1, keepdims=True)
    eq = ConvexHull(P).equations
    off = np.full(len(P), np.nan)
    for i in range(len(P)):
        through = np.abs(eq[:, :3] @ P[i] + eq[:, 3]) < 1e-7
        if through.any():
            off[i] = np.degrees(np.arccos(np.clip(eq[through, :3] @ N[i], -1, 1))).min()
    return off


def _figure(dev, mesh, path):
    """The hull and the tangent-cell housing side by side with the shipped sensors and their normals."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from layoutkit.io.figures import save_figure

    P, N = dev.layout.positions, dev.layout.normals
    fig = plt.figure(figsize=(10, 4.6))
    for j, (title, m) in enumerate((("convex hull of the positions", dev.hull), ("tangent-cell housing", mesh))):
        ax = fig.add_subplot(1, 2, j + 1, projection="3d")
        v = m.vertices
        ax.plot_trisurf(v[:, 0], v[:, 1], v[:, 2], triangles=m.faces, color="0.8", alpha=0.45, linewidth=0.2,
                        edgecolor="0.5")
        ax.scatter(*P.T, c="tab:red", s=12, depthshade=False)
        ax.quiver(*P.T, *(0.015 * N.T), color="tab:red", linewidth=0.8)
        ax.set_title(f"{dev.name}: {title} ({m.volume * 1e6:.0f} cm³)", fontsize=9)
        ax.view_init(elev=30, azim=-60)
        ax.set_axis_off()
    save_figure(fig, path, caption="Red: the shipped sensors and their normals (15 mm). Right: each sensor's Voronoi "
                                   "cell of the hull cut by its tangent plane (housing.py).")


if __name__ == "__main__":
    main()
