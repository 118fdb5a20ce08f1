"""Sensor layouts: the JSON file format (docs/layout-format.md), load and save.

A layout file is JSON ``{"units": "m", "sensors": [{"id": str, "position": [x, y, z],
"normal": [nx, ny, nz]}, ...], ...}``; other top-level and per-sensor keys are kept in
``metadata`` / ``extra`` and written back. Inside the library positions are metres.
"""
from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .io.jsonfile import to_jsonable
from ._validate import as_array, check_extent, check_finite, number_list, read_structured, unknown_keys
from ._validate import ValidationWarning
from .units import LENGTH_UNITS

__all__ = ["Layout", "load_layout", "save_layout", "KNOWN_KEYS", "KNOWN_SENSOR_KEYS"]

#: Top-level keys layoutkit itself reads or writes (docs/layout-format.md). Other top-level keys are
#: metadata (importers add their own) and pass; unknown per-sensor keys warn (typos such as 'postion').
KNOWN_KEYS = frozenset({"units", "sensors", "name", "note", "mesh", "mesh_sha256", "kind", "spacing_m", "flat_only",
                        "keepout", "objective", "units_source", "rho", "value", "bound", "gap", "certified_by",
                        "method", "min_visible", "candidate_ids", "dop_stats", "envelope", "spec", "provenance",
                        "design_value", "value_refers_to"})
#: Per-sensor keys layoutkit reads or writes.
KNOWN_SENSOR_KEYS = frozenset({"id", "position", "normal", "face", "part", "candidate"})
#: Two sensors closer than this (m) are the same place: an error.
DUPLICATE_TOL_M = 1e-9


@dataclass(frozen=True)
class Layout:
    """A photodiode layout in the body frame.

    positions : (n, 3) float, m; normals : (n, 3) float, unit outward normals; ids : n strings.
    metadata : other top-level keys of the file (objective, mesh hash, ...).
    extra : per-sensor extra keys, a tuple of dicts (may be empty dicts).
    """

    positions: np.ndarray
    normals: np.ndarray
    ids: tuple
    metadata: dict = field(default_factory=dict)
    extra: tuple = ()

    def __post_init__(self):
        P = as_array(self.positions, "positions", (None, 3))
        N = as_array(self.normals, "normals", (P.shape[0], 3))
        check_finite(P, "positions")
        check_finite(N, "normals")
        nrm = np.linalg.norm(N, axis=1)
        if np.any(nrm < 1e-9):
            raise ValueError(f"normals: sensor(s) {np.flatnonzero(nrm < 1e-9).tolist()} have zero length")
        ids = tuple(str(i) for i in self.ids)
        if len(ids) != P.shape[0]:
            raise ValueError(f"ids: expected {P.shape[0]} ids, got {len(ids)}")
        if len(set(ids)) != len(ids):
            raise ValueError("ids: sensor ids must be unique")
        extra = tuple(self.extra) if self.extra else tuple({} for _ in ids)
        object.__setattr__(self, "positions", P)
        object.__setattr__(self, "normals", N / nrm[:, None])
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "extra", extra)

    @property
    def n(self) -> int:
        return self.positions.shape[0]

    def subset(self, index) -> "Layout":
        """The layout restricted to sensor indices ``index``."""
        index = np.asarray(index, int)
        return Layout(self.positions[index], self.normals[index], tuple(self.ids[i] for i in index),
                      dict(self.metadata), tuple(self.extra[i] for i in index))

    @classmethod
    def from_dict(cls, d: dict) -> "Layout":
        if not isinstance(d, dict):
            raise ValueError("layout: expected a JSON object with 'units' and 'sensors'")
        units = d.get("units", "m")
        if units not in LENGTH_UNITS:
            raise ValueError(f"layout units: expected one of {sorted(LENGTH_UNITS)}, got {units!r}")
        scale = LENGTH_UNITS[units]
        sensors = d.get("sensors")
        if not isinstance(sensors, list) or not sensors:
            raise ValueError("layout: 'sensors' must be a non-empty list")
        pos, nor, ids, extra = [], [], [], []
        for k, s in enumerate(sensors):
            if not isinstance(s, dict):
                raise ValueError(f"layout sensor {k}: expected an object with 'id', 'position', 'normal', got {s!r}")
            where = f"layout sensor {k}" + (f" (id {s['id']!r})" if "id" in s else "")
            missing = [key for key in ("position", "normal") if key not in s]
            if missing:
                raise ValueError(f"{where}: needs numeric 'position' and 'normal' (missing {', '.join(missing)})")
            pos.append(number_list(s["position"], f"{where}: 'position'"))
            nor.append(number_list(s["normal"], f"{where}: 'normal'"))
            if "id" not in s:
                warnings.warn(ValidationWarning(f"{where}: no 'id'; named {str(k)!r} after its index"), stacklevel=2)
            ids.append(str(s.get("id", k)))
            unknown_keys(s, KNOWN_SENSOR_KEYS, where)
            extra.append({key: val for key, val in s.items() if key not in ("id", "position", "normal")})
        P = np.asarray(pos) * scale
        _check_duplicate_positions(P, ids)
        if len(P) > 1:
            check_extent(float(np.max(P.max(0) - P.min(0))), "layout: the sensors", units)
        meta = {key: val for key, val in d.items() if key not in ("units", "sensors")}
        return cls(P, np.asarray(nor), tuple(ids), meta, tuple(extra))

    def to_dict(self) -> dict:
        sensors = [
            {"id": i, "position": [float(x) for x in p], "normal": [float(x) for x in q], **e}
            for i, p, q, e in zip(self.ids, self.positions, self.normals, self.extra)
        ]
        return {"units": "m", "sensors": sensors, **self.metadata}


def _check_duplicate_positions(P: np.ndarray, ids) -> None:
    """ValueError naming the first two sensors at the same position (within DUPLICATE_TOL_M)."""
    if len(P) < 2:
        return
    order = np.lexsort(P.T[::-1])
    Q = P[order]
    close = np.flatnonzero(np.all(np.abs(np.diff(Q, axis=0)) <= DUPLICATE_TOL_M, axis=1))
    if close.size:
        a, b = sorted((int(order[close[0]]), int(order[close[0] + 1])))
        raise ValueError(f"layout sensors {a} (id {ids[a]!r}) and {b} (id {ids[b]!r}) have the same position "
                         f"{P[a].tolist()} m; each sensor needs its own place")


def load_layout(path) -> Layout:
    """Read a layout JSON file; raises ``ValueError`` with the file name on bad content."""
    path = Path(path)
    d = read_structured(path, "layout", "JSON", json.loads, json.JSONDecodeError)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            lay = Layout.from_dict(d)
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None
    for w in caught:  # again, naming the file, under the caller's filters
        warnings.warn(w.category(f"{path}: {w.message}"), stacklevel=2)
    return lay


def save_layout(layout: Layout, path) -> None:
    """Write ``layout`` as JSON (units m)."""
    from .io.atomic import atomic_write_text

    atomic_write_text(path, json.dumps(to_jsonable(layout.to_dict()), indent=2) + "\n")

