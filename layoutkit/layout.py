"""Sensor layouts: the JSON file format (docs/layout-format.md), load and save.

A layout file is JSON ``{"units": "m", "sensors": [{"id": str, "position": [x, y, z],
"normal": [nx, ny, nz]}, ...], ...}``; other top-level and per-sensor keys are kept in
``metadata`` / ``extra`` and written back. Inside the library positions are metres.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .io.jsonfile import to_jsonable
from ._validate import as_array, check_finite, read_structured
from .units import LENGTH_UNITS

__all__ = ["UNIT_SCALE", "Layout", "load_layout", "save_layout"]

#: Back-compat name of :data:`layoutkit.units.LENGTH_UNITS` (metres per unit).
UNIT_SCALE = LENGTH_UNITS


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
            try:
                pos.append([float(x) for x in s["position"]])
                nor.append([float(x) for x in s["normal"]])
            except (KeyError, TypeError, ValueError) as exc:
                raise ValueError(f"layout sensor {k}: needs numeric 'position' and 'normal' ({exc})") from None
            ids.append(str(s.get("id", k)))
            extra.append({key: val for key, val in s.items() if key not in ("id", "position", "normal")})
        meta = {key: val for key, val in d.items() if key not in ("units", "sensors")}
        return cls(np.asarray(pos) * scale, np.asarray(nor), tuple(ids), meta, tuple(extra))

    def to_dict(self) -> dict:
        sensors = [
            {"id": i, "position": [float(x) for x in p], "normal": [float(x) for x in q], **e}
            for i, p, q, e in zip(self.ids, self.positions, self.normals, self.extra)
        ]
        return {"units": "m", "sensors": sensors, **self.metadata}


def load_layout(path) -> Layout:
    """Read a layout JSON file; raises ``ValueError`` with the file name on bad content."""
    path = Path(path)
    d = read_structured(path, "layout", "JSON", json.loads, json.JSONDecodeError)
    try:
        return Layout.from_dict(d)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def save_layout(layout: Layout, path) -> None:
    """Write ``layout`` as JSON (units m)."""
    from .io.atomic import atomic_write_text

    atomic_write_text(path, json.dumps(to_jsonable(layout.to_dict()), indent=2) + "\n")

