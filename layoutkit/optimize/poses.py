"""Pose sets of an envelope for the dense loop (:mod:`layoutkit.optimize.dense`): descriptors, space-filling
choice, far-range copies and the range sweep along a pose's ray.

Frames: body poses in the world frame (``p_world = R p_body + t``, m); stations as
:class:`layoutkit.lighthouse.Station`; positions and normals in the body frame.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["pose_descriptors", "farthest_point_poses", "far_range_poses", "range_sweep_poses"]


def pose_descriptors(R, t, stations, range_weight=0.5, range_span=None):
    """Pose descriptors ``(P, 3 S + 1)`` for space-filling pose designs.

    R (P, 3, 3), t (P, 3): body poses in the world frame (``p_world = R p + t``, m); stations: list
    of :class:`layoutkit.lighthouse.Station`. Per station the unit direction from the body origin to
    the station in the BODY frame (what decides which sites are lit and how they are foreshortened),
    then the range to the first station scaled to [0, ``range_weight``] over the set (ADOP grows
    with range). Euclidean distance between descriptors ~ angle (rad) between attitudes. range_span :
    ``(r_min, r_max)`` of the scaling (None: the set's own; give it to add poses to an existing set).
    """
    R = np.asarray(R, float)
    t = np.asarray(t, float)
    cols = []
    for st in stations:
        d = np.asarray(st.translation, float)[None] - t
        db = np.einsum("pji,pj->pi", R, d)  # R^T d
        cols.append(db / np.maximum(np.linalg.norm(db, axis=1, keepdims=True), 1e-300))
    r = np.linalg.norm(np.asarray(stations[0].translation, float)[None] - t, axis=1)
    lo, hi = (r.min(), r.max()) if range_span is None and len(r) else (range_span or (0.0, 0.0))
    span = hi - lo
    cols.append((range_weight * (r - lo) / span if span > 0 else np.zeros_like(r))[:, None])
    return np.concatenate(cols, axis=1)


def farthest_point_poses(desc, count, start=()):
    """Indices of ``count`` rows of ``desc (P, D)`` by farthest-point sampling (greedy maximin).

    start : indices already chosen (e.g. the design poses); the new ones are each as far as possible
    from everything chosen before. Deterministic. Returns (count,) int (fewer if P is smaller).
    """
    desc = np.asarray(desc, float)
    P = len(desc)
    start = np.asarray(start, int)
    if len(start):
        dmin = np.full(P, np.inf)
        for s0 in range(0, len(start), 256):  # bounded memory: (P, 256) distances at a time
            blk = desc[start[s0:s0 + 256]]
            dmin = np.minimum(dmin, np.sqrt(((desc[:, None, :] - blk[None]) ** 2).sum(-1)).min(axis=1))
    else:
        dmin = np.linalg.norm(desc - desc.mean(axis=0), axis=1) + 1e-12  # first pick: the most extreme
    out = []
    for _ in range(min(int(count), P - len(start))):
        j = int(np.argmax(dmin))
        if not dmin[j] > 0:
            break
        out.append(j)
        dmin = np.minimum(dmin, np.linalg.norm(desc - desc[j], axis=1))
    return np.asarray(out, int)


def far_range_poses(env, R, t):
    """Copies of poses ``R (P, 3, 3), t (P, 3)`` moved along their bearing from the envelope's reference
    station to its maximum range (``env.range_m[1]``): same attitude, same bearing, so the
    same body-frame direction of that station.

    Range dominance: the sweep-angle Jacobian of a sensor scales as 1/range, so with the same lit sensors
    the DOP of a pose grows (about linearly) with its range; the copy is then at least as bad for every
    layout (measured: with the same lit set, copy DOP ≥ DOP on every pose, and ≥ 0.96 × the range ratio ×
    DOP). What breaks it is parallax — a sensor near its half-angle lit at one range and not the other
    (~1.5 % of poses per layout) — so the originals stay in the dense set. A working set of far-range copies
    samples the binding part of the envelope (for each attitude, its far end) instead of one range per
    attitude: a layout tuned on random ranges leaves attitude pockets whose samples all happen to be near,
    and fresh poses there at far range exceed the tuned value (issue 13). Measured on the study device it
    did not lower the held-out worst case (parallax pockets at nearer ranges took over; docs/optimize.md).
    """
    ref = env.stations[env.reference_station]
    s = np.asarray(ref.translation, float)
    d = np.asarray(t, float) - s
    r = np.linalg.norm(d, axis=1, keepdims=True)
    return np.asarray(R, float).copy(), s + d * (float(env.range_m[1]) / np.maximum(r, 1e-300))


def range_sweep_poses(env, R, t, positions, normals, half_angle_deg=60.0, delta=1e-4):
    """The poses along each pose's range segment where the lit set of a layout can change.

    R (P, 3, 3), t (P, 3): world poses of ``env`` (the ray of a pose: same attitude, bearing from the
    envelope's reference station, range over ``env.range_m``); positions, normals (n, 3): the layout's
    sensors in the body frame (m, unit). Along a ray the body-frame direction ``b`` of the station is
    fixed and the sensor-to-station vector is ``-(p + r b)``, so sensor ``p, n`` faces the station
    (angle to its normal ≤ ``half_angle_deg``, :func:`layoutkit.visibility.facing_mask`) iff
    ``a + β r ≥ c |p + r b|`` with ``a = -n·p``, ``β = -n·b``, ``c = cos(half-angle)``: squared, a quadratic
    in r whose roots (on the cone's front sheet) are the crossing ranges. Between crossings the lit set
    is fixed and the DOP grows with range (the Jacobian of a sweep angle scales as 1/r:
    :func:`far_range_poses`), so the worst case of the segment is at its ends; the poses returned are, for
    every ray, both ends of the range interval and ``r_c (1 ∓ delta)`` on both sides of each crossing
    ``r_c`` inside it. All are poses of the envelope, so the values there are values of the
    envelope. Occlusion and other stations are not swept (their visibility is evaluated at these points;
    exact facing geometry of the reference station only). Returns ``(R_s, t_s, src)`` with ``src`` (M,)
    the index of the source pose of every returned pose.
    """
    ref = env.stations[env.reference_station]
    s = np.asarray(ref.translation, float)
    R = np.asarray(R, float)
    d = np.asarray(t, float) - s
    r = np.linalg.norm(d, axis=1, keepdims=True)
    u = d / np.maximum(r, 1e-300)  # world bearing station -> body
    b = np.einsum("pji,pj->pi", R, u)  # body frame; the station is at -r b from the body origin
    pos, nor = np.asarray(positions, float), np.asarray(normals, float)
    c2 = math.cos(math.radians(float(half_angle_deg))) ** 2
    al = -np.sum(nor * pos, axis=1)[None]  # (1, n)
    be = -(b @ nor.T)  # (P, n)
    qa = be * be - c2  # (a + β r)^2 - c^2 (|p|^2 + 2 r p·b + r^2) = qa r^2 + qb r + qc
    qb = 2.0 * (al * be - c2 * (b @ pos.T))
    qc = al * al - c2 * np.sum(pos * pos, axis=1)[None]
    disc = qb * qb - 4.0 * qa * qc
    lin = np.abs(qa) < 1e-12
    sq = np.sqrt(np.maximum(disc, 0.0))
    r0, r1 = (float(x) for x in env.range_m)
    cols = [np.full((len(R), 1), r1), np.full((len(R), 1), r0)]
    with np.errstate(divide="ignore", invalid="ignore"):
        quad = ~lin & (disc >= 0)
        for root in (np.where(quad, (-qb - sq) / (2 * qa), np.nan), np.where(quad, (-qb + sq) / (2 * qa), np.nan),
                     np.where(lin, -qc / qb, np.nan)):
            ok = np.isfinite(root) & (root > r0) & (root < r1) & (al + be * root >= 0)
            for f in (1.0 - delta, 1.0 + delta):
                cols.append(np.where(ok, np.clip(root * f, r0, r1), np.nan))
    rr = np.concatenate(cols, axis=1)  # (P, 2 + 6 n)
    src, col = np.nonzero(np.isfinite(rr))
    return R[src].copy(), s + u[src] * rr[src, col][:, None], src
