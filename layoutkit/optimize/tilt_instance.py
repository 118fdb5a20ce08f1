"""A small instance where surface normals point away from the envelope (tilt study and tests).

``n`` sites on a sphere cap of radius 0.1 m at polar angles ``lo..hi`` deg from the body +z axis,
normals radial (so they lean ``lo..hi`` deg away from +z); poses from
:func:`layoutkit.optimize.instances.envelope_poses` with body +z towards the station within
``cone_deg``. With a 60° acceptance half-angle, untilted sensors are lit only at part of the poses.
"""
from __future__ import annotations

import numpy as np

from .instances import envelope_poses

__all__ = ["leaning_sites", "leaning_instance"]


def leaning_sites(n, lo=20.0, hi=45.0):
    th = np.deg2rad(np.linspace(lo, hi, n))
    ph = np.linspace(0, 2 * np.pi, n, endpoint=False) + 0.3
    nor = np.c_[np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)]
    return 0.1 * nor, nor


def leaning_instance(n=7, P=20, lo=20.0, hi=45.0, cone_deg=25.0, seed=4):
    pos, nor = leaning_sites(n, lo, hi)
    R, t = envelope_poses(P, np.random.default_rng(seed), cone_deg=cone_deg)
    return pos, nor, R, t
