"""Candidate photodiode sites on a mesh: even surface sampling, keep-outs, flat faces.

:func:`sample_candidates` draws a dense area-uniform sample of the surface
(``trimesh.sample.sample_surface``), drops points in keep-out regions or off the allowed faces,
then thins it with greedy Poisson-disk (dart-throwing) selection in random order: a point is kept
iff no already kept point lies within ``spacing`` (Euclidean). The result is a maximal set with
every pairwise distance ≥ ``spacing`` and roughly uniform density. Each candidate carries the
outward normal of the face it lies on (outward for a watertight, consistently wound mesh).

Keep-outs are small frozen dataclasses (:class:`KeepOutBox`, :class:`KeepOutPart`,
:class:`KeepOutCone`) with an ``excludes(points, normals, faces, mesh) -> bool mask`` method;
:func:`parse_keepout` turns a CLI string into one.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ._validate import as_array
from .layout import Layout

__all__ = ["KeepOut", "KeepOutBox", "KeepOutPart", "KeepOutCone", "parse_keepout", "flat_faces",
           "sample_candidates", "OVERSAMPLE"]

#: Dense sample size per ``spacing²`` of allowed area before thinning (≈ 10 darts per final site).
OVERSAMPLE = 12.0
_MAX_DENSE = 400_000


class KeepOut(Protocol):
    def excludes(self, points: np.ndarray, normals: np.ndarray, faces: np.ndarray, mesh) -> np.ndarray:
        """(m, 3) points, (m, 3) unit normals, (m,) face indices → (m,) bool, True = not allowed."""


@dataclass(frozen=True)
class KeepOutBox:
    """Axis-aligned box in the body frame (m): points inside (boundary included) are excluded."""

    lower: tuple
    upper: tuple

    def __post_init__(self):
        lo = tuple(float(x) for x in self.lower)
        hi = tuple(float(x) for x in self.upper)
        if len(lo) != 3 or len(hi) != 3 or any(a > b for a, b in zip(lo, hi)):
            bad = [f"{'xyz'[i]} {a:g} > {b:g}" for i, (a, b) in enumerate(zip(lo, hi)) if a > b]
            raise ValueError(f"keep-out box: the first corner must be the lower one (x0 <= x1, y0 <= y1, z0 <= z1), "
                             f"got {', '.join(bad) or 'not 3 numbers each'} (m)")
        object.__setattr__(self, "lower", lo)
        object.__setattr__(self, "upper", hi)

    def excludes(self, points, normals, faces, mesh):
        return np.all((points >= self.lower) & (points <= self.upper), axis=1)


@dataclass(frozen=True)
class KeepOutPart:
    """A named part / face group of ``mesh.metadata["parts"]``: its faces are excluded."""

    name: str

    def excludes(self, points, normals, faces, mesh):
        parts = mesh.metadata.get("parts") or {}
        if self.name not in parts:
            raise ValueError(f"keep-out part {self.name!r}: the mesh has no such part "
                             f"(parts: {sorted(parts) or 'none'})")
        return np.isin(faces, np.asarray(parts[self.name]))


@dataclass(frozen=True)
class KeepOutCone:
    """Normals within ``half_angle_deg`` of ``direction`` (body frame) are excluded."""

    direction: tuple
    half_angle_deg: float

    def __post_init__(self):
        d = np.asarray(self.direction, float)
        if d.shape != (3,) or not np.isfinite(d).all() or np.linalg.norm(d) < 1e-12:
            raise ValueError(f"keep-out cone: direction must be 3 finite numbers, not all zero, got {self.direction}")
        object.__setattr__(self, "direction", tuple(float(x) for x in d / np.linalg.norm(d)))

    def excludes(self, points, normals, faces, mesh):
        return normals @ np.asarray(self.direction) >= np.cos(np.deg2rad(self.half_angle_deg))


def parse_keepout(spec: str, length_scale: float = 1e-3) -> KeepOut:
    """CLI keep-out string → keep-out object.

    ``box:x0,y0,z0,x1,y1,z1`` (lengths × ``length_scale``, default mm → m), ``part:NAME``,
    ``cone:dx,dy,dz,HALF_ANGLE_DEG``.
    """
    kind, _, arg = spec.partition(":")
    if kind == "part" and arg:
        return KeepOutPart(arg)
    try:
        vals = [float(x) for x in arg.split(",")]
    except ValueError:
        vals = []
    if not all(np.isfinite(vals)):
        raise ValueError(f"keep-out {spec!r}: NaN or infinite value")
    try:  # the right shape: the object's own checks say what is wrong with the numbers
        if kind == "box" and len(vals) == 6:
            v = np.asarray(vals) * length_scale
            return KeepOutBox(tuple(v[:3]), tuple(v[3:]))
        if kind == "cone" and len(vals) == 4:
            return KeepOutCone(tuple(vals[:3]), vals[3])
    except ValueError as exc:
        raise ValueError(f"keep-out {spec!r}: {exc}") from None
    raise ValueError(f"keep-out {spec!r}: expected box:x0,y0,z0,x1,y1,z1 | part:NAME | cone:dx,dy,dz,half_angle_deg")


def flat_faces(mesh, min_area: float) -> np.ndarray:
    """(F,) bool: faces whose coplanar facet (``mesh.facets``; a lone face counts alone) has area ≥ ``min_area`` m²."""
    area = np.asarray(mesh.area_faces, float).copy()
    for facet, a in zip(mesh.facets, mesh.facets_area):
        area[facet] = a
    return area >= min_area


def sample_candidates(mesh, *, spacing, keepout=(), flat_only=False, normal_filter=None, rng=None,
                      max_count=None, flat_min_area=None) -> Layout:
    """Evenly spaced candidate sites on ``mesh`` as a :class:`Layout` (body frame, m).

    spacing : minimum Euclidean distance between candidates (m).
    keepout : iterable of keep-out objects (or CLI strings, see :func:`parse_keepout`).
    flat_only : keep only faces of coplanar facets with area ≥ ``flat_min_area``
        (default ``(2 spacing)²``) — flat spots where a photodiode can be mounted.
    normal_filter : None, a ``(direction (3,), half_angle_deg)`` pair (keep normals within the cone),
        or a callable ``normals (m, 3) -> bool (m,)`` (True = keep).
    rng : ``np.random.Generator`` (or seed) for the sampling; ``max_count`` : keep at most this many
        (a uniformly random subset, so spacing still holds).

    Returns a Layout with ids ``c0000, c0001, ...``, per-sensor extra ``{"face": i[, "part": name]}``
    and metadata ``{"kind": "candidates", "spacing_m", "mesh_sha256", ...}``. Zero allowed area
    raises ``ValueError`` (a Layout needs at least one sensor).
    """
    import trimesh

    from .mesh import mesh_hash

    spacing = float(spacing)
    if not spacing > 0:
        raise ValueError(f"spacing: expected a positive length in m, got {spacing}")
    rng = np.random.default_rng(rng)
    keepout = [parse_keepout(k) if isinstance(k, str) else k for k in keepout]

    allowed = np.ones(len(mesh.faces), dtype=bool)
    if flat_only:
        allowed &= flat_faces(mesh, (2 * spacing) ** 2 if flat_min_area is None else float(flat_min_area))
    weight = np.where(allowed, mesh.area_faces, 0.0)
    area = float(weight.sum())
    if area <= 0:
        raise ValueError("candidates: no allowed surface (flat_only left no face large enough)")
    n_want = int(max(100, np.ceil(OVERSAMPLE * area / spacing ** 2)))
    n_dense = min(_MAX_DENSE, n_want)
    if n_want > _MAX_DENSE:
        import warnings

        warnings.warn(f"candidates: spacing {spacing:g} m on {area:.4g} m^2 would need {n_want} dense samples; "
                      f"capped at {_MAX_DENSE}, so the sites may leave gaps wider than the spacing",
                      RuntimeWarning, stacklevel=2)
    pts, faces = trimesh.sample.sample_surface(mesh, n_dense, face_weight=weight, seed=rng)[:2]
    nor = mesh.face_normals[faces]

    keep = np.ones(len(pts), dtype=bool)
    for k in keepout:
        keep &= ~np.asarray(k.excludes(pts, nor, faces, mesh), bool)
    if normal_filter is not None:
        if callable(normal_filter):
            keep &= np.asarray(normal_filter(nor), bool)
        else:
            direction, half = normal_filter
            d = as_array(direction, "normal_filter direction", (3,))
            keep &= nor @ (d / np.linalg.norm(d)) >= np.cos(np.deg2rad(half))
    pts, faces, nor = pts[keep], faces[keep], nor[keep]
    if len(pts) == 0:
        raise ValueError("candidates: every sample fell in a keep-out region or failed the normal filter")

    sel = _poisson_thin(pts, spacing, rng)
    if max_count is not None and len(sel) > max_count:
        sel = np.sort(rng.choice(sel, int(max_count), replace=False))
    pts, faces, nor = pts[sel], faces[sel], nor[sel]

    part_of = _face_parts(mesh)
    extra = tuple({"face": int(f), **({"part": part_of[f]} if part_of is not None else {})} for f in faces)
    meta = {"kind": "candidates", "spacing_m": spacing, "mesh_sha256": mesh_hash(mesh),
            "flat_only": bool(flat_only), "keepout": [repr(k) for k in keepout]}
    if mesh.metadata.get("source"):
        meta["mesh"] = str(mesh.metadata["source"])
    ids = tuple(f"c{i:04d}" for i in range(len(pts)))
    return Layout(pts, nor, ids, meta, extra)


def _poisson_thin(points: np.ndarray, radius: float, rng) -> np.ndarray:
    """Greedy dart throwing: indices (sorted) of a maximal subset with pairwise distance ≥ ``radius``."""
    from scipy.sparse import coo_matrix
    from scipy.spatial import cKDTree

    n = len(points)
    pairs = cKDTree(points).query_pairs(radius * (1 - 1e-12), output_type="ndarray")
    adj = coo_matrix((np.ones(2 * len(pairs), bool), (np.r_[pairs[:, 0], pairs[:, 1]], np.r_[pairs[:, 1], pairs[:, 0]])),
                     shape=(n, n)).tocsr()
    indptr, indices = adj.indptr, adj.indices
    blocked = np.zeros(n, dtype=bool)
    chosen = []
    for i in rng.permutation(n):
        if not blocked[i]:
            chosen.append(i)
            blocked[indices[indptr[i]:indptr[i + 1]]] = True
    return np.sort(np.asarray(chosen, dtype=np.int64))


def _face_parts(mesh):
    parts = mesh.metadata.get("parts")
    if not parts:
        return None
    out = np.empty(len(mesh.faces), dtype=object)
    out[:] = None
    for name, idx in parts.items():
        out[np.asarray(idx)] = str(name)
    return out
