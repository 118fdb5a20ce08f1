"""Synthetic optimisation instances (benchmarks and tests): a box target in front of one station.

Candidates are sampled uniformly on the surface of a convex box (so the normal-cone test is the
exact self-occlusion test); poses put the body 1–3 m in front of the station inside the field of
view, its +z face turned towards the station within a cone, with random roll. A candidate is lit if
it faces the station within the sensor's acceptance half-angle and lies in the 120° field of view.
"""
from __future__ import annotations

import numpy as np

from ..geometry import look_at_rotation, rotvec_to_matrix

__all__ = ["box_candidates", "envelope_poses", "cone_visibility", "synthetic_instance"]


def box_candidates(n, size=(0.3, 0.3, 0.15), rng=None, bottom=False):
    """``n`` sites on the surface of a box centred at the origin: ``(positions, normals)`` (n, 3).

    Faces are sampled in proportion to their area; ``bottom=False`` leaves out the -z face
    (mounting side)."""
    rng = np.random.default_rng(rng)
    h = np.asarray(size, float) / 2
    faces = []
    for ax in range(3):
        for sgn in (1, -1):
            if ax == 2 and sgn == -1 and not bottom:
                continue
            o = [a for a in range(3) if a != ax]
            faces.append((ax, sgn, o, 4 * h[o[0]] * h[o[1]]))
    area = np.array([f[3] for f in faces])
    which = rng.choice(len(faces), n, p=area / area.sum())
    pos = np.empty((n, 3))
    nor = np.zeros((n, 3))
    for f, (ax, sgn, o, _) in enumerate(faces):
        m = which == f
        c = m.sum()
        pos[m, ax] = sgn * h[ax]
        pos[m, o[0]] = rng.uniform(-h[o[0]], h[o[0]], c) * 0.95
        pos[m, o[1]] = rng.uniform(-h[o[1]], h[o[1]], c) * 0.95
        nor[m, ax] = sgn
    return pos, nor


def envelope_poses(n, rng=None, distance=(1.0, 3.0), half_fov_deg=40.0, cone_deg=50.0):
    """``n`` body poses ``(R (n, 3, 3), t (n, 3))`` in the station frame (z = boresight).

    t: range uniform in ``distance`` (m), direction uniform within ``half_fov_deg`` of boresight;
    R: body +z towards the station within ``cone_deg``, random roll about it."""
    rng = np.random.default_rng(rng)
    r = rng.uniform(*distance, n)
    a = np.tan(np.deg2rad(half_fov_deg))
    d = np.c_[rng.uniform(-a, a, n), rng.uniform(-a, a, n), np.ones(n)]
    t = d / np.linalg.norm(d, axis=1, keepdims=True) * r[:, None]
    R = np.empty((n, 3, 3))
    for i in range(n):
        to_station = -t[i] / np.linalg.norm(t[i])
        # tilt the facing direction inside the cone
        tilt = np.deg2rad(cone_deg) * np.sqrt(rng.random())
        ax = np.cross(to_station, rng.normal(size=3))
        ax /= np.linalg.norm(ax)
        f = rotvec_to_matrix(ax * tilt) @ to_station
        # rotation taking body +z to f, then a random roll about f
        Rf = look_at_rotation(f).T  # columns x, y, z: maps body +z to f
        roll = rotvec_to_matrix(f * rng.uniform(-np.pi, np.pi))
        R[i] = roll @ Rf
    return R, t


def cone_visibility(positions, normals, R, t, half_angle_deg=70.0, fov_deg=120.0):
    """(P, N) bool: the site faces the station within ``half_angle_deg`` and is in the FOV
    (:func:`layoutkit.visibility.facing_mask`; exact for a convex body)."""
    from ..visibility import facing_mask

    return facing_mask(positions, normals, R, t, half_angle_deg=half_angle_deg, fov_deg=fov_deg)


def synthetic_instance(n_candidates, n_poses, rng=None, size=(0.3, 0.3, 0.15), cone_deg=60.0,
                       half_angle_deg=60.0, **pose_kw):
    """A box target instance: dict with positions, normals, visible (P, N), rotations, translations.

    cone_deg : attitude cone of the body +z axis about the line of sight; half_angle_deg : sensor
    acceptance half-angle (photodiode field of view)."""
    rng = np.random.default_rng(rng)
    pos, nor = box_candidates(n_candidates, size, rng)
    R, t = envelope_poses(n_poses, rng, cone_deg=cone_deg, **pose_kw)
    vis = cone_visibility(pos, nor, R, t, half_angle_deg=half_angle_deg)
    return {"positions": pos, "normals": nor, "visible": vis, "rotations": R, "translations": t}
