"""Which sensors each station sees: field of view, acceptance cone, range and self-occlusion.

A sensor at body position ``p`` with outward unit normal ``m`` is *visible* from a station at a
body pose ``(R, t)`` in the station frame (``p_lh = R p + t``) iff

1. ``p_lh`` is in the station's field of view: both sweep angles within ``fov/2`` of 90° and
   ``z > 0`` (:func:`layoutkit.lighthouse.in_field_of_view`);
2. the angle between ``m`` and the direction from the sensor to the station is at most the
   sensor acceptance half-angle (default 60°);
3. ``|p_lh| <= max_range`` (if given);
4. the open segment from the sensor to the station crosses no triangle of the mesh.

The occlusion test (4) runs in the **body frame**: the station position in the body frame is
``s = -R^T t``; a ray starts at the sensor pushed off the surface along its normal by
``surface_offset`` (default ``1e-5 × mesh.scale``, 0.1 mm on an 8 m model) and points at ``s``;
the sensor is occluded iff the ray's first hit is closer than the station. The first hit comes from
a ray engine (:data:`RAY_ENGINES`): ``"embree"`` (embreex through trimesh, 3–5 M rays/s) or
``"triangle"`` (trimesh's pure-numpy engine, ~10³ rays/s, for cross-checks). Only pairs that pass
the cheap tests 1–3 are sent to the ray engine, in chunks of bounded size.

Grazing tolerance: embree intersects in float32 (trimesh rescales the model first), so a ray that
passes within ~1e-6 × mesh scale of a triangle edge, or runs nearly parallel to a face, may be
classified either way; the hit distance itself is recomputed in float64 from the hit triangle's
plane. ``benchmarks/bench_visibility.py`` measures agreement with a brute-force float64
segment–triangle test outside a 10 µm edge band (docs/meshes.md).
"""
from __future__ import annotations

from typing import Protocol

import numpy as np

from ._validate import as_array, check_finite
from .geometry import transform_points
from .lighthouse import in_field_of_view

__all__ = ["facing_mask", "RAY_ENGINES", "RayEngine", "ray_engine", "visible_sensors", "envelope_visibility",
           "first_hit_distance", "segment_occlusion_reference", "DEFAULT_CHUNK"]


def facing_mask(positions, normals, rotation, translation, *, half_angle_deg: float = 60.0,
                fov_deg: float = 120.0) -> np.ndarray:
    """Sensors facing a station at the origin and in its field of view, ``(P, n)`` bool.

    positions, normals : (n, 3) body frame; rotation (P, 3, 3), translation (P, 3): body pose in
    the station frame. A sensor is lit when the angle between its normal and the direction to
    the station is ≤ ``half_angle_deg`` and both sweep angles are within ``fov_deg / 2`` of 90°.
    No occlusion test: exact for convex targets.
    Used by the simulators, the optimiser's instances and the Chen study (one lit rule).
    """
    P = as_array(positions, "positions", (None, 3))
    N = as_array(normals, "normals", (P.shape[0], 3))
    R = as_array(rotation, "rotation", (..., 3, 3))
    t = as_array(translation, "translation", (..., 3))
    p_lh = transform_points(R, t, P)
    n_lh = np.einsum("...ij,nj->...ni", R, N)
    to_station = -p_lh / np.linalg.norm(p_lh, axis=-1, keepdims=True)
    cos = np.sum(n_lh * to_station, -1)
    return (cos >= np.cos(np.deg2rad(half_angle_deg))) & in_field_of_view(p_lh, fov_deg)


#: Pose × sensor pairs processed per chunk (bounds memory to a few tens of MB).
DEFAULT_CHUNK = 1 << 17


class RayEngine(Protocol):
    """What the occlusion test needs from a trimesh ray intersector."""

    def intersects_id(self, ray_origins, ray_directions, multiple_hits=True, max_hits=100,
                      return_locations=False): ...


def _embree(mesh):
    from trimesh.ray import ray_pyembree  # ImportError when embreex is missing

    ray = getattr(mesh, "ray", None)
    if isinstance(ray, ray_pyembree.RayMeshIntersector):
        return ray  # trimesh builds it at load time and caches its scene
    return ray_pyembree.RayMeshIntersector(mesh)


def _triangle(mesh):
    from trimesh.ray import ray_triangle

    return ray_triangle.RayMeshIntersector(mesh)


#: name → factory ``mesh -> RayEngine``.
RAY_ENGINES = {"embree": _embree, "triangle": _triangle}


def ray_engine(mesh, name: str = "embree") -> RayEngine:
    """The ray intersector ``name`` (a key of :data:`RAY_ENGINES`) for ``mesh``.

    Raises ``ValueError`` for an unknown name and for ``"embree"`` without embreex installed.
    """
    if name not in RAY_ENGINES:
        raise ValueError(f"ray engine: expected one of {sorted(RAY_ENGINES)}, got {name!r}")
    try:
        return RAY_ENGINES[name](mesh)
    except ImportError:
        raise ValueError("ray engine 'embree' needs the embreex package (pip install embreex); "
                         "engine='triangle' works without it but is ~10^4 times slower") from None


def first_hit_distance(mesh, origins, directions, engine: RayEngine) -> np.ndarray:
    """Distance (m) along unit ``directions (m, 3)`` from ``origins (m, 3)`` to the first triangle hit.

    ``inf`` where the ray hits nothing. The hit triangle comes from ``engine``; the distance is
    recomputed in float64 from that triangle's plane (the centroid's distance for a ray that runs
    parallel to the plane).
    """
    o = np.asarray(origins, float)
    d = np.asarray(directions, float)
    out = np.full(len(o), np.inf)
    if len(o) == 0:
        return out
    tri, ray = engine.intersects_id(o, d, multiple_hits=False, return_locations=False)[:2]
    tri = np.asarray(tri, dtype=np.int64)
    ray = np.asarray(ray, dtype=np.int64)
    if len(tri) == 0:
        return out
    nf = mesh.face_normals[tri]
    v0 = mesh.triangles[tri, 0]
    den = np.einsum("ij,ij->i", d[ray], nf)
    num = np.einsum("ij,ij->i", v0 - o[ray], nf)
    par = np.abs(den) < 1e-9
    t = np.where(par, np.einsum("ij,ij->i", mesh.triangles_center[tri] - o[ray], d[ray]),
                 num / np.where(par, 1.0, den))
    out[ray] = np.minimum(out[ray], t)
    return out


def visible_sensors(mesh, positions, normals, rotation, translation, *, sensor_half_angle_deg=60.0,
                    fov_deg=120.0, max_range=None, occlusion=True, engine="embree",
                    surface_offset=None, chunk=DEFAULT_CHUNK) -> np.ndarray:
    """Visibility of ``n`` sensors at ``P`` poses from one station at the origin.

    mesh : trimesh.Trimesh, body frame, m (the occluder).
    positions, normals : (n, 3) sensor positions (m) and outward normals, body frame.
    rotation : (P, 3, 3) or (3, 3); translation : (P, 3) or (3,) — body pose in the station
        frame, ``p_lh = R p_body + t``.
    sensor_half_angle_deg : acceptance cone half-angle of a photodiode (deg).
    fov_deg : station field of view (both sweep angles within fov/2 of 90°).
    max_range : optional maximum sensor–station distance (m).
    occlusion : run the mesh occlusion test (False: only tests 1–3).
    engine : ray engine name (:data:`RAY_ENGINES`) or an intersector object.
    surface_offset : push-off of ray origins along the normal (m); default ``1e-5 * mesh.scale``.
    chunk : pose × sensor pairs per batch (memory bound).

    Returns (P, n) bool (``(n,)`` for a single pose given as (3, 3), (3,)).
    """
    P_ = as_array(positions, "positions", (None, 3))
    N_ = as_array(normals, "normals", (P_.shape[0], 3))
    R = as_array(rotation, "rotation", (..., 3, 3))
    t = as_array(translation, "translation", (..., 3))
    for a, name in ((P_, "positions"), (N_, "normals"), (R, "rotation"), (t, "translation")):
        check_finite(a, name)
    single = R.ndim == 2
    R = R.reshape(-1, 3, 3)
    t = t.reshape(-1, 3)
    if len(R) != len(t):
        raise ValueError(f"rotation and translation: expected the same number of poses, got {len(R)} and {len(t)}")
    nrm = np.linalg.norm(N_, axis=1)
    if np.any(nrm < 1e-12):
        raise ValueError("normals: zero-length normal(s)")
    N_ = N_ / nrm[:, None]
    n = len(P_)
    cos_half = np.cos(np.deg2rad(sensor_half_angle_deg))
    eng = (ray_engine(mesh, engine) if isinstance(engine, str) else engine) if occlusion else None
    if surface_offset is None:
        surface_offset = 1e-5 * float(mesh.scale)

    out = np.zeros((len(R), n), dtype=bool)
    pn = np.einsum("ij,ij->i", P_, N_)  # p . m per sensor
    pp = np.einsum("ij,ij->i", P_, P_)
    step = max(1, int(chunk) // max(n, 1))
    for a in range(0, len(R), step):
        Rc, tc = R[a:a + step], t[a:a + step]
        ok = _in_fov(P_ @ np.swapaxes(Rc, 1, 2) + tc[:, None, :], fov_deg)  # p_lh = R p + t
        s_body = -np.einsum("pji,pj->pi", Rc, tc)  # station in the body frame: -R^T t
        # sensor -> station vector s - p, without materialising it: dot with m, squared length
        dot = s_body @ N_.T - pn[None]
        dist2 = np.maximum(np.einsum("pi,pi->p", s_body, s_body)[:, None] - 2.0 * (s_body @ P_.T) + pp[None], 0.0)
        ok &= (dot >= 0) & (dot * dot >= cos_half * cos_half * dist2) if cos_half >= 0 else (
            (dot >= 0) | (dot * dot <= cos_half * cos_half * dist2))
        if max_range is not None:
            ok &= dist2 <= max_range * max_range
        if occlusion:
            ip, isn = np.nonzero(ok)
            if len(ip):
                o = P_[isn] + surface_offset * N_[isn]
                d = s_body[ip] - o
                L = np.linalg.norm(d, axis=1)
                d /= L[:, None]
                hit = first_hit_distance(mesh, o, d, eng)
                ok[ip, isn] = hit >= L
        out[a:a + step] = ok
    return out[0] if single else out


def _in_fov(points_lh: np.ndarray, fov_deg: float) -> np.ndarray:
    """Same test as :func:`layoutkit.lighthouse.in_field_of_view` without arctan:
    ``|theta - 90°| <= fov/2`` for both sweep angles and z > 0  ⇔  ``|x|, |y| <= z tan(fov/2)``, z > 0
    (for fov < 180°; cot theta = x/z, Chen eq. 2)."""
    half = np.deg2rad(fov_deg) / 2.0
    if half >= np.pi / 2:
        return in_field_of_view(points_lh, fov_deg)
    x, y, z = points_lh[..., 0], points_lh[..., 1], points_lh[..., 2]
    lim = z * (np.tan(half) + 1e-12)
    return (z > 0) & (np.abs(x) <= lim) & (np.abs(y) <= lim)


def envelope_visibility(mesh, positions, normals, rotations, translations, stations, **kw) -> np.ndarray:
    """Visibility ``(P, S, n)`` bool of ``n`` sensors at ``P`` body poses from ``S`` stations.

    rotations (P, 3, 3), translations (P, 3): body pose in the WORLD frame
    (``p_world = R p_body + t``). stations : sequence of :class:`layoutkit.lighthouse.Station`
    (station pose in the world frame). Each station's poses are moved into its frame
    (:meth:`Station.world_to_station`) and passed to :func:`visible_sensors` with the station's
    ``fov_deg``; other keywords (``sensor_half_angle_deg``, ``max_range``, ``engine`` ...) pass through.
    """
    R = as_array(rotations, "rotations", (None, 3, 3))
    t = as_array(translations, "translations", (R.shape[0], 3))
    if not stations:
        raise ValueError("stations: need at least one station")
    kw = dict(kw)
    if "fov_deg" in kw:
        raise ValueError("envelope_visibility: the field of view comes from each Station.fov_deg, not a keyword")
    if kw.get("occlusion", True) and isinstance(kw.get("engine", "embree"), str):
        kw["engine"] = ray_engine(mesh, kw.get("engine", "embree"))  # build the scene once
    out = []
    for st in stations:
        Rs, ts = st.world_to_station(R, t)
        out.append(visible_sensors(mesh, positions, normals, Rs, ts, fov_deg=st.fov_deg, **kw))
    return np.stack(out, axis=1)


def segment_occlusion_reference(triangles, origins, targets, *, tol=1e-5, chunk_elements=1 << 21):
    """Brute-force reference for the occlusion test: every segment against ALL triangles, float64 numpy.

    triangles : (T, 3, 3) m; origins, targets : (m, 3) m (segment ends). No ray engine, no
    acceleration structure: for each segment and triangle the crossing of the triangle's plane
    ``t = (v0 - o)·n / (d·n)`` and the signed in-plane distances of the crossing point to the three
    edge lines (positive inside; edge-function form of the Möller–Trumbore barycentric test, in
    metres), all as dense (segments × triangles) matrix products.

    A triangle *robustly* blocks a segment when the crossing lies more than ``tol`` (m) inside every
    edge and more than ``tol`` from both ends; it *nearly* blocks it when the crossing lies less than
    ``tol`` outside the triangle and within ``tol`` of the segment. The in-plane tolerance is divided
    by the cosine between segment and face normal (a grazing ray turns a tiny plane error into a
    large shift). Returns ``(occluded, ambiguous)`` (m,) bool: occluded = some triangle robustly
    blocks; ambiguous = not occluded but some triangle nearly blocks, or the segment runs parallel
    to a face within ``tol`` of its plane — such pairs are excluded when comparing engines.
    """
    tri = as_array(triangles, "triangles", (None, 3, 3))
    o = as_array(origins, "origins", (None, 3))
    s = as_array(targets, "targets", (o.shape[0], 3))
    v0 = tri[:, 0]
    cr = np.cross(tri[:, 1] - v0, tri[:, 2] - v0)
    area2 = np.linalg.norm(cr, axis=1)
    good = area2 > 0
    n = cr / np.where(good, area2, 1.0)[:, None]  # (T, 3) unit normals
    n0 = np.einsum("tk,tk->t", n, v0)
    # inward unit normals of the edge lines in the face plane, and offsets: dist_i(x) = x.W_i + c_i
    W, C = [], []
    for a, b in ((0, 1), (1, 2), (2, 0)):
        e = tri[:, b] - tri[:, a]
        w = np.cross(n, e)
        w /= np.maximum(np.linalg.norm(w, axis=1), 1e-300)[:, None]
        W.append(w)
        C.append(-np.einsum("tk,tk->t", w, tri[:, a]))
    seg = s - o
    L = np.linalg.norm(seg, axis=1)
    d = seg / L[:, None]
    occ = np.zeros(len(o), bool)
    amb = np.zeros(len(o), bool)
    step = max(1, int(chunk_elements) // max(len(tri), 1))
    for a in range(0, len(o), step):
        oc, dc, Lc = o[a:a + step], d[a:a + step], L[a:a + step, None]
        den = dc @ n.T  # (m, T)  d.n
        dist0 = n0[None] - oc @ n.T  # signed distance of the plane from o along n
        cos = np.abs(den)
        par = cos < 1e-9
        t = dist0 / np.where(par, 1.0, den)
        margin = None
        for w, c in zip(W, C):
            m_i = (oc @ w.T + c[None]) + t * (dc @ w.T)
            margin = m_i if margin is None else np.minimum(margin, m_i)
        tol_plane = tol / np.maximum(cos, 1e-6)
        ok = ~par & good[None]
        robust = ok & (margin > tol_plane) & (t > tol) & (t < Lc - tol)
        near = ok & (margin > -tol_plane) & (t > -tol) & (t < Lc + tol)
        near |= par & good[None] & (np.abs(dist0) < tol)
        occ[a:a + step] = robust.any(1)
        amb[a:a + step] = near.any(1) & ~occ[a:a + step]
    return occ, amb
