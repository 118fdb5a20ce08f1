"""Simulated lighthouse measurements of a layout: lit sets and noisy, quantised sweep angles.

Pure numpy; the measurement chain of design §3: true angles (Chen eq. 2) + correlated noise
(eq. 19) + counter quantisation. Occlusion by a mesh is the visibility room's job
(:mod:`layoutkit.visibility`, which also owns the lit rule :func:`~layoutkit.visibility.facing_mask`,
re-exported here for old imports).
"""
from __future__ import annotations

import numpy as np

from ._validate import as_array
from .geometry import random_rotations, transform_points
from .lighthouse import DEFAULT_CLOCK_HZ, LH1_ROTOR_RPM, in_field_of_view, quantize_angles, sweep_angles
from .noise import sample_angle_noise
from .visibility import facing_mask  # re-export: the lit rule lives in the visibility room

__all__ = ["facing_mask", "simulate_angles", "simulate_station_angles", "stations_looking_at", "poses_in_front"]


def simulate_angles(points_body, rotation, translation, *, sigma: float, rho: float,
                    rng: np.random.Generator, quantize: bool = True,
                    rotor_rpm: float = LH1_ROTOR_RPM, clock_hz: float = DEFAULT_CLOCK_HZ) -> np.ndarray:
    """Noisy measured sweep angles ``(F, n, 2)`` rad for body poses ``(F, 3, 3), (F, 3)``.

    points_body : (n, 3) m. Noise: sigma (rad), same-rotor correlation rho (Chen eq. 19),
    then rounding to the counter tick when ``quantize``.
    """
    R = as_array(rotation, "rotation", (None, 3, 3))
    t = as_array(translation, "translation", (R.shape[0], 3))
    P = as_array(points_body, "points_body", (None, 3))
    ang = sweep_angles(transform_points(R, t, P))
    ang = ang + sample_angle_noise(ang.shape[:-1], sigma, rho, rng)
    if quantize:
        ang = quantize_angles(ang, rotor_rpm, clock_hz)
    return ang


def simulate_station_angles(points_body, rotation, translation, stations, *, sigma: float, rho: float,
                            rng: np.random.Generator, dt=None, velocity=None) -> np.ndarray:
    """Noisy measured angles ``(F, S, n, 2)`` rad of S stations through their forward models.

    points_body : (n, 3) m; rotation (F, 3, 3), translation (F, 3) m: body poses in the stations'
    world frame. stations : :class:`layoutkit.lighthouse.Station` with kind and calibration — the
    angles are the calibrated (distorted) ones a real station with those parameters reports
    (:func:`layoutkit.lighthouse.measure`). Noise per station: sigma (rad), same-rotor correlation
    rho (Chen eq. 19). ``dt (F, S)`` s and ``velocity (omega, v)`` move the body during the window
    (:func:`layoutkit.joint.model_angles_jacobian`). No visibility mask is applied.
    """
    from .joint import model_angles_jacobian

    R = as_array(rotation, "rotation", (None, 3, 3))
    t = as_array(translation, "translation", (R.shape[0], 3))
    P = as_array(points_body, "points_body", (None, 3))
    ang = model_angles_jacobian(P, R, t, list(stations), dt=dt, velocity=velocity, jacobian=False)[0]
    return ang + sample_angle_noise(ang.shape[:-1], sigma, rho, rng)


def stations_looking_at(positions, target=(0.0, 0.0, 0.0), *, kind: str = "lh1", calibrations=None,
                        up_hint=(0.0, 0.0, 1.0)) -> list:
    """Stations at ``positions (S, 3)`` m (world) with boresight (z) toward ``target``.

    calibrations : optional S :class:`layoutkit.lighthouse.Calibration` (or None each).
    Returns a list of :class:`layoutkit.lighthouse.Station` with ids "0", "1", ...
    """
    from .geometry import look_at_rotation
    from .lighthouse import Station

    pos = as_array(positions, "positions", (None, 3))
    cals = list(calibrations) if calibrations is not None else [None] * len(pos)
    out = []
    for k, p in enumerate(pos):
        R = look_at_rotation(np.asarray(target, float) - p, up_hint).T  # columns = station axes in the world
        out.append(Station(id=str(k), rotation=R, translation=p, kind=kind, calibration=cals[k]))
    return out


def poses_in_front(count: int, rng: np.random.Generator, *, x_range=(-1.5, 1.5), z_range=(0.5, 3.5),
                   height: float = 0.3, fov_deg: float = 120.0, margin_deg: float = 5.0):
    """Positions on a horizontal 3 m × 3 m area in front of a station and uniform attitudes.

    The station looks horizontally (z boresight, y down); the area is the plane y = ``height``
    (m below the rotor), x in ``x_range``, z in ``z_range`` — the paper's marble table (Chen §4.2).
    Positions outside the field of view (less ``margin_deg``) are redrawn.
    Returns rotation (count, 3, 3), translation (count, 3).
    """
    out = np.empty((0, 3))
    while len(out) < count:
        m = 2 * (count - len(out)) + 8
        t = np.column_stack([rng.uniform(*x_range, m), np.full(m, height), rng.uniform(*z_range, m)])
        ok = in_field_of_view(t[:, None, :], fov_deg - 2 * margin_deg)[:, 0]
        out = np.vstack([out, t[ok]])
    return random_rotations(count, rng), out[:count]
