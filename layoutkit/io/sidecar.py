"""The capture sidecar ``<capture>.json``: one frozen dataclass, written and read one way.

A capture (:mod:`layoutkit.live.capture`) is the raw bytes, a timing index and this sidecar. It
records what is needed to decode and solve the bytes later: the protocol (+ options), the
station set-up (:mod:`layoutkit.io.stations`), the layout (inline dict or a path), the serial
port settings, and the start/end time and byte count. Keys this version does not know are kept
in ``extra`` and written back unchanged (captures are archives; a newer writer's keys survive).

Legacy form: ``"protocol": {"name": ..., "options": {...}}`` reads as ``protocol`` +
``protocol_options``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

from .atomic import atomic_write_text
from .stations import stations_from_list, stations_to_list

__all__ = ["FORMAT", "FORMAT_VERSION", "CaptureSidecar", "sidecar_path", "read_sidecar", "write_sidecar"]

FORMAT = "layoutkit-capture"
FORMAT_VERSION = 1


def sidecar_path(path) -> Path:
    """``<capture>.json``."""
    return Path(str(path) + ".json")


@dataclass(frozen=True)
class CaptureSidecar:
    """What a capture needs to be decoded and solved later.

    protocol : registered protocol name (None = unknown; readers default to ``layoutkit``);
    protocol_options : decoder options; stations : tuple of :class:`~layoutkit.lighthouse.Station`;
    layout : layout dict (``Layout.to_dict()``), a path, or None; port : serial settings;
    source : who wrote it ("live", "fake-fpga", an importer); n_sensors : int or None;
    start_time_utc / end_time_utc : ISO 8601; bytes : byte count at close; decode : decoder
    statistics at close; simulator : simulator settings (fake-fpga); extra : other keys, kept.
    """

    protocol: str | None = None
    protocol_options: dict = field(default_factory=dict)
    stations: tuple = ()
    layout: object = None
    port: dict | None = None
    source: str | None = None
    n_sensors: int | None = None
    start_time_utc: str | None = None
    end_time_utc: str | None = None
    bytes: int | None = None
    decode: dict | None = None
    simulator: dict | None = None
    format: str = FORMAT
    format_version: int = FORMAT_VERSION
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "stations", tuple(self.stations or ()))
        object.__setattr__(self, "protocol_options", dict(self.protocol_options or {}))
        object.__setattr__(self, "extra", dict(self.extra or {}))

    def to_dict(self) -> dict:
        """Plain JSON types (stations as dicts); ``extra`` keys merged at the top level."""
        from .jsonfile import to_jsonable

        out = {}
        for f in fields(self):
            if f.name == "extra":
                continue
            v = getattr(self, f.name)
            if f.name == "stations":
                v = stations_to_list(v)
            if v is None or (f.name == "protocol_options" and not v and self.protocol is None):
                continue
            out[f.name] = v
        for k, v in self.extra.items():
            out.setdefault(k, v)
        return to_jsonable(out)

    @classmethod
    def from_dict(cls, d: dict, where: str = "capture sidecar") -> "CaptureSidecar":
        """Inverse of :meth:`to_dict`; ``ValueError`` naming ``where`` and the field."""
        if isinstance(d, CaptureSidecar):
            return d
        if not isinstance(d, dict):
            raise ValueError(f"{where}: expected a JSON object, got {type(d).__name__}")
        d = dict(d)
        known = {f.name for f in fields(cls)} - {"extra"}
        kw = {k: d.pop(k) for k in list(d) if k in known}
        p = kw.get("protocol")
        opts = kw.get("protocol_options") or {}
        if not isinstance(opts, dict):
            raise ValueError(f"{where}.protocol_options: expected an object, got {type(opts).__name__}")
        opts = dict(opts)
        if isinstance(p, dict):  # legacy {"name": ..., "options": {...}}
            opts.update(p.get("options") or {})
            p = p.get("name")
        if p is not None and not isinstance(p, str):
            raise ValueError(f"{where}.protocol: expected a name, got {p!r}")
        kw["protocol"], kw["protocol_options"] = p, opts
        try:
            kw["stations"] = stations_from_list(kw.get("stations"), f"{where}.stations")
        except ValueError as exc:
            raise ValueError(str(exc)) from None
        for k in ("port", "decode", "simulator"):
            if kw.get(k) is not None and not isinstance(kw[k], dict):
                raise ValueError(f"{where}.{k}: expected an object, got {type(kw[k]).__name__}")
        for k in ("n_sensors", "bytes", "format_version"):
            if kw.get(k) is not None:
                try:
                    kw[k] = int(kw[k])
                except (TypeError, ValueError):
                    raise ValueError(f"{where}.{k}: expected an integer, got {kw[k]!r}") from None
        return cls(**kw, extra=d)

    def updated(self, **changes) -> "CaptureSidecar":
        """A copy with ``changes``; unknown names go to ``extra``."""
        known = {f.name for f in fields(self)} - {"extra"}
        extra = dict(self.extra)
        extra.update({k: v for k, v in changes.items() if k not in known})
        return replace(self, extra=extra, **{k: v for k, v in changes.items() if k in known})


def write_sidecar(capture, sidecar: CaptureSidecar) -> Path:
    """Write ``<capture>.json`` atomically; returns its path."""
    p = sidecar_path(capture)
    atomic_write_text(p, json.dumps(CaptureSidecar.from_dict(sidecar).to_dict(), indent=2) + "\n")
    return p


def read_sidecar(capture) -> CaptureSidecar:
    """The sidecar of ``capture`` (an empty :class:`CaptureSidecar` when there is none).

    ``ValueError`` naming the sidecar file for bad JSON or a bad field.
    """
    p = sidecar_path(capture)
    if not p.exists():
        return CaptureSidecar()
    try:
        data = json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{p}: not valid JSON ({exc})") from None
    except UnicodeDecodeError:
        raise ValueError(f"{p}: not valid JSON (a binary file, not text)") from None
    return CaptureSidecar.from_dict(data, where=str(p))
