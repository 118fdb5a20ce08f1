"""Spacecraft meshes: load (STL, OBJ, PLY, OFF, GLB/GLTF) in metres, check, describe, hash.

Everything returned is a :class:`trimesh.Trimesh` in the body frame, in metres. Files made
of several parts (GLB/GLTF scenes, multi-object OBJ) are concatenated; the part names are kept in
``mesh.metadata["parts"]`` as ``{name: int array of face indices}`` — the same convention as
the builders in :mod:`layoutkit.shapes` — so that candidate keep-outs can name them.

Bad input fails with a ``ValueError`` that names the file and the problem (empty file, unknown
format, non-finite vertices, no faces, zero area). Suspicious input warns with
:class:`MeshWarning` (size that looks like the wrong unit, not watertight, degenerate faces
dropped). See docs/meshes.md.
"""
from __future__ import annotations

import hashlib
import warnings
from pathlib import Path

import numpy as np

from .units import LENGTH_UNITS

__all__ = ["MESH_FORMATS", "MeshWarning", "load_mesh", "mesh_hash", "describe_mesh", "save_mesh"]

#: File suffixes :func:`load_mesh` reads (trimesh loaders).
MESH_FORMATS = ("stl", "obj", "ply", "off", "glb", "gltf")

from ._validate import MAX_PLAUSIBLE_EXTENT_M, MIN_PLAUSIBLE_EXTENT_M, OddSizeWarning  # noqa: E402  (one limit)


class MeshWarning(UserWarning):
    """A mesh loaded but looks suspicious (wrong unit, open surface, degenerate faces)."""


class MeshUnitsWarning(MeshWarning, OddSizeWarning):
    """The mesh's size is implausible for a spacecraft in the given unit (probably the wrong --units)."""



def _check_binary_stl_size(path: Path) -> None:
    """A binary STL's header gives its triangle count N; the file must then be 84 + 50 N bytes.
    A shorter one was cut off (a copy or download that did not finish): say so, with the sizes,
    instead of whatever the partial parse yields ("no faces" or a silently smaller mesh)."""
    import struct

    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(84)
    if len(head) < 84:
        if head.lstrip().lower().startswith(b"solid"):
            return  # a (tiny) ASCII STL: trimesh's parser says what is wrong with it
        raise ValueError(f"{path}: truncated STL: {size} bytes, shorter than the 84-byte binary header")
    (n,) = struct.unpack("<I", head[80:84])
    want = 84 + 50 * n
    if size == want or head.lstrip().lower().startswith(b"solid"):
        return  # complete binary, or ASCII (trimesh's parser checks that)
    if size < want:
        raise ValueError(f"{path}: truncated binary STL: the header announces {n} triangles ({want} bytes), "
                         f"the file has {size} bytes ({(size - 84) // 50} whole triangles)")

def load_mesh(path, units: str = "m"):
    """Read a mesh file and return a :class:`trimesh.Trimesh` in metres (body frame).

    path : STL, OBJ, PLY, OFF, GLB or GLTF file. Scenes are flattened with their node
    transforms applied; part names go to ``mesh.metadata["parts"]``.
    units : the length unit of the file, one of ``mm, cm, m, in``; coordinates are scaled to m.

    Raises ``ValueError`` ("<path>: ...") for a missing or empty file, an unknown format,
    unreadable content, non-finite vertex coordinates, no faces or zero total area.
    Warns (:class:`MeshWarning`) when the largest extent is > 100 m or < 1 cm after scaling
    (probably the wrong ``units``), when zero-area faces were dropped, and when the mesh is not
    watertight (visibility still works; it treats the mesh as a surface).
    """
    import trimesh

    path = Path(path)
    if units not in LENGTH_UNITS:
        raise ValueError(f"units: expected one of {sorted(LENGTH_UNITS)}, got {units!r}")
    scale = LENGTH_UNITS[units]
    fmt = path.suffix.lower().lstrip(".")
    if fmt not in MESH_FORMATS:
        raise ValueError(f"{path}: unknown mesh format {path.suffix or '(no suffix)'!r}; "
                         f"supported: {', '.join('.' + f for f in MESH_FORMATS)}")
    if not path.is_file():
        raise ValueError(f"{path}: no such mesh file")
    if path.stat().st_size == 0:
        raise ValueError(f"{path}: empty file")
    if fmt == "stl":
        _check_binary_stl_size(path)
    try:
        loaded = trimesh.load(str(path), file_type=fmt, process=False)
    except Exception as exc:  # trimesh raises many types for malformed files
        raise ValueError(f"{path}: could not read as {fmt.upper()} ({type(exc).__name__}: {exc})") from None

    mesh = _flatten(loaded, path)
    V = np.asarray(mesh.vertices, dtype=float)
    F = np.asarray(mesh.faces)
    if len(F) == 0 or len(V) == 0:
        raise ValueError(f"{path}: no faces (empty mesh or point cloud)")
    bad = int(np.size(V) - np.count_nonzero(np.isfinite(V)))
    if bad:
        raise ValueError(f"{path}: {bad} non-finite vertex coordinate(s) (NaN or inf)")

    mesh.apply_scale(scale)
    area = mesh.area_faces
    if not np.any(area > 0):
        raise ValueError(f"{path}: degenerate mesh (total surface area is zero)")
    # Merge duplicate vertices (STL stores three per face); face order is kept.
    mesh.merge_vertices()
    keep = mesh.area_faces > 0
    if not np.all(keep):
        n_bad = int(np.count_nonzero(~keep))
        _update_faces(mesh, keep)
        warnings.warn(f"{path}: dropped {n_bad} zero-area face(s)", MeshWarning, stacklevel=2)

    extent = float(np.max(mesh.extents))
    if extent > MAX_PLAUSIBLE_EXTENT_M:
        warnings.warn(f"{path}: largest extent is {extent:.4g} m with units={units!r}; "
                      f"if the file is in millimetres pass units='mm'", MeshUnitsWarning, stacklevel=2)
    elif extent < MIN_PLAUSIBLE_EXTENT_M:
        warnings.warn(f"{path}: largest extent is {extent * 1000:.4g} mm with units={units!r}; "
                      f"if the file is in metres pass units='m'", MeshUnitsWarning, stacklevel=2)
    if not mesh.is_watertight:
        warnings.warn(f"{path}: mesh is not watertight ({_open_edge_count(mesh)} open edge(s), "
                      f"{_nonmanifold_edge_count(mesh)} edge(s) shared by more than two faces); "
                      f"outward normals and occlusion treat it as a bare surface", MeshWarning, stacklevel=2)
    mesh.metadata["source"] = str(path)
    mesh.metadata["units_in_file"] = units
    return mesh


def save_mesh(mesh, path) -> None:
    """Write ``mesh`` (m) to ``path``; GLB/GLTF keep the parts as named scene nodes."""
    import trimesh

    path = Path(path)
    fmt = path.suffix.lower().lstrip(".")
    parts = mesh.metadata.get("parts")
    if fmt in ("glb", "gltf") and parts:
        scene = trimesh.Scene()
        for name, idx in parts.items():
            scene.add_geometry(mesh.submesh([np.asarray(idx)], append=True), node_name=name, geom_name=name)
        scene.export(str(path))
    else:
        mesh.export(str(path))


def mesh_hash(mesh) -> str:
    """SHA-256 (hex) of the float64 vertices and int64 faces: identifies the mesh a layout was made on."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(mesh.vertices, dtype="<f8").tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype="<i8").tobytes())
    return h.hexdigest()


def describe_mesh(mesh) -> dict:
    """Summary for reports and ``layoutkit mesh-info``: sizes in m, counts, watertightness, parts."""
    parts = mesh.metadata.get("parts") or {}
    return {
        "vertices": int(len(mesh.vertices)),
        "faces": int(len(mesh.faces)),
        "extents_m": [float(x) for x in mesh.extents],
        "bounds_m": np.asarray(mesh.bounds, float).tolist(),
        "area_m2": float(mesh.area),
        "watertight": bool(mesh.is_watertight),
        "volume_m3": float(mesh.volume) if mesh.is_watertight else None,
        "open_edges": _open_edge_count(mesh),
        "parts": {str(k): int(len(v)) for k, v in parts.items()},
        "sha256": mesh_hash(mesh),
    }


def _flatten(loaded, path):
    """trimesh.load result (Trimesh, Scene, or PointCloud) → one Trimesh with ``metadata['parts']``."""
    import trimesh

    if isinstance(loaded, trimesh.Trimesh):
        return loaded
    if isinstance(loaded, trimesh.Scene):
        pieces = {}
        for node in loaded.graph.nodes_geometry:
            transform, geom_name = loaded.graph[node]
            geom = loaded.geometry[geom_name]
            if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
                continue
            name = str(node)
            while name in pieces:
                name += "_"
            pieces[name] = geom.copy().apply_transform(transform)
        if not pieces:
            raise ValueError(f"{path}: no faces (empty mesh or point cloud)")
        from .shapes import assemble_parts

        return assemble_parts(pieces)
    raise ValueError(f"{path}: no faces (empty mesh or point cloud)")


def _update_faces(mesh, keep: np.ndarray) -> None:
    """Drop faces where ``keep`` is False and renumber ``metadata['parts']`` to match."""
    parts = mesh.metadata.get("parts")
    new_index = np.cumsum(keep) - 1
    mesh.update_faces(keep)
    if parts:
        mesh.metadata["parts"] = {k: new_index[np.asarray(v)[keep[np.asarray(v)]]] for k, v in parts.items()}


def _open_edge_count(mesh) -> int:
    """Edges used by exactly one face (0 for a closed surface)."""
    import trimesh

    edges = mesh.edges_sorted
    if len(edges) == 0:
        return 0
    return int(len(trimesh.grouping.group_rows(edges, require_count=1)))


def _nonmanifold_edge_count(mesh) -> int:
    """Edges used by more than two faces."""
    edges = mesh.edges_sorted
    if len(edges) == 0:
        return 0
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return int(np.count_nonzero(counts > 2))
