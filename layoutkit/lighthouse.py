"""Lighthouse measurement model: sweep angles, timing, field of view, stations (design §2–§3).

Why one module of ~650 lines: it is the ONE owner of the station conventions (docs/architecture.md):
the ideal model, the calibration model with its analytic Jacobians, and the libsurvive and
Crazyflie conventions mapped onto it belong together, so no second copy of a convention appears.

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
    "check_station_ids",
    "LH1_ROTOR_RPM",
    "DEFAULT_CLOCK_HZ",
    "hit_offset",
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
    "lh2_to_lh1_angles",
    "angles_to_ray",
    "sweep_to_lh2_angles",
    "CALIBRATION_PARAMS",
    "MODEL_PARAMS",
    "Calibration",
    "measure",
    "measure_jacobian",
    "distort",
    "undistort",
    "to_sweep_angles",
    "calibration_from_libsurvive",
    "calibration_from_crazyflie",
    "calibration_from_dict",
    "SweepCalibration",
    "StationCalibration",
    "lh1_model",
    "lh2_model",
    "calibrate_lh1",
    "calibrate_lh2",
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


def hit_offset(st: Station, kind: str, ang, axis: int = 0):
    """Hit time after the sweep's time (s) of angle(s) ``ang`` rad of station ``st`` on ``axis``: LH1
    ``theta / omega`` after the sync, LH2 plane ``axis`` ``(alpha + pi -/+ pi/3) / omega`` after the
    rotor zero (the decoder's plane angles ``a0 = off0 omega - pi + pi/3``, ``a1 = off1 omega - pi -
    pi/3``), ``omega`` the rotor's :func:`angular_rate`."""
    omega = angular_rate(st.rotor_rpm)
    if kind == "lh2":
        return (ang + np.pi + (-np.pi / 3 if axis == 0 else np.pi / 3)) / omega
    return ang / omega


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


def check_station_ids(stations, where: str = "stations") -> None:
    """``ValueError`` when two stations of a list share an ``id`` (results and reports key on it)."""
    ids = [str(s.id) for s in stations]
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise ValueError(f"{where}: station id(s) {', '.join(map(repr, dup))} used by more than one station "
                         f"(ids: {ids}); give every station its own id (a foreign id can go in 'source_id')")


@dataclass(frozen=True)
class Station:
    """A base station with a known pose in the world frame.

    rotation : (3, 3) and translation : (3,) map station-frame points to the world frame,
    ``p_world = rotation @ p_station + translation`` (m). ``kind`` is ``"lh1"`` or ``"lh2"``.
    calibration : the station's :class:`Calibration` (None = ideal); solvers and DOP go through
    :func:`measure` with it.
    source_id : the id a foreign source gave the station (e.g. libsurvive's lighthouse serial, which
    is not unique: ``nan_crash_windows`` names three lighthouses 2147483647); ``id`` is what
    layoutkit keys on and must be unique in a stations list (:func:`check_station_ids`).
    To and from JSON: :mod:`layoutkit.io.stations`.
    """

    id: str = "A"
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    kind: str = "lh1"
    rotor_rpm: float = LH1_ROTOR_RPM
    clock_hz: float = DEFAULT_CLOCK_HZ
    fov_deg: float = 120.0
    calibration: "Calibration | None" = None
    source_id: "str | None" = None

    def __post_init__(self):
        R = as_array(self.rotation, "Station.rotation", (3, 3))
        t = as_array(self.translation, "Station.translation", (3,))
        check_finite(R, "Station.rotation")
        check_finite(t, "Station.translation")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise ValueError("Station.rotation: expected a proper rotation matrix")
        if self.kind not in ("lh1", "lh2"):
            raise ValueError(f"Station.kind: expected 'lh1' or 'lh2', got {self.kind!r}")
        if self.calibration is not None:
            if not isinstance(self.calibration, Calibration):
                raise ValueError("Station.calibration: expected a layoutkit.lighthouse.Calibration or None")
            if self.calibration.kind != self.kind:
                raise ValueError(f"Station.calibration: a {self.calibration.kind} model on a {self.kind} station")
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


def lh2_to_lh1_angles(plane_angles, tilt_rad: float = LH2_TILT_RAD) -> np.ndarray:
    """LH2 light-plane angles ``(..., 2)`` rad → LH1-equivalent ``[theta_x, theta_y]`` ``(..., 2)``.

    Inverts :func:`lh2_sweep_angles` (planes tilted ``-tilt`` and ``+tilt``): with
    ``base = (a0 + a1) / 2`` and ``s = sin((a1 - a0) / 2) / tan(tilt)`` the ray direction in the
    package's station frame is ``(sin base, s, cos base)``, whose LH1 angles are
    ``theta_x = atan2(cos base, sin base)``, ``theta_y = atan2(cos base, s)`` (Chen eq. 2).
    ``tilt_rad`` is the nominal plane tilt (30° on every LH2 station); a station's own tilt error
    belongs in its :class:`Calibration`, not here.
    """
    a = np.asarray(plane_angles, dtype=float)
    base = 0.5 * (a[..., 0] + a[..., 1])
    s = np.sin(0.5 * (a[..., 1] - a[..., 0])) / np.tan(tilt_rad)
    c = np.cos(base)
    return np.stack([np.arctan2(c, np.sin(base)), np.arctan2(c, s)], -1)


def angles_to_ray(theta) -> np.ndarray:
    """LH1 sweep angles ``(..., 2)`` → a ray ``(..., 3)`` in the station frame with those angles
    (``(cot theta_x, cot theta_y, 1)`` scaled by ``sin theta_x sin theta_y``; Chen eq. 2)."""
    th = np.asarray(theta, float)
    sx, sy = np.sin(th[..., 0]), np.sin(th[..., 1])
    return np.stack([np.cos(th[..., 0]) * sy, np.cos(th[..., 1]) * sx, sx * sy], -1)


def sweep_to_lh2_angles(theta, tilt_rad: float = LH2_TILT_RAD) -> np.ndarray:
    """LH1-equivalent sweep angles ``(..., 2)`` → LH2 light-plane angles (inverse of
    :func:`lh2_to_lh1_angles`); NaN stays NaN."""
    return lh2_sweep_angles(angles_to_ray(theta), tilt_rad)


# ------------------------------------------------------------------------------ calibration
# The station calibration model (docs/calibration.md has the derivation and the mapping of the
# libsurvive and Crazyflie-firmware conventions onto it). Everything below is in this package's
# station frame (z = boresight) and angle conventions (LH1: theta in (0, pi), 90° on boresight;
# LH2: light-plane angles, 0 on boresight).

#: Per-axis calibration parameter order of :attr:`Calibration.params` (radians, curve in rad/rad²).
CALIBRATION_PARAMS = ("phase", "tilt", "curve", "gib_phase", "gib_mag", "ogee_phase", "ogee_mag")
N_CAL = len(CALIBRATION_PARAMS)
#: Parameters each model uses (LH1 has no ogee term in either public model).
MODEL_PARAMS = {"lh1": CALIBRATION_PARAMS[:5], "lh2": CALIBRATION_PARAMS}
GIB_ARGUMENTS = ("ideal", "corrected")
# libsurvive survive_reproject_gen2.c calc_cal_series: the LH2 curve polynomial
# P(s) = f0 s^5 + f1 s^4 + f2 s^3 + f3 s^2 (its f[4], f[5] are zero) and its derivative.
_LH2_CURVE_SERIES = (-8.0108022e-06, 0.0028679863, 5.3685255000000001e-06, 0.0076069798000000001)


@dataclass(frozen=True, eq=False)
class Calibration:
    """Factory (or self-) calibration of one station, in this package's one internal model.

    params : (2, 7) float, rows = axis (LH1: x sweep, y sweep; LH2: plane 0 (t = -30°), plane 1
        (t = +30°)), columns :data:`CALIBRATION_PARAMS` (rad; curve rad per rad²).
    kind : "lh1" or "lh2".
    gib_argument : where the gib sinusoid is evaluated — "ideal" (the ideal angle; LH2: the ideal
        azimuth; Crazyflie firmware) or "corrected" (after phase and tilt; LH2 after tilt and curve;
        libsurvive). The two public models differ here by ~gib_mag × phase, too much to ignore.

    Forward model per axis (docs/calibration.md §2), LH1 x axis with ``p = (x, y, z)``:
    ``theta' = theta + phase + asin(tan(tilt) y / sqrt(x² + z²)) + curve atan2(y, z)²
    + gib_mag sin(xi + gib_phase)``; the y axis swaps x and y. LH2 plane i, ``t_i = ∓30°``:
    ``beta = atan2(x, z) + asin(A2)`` with ``A2`` libsurvive's curve/ogee-corrected
    ``tan(t_i - tilt) y / sqrt(x² + z²)``, ``alpha' = beta + phase + gib_mag sin(xi + gib_phase)``.
    """

    params: np.ndarray = field(default_factory=lambda: np.zeros((2, N_CAL)))
    kind: str = "lh1"
    gib_argument: str = "ideal"

    def __post_init__(self):
        p = as_array(self.params, "Calibration.params", (2, N_CAL)).copy()
        check_finite(p, "Calibration.params")
        if self.kind not in MODEL_PARAMS:
            raise ValueError(f"Calibration.kind: expected 'lh1' or 'lh2', got {self.kind!r}")
        if self.gib_argument not in GIB_ARGUMENTS:
            raise ValueError(f"Calibration.gib_argument: expected one of {GIB_ARGUMENTS}, got {self.gib_argument!r}")
        p.setflags(write=False)
        object.__setattr__(self, "params", p)

    @classmethod
    def zero(cls, kind: str = "lh1", gib_argument: str = "ideal") -> "Calibration":
        """The ideal station (all parameters zero)."""
        return cls(np.zeros((2, N_CAL)), kind, gib_argument)

    def replace(self, params) -> "Calibration":
        """The same model with other parameter values ``(2, 7)``."""
        return Calibration(params, self.kind, self.gib_argument)

    def to_dict(self) -> dict:
        """JSON-ready dict: ``{"convention": "layoutkit", kind, gib_argument, <name>: [axis0, axis1]}``."""
        d = {"convention": "layoutkit", "kind": self.kind, "gib_argument": self.gib_argument}
        for j, name in enumerate(CALIBRATION_PARAMS):
            d[name] = [float(self.params[0, j]), float(self.params[1, j])]
        return d


def measure(points_lh, calib: "Calibration | None" = None, kind: str | None = None) -> np.ndarray:
    """Calibrated (distorted) angles of points in the station frame: the forward model.

    The angles a station of the given kind reports for points in its frame, with its calibration's
    per-axis terms (phase, tilt, curve, gib, ogee; docs/calibration.md §2). Solvers minimise
    residuals against it (:mod:`layoutkit.joint`); they never pre-correct the measurements.

    Args:
        points_lh: (..., n, 3) float, m — points in the station frame (z = boresight, Chen eq. 2).
        calib: :class:`Calibration` or None (ideal station).
        kind: ``"lh1"`` or ``"lh2"`` for an ideal station (default LH1); must equal
            ``calib.kind`` when both are given (else ``ValueError``).

    Returns:
        (..., n, 2) float, rad: LH1 sweep angles ``[theta_x', theta_y']`` (as :func:`sweep_angles`
        when ideal, in (0, pi) for z > 0), or LH2 light-plane angles (as :func:`lh2_sweep_angles`
        when ideal).

    Example (ideal LH1: the sweep angles; a point on the boresight is at 90° on both axes):

    >>> import numpy as np
    >>> p = np.array([[0.0, 0.0, 2.0], [0.3, -0.2, 2.0]])
    >>> np.degrees(measure(p)[0]).tolist()
    [90.0, 90.0]
    >>> bool(np.allclose(measure(p), sweep_angles(p)))
    True
    >>> measure(p, Calibration.zero("lh2")).shape  # LH2: two light-plane angles per point
    (2, 2)
    """
    return measure_jacobian(points_lh, calib, kind, jacobian=False)[0]


def measure_jacobian(points_lh, calib: "Calibration | None" = None, kind: str | None = None, *,
                     jacobian: bool = True):
    """Forward model and its analytic Jacobians.

    Returns ``(angles (..., n, 2), d_point (..., n, 2, 3), d_params (..., n, 2, 7))``: the
    derivative of each angle with respect to the point in the station frame (rad/m) and with
    respect to its own axis' parameters (row ``k`` of ``d_params`` belongs to ``params[k]``;
    the other axis' parameters do not enter). With ``jacobian=False`` the two Jacobians are None.
    Forward-mode differentiation of the closed form (docs/calibration.md §2); the tests check
    both against central finite differences.
    """
    p = as_array(points_lh, "points_lh", (..., 3))
    if calib is None:
        calib = Calibration.zero(kind or "lh1")
    elif kind is not None and kind != calib.kind:
        raise ValueError(f"kind {kind!r} differs from the calibration's kind {calib.kind!r}")
    fn = _lh1_axis if calib.kind == "lh1" else _lh2_axis
    corrected = calib.gib_argument == "corrected"
    ang, dp, dc = [], [], []
    for k in (0, 1):
        a, g = fn(p, k, calib.params[k], corrected, jacobian)
        ang.append(a)
        if jacobian:
            dp.append(g[..., :3])
            dc.append(g[..., 3:])
    angles = np.stack(ang, -1)
    if not jacobian:
        return angles, None, None
    return angles, np.stack(dp, -2), np.stack(dc, -2)


# Forward-mode helpers: a value ``v (...)`` travels with its gradient ``dv (..., 10)`` over the
# inputs (x, y, z, phase, tilt, curve, gib_phase, gib_mag, ogee_phase, ogee_mag).
def _unit(shape, i, on):
    if not on:
        return None
    d = np.zeros(shape + (3 + N_CAL,))
    d[..., i] = 1.0
    return d


def _d_atan2(a, da, b, db):
    """atan2(a, b) and its gradient."""
    v = np.arctan2(a, b)
    if da is None:
        return v, None
    return v, (b[..., None] * da - a[..., None] * db) / (a * a + b * b)[..., None]


def _d_asin_clip(u, du):
    """asin(clip(u, -1, 1)) and its gradient (zero where clipped)."""
    uc = np.clip(u, -1.0, 1.0)
    v = np.arcsin(uc)
    if du is None:
        return v, None
    inside = np.abs(u) < 1.0
    w = np.where(inside, 1.0 / np.sqrt(np.where(inside, 1.0 - uc * uc, 1.0)), 0.0)
    return v, w[..., None] * du


def _gib(base, dbase, xi, dxi, c, on):
    """``base + gib_mag sin(xi + gib_phase)`` and its gradient."""
    arg = xi + c[3]
    v = base + c[4] * np.sin(arg)
    if not on:
        return v, None
    d = dbase + (c[4] * np.cos(arg))[..., None] * dxi
    d[..., 3 + 3] += c[4] * np.cos(arg)
    d[..., 3 + 4] += np.sin(arg)
    return v, d


def _lh1_axis(p, k, c, corrected, on):
    """LH1 axis k (0: x sweep, 1: y sweep): docs/calibration.md eq. (C1)."""
    shp = p.shape[:-1]
    a, o, z = (p[..., 0], p[..., 1], p[..., 2]) if k == 0 else (p[..., 1], p[..., 0], p[..., 2])
    ia, io = (0, 1) if k == 0 else (1, 0)
    da, do, dz = _unit(shp, ia, on), _unit(shp, io, on), _unit(shp, 2, on)
    theta, dtheta = _d_atan2(z, dz, a, da)                      # ideal angle (Chen eq. 2)
    rho2 = a * a + z * z
    rho = np.sqrt(rho2)
    tt = np.tan(c[1])
    u = tt * o / rho
    du = None
    if on:
        du = tt * (do / rho[..., None] - (o / (rho2 * rho))[..., None] * (a[..., None] * da + z[..., None] * dz))
        du[..., 3 + 1] += o / rho / np.cos(c[1]) ** 2
    tilt, dtilt = _d_asin_clip(u, du)
    psi, dpsi = _d_atan2(o, do, z, dz)                          # the other axis' angle off boresight
    corr = theta + c[0] + tilt
    dcorr = None
    if on:
        dcorr = dtheta + dtilt
        dcorr[..., 3 + 0] += 1.0
    base = corr + c[2] * psi * psi
    dbase = None
    if on:
        dbase = dcorr + (2.0 * c[2] * psi)[..., None] * dpsi
        dbase[..., 3 + 2] += psi * psi
    xi, dxi = (corr, dcorr) if corrected else (theta, dtheta)
    return _gib(base, dbase, xi, dxi, c, on)


def _lh2_axis(p, k, c, corrected, on):
    """LH2 plane k (0: t = -30°, 1: t = +30°): docs/calibration.md eq. (C2)."""
    shp = p.shape[:-1]
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    dx, dy, dz = _unit(shp, 0, on), _unit(shp, 1, on), _unit(shp, 2, on)
    t = (-LH2_TILT_RAD, LH2_TILT_RAD)[k] - c[1]                  # plane tilt t_k - tilt
    az, daz = _d_atan2(x, dx, z, dz)                             # ideal azimuth
    rho2 = x * x + z * z
    rho = np.sqrt(rho2)
    r3 = np.sqrt(rho2 + y * y)
    tn, ct, st = np.tan(t), np.cos(t), np.sin(t)
    A1 = tn * y / rho
    dA1 = None
    if on:
        dA1 = tn * (dy / rho[..., None] - (y / (rho2 * rho))[..., None] * (x[..., None] * dx + z[..., None] * dz))
        dA1[..., 3 + 1] -= y / rho / ct ** 2                     # d/dtilt: dt = -dtilt
    s1, ds1 = _d_asin_clip(A1, dA1)
    alpha1 = az + s1                                             # tilt-only plane angle
    # curve and ogee: K = curve + ogee_mag cos(alpha1 - ogee_phase)
    og = alpha1 - c[5]
    K = c[2] + c[6] * np.cos(og)
    # s = asin(-y / (|p| cos t)), P(s), P'(s)
    w = -y / (r3 * ct)
    dw = None
    if on:
        dK = -(c[6] * np.sin(og))[..., None] * (daz + ds1)
        dK[..., 3 + 2] += 1.0
        dK[..., 3 + 5] += c[6] * np.sin(og)
        dK[..., 3 + 6] += np.cos(og)
        dr3 = (x[..., None] * dx + y[..., None] * dy + z[..., None] * dz) / r3[..., None]
        dw = -dy / (r3 * ct)[..., None] + (y / (r3 * r3 * ct))[..., None] * dr3
        dw[..., 3 + 1] += -y / r3 * (-st / ct ** 2)              # d(1/cos t)/dtilt = -sin t / cos² t
    s, ds = _d_asin_clip(w, dw)
    f0, f1, f2, f3 = _LH2_CURVE_SERIES
    P = ((((f0 * s + f1) * s + f2) * s + f3) * s) * s
    dP = (((5 * f0 * s + 4 * f1) * s + 3 * f2) * s + 2 * f3) * s
    ddP = ((20 * f0 * s + 12 * f1) * s + 6 * f2) * s + 2 * f3
    den = ct + dP * K * st
    A2 = np.clip(A1, -1.0, 1.0) + P * K / den
    dA2 = None
    if on:
        dden = (dP * st)[..., None] * dK + (K * st)[..., None] * (ddP[..., None] * ds)
        dden[..., 3 + 1] += -st * -1.0 + dP * K * ct * -1.0       # d ct/dtilt = sin t, d st/dtilt = -cos t
        dA2 = (np.where(np.abs(A1) < 1.0, 1.0, 0.0)[..., None] * dA1 + ((K / den)[..., None] * (dP[..., None] * ds) + (P / den)[..., None] * dK
                      - (P * K / den ** 2)[..., None] * dden))
    s2, ds2 = _d_asin_clip(A2, dA2)
    beta = az + s2
    dbeta = None
    if on:
        dbeta = daz + ds2
    base = beta + c[0]
    dbase = None
    if on:
        dbase = dbeta.copy()
        dbase[..., 3 + 0] += 1.0
    xi, dxi = (beta, dbeta) if corrected else (az, daz)
    return _gib(base, dbase, xi, dxi, c, on)


def distort(ideal_angles, calib: Calibration) -> np.ndarray:
    """Ideal angles ``(..., 2)`` (this package's convention for ``calib.kind``) → measured angles.

    The ray is rebuilt from the ideal angles (LH1: ``(cot theta_x, cot theta_y, 1)``, Chen eq. 2;
    LH2: the inverse of :func:`lh2_sweep_angles`) and passed through :func:`measure`.
    """
    a = np.asarray(ideal_angles, float)
    th = a if calib.kind == "lh1" else lh2_to_lh1_angles(a)
    return measure(angles_to_ray(th)[..., None, :], calib)[..., 0, :]


def undistort(measured, calib: Calibration, *, max_iterations: int = 5, tol: float = 5e-4) -> np.ndarray:
    """Measured angles ``(..., 2)`` → ideal angles by fixed-point iteration (the firmware's inverse).

    ``est <- est + (measured - distort(est))`` from ``est = measured``, stopping after
    ``max_iterations`` steps or once every step is below ``tol`` rad (Crazyflie
    ``lighthouse_calibration.c``: 5 steps, 5e-4 rad). The residual error after stopping is about
    the last step times the contraction factor (~|d distortion / d angle|, ~0.02 for factory
    parameters). Prefer solving through :func:`measure`; this exists for angle-space outputs.
    """
    raw = np.asarray(measured, float)
    est = raw.copy()
    active = np.ones(raw.shape[:-1], bool)      # per sample, as the firmware stops per sample
    for _ in range(int(max_iterations)):
        if not np.any(active):
            break
        d = raw[active] - distort(est[active], calib)
        est[active] = est[active] + d
        active[active] = np.any(~(np.abs(d) < tol), -1)
    return est


def to_sweep_angles(measured, kind: str, calibration: Calibration | None = None, *, max_iterations: int = 20,
                    tol: float = 1e-9) -> np.ndarray:
    """A station's angles ``(..., 2)`` rad in its own convention (``kind`` "lh1": sweep angles,
    "lh2": light-plane angles) → LH1-equivalent sweep angles ``[theta_x, theta_y]``; with a
    ``calibration``, the ideal ones.

    The one path from what a decoder measures to what the ideal PnP fits: the calibration's
    fixed-point inverse (:func:`undistort`, to ``tol`` or ``max_iterations`` steps; the firmware's
    own is 5 steps / 5e-4 rad) when ``calibration`` is given, then for LH2 the light planes → sweep
    angles (:func:`lh2_to_lh1_angles`). NaN (a sensor not seen) stays NaN.
    """
    a = np.asarray(measured, float)
    if calibration is not None:
        with np.errstate(invalid="ignore"):
            a = undistort(a, calibration, max_iterations=max_iterations, tol=tol)
    return lh2_to_lh1_angles(a) if kind == "lh2" else a


# -------------------------------------------------------------- the two public conventions
# docs/calibration.md §3 derives each line. Angles: libsurvive LH1 a_ls = theta - pi/2, LH2
# a_ls = -alpha; Crazyflie LH1 a_cf = pi/2 - theta, LH2 a_cf = alpha. Frames: libsurvive
# lighthouse frame = ours turned by diag(1, -1, -1); Bitcraze station frame x_bc = z, y_bc = x,
# z_bc = y.

# accepted spellings: the recording's fcal* keys and BaseStationCal's field names
LIBSURVIVE_KEYS = {"phase": ("fcalphase",), "tilt": ("fcaltilt",), "curve": ("fcalcurve",),
                   "gib_phase": ("fcalgibpha", "gibpha"), "gib_mag": ("fcalgibmag", "gibmag"),
                   "ogee_phase": ("fcalogeephase", "ogeephase"), "ogee_mag": ("fcalogeemag", "ogeemag")}
CRAZYFLIE_KEYS = {"phase": "phase", "tilt": "tilt", "curve": "curve", "gib_phase": "gibphase",
                  "gib_mag": "gibmag", "ogee_phase": "ogeephase", "ogee_mag": "ogeemag"}


def calibration_from_libsurvive(values: dict, kind: str) -> Calibration:
    """libsurvive factory calibration (``BaseStationCal``: ``{name: [axis0, axis1]}`` with the
    names of :data:`CALIBRATION_PARAMS` or the recording's ``fcal*`` keys) → :class:`Calibration`.

    LH1 (``survive_reproject.c``): phase -phase, tilt ±atan(tilt) (x: +, y: -), curve, gib_phase
    gibpha - pi/2, gib_mag gibmag; gib on the corrected angle. LH2 (``survive_reproject_gen2.c``):
    phase, tilt, curve, ogee as given, gib_phase -gibpha - pi/2; gib on the corrected angle.
    """
    v = _per_axis(values, LIBSURVIVE_KEYS, "libsurvive calibration")
    out = np.zeros((2, N_CAL))
    ip = {n: j for j, n in enumerate(CALIBRATION_PARAMS)}
    for k in (0, 1):
        if kind == "lh1":
            out[k, ip["phase"]] = -v["phase"][k]
            out[k, ip["tilt"]] = (1.0 if k == 0 else -1.0) * np.arctan(v["tilt"][k])
            out[k, ip["curve"]] = v["curve"][k]
            out[k, ip["gib_phase"]] = v["gib_phase"][k] - np.pi / 2
            out[k, ip["gib_mag"]] = v["gib_mag"][k]
        elif kind == "lh2":
            out[k, ip["phase"]] = v["phase"][k]
            out[k, ip["tilt"]] = v["tilt"][k]
            out[k, ip["curve"]] = v["curve"][k]
            out[k, ip["gib_phase"]] = -v["gib_phase"][k] - np.pi / 2
            out[k, ip["gib_mag"]] = v["gib_mag"][k]
            out[k, ip["ogee_phase"]] = v["ogee_phase"][k]
            out[k, ip["ogee_mag"]] = v["ogee_mag"][k]
        else:
            raise ValueError(f"kind: expected 'lh1' or 'lh2', got {kind!r}")
    return Calibration(out, kind, "corrected")


def calibration_from_crazyflie(sweeps, kind: str) -> Calibration:
    """Crazyflie firmware calibration (two sweeps, each a mapping or :class:`SweepCalibration`
    with ``phase, tilt, curve, gibmag, gibphase, ogeemag, ogeephase``) → :class:`Calibration`.

    LH1 (``lighthouseCalibrationMeasurementModelLh1``): phase, tilt (sweep 1: -tilt), curve,
    gib_phase -gibphase - pi/2, gib_mag; LH2 (``...Lh2``): phase -phase, tilt, gib_phase
    gibphase + pi/2, gib_mag; curve and ogee are not used by the firmware and are set to 0.
    The gib term is evaluated on the ideal angle (LH2: ideal azimuth).
    """
    sw = list(sweeps)
    if len(sw) < 2:
        raise ValueError("Crazyflie calibration: two sweeps required")
    get = lambda s, n: float(getattr(s, n) if not isinstance(s, dict) else s.get(n, 0.0))  # noqa: E731
    out = np.zeros((2, N_CAL))
    ip = {n: j for j, n in enumerate(CALIBRATION_PARAMS)}
    for k in (0, 1):
        s = sw[k]
        ph, ti, cu, gm, gp = (get(s, n) for n in ("phase", "tilt", "curve", "gibmag", "gibphase"))
        if kind == "lh1":
            out[k, ip["phase"]], out[k, ip["tilt"]], out[k, ip["curve"]] = ph, (ti if k == 0 else -ti), cu
            out[k, ip["gib_phase"]], out[k, ip["gib_mag"]] = -gp - np.pi / 2, gm
        elif kind == "lh2":
            out[k, ip["phase"]], out[k, ip["tilt"]] = -ph, ti
            out[k, ip["gib_phase"]], out[k, ip["gib_mag"]] = gp + np.pi / 2, gm
        else:
            raise ValueError(f"kind: expected 'lh1' or 'lh2', got {kind!r}")
    return Calibration(out, kind, "ideal")


def calibration_from_dict(d: dict, kind: str | None = None, *, what: str = "calibration") -> Calibration:
    """A stations-file ``calibration`` entry → :class:`Calibration`.

    ``convention``: "layoutkit" (this model's parameters, :meth:`Calibration.to_dict`),
    "libsurvive" (default when ``fcal*`` keys are present) or "crazyflie" (``sweeps: [{...}, {...}]``).
    ``kind`` ("lh1"/"lh2") comes from the entry or the station. Raises ValueError naming ``what``.
    """
    if not isinstance(d, dict):
        raise ValueError(f"{what}: expected an object, got {type(d).__name__}")
    conv = d.get("convention")
    if conv is None:
        conv = ("crazyflie" if "sweeps" in d else
                "libsurvive" if any(k.startswith("fcal") or k in ("gibpha", "gibmag") for k in d) else "layoutkit")
    kind = d.get("kind", kind) or "lh1"
    try:
        if conv == "layoutkit":
            v = _per_axis(d, {n: n for n in CALIBRATION_PARAMS}, what)
            params = np.array([[v[n][k] for n in CALIBRATION_PARAMS] for k in (0, 1)])
            return Calibration(params, kind, d.get("gib_argument", "ideal"))
        if conv == "libsurvive":
            return calibration_from_libsurvive(d, kind)
        if conv == "crazyflie":
            return calibration_from_crazyflie(d["sweeps"], kind)
    except (KeyError, TypeError) as exc:
        raise ValueError(f"{what}: bad entry ({exc})") from None
    raise ValueError(f"{what}.convention: expected 'layoutkit', 'libsurvive' or 'crazyflie', got {conv!r}")


def _per_axis(values: dict, keys: dict, what: str) -> dict:
    """``{name: (axis0, axis1)}`` from a dict keyed by ``name`` or by ``keys[name]`` (missing → 0)."""
    out = {}
    for name, alts in keys.items():
        raw = values.get(name, (0.0, 0.0))
        for alt in ((alts,) if isinstance(alts, str) else alts):
            if name not in values and alt in values:
                raw = values[alt]
        try:
            pair = [float(x) for x in (raw if isinstance(raw, (list, tuple, np.ndarray)) else [raw, raw])]
        except (TypeError, ValueError):
            raise ValueError(f"{what}.{name}: expected two numbers, got {raw!r}") from None
        if len(pair) != 2 or not all(np.isfinite(pair)):
            raise ValueError(f"{what}.{name}: expected two finite numbers, got {raw!r}")
        out[name] = pair
    return out


# Crazyflie firmware records and angle API (moved from live/protocols/bitcraze.py; the decoder
# and the system-config reader use them through re-exports there).
@dataclass(frozen=True)
class SweepCalibration:
    """Factory calibration of one sweep / light plane as the Crazyflie firmware stores it (rad)."""

    phase: float = 0.0
    tilt: float = 0.0
    curve: float = 0.0
    gibmag: float = 0.0
    gibphase: float = 0.0
    ogeemag: float = 0.0
    ogeephase: float = 0.0


@dataclass(frozen=True)
class StationCalibration:
    """The two sweeps' :class:`SweepCalibration` of one station and its OOTX ``uid``."""

    sweeps: tuple = (SweepCalibration(), SweepCalibration())
    uid: int = 0

    def to_calibration(self, kind: str) -> Calibration:
        """This record in the internal model (:func:`calibration_from_crazyflie`)."""
        return calibration_from_crazyflie(self.sweeps, kind)


def _as_calibration(calib, kind) -> Calibration:
    return calib if isinstance(calib, Calibration) else calibration_from_crazyflie(calib.sweeps, kind)


def lh1_model(ax_ideal, ay_ideal, calib) -> np.ndarray:
    """Firmware LH1 distortion in the firmware's angles ``a = pi/2 - theta``: ideal → measured ``(..., 2)``.

    calib : :class:`StationCalibration` (firmware convention) or :class:`Calibration`.
    """
    a = np.stack([np.asarray(ax_ideal, float), np.asarray(ay_ideal, float)], -1)
    return np.pi / 2 - distort(np.pi / 2 - a, _as_calibration(calib, "lh1"))


def lh2_model(a1_ideal, a2_ideal, calib) -> np.ndarray:
    """Firmware LH2 distortion of light-plane angles (same convention as ours): ideal → measured."""
    a = np.stack([np.asarray(a1_ideal, float), np.asarray(a2_ideal, float)], -1)
    return distort(a, _as_calibration(calib, "lh2"))


def calibrate_lh1(raw, calib, *, max_iterations: int = 50, tol: float = 1e-10) -> np.ndarray:
    """Measured LH1 firmware angles ``(..., 2)`` → ideal (inverse of :func:`lh1_model`).

    Iterates to 1e-10 rad by default (the firmware stops at 5e-4 rad or 5 steps: pass
    ``max_iterations=5, tol=5e-4`` to reproduce it).
    """
    th = undistort(np.pi / 2 - np.asarray(raw, float), _as_calibration(calib, "lh1"),
                   max_iterations=max_iterations, tol=tol)
    return np.pi / 2 - th


def calibrate_lh2(raw, calib, *, max_iterations: int = 50, tol: float = 1e-10) -> np.ndarray:
    """Measured LH2 plane angles ``(..., 2)`` → ideal (inverse of :func:`lh2_model`)."""
    return undistort(raw, _as_calibration(calib, "lh2"), max_iterations=max_iterations, tol=tol)
