"""Lighthouse measurement model: sweep angles, timing, field of view, stations (design §2–§3).

Lighthouse frame: origin at the rotor centre, z = boresight, x and y the two
sweep directions. For a point ``p = (x, y, z)`` the LH1 sweep angles are
``theta_x = atan2(z, x)``, ``theta_y = atan2(z, y)`` (Chen eq. 2), so
``cot(theta_x) = x / z`` and 90° is on boresight.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ._validate import as_array, check_finite

__all__ = [
    "LH1_ROTOR_RPM",
    "DEFAULT_CLOCK_HZ",
    "sweep_angles",
    "angles_to_normalized",
    "normalized_to_angles",
    "in_field_of_view",
    "angular_rate",
    "angles_to_ticks",
    "ticks_to_angles",
    "quantize_angles",
    "lh2_sweep_angles",
    "Station",
    "points_in_station",
]

LH1_ROTOR_RPM = 3600.0
DEFAULT_CLOCK_HZ = 50e6
LH2_TILT_RAD = np.pi / 6


def sweep_angles(points_lh) -> np.ndarray:
    """LH1 sweep angles of points in the lighthouse frame.

    points_lh : (..., n, 3) float, m, lighthouse frame.
    Returns (..., n, 2) float, rad: ``[theta_x, theta_y]`` (Chen eq. 2), in (0, pi) for z > 0.
    """
    p = as_array(points_lh, "points_lh", (..., 3))
    return np.stack([np.arctan2(p[..., 2], p[..., 0]), np.arctan2(p[..., 2], p[..., 1])], -1)


def angles_to_normalized(angles) -> np.ndarray:
    """Sweep angles ``(..., 2)`` rad → normalised image coordinates ``(x/z, y/z) = cot(theta)``."""
    a = np.asarray(angles, dtype=float)
    return np.cos(a) / np.sin(a)


def normalized_to_angles(uv) -> np.ndarray:
    """Normalised coordinates ``(..., 2)`` (x/z, y/z) → sweep angles (rad) for points with z > 0."""
    uv = np.asarray(uv, dtype=float)
    return np.arctan2(1.0, uv)


def in_field_of_view(points_lh, fov_deg: float = 120.0) -> np.ndarray:
    """True where both sweep angles are within ``fov/2`` of 90° and z > 0.

    points_lh : (..., n, 3) m → (..., n) bool. The default 120° × 120° field is theta in [30°, 150°].
    """
    p = as_array(points_lh, "points_lh", (..., 3))
    half = np.deg2rad(fov_deg) / 2.0
    th = sweep_angles(p)
    ok = np.all(np.abs(th - np.pi / 2) <= half + 1e-12, axis=-1)
    return ok & (p[..., 2] > 0)


def angular_rate(rotor_rpm: float = LH1_ROTOR_RPM) -> float:
    """Rotor angular rate omega in rad/s (3600 rpm → 120 pi)."""
    return 2.0 * np.pi * rotor_rpm / 60.0


def angles_to_ticks(angles, rotor_rpm: float = LH1_ROTOR_RPM, clock_hz: float = DEFAULT_CLOCK_HZ):
    """Sweep angle (rad) → counter ticks after the sync flash, ``theta = omega (t_hit - t_sync)`` (Chen eq. 1).

    Returns float ticks (not rounded); use :func:`quantize_angles` to model the counter.
    """
    return np.asarray(angles, dtype=float) / angular_rate(rotor_rpm) * clock_hz


def ticks_to_angles(ticks, rotor_rpm: float = LH1_ROTOR_RPM, clock_hz: float = DEFAULT_CLOCK_HZ):
    """Counter ticks after the sync flash → sweep angle in rad (Chen eq. 1)."""
    return np.asarray(ticks, dtype=float) * angular_rate(rotor_rpm) / clock_hz


def quantize_angles(angles, rotor_rpm: float = LH1_ROTOR_RPM, clock_hz: float = DEFAULT_CLOCK_HZ):
    """Round angles to the counter resolution (one tick = 7.54e-6 rad at 3600 rpm, 50 MHz)."""
    return ticks_to_angles(np.round(angles_to_ticks(angles, rotor_rpm, clock_hz)), rotor_rpm, clock_hz)


def lh2_sweep_angles(points_lh, tilt_rad: float = LH2_TILT_RAD) -> np.ndarray:
    """LH2 slanted-plane sweep angles (Bitcraze model), points ``(..., n, 3)`` → ``(..., n, 2)`` rad.

    In the lighthouse frame of this package (z boresight), Bitcraze's station frame has
    x forward; we map ``x_bc = z, y_bc = x, z_bc = y``. Then for the two light planes
    tilted by ``t = -tilt`` and ``t = +tilt``:
    ``alpha = atan2(y_bc, x_bc) + asin(z_bc * tan(t) / sqrt(x_bc² + y_bc²))``.
    """
    p = as_array(points_lh, "points_lh", (..., 3))
    xb, yb, zb = p[..., 2], p[..., 0], p[..., 1]
    r = np.hypot(xb, yb)
    base = np.arctan2(yb, xb)
    out = []
    for t in (-tilt_rad, tilt_rad):
        out.append(base + np.arcsin(np.clip(zb * np.tan(t) / r, -1.0, 1.0)))
    return np.stack(out, -1)


@dataclass(frozen=True)
class Station:
    """A base station with a known pose in the world frame.

    rotation : (3, 3) and translation : (3,) map station-frame points to the world frame,
    ``p_world = rotation @ p_station + translation`` (m). ``kind`` is ``"lh1"`` or ``"lh2"``.
    """

    id: str = "A"
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    kind: str = "lh1"
    rotor_rpm: float = LH1_ROTOR_RPM
    clock_hz: float = DEFAULT_CLOCK_HZ
    fov_deg: float = 120.0

    def __post_init__(self):
        R = as_array(self.rotation, "Station.rotation", (3, 3))
        t = as_array(self.translation, "Station.translation", (3,))
        check_finite(R, "Station.rotation")
        check_finite(t, "Station.translation")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise ValueError("Station.rotation: expected a proper rotation matrix")
        if self.kind not in ("lh1", "lh2"):
            raise ValueError(f"Station.kind: expected 'lh1' or 'lh2', got {self.kind!r}")
        object.__setattr__(self, "rotation", R)
        object.__setattr__(self, "translation", t)

    def world_to_station(self, rotation_world, translation_world):
        """Body pose in the world ``(..., 3, 3), (..., 3)`` → body pose in this station's frame."""
        Rt = self.rotation.T
        R = np.einsum("ij,...jk->...ik", Rt, np.asarray(rotation_world, float))
        t = np.einsum("ij,...j->...i", Rt, np.asarray(translation_world, float) - self.translation)
        return R, t


def points_in_station(station: Station, points_world) -> np.ndarray:
    """World points ``(..., n, 3)`` → the same points in the station frame."""
    p = np.asarray(points_world, dtype=float)
    return (p - station.translation) @ station.rotation
