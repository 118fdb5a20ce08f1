"""Stations JSON: :class:`layoutkit.lighthouse.Station` to and from plain dicts and files.

One station is ``{"id": "A", "kind": "lh1", "rotation": [[...], [...], [...]], "translation":
[x, y, z], "rotor_rpm": 3600.0, "clock_hz": 5e7, "fov_deg": 120.0, "calibration": {...}}``:
``rotation`` (3×3, row-major) and ``translation`` (m) map station-frame points into the world,
``p_world = R p_station + t``. ``calibration`` (optional) holds the per-axis calibration
parameters, read by :func:`layoutkit.lighthouse.calibration_from_dict` (layoutkit, libsurvive or
Crazyflie convention) into ``Station.calibration`` and written back by
:meth:`~layoutkit.lighthouse.Calibration.to_dict` (layoutkit convention, the same model). Every key but ``rotation``/``translation`` is optional (defaults of ``Station``);
unknown keys are an error naming the station and the key. ``source_id`` (optional) keeps the id a
foreign source gave the station (libsurvive's lighthouse serial); ``id`` must be unique in a file
(duplicates are refused with a message: results and reports key on it).

A stations file is JSON ``{"stations": [station, ...]}`` (a bare list is accepted on reading).
Capture sidecars (:mod:`layoutkit.io.sidecar`) embed the same list. The user-facing envelope
TOML describes stations differently (``position_m``, ``look_at_m``, ``rotvec_deg``; see
:mod:`layoutkit.envelope`) and builds the same ``Station``.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .atomic import atomic_write_text

__all__ = ["STATION_KEYS", "station_to_dict", "station_from_dict", "stations_to_list", "stations_from_list",
           "read_stations", "write_stations"]

#: Keys of one station entry.
STATION_KEYS = ("id", "kind", "rotation", "translation", "rotor_rpm", "clock_hz", "fov_deg", "calibration",
                "source_id")


def station_to_dict(station) -> dict:
    """A :class:`~layoutkit.lighthouse.Station` as plain JSON types."""
    from .jsonfile import to_jsonable

    return {"id": str(station.id), "kind": station.kind, "rotation": np.asarray(station.rotation).tolist(),
            "translation": np.asarray(station.translation).tolist(), "rotor_rpm": float(station.rotor_rpm),
            "clock_hz": float(station.clock_hz), "fov_deg": float(station.fov_deg),
            **({} if station.calibration is None else {"calibration": to_jsonable(station.calibration.to_dict())}),
            **({} if getattr(station, "source_id", None) is None else {"source_id": str(station.source_id)})}


def station_from_dict(d: dict, where: str = "station"):
    """Inverse of :func:`station_to_dict`; ``ValueError`` naming ``where`` and the key."""
    from ..lighthouse import Station, calibration_from_dict

    if not isinstance(d, dict):
        raise ValueError(f"{where}: expected an object, got {type(d).__name__}")
    unknown = sorted(set(d) - set(STATION_KEYS))
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {', '.join(map(repr, unknown))} "
                         f"(expected {', '.join(STATION_KEYS)})")
    kw = {}
    for k in STATION_KEYS:
        if k not in d:
            continue
        v = d[k]
        try:
            if k in ("rotor_rpm", "clock_hz", "fov_deg"):
                v = float(v)
            elif k in ("rotation", "translation"):
                v = np.asarray(v, dtype=float)
            elif k == "calibration":
                continue  # below, once the kind is known
            else:
                v = str(v)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{where}.{k}: {exc}") from None
        kw[k] = v
    if d.get("calibration") is not None:
        kw["calibration"] = calibration_from_dict(d["calibration"], kw.get("kind", "lh1"), what=f"{where}.calibration")
    try:
        return Station(**kw)
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None


def stations_to_list(stations) -> list:
    return [station_to_dict(s) for s in stations or ()]


def stations_from_list(items, where: str = "stations") -> tuple:
    if items is None:
        return ()
    if not isinstance(items, (list, tuple)):
        raise ValueError(f"{where}: expected a list of stations, got {type(items).__name__}")
    from ..lighthouse import check_station_ids

    out = tuple(station_from_dict(d, f"{where}[{k}]") for k, d in enumerate(items))
    check_station_ids(out, where)
    return out


def read_stations(path) -> tuple:
    """Stations of a JSON file (``{"stations": [...]}`` or a list); ``ValueError`` naming the file."""
    from .._validate import read_structured

    path = Path(path)
    data = read_structured(path, "stations", "JSON", json.loads, json.JSONDecodeError)
    items = data.get("stations") if isinstance(data, dict) else data
    if isinstance(data, dict) and "stations" not in data:
        raise ValueError(f"{path}: expected a 'stations' list")
    try:
        return stations_from_list(items)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def write_stations(path, stations) -> Path:
    """Write ``{"stations": [...]}`` atomically; returns the path."""
    atomic_write_text(path, json.dumps({"stations": stations_to_list(stations)}, indent=2) + "\n")
    return Path(path)
