"""Vive / Index device calibration JSON (``lighthouse_config``) → layout.

The JSON a Vive/Index device reports about itself (libsurvive records it as the ``CONFIG`` line
of a recording; OpenVR tools dump it as a file) carries
``lighthouse_config.modelPoints`` (n × 3, metres, device frame) and
``lighthouse_config.modelNormals`` (n × 3, unit), plus optional ``device_class``,
``model_number``, ``device_serial_number``. The sensor ids of the layout are the indices into
``modelPoints`` (``"0"``, ``"1"``, ...), which are the sensor numbers libsurvive reports in its
light events (after the device's ``channelMap``).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..layout import Layout

__all__ = ["layout_from_config", "read_vive_config", "config_from_layout"]

_META_KEYS = ("device_class", "model_number", "device_serial_number", "manufacturer")


def layout_from_config(cfg: dict, *, source: str = "config") -> Layout:
    """A :class:`~layoutkit.layout.Layout` from a device configuration dict.

    Raises ``ValueError`` naming ``source`` and the missing / malformed field.
    """
    if not isinstance(cfg, dict):
        raise ValueError(f"{source}: expected a JSON object with 'lighthouse_config'")
    lc = cfg.get("lighthouse_config")
    if not isinstance(lc, dict):
        raise ValueError(f"{source}: no 'lighthouse_config' object (keys: {sorted(cfg)[:8]})")
    for key in ("modelPoints", "modelNormals"):
        if key not in lc:
            raise ValueError(f"{source}: lighthouse_config lacks '{key}'")
    try:
        P = np.asarray(lc["modelPoints"], float)
        N = np.asarray(lc["modelNormals"], float)
    except (TypeError, ValueError):
        raise ValueError(f"{source}: lighthouse_config.modelPoints / modelNormals must be lists of 3 numbers") from None
    if P.ndim != 2 or P.shape[1] != 3 or P.shape[0] == 0:
        raise ValueError(f"{source}: lighthouse_config.modelPoints: expected n × 3 numbers, got shape {P.shape}")
    if N.shape != P.shape:
        raise ValueError(f"{source}: lighthouse_config.modelNormals has shape {N.shape}, modelPoints {P.shape}")
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(N))):
        raise ValueError(f"{source}: lighthouse_config has non-finite model points or normals")
    meta = {"source": {"format": "vive-config", "file": source}}
    for k in _META_KEYS:
        if k in cfg:
            meta[k] = cfg[k]
    if "channelMap" in lc:
        meta["channel_map"] = [int(c) for c in lc["channelMap"]]
    try:
        return Layout(P, N, tuple(str(i) for i in range(len(P))), meta)
    except ValueError as exc:
        raise ValueError(f"{source}: {exc}") from None


def read_vive_config(path) -> Layout:
    """Read a device calibration JSON file → layout (``ValueError`` naming the file)."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ValueError(f"{path}: no such file") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a JSON text file") from None
    try:
        cfg = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    return layout_from_config(cfg, source=str(path))


def config_from_layout(layout: Layout, **meta) -> dict:
    """The device configuration dict of a layout (the inverse of :func:`layout_from_config`)."""
    cfg = {k: v for k, v in meta.items()}
    cfg["lighthouse_config"] = {"modelPoints": np.asarray(layout.positions).tolist(),
                                "modelNormals": np.asarray(layout.normals).tolist(),
                                "channelMap": list(range(layout.n))}
    return cfg
