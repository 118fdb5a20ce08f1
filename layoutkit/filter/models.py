"""Sweep-angle forward models for the filter: ``h(points_body, R, t, station) -> angles`` + Jacobian.

A forward model maps a body pose in the **world** frame (``p_world = R p_body + t``) and a
:class:`layoutkit.lighthouse.Station` (station-to-world pose, kind, calibration) to the two sweep
angles of every sensor, and gives the Jacobian of those angles with respect to the left pose
perturbation in the world frame, ``R <- exp([dphi]x) R``, ``t <- t + dt`` (design §2, §5; the
convention of :func:`layoutkit.dop.angle_jacobian`). The filter only talks to this protocol.

Registered models (:data:`FORWARD_MODELS`):

- ``"station"`` (default): each station's own model — its :class:`~layoutkit.lighthouse.Calibration`
  through :func:`layoutkit.lighthouse.measure_jacobian` (factory phase, tilt, curve, gib, ogee;
  docs/calibration.md), the ideal LH1 / LH2 model when it has none;
- ``"plain"``: always the ideal models (:func:`~layoutkit.lighthouse.sweep_angles`, Chen eq. 2;
  :func:`~layoutkit.lighthouse.lh2_sweep_angles`), ignoring any calibration.

Shapes: points_body ``(..., n, 3)`` m; R ``(..., 3, 3)``; t ``(..., 3)`` m → angles
``(..., n, 2)`` rad (LH1 ``[theta_x, theta_y]``, LH2 ``[alpha_plane0, alpha_plane1]``) and
Jacobian ``(..., n, 2, 6)`` rad per (rad, m), rotation block first.
"""
from __future__ import annotations

from typing import Protocol

import numpy as np

from ..lighthouse import LH2_TILT_RAD, Station, lh2_sweep_angles, measure_jacobian, sweep_angles

__all__ = ["ForwardModel", "PlainSweepModel", "StationSweepModel", "FORWARD_MODELS", "station_points",
           "angle_gradient", "pose_jacobian"]


class ForwardModel(Protocol):
    """Sweep angles of a rigid body seen by one station, and their pose Jacobian (module docstring)."""

    def __call__(self, points_body, rotation, translation, station: Station) -> np.ndarray: ...

    def jacobian(self, points_body, rotation, translation, station: Station) -> np.ndarray: ...


def station_points(points_body, rotation, translation, station: Station):
    """Lever ``l = R p_body`` (world axes) and the sensor points in the station frame, both (..., n, 3) m."""
    lever = np.asarray(points_body, float) @ np.swapaxes(np.asarray(rotation, float), -1, -2)
    pw = lever + np.asarray(translation, float)[..., None, :]
    return lever, (pw - station.translation) @ station.rotation


def angle_gradient(points_station, kind: str = "lh1", tilt_rad: float = LH2_TILT_RAD) -> np.ndarray:
    """d angles / d p_station, (..., n, 2, 3) rad/m, for the plain LH1 / LH2 models.

    LH1 (Chen eq. 2): ``d theta_x/dp = (-z, 0, x)/(x²+z²)``, ``d theta_y/dp = (0, -z, y)/(y²+z²)``.
    LH2 (:func:`layoutkit.lighthouse.lh2_sweep_angles`, ``xb = z, yb = x, zb = y``, ``r = hypot(xb, yb)``):
    ``alpha = atan2(yb, xb) + asin(u)``, ``u = zb tan(t) / r``:
    ``d atan2 = (xb dyb - yb dxb) / r²``, ``du = tan(t) dzb / r - u (xb dxb + yb dyb) / r²``,
    ``d asin(u) = du / sqrt(1 - u²)``.
    """
    p = np.asarray(points_station, float)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    out = np.zeros(p.shape[:-1] + (2, 3))
    if kind == "lh1":
        ix = 1.0 / (x * x + z * z)
        iy = 1.0 / (y * y + z * z)
        out[..., 0, 0] = -z * ix
        out[..., 0, 2] = x * ix
        out[..., 1, 1] = -z * iy
        out[..., 1, 2] = y * iy
        return out
    xb, yb, zb = z, x, y
    r2 = xb * xb + yb * yb
    r = np.sqrt(r2)
    # d atan2(yb, xb) in (x, y, z) of the station frame: dyb = dx, dxb = dz
    ga = np.stack([xb / r2, np.zeros_like(x), -yb / r2], -1)
    for k, tt in enumerate((-tilt_rad, tilt_rad)):
        kk = np.tan(tt)
        u = zb * kk / r
        s = 1.0 / np.sqrt(np.maximum(1.0 - u * u, 1e-300))
        # du/dx (via yb), du/dy (via zb), du/dz (via xb)
        du = np.stack([-u * yb / r2, kk / r + 0.0 * x, -u * xb / r2], -1)
        out[..., k, :] = ga + du * s[..., None]
    return out


class PlainSweepModel:
    """The uncalibrated models: LH1 :func:`~layoutkit.lighthouse.sweep_angles` (Chen eq. 2) and LH2
    :func:`~layoutkit.lighthouse.lh2_sweep_angles` (Bitcraze slanted planes), chosen by ``station.kind``."""

    def __call__(self, points_body, rotation, translation, station: Station) -> np.ndarray:
        _, ps = station_points(points_body, rotation, translation, station)
        return lh2_sweep_angles(ps) if station.kind == "lh2" else sweep_angles(ps)

    def jacobian(self, points_body, rotation, translation, station: Station) -> np.ndarray:
        lever, ps = station_points(points_body, rotation, translation, station)
        return pose_jacobian(lever, angle_gradient(ps, station.kind), station)

    def angles_and_jacobian(self, points_body, rotation, translation, station: Station):
        """Both at once (one transform): ``(angles (..., n, 2), jacobian (..., n, 2, 6))``.

        The filter's per-sweep hot path: for a single pose ``(n, 3), (3, 3), (3,)`` the LH1 case is
        written out per component (the same formulas as :func:`angle_gradient` and
        :func:`pose_jacobian`; ``tests/test_filter.py`` checks both against finite differences).
        """
        R = np.asarray(rotation, float)
        if station.kind != "lh1" or R.ndim != 2:
            lever, ps = station_points(points_body, rotation, translation, station)
            ang = lh2_sweep_angles(ps) if station.kind == "lh2" else sweep_angles(ps)
            return ang, pose_jacobian(lever, angle_gradient(ps, station.kind), station)
        lever = np.asarray(points_body, float) @ R.T
        Rs = station.rotation
        ps = (lever + (np.asarray(translation, float) - station.translation)) @ Rs
        x, y, z = ps[:, 0], ps[:, 1], ps[:, 2]
        n = x.shape[0]
        ang = np.empty((n, 2))
        ang[:, 0] = np.arctan2(z, x)
        ang[:, 1] = np.arctan2(z, y)
        ix = 1.0 / (x * x + z * z)
        iy = 1.0 / (y * y + z * z)
        g = np.zeros((n, 2, 3))
        g[:, 0, 0] = -z * ix
        g[:, 0, 2] = x * ix
        g[:, 1, 1] = -z * iy
        g[:, 1, 2] = y * iy
        a = g @ Rs.T  # d angle / d p_world, (n, 2, 3)
        J = np.empty((n, 2, 6))
        J[..., 3:] = a
        lx, ly, lz = lever[:, None, 0], lever[:, None, 1], lever[:, None, 2]
        ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
        J[..., 0] = ly * az - lz * ay
        J[..., 1] = lz * ax - lx * az
        J[..., 2] = lx * ay - ly * ax
        return ang, J


    def sweep_rows(self, points_body, rotation, translation, station: Station, axis: int):
        """One axis only, single pose: ``(angles (m,), rows (m, 6))`` — the filter's per-sweep fast
        path (optional for other models; the filter falls back to ``angles_and_jacobian`` /
        ``__call__`` + ``jacobian``). LH1: only ``theta_axis = atan2(z, x_axis)`` and its gradient
        ``(-z e_axis + x_axis e_z) / (x_axis² + z²)`` (Chen eq. 2)."""
        R = np.asarray(rotation, float)
        if station.kind != "lh1" or R.ndim != 2:
            ang, J = self.angles_and_jacobian(points_body, rotation, translation, station)
            return ang[:, axis], J[:, axis, :]
        lever = points_body @ R.T
        Rs = station.rotation
        ps = (lever + (translation - station.translation)) @ Rs
        u = ps[:, axis]
        z = ps[:, 2]
        inv = 1.0 / (u * u + z * z)
        gu, gz = -z * inv, u * inv
        a = gu[:, None] * Rs[:, axis] + gz[:, None] * Rs[:, 2]  # d theta / d p_world, (m, 3)
        rows = np.empty((u.shape[0], 6))
        rows[:, 3:] = a
        lx, ly, lz = lever[:, 0], lever[:, 1], lever[:, 2]
        ax, ay, az = a[:, 0], a[:, 1], a[:, 2]
        rows[:, 0] = ly * az - lz * ay
        rows[:, 1] = lz * ax - lx * az
        rows[:, 2] = lx * ay - ly * ax
        return np.arctan2(z, u), rows


def pose_jacobian(lever, grad_station, station: Station) -> np.ndarray:
    """Chain rule to the world-frame pose perturbation: ``d p_station = R_s^T (-[l]x dphi + dt)``.

    lever (..., n, 3) m world axes; grad_station (..., n, 2, 3) → (..., n, 2, 6). A row ``a`` of
    ``d angle / d p_world`` gives ``(l × a, a)`` (``a^T (-[l]x) = (l × a)^T``).
    """
    a = grad_station @ station.rotation.T  # d angle / d p_world
    l = np.asarray(lever, float)[..., None, :]
    return np.concatenate([np.cross(l, a), a], -1)


class StationSweepModel(PlainSweepModel):
    """Each station's calibrated model (:func:`layoutkit.lighthouse.measure_jacobian` with
    ``station.calibration``); stations without a calibration use the ideal model's fast paths."""

    def __call__(self, points_body, rotation, translation, station: Station) -> np.ndarray:
        if station.calibration is None:
            return super().__call__(points_body, rotation, translation, station)
        _, ps = station_points(points_body, rotation, translation, station)
        return measure_jacobian(ps, station.calibration, station.kind, jacobian=False)[0]

    def jacobian(self, points_body, rotation, translation, station: Station) -> np.ndarray:
        return self.angles_and_jacobian(points_body, rotation, translation, station)[1]

    def angles_and_jacobian(self, points_body, rotation, translation, station: Station):
        if station.calibration is None:
            return super().angles_and_jacobian(points_body, rotation, translation, station)
        lever, ps = station_points(points_body, rotation, translation, station)
        ang, dp, _ = measure_jacobian(ps, station.calibration, station.kind)
        return ang, pose_jacobian(lever, dp, station)

    def sweep_rows(self, points_body, rotation, translation, station: Station, axis: int):
        if station.calibration is None:
            return super().sweep_rows(points_body, rotation, translation, station, axis)
        ang, J = self.angles_and_jacobian(points_body, rotation, translation, station)
        return ang[:, axis], J[:, axis, :]


#: Registry of forward models by name (``--filter-model`` offers these).
FORWARD_MODELS: "dict[str, ForwardModel]" = {"station": StationSweepModel(), "plain": PlainSweepModel()}
