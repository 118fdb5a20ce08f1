"""Angle Jacobians, pose covariance H, ADOP/PDOP, measured precision and accuracy (Chen §3, eqs. 13–25).

Perturbation convention (design §2, §5): ``R <- exp([dphi]x) R``, ``t <- t + dt``; the 6-vector is
``(dphi, dt)``, rotation block first. Per sensor, with ``p = (x, y, z)`` in the station frame:
``d theta_x / d p = (-z, 0, x) / (x² + z²)``, ``d theta_y / d p = (0, -z, y) / (y² + z²)`` and
``d p / d(dphi, dt) = [-[p - t]x, I]``. The paper's rotation-vector route (eqs. 8–14 with
``J_r``, eq. 21) gives the same ADOP/PDOP; ``tests/test_dop.py`` checks it by finite differences.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import status as _status
from ._validate import as_array, check_finite
from .geometry import attitude_error, nearest_rotation
from .lighthouse import Station, measure_jacobian
from .units import RAD2DEG

__all__ = [
    "DopResult",
    "angle_jacobian",
    "dop_from_jacobian",
    "pose_dop",
    "precision",
    "pose_errors",
    "predicted_precision",
    "gross_failures",
    "GROSS_FAILURE_DEG",
    "rms",
]

# Relative conditioning below which H is reported as singular (degenerate geometry).
_RCOND = 1e-12


@dataclass(frozen=True)
class DopResult:
    """ADOP/PDOP of a batch of poses.

    adop : (...,) float, deg of attitude per rad of angle noise (Chen eq. 22); inf where singular.
    pdop : (...,) float, m of position per rad of angle noise; inf where singular.
    cov : (..., 6, 6) float, H of eq. (18) in (dphi rad, dt m) per rad², rotation block first.
    success : (...,) bool; status : (...,) int codes of :mod:`layoutkit.status` (0 ok, 1 too few lit
    sensors, 2 degenerate = singular geometry).
    n_visible : (...,) int, angle pairs used.
    """

    adop: np.ndarray
    pdop: np.ndarray
    cov: np.ndarray
    success: np.ndarray
    status: np.ndarray
    n_visible: np.ndarray

    @property
    def message(self) -> str:
        s = np.asarray(self.status)
        if np.all(s == 0):
            return "ok"
        return (f"{int(np.sum(s == 1))} pose(s) with fewer than 3 lit sensors (6 angles), "
                f"{int(np.sum(s == 2))} with singular geometry")


def angle_jacobian(points_lh, lever_world=None, station_rotation=None) -> np.ndarray:
    """Jacobian of the sweep angles with respect to the body pose perturbation ``(dphi, dt)``.

    points_lh : (..., n, 3) float, m, sensor positions in the station frame.
    lever_world : (..., n, 3) float, m, ``R_body @ p_body`` in the frame in which the pose is
        perturbed (the station frame for a single station, i.e. ``points_lh - t``).
    station_rotation : (3, 3), optional, station-to-world rotation; the pose is then perturbed in
        the world frame.
    Returns (..., n, 2, 6) float, rad per (rad, m). Chen eqs. (10)–(14) in left-perturbation form.
    """
    p = np.asarray(points_lh, dtype=float)
    if lever_world is None:
        raise ValueError("angle_jacobian: lever_world (R @ p_body) is required")
    lever = np.asarray(lever_world, dtype=float)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    dx = 1.0 / (x * x + z * z)
    dy = 1.0 / (y * y + z * z)
    # d theta / d p_station, rows (..., n, 2, 3): x row (-z, 0, x)/dx, y row (0, -z, y)/dy
    dth = np.zeros(p.shape[:-1] + (2, 3))
    dth[..., 0, 0] = -z * dx
    dth[..., 0, 2] = x * dx
    dth[..., 1, 1] = -z * dy
    dth[..., 1, 2] = y * dy
    if station_rotation is not None:
        dth = dth @ np.asarray(station_rotation, float).T  # d p_station = R_s^T d p_world
    out = np.empty(p.shape[:-1] + (2, 6))
    # d p / d dphi = -[l]x with l = R p_body; a row a^T(-[l]x) equals (l x a)^T
    lx, ly, lz = lever[..., None, 0], lever[..., None, 1], lever[..., None, 2]
    ax, ay, az = dth[..., 0], dth[..., 1], dth[..., 2]
    out[..., 0] = ly * az - lz * ay
    out[..., 1] = lz * ax - lx * az
    out[..., 2] = lx * ay - ly * ax
    out[..., 3:] = dth
    return out


def _model_jacobian(p_s, lever, station: Station) -> np.ndarray:
    """``angle_jacobian`` with ``d angle / d p_s`` from :func:`layoutkit.lighthouse.measure_jacobian`
    (the station's kind and calibration): rows ``[l x a, a]``, ``a = R_s (d angle / d p_s)``."""
    _, dp, _ = measure_jacobian(p_s, station.calibration, station.kind)
    a = dp @ station.rotation.T
    out = np.empty(a.shape[:-1] + (6,))
    out[..., :3] = np.cross(np.asarray(lever, float)[..., None, :], a)
    out[..., 3:] = a
    return out


def dop_from_jacobian(jac, rho: float = 0.0, visible=None) -> DopResult:
    """ADOP/PDOP from per-sensor angle Jacobians.

    jac : (..., S, n, 2, 6) float — S stations (rotor sweeps), n sensors, [theta_x, theta_y] rows.
    rho : same-rotor correlation (Chen eq. 19); only angles of the same station and axis correlate.
    visible : bool broadcastable to (..., S, n) (lit sensors) or exactly (..., S, n, 2) (seen
        angles: a sensor seen on one axis contributes its one row); default all.
    status 1 ("too few") when fewer than 6 angles are seen (for per-sensor masks: fewer than 3
    sensors, the same count), 2 when H is singular.
    Implements eq. (18) in closed form: with ``A = J^T J`` and ``b_{s,axis} = sum_i v_i j_{s,i,axis}``,
    ``J^T R J = (1 - rho) A + rho sum b b^T`` and ``H = A^-1 J^T R J A^-1``.
    """
    J = np.asarray(jac, dtype=float)
    if J.ndim < 4 or J.shape[-2:] != (2, 6):
        raise ValueError(f"jac: expected shape (..., S, n, 2, 6), got {J.shape}")
    v = np.ones(J.shape[:-2], bool) if visible is None else np.asarray(visible, bool)
    per_angle = v.ndim == J.ndim - 1 and v.shape[-1] == 2 and v.shape[-2] == J.shape[-3]
    try:
        v = np.broadcast_to(v, J.shape[:-1]) if per_angle else np.broadcast_to(v[..., None], J.shape[:-1])
    except ValueError:
        raise ValueError(f"visible: expected shape {J.shape[:-2]} or {J.shape[:-1]}, got {v.shape}") from None
    Jm = J * v[..., None]
    Jv = Jm.reshape(J.shape[:-4] + (-1, 6))
    A = np.swapaxes(Jv, -1, -2) @ Jv  # sum over stations, sensors, axes of j j^T
    b = Jm.sum(axis=-3).reshape(J.shape[:-4] + (-1, 6))  # (..., 2S, 6): per station and axis
    M = (1.0 - rho) * A + rho * (np.swapaxes(b, -1, -2) @ b)
    n_angles = v.sum(axis=(-1, -2, -3))
    nvis = v.any(-1).sum(axis=(-1, -2))
    singular = _singular(A)
    Asafe = np.where(singular[..., None, None], np.eye(6), A)
    Ainv = np.linalg.inv(Asafe)
    H = Ainv @ M @ Ainv  # Chen eq. (18)
    H = 0.5 * (H + np.swapaxes(H, -1, -2))
    status = np.where(n_angles < 6, _status.TOO_FEW_LIT, np.where(singular, _status.DEGENERATE, _status.OK))
    ok = status == 0
    tr_rot = np.trace(H[..., :3, :3], axis1=-2, axis2=-1)
    tr_t = np.trace(H[..., 3:, 3:], axis1=-2, axis2=-1)
    adop = np.where(ok, RAD2DEG * np.sqrt(np.maximum(tr_rot, 0)), np.inf)  # eq. (22)
    pdop = np.where(ok, np.sqrt(np.maximum(tr_t, 0)), np.inf)
    H = np.where(ok[..., None, None], H, np.nan)
    return DopResult(adop=adop, pdop=pdop, cov=H, success=ok, status=status, n_visible=nvis)


def _singular(A: np.ndarray) -> np.ndarray:
    """True where the 6×6 normal matrices ``A (..., 6, 6)`` are singular to working precision.

    Relative smallest eigenvalue below ``_RCOND``. A batched Cholesky screens the common
    well-conditioned case; only matrices it cannot vouch for go to ``eigvalsh``.
    """
    scale = np.trace(A, axis1=-2, axis2=-1)[..., None, None] / 6.0
    An = A / np.where(scale > 0, scale, 1.0)
    risky = np.ones(A.shape[:-2], bool)
    try:
        d = np.diagonal(np.linalg.cholesky(An), axis1=-2, axis2=-1) ** 2
        risky = d.min(-1) < 1e-6 * d.max(-1)
    except np.linalg.LinAlgError:
        pass
    singular = np.zeros(A.shape[:-2], bool)
    if np.any(risky):
        w = np.linalg.eigvalsh(An[risky])
        singular[risky] = w[..., 0] <= _RCOND * np.maximum(w[..., -1], 1e-300)
    return singular


def pose_dop(points_body, rotation, translation, rho: float = 0.0, visible=None,
             stations: "list[Station] | None" = None) -> DopResult:
    """ADOP/PDOP of a sensor layout at one or many poses (Chen eqs. 18–22).

    The predicted pose covariance per unit angle noise, ``H = A^-1 J^T R_theta J A^-1`` with the
    angle Jacobian ``J`` (eqs. 10–14) and the same-rotor correlation ``R_theta`` (eq. 19); ADOP and
    PDOP are the root traces of its attitude and position blocks (eq. 22). Multiply by the angle
    noise sigma (rad) for the predicted precision (:func:`predicted_precision`, eq. 24).

    Args:
        points_body: (n, 3) or (..., n, 3) float, m — sensor positions in the body frame.
        rotation: (..., 3, 3) and translation: (..., 3) m — the body pose ``p = R p_body + t`` in
            the frame of the single lighthouse (``stations=None``; z = boresight) or in the world
            frame of ``stations``.
        rho: same-rotor correlation of the angle noise, in [0, 1) (0.8717 measured in the paper).
        visible: lit sensors, (..., n) bool for one station or (..., S, n) for S stations, or with
            a trailing axis of 2 (``(..., n, 2)`` / ``(..., S, n, 2)``) per angle; default all.
        stations: optional list of :class:`layoutkit.lighthouse.Station` with poses in one world
            frame; each station's kind (LH1 sweeps / LH2 planes) and calibration enter through its
            forward model's Jacobian (:func:`layoutkit.lighthouse.measure_jacobian`).

    Returns:
        :class:`DopResult` with batch shape ``(...)``: ``adop`` deg of attitude per rad of angle
        noise, ``pdop`` m per rad, ``cov`` (..., 6, 6) H in (dphi rad, dt m) per rad² (rotation
        first, left perturbation in the station/world frame), ``status`` codes of
        :mod:`layoutkit.status` (fewer than 6 seen angles: ``too_few_lit``; singular geometry:
        ``degenerate``; both with inf DOP), ``n_visible``. Numerical degeneracy is a status, never
        an exception.

    Example (the Chen target's 12 sensors 2 m in front of one station, the paper's rho):

    >>> import numpy as np
    >>> from layoutkit.shapes import chen_target
    >>> P = chen_target()[1].positions
    >>> r = pose_dop(P, np.eye(3), [0.0, 0.0, 2.0], rho=0.8717)
    >>> r.message, r.cov.shape
    ('ok', (6, 6))
    >>> bool(np.isclose(r.adop, np.degrees(np.sqrt(np.trace(r.cov[:3, :3])))))  # Chen eq. 22
    True
    >>> pose_dop(P[:2], np.eye(3), [0.0, 0.0, 2.0]).message  # 4 angles for 6 unknowns
    '1 pose(s) with fewer than 3 lit sensors (6 angles), 0 with singular geometry'
    """
    P = as_array(points_body, "points_body", (..., None, 3))
    R = as_array(rotation, "rotation", (..., 3, 3))
    t = as_array(translation, "translation", (..., 3))
    for a, nm in ((P, "points_body"), (R, "rotation"), (t, "translation")):
        check_finite(a, nm)
    if R.shape[:-2] != t.shape[:-1]:
        raise ValueError(f"rotation {R.shape} and translation {t.shape}: batch shapes differ")
    lever = P @ np.swapaxes(R, -1, -2)  # R p_body, (..., n, 3)
    if stations is None:
        p_lh = lever + t[..., None, :]
        J = angle_jacobian(p_lh, lever)[..., None, :, :, :]
        if visible is not None:
            visible = np.asarray(visible, bool)
            per_angle = visible.ndim >= 2 and visible.shape[-1] == 2 and visible.shape[-2] == P.shape[-2] and (
                visible.ndim == R.ndim or P.shape[-2] != 2)
            visible = visible[..., None, :, :] if per_angle else visible[..., None, :]
    else:
        Js = []
        for st in stations:
            pw = lever + t[..., None, :]
            p_s = (pw - st.translation) @ st.rotation
            if st.kind == "lh1" and st.calibration is None:
                Js.append(angle_jacobian(p_s, lever, st.rotation))
            else:  # LH2 planes and calibrated stations: the forward model's own Jacobian
                Js.append(_model_jacobian(p_s, lever, st))
        J = np.stack(Js, -4)
    if visible is not None:
        visible = np.asarray(visible, bool)
        per_angle = visible.ndim == J.ndim - 1 and visible.shape[-1] == 2 and visible.shape[-2] == J.shape[-3]
        visible = np.broadcast_to(visible, J.shape[:-1] if per_angle else J.shape[:-2])
    return dop_from_jacobian(J, rho, visible)


def precision(rotations, translations):
    """Measured precision of a static group (Chen eq. 23).

    rotations : (..., N, 3, 3), translations : (..., N, 3) m.
    Returns ``(sigma_rot_rad, sigma_trans_m)`` each (...,): RMS rotation-vector norm of
    ``R_i R_mean^T`` and RMS of ``|t_i - t_mean|``. The mean rotation is the chordal mean
    (equal to the paper's mean rotation vector to second order for small spreads).
    """
    R = as_array(rotations, "rotations", (..., None, 3, 3))
    t = as_array(translations, "translations", (..., None, 3))
    # chordal mean: project the arithmetic mean of matrices onto SO(3)
    Rm = nearest_rotation(R.mean(axis=-3))
    e_rot = attitude_error(R, Rm[..., None, :, :])
    tm = t.mean(axis=-2, keepdims=True)
    e_t = np.linalg.norm(t - tm, axis=-1)
    return rms(e_rot, axis=-1), rms(e_t, axis=-1)


def predicted_precision(adop, pdop, sigma: float, axis=None):
    """Predicted RMS precision over poses (Chen eq. 24): ``sqrt(mean(ADOP²)) sigma`` and
    ``sqrt(mean(PDOP²)) sigma``.

    adop : (...,) deg per rad of angle noise; pdop : (...,) m per rad; sigma : rad (angle noise
    1-sigma); axis : the axis (or axes) averaged over (None = all). Returns ``(rot_deg, trans_m)``.
    """
    a = np.asarray(adop, dtype=float)
    p = np.asarray(pdop, dtype=float)
    return np.sqrt(np.mean(a * a, axis=axis)) * sigma, np.sqrt(np.mean(p * p, axis=axis)) * sigma


#: Attitude error above which a solve counts as a gross failure (wrong PnP basin, e.g. the planar
#: two-fold ambiguity of 4 coplanar lit sensors under noise; docs/pnp.md), reported apart.
GROSS_FAILURE_DEG = 1.0


def gross_failures(rotation_error, *, success=None, translation=None, threshold_deg: float = GROSS_FAILURE_DEG):
    """Frames that are gross failures, ``(...,)`` bool: the solve failed (``success`` False), or its
    attitude error ``rotation_error`` (rad, Chen eq. 25) exceeds ``threshold_deg``, or its
    ``translation (..., 3)`` puts the body behind the station (``t_z <= 0``)."""
    e = np.asarray(rotation_error, dtype=float)
    bad = ~(e <= np.deg2rad(threshold_deg))  # NaN errors are failures
    if success is not None:
        bad |= ~np.asarray(success, dtype=bool)
    if translation is not None:
        bad |= ~(np.asarray(translation, dtype=float)[..., 2] > 0)
    return bad


def pose_errors(rotation_est, translation_est, rotation_ref, translation_ref):
    """Accuracy against a reference (Chen eq. 25), per frame: ``(e_rot_rad, e_trans_m)``."""
    e_rot = attitude_error(rotation_est, rotation_ref)
    e_t = np.linalg.norm(np.asarray(translation_est, float) - np.asarray(translation_ref, float), axis=-1)
    return e_rot, e_t


def rms(x, axis=None):
    """Root mean square along ``axis``."""
    x = np.asarray(x, dtype=float)
    return np.sqrt(np.mean(x * x, axis=axis))
