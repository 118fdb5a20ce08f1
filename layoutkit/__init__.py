"""layoutkit — photodiode layouts for lighthouse-based spacecraft relative pose measurement.

The public names below are imported lazily so that ``import layoutkit`` stays cheap
(no cvxpy, pyvista, serial or OpenCV at import time).
"""
from __future__ import annotations

import importlib

__version__ = "0.1.0"

_EXPORTS = {
    # core (issue: core engine)
    "sweep_angles": "layoutkit.lighthouse",
    "Station": "layoutkit.lighthouse",
    "pose_dop": "layoutkit.dop",
    "DopResult": "layoutkit.dop",
    "precision": "layoutkit.dop",
    "pose_errors": "layoutkit.dop",
    "sample_angle_noise": "layoutkit.noise",
    "solve_pnp": "layoutkit.pnp",
    "PnPResult": "layoutkit.pnp",
    "Layout": "layoutkit.layout",
    "load_layout": "layoutkit.layout",
    "save_layout": "layoutkit.layout",
    # meshes and visibility
    "load_mesh": "layoutkit.mesh",
    "sample_candidates": "layoutkit.candidates",
    "load_envelope": "layoutkit.envelope",
    "Envelope": "layoutkit.envelope",
    "visible_sensors": "layoutkit.visibility",
    "envelope_visibility": "layoutkit.visibility",
    "tracking_quality_map": "layoutkit.quality",
    # optimiser
    "optimize_layout": "layoutkit.optimize",
    # camera
    "rectangle_attitude": "layoutkit.camera",
    "euler_zyx": "layoutkit.camera",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    mod = _EXPORTS.get(name)
    if mod is None:
        raise AttributeError(f"module 'layoutkit' has no attribute {name!r}")
    value = getattr(importlib.import_module(mod), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
