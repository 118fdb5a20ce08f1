"""Unit constants and length-unit tables: the one owner of every unit conversion (after
trimesh's ``units.py``).

Inside layoutkit everything is SI: metres, radians, seconds. Degrees, arcseconds, millimetres
appear only at the boundary (CLI flags and file columns that name their unit); convert with these
constants, never with a local literal.
"""
from __future__ import annotations

import math

__all__ = [
    "ARCSEC", "DEG", "RAD2DEG", "DEG2RAD", "DEG_PER_S", "STANDARD_GRAVITY", "LENGTH_UNITS", "LENGTH_UNIT_NAMES",
    "SIGMA_THETA_PAPER", "SIGMA_THETA_PAPER_ARCSEC", "RHO_PAPER", "length_scale",
]

#: One arcsecond in radians.
ARCSEC = math.pi / 180.0 / 3600.0
#: One degree in radians.
DEG = math.pi / 180.0
DEG2RAD = DEG
#: Radians to degrees.
RAD2DEG = 180.0 / math.pi
#: One degree per second in rad/s (gyro rates logged in deg/s, e.g. the Crazyflie's ``gyro.x``).
DEG_PER_S = DEG
#: Standard gravity, m/s² per g (accelerations logged in g, e.g. the Crazyflie's ``acc.x``; CGPM 1901).
STANDARD_GRAVITY = 9.80665

#: Length units accepted for meshes, layouts and reference tables: metres per unit.
LENGTH_UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254}
LENGTH_UNIT_NAMES = tuple(LENGTH_UNITS)

# Chen §4.2 quotes sigma_theta = 4.014e-5 rad "(8.8'')". 8.8'' is really 4.266e-5 rad (4.014e-5 rad
# is 8.28''); the radian value is the one the paper used in eq. (24), so it is our default.
SIGMA_THETA_PAPER = 4.014e-5
SIGMA_THETA_PAPER_ARCSEC = SIGMA_THETA_PAPER / ARCSEC
#: Same-rotor angle correlation measured by Chen et al. (eq. 19).
RHO_PAPER = 0.8717


def length_scale(unit: str, what: str = "units") -> float:
    """Metres per ``unit``; ``ValueError`` naming ``what`` for an unknown unit."""
    try:
        return LENGTH_UNITS[unit]
    except KeyError:
        raise ValueError(f"{what}: expected one of {', '.join(LENGTH_UNIT_NAMES)}, got {unit!r}") from None
