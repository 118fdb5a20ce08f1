"""Rotation averaging and the fixed rotations between two attitude streams (one core for every
alignment in layoutkit: motion-capture references, camera cross-checks, calibration).

Two streams observe the same rigid target: ``R_a(t) ≈ X R_b(t) Y`` with fixed ``X`` (frame of
stream a ← frame of stream b, e.g. camera ← lighthouse) and ``Y`` (target frame of b ← target
frame of a, e.g. body ← camera face). Estimation, after the hand-eye literature:

1. ``X`` from relative motions (``Y`` cancels): ``log(R_a,j R_a,i^T) = X log(R_b,j R_b,i^T)``,
   a Wahba problem on rotation-vector pairs (Kabsch / :func:`wahba`); needs motion about at least
   two axes, else ``X`` is not observable (status ``"degenerate_rotation"``).
2. ``Y`` as the chordal L2 mean (:func:`chordal_mean`) of ``R_b^T X^T R_a``, then Gauss-Newton on
   the geodesic residuals ``log(R_a^T X R_b Y)`` over both (minimum-norm steps: with too little
   motion the split between X and Y is a gauge the data cannot see, and the residual is still
   minimised).
3. Optional outlier round: pairs whose residual exceeds ``outlier_factor`` × the median are
   dropped and the means recomputed once.

Without a body offset (``Y = I``) step 2 alone is the chordal mean, and no motion is needed.
Failures are statuses, never exceptions.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import attitude_error, ensure_rotation, matrix_to_rotvec, nearest_rotation

__all__ = ["chordal_mean", "wahba", "relative_rotvec_pairs", "RotationPairFit", "fit_rotation_pair",
           "quaternion_to_matrix", "matrix_to_quaternion"]


def quaternion_to_matrix(q, *, scalar_first: bool = False) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` → rotation matrices ``(..., 3, 3)`` (active, ``p' = R p``).

    The one place that knows quaternion component orders: ``[x, y, z, w]`` (scipy, the filter,
    ``qx,qy,qz,qw`` CSV columns) or, with ``scalar_first``, ``[w, x, y, z]`` (libsurvive). Every
    row must have a non-zero norm (it is normalised).
    """
    from scipy.spatial.transform import Rotation

    q = np.asarray(q, float)
    R = Rotation.from_quat(q.reshape(-1, 4), scalar_first=scalar_first).as_matrix()
    return R.reshape(q.shape[:-1] + (3, 3))


def matrix_to_quaternion(R, *, scalar_first: bool = False) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` → unit quaternions ``(..., 4)`` with a non-negative scalar
    part, in the order of :func:`quaternion_to_matrix` (``[x, y, z, w]``, or ``[w, x, y, z]`` with
    ``scalar_first``)."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, float)
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()
    q = np.where(q[:, 3:] < 0, -q, q)
    if scalar_first:
        q = q[:, [3, 0, 1, 2]]
    return q.reshape(R.shape[:-2] + (4,))


def chordal_mean(rotations, weights=None) -> np.ndarray:
    """Chordal L2 mean of rotations ``(N, 3, 3)``: the rotation nearest their (weighted) sum."""
    M = np.asarray(rotations, float)
    if weights is not None:
        M = M * np.asarray(weights, float)[:, None, None]
    return nearest_rotation(np.sum(M, axis=0))


def wahba(a, b) -> np.ndarray:
    """Rotation ``X`` minimising ``sum |a_i - X b_i|^2`` for vectors ``a, b (N, 3)`` (Kabsch)."""
    H = np.asarray(a, float).T @ np.asarray(b, float)
    return nearest_rotation(H)


def relative_rotvec_pairs(R_a, R_b, *, min_angle: float = np.deg2rad(5.0), max_angle: float = np.deg2rad(170.0),
                          lags=None, valid: bool = False):
    """Rotation vectors of relative motions ``R_j R_i^T`` of both streams over several index lags.

    Returns ``(a (M, 3), b (M, 3))`` with the pairs whose stream-b angle lies in
    ``[min_angle, max_angle]`` (small motions are noise, near-180° ones are ill-conditioned).
    valid : both streams are proper rotations to rounding (see :func:`layoutkit.geometry.matrix_to_rotvec`).
    """
    N = len(R_a)
    if lags is None:
        lags = np.unique(np.clip(np.geomspace(1, max(N // 2, 1), 6).astype(int), 1, max(N - 1, 1)))
    aa, bb = [], []
    for lag in lags:
        if lag >= N:
            continue
        a = matrix_to_rotvec(R_a[lag:] @ np.swapaxes(R_a[:-lag], -1, -2), assume_valid=valid)
        b = matrix_to_rotvec(R_b[lag:] @ np.swapaxes(R_b[:-lag], -1, -2), assume_valid=valid)
        ang = np.linalg.norm(b, axis=-1)
        ok = (ang >= min_angle) & (ang <= max_angle)
        aa.append(a[ok])
        bb.append(b[ok])
    if not aa:
        return np.zeros((0, 3)), np.zeros((0, 3))
    return np.concatenate(aa), np.concatenate(bb)


@dataclass(frozen=True)
class RotationPairFit:
    """Result of :func:`fit_rotation_pair`: ``R_a ≈ X R_b Y``.

    X, Y : (3, 3). residual_rad : (N,) attitude error of ``R_a`` vs ``X R_b Y`` per pair.
    inlier : (N,) bool, pairs used in the final means. success, status ("ok", "too_few_samples",
    "degenerate_rotation"), message. cov : (6, 6) (or (3, 3) without a body offset) covariance of
    the small-angle errors of (X, Y), rad², from the Gauss-Newton normal matrix and the residual
    scatter — large where the motion does not separate X from Y.
    """

    X: np.ndarray
    Y: np.ndarray
    residual_rad: np.ndarray
    inlier: np.ndarray
    success: bool
    status: str
    message: str
    cov: np.ndarray | None = None

    @property
    def X_sigma_rad(self) -> float:
        """1-sigma attitude uncertainty of X, rad (sqrt of the trace of its block)."""
        return float(np.sqrt(np.trace(self.cov[:3, :3]))) if self.cov is not None else float("nan")

    @property
    def Y_sigma_rad(self) -> float:
        """1-sigma attitude uncertainty of Y, rad (NaN without a body offset)."""
        if self.cov is None or self.cov.shape[0] < 6:
            return float("nan")
        return float(np.sqrt(np.trace(self.cov[3:, 3:])))

    @property
    def rms_rad(self) -> float:
        d = self.residual_rad[self.inlier]
        return float(np.sqrt(np.mean(d ** 2))) if d.size else float("nan")


def _gauss_newton(Ra, Rb, X, Y, body_offset: bool, iterations: int):
    """Minimise ``sum |log(Ra_i^T X Rb_i Y)|^2`` over X (and Y) from a start, by Gauss-Newton.

    With ``X <- exp([dx]) X`` and ``Y <- Y exp([dy])`` the residual is, to first order,
    ``e_i + Ra_i^T dx + dy`` (``e_i = log(Ra_i^T X Rb_i Y)``): a linear least-squares step in
    ``(dx, dy)``; the minimum-norm step handles the gauge that too little motion leaves free.
    """
    from .geometry import rotvec_to_matrix

    N = len(Ra)
    RaT = np.swapaxes(Ra, -1, -2)
    if body_offset:
        J = np.concatenate([RaT, np.broadcast_to(np.eye(3), (N, 3, 3))], axis=-1).reshape(3 * N, 6)
    else:
        J = RaT.reshape(3 * N, 3)
    # J depends on Ra only: its pseudo-inverse (the minimum-norm least-squares solution, singular values
    # below 1e-9 of the largest cut, as lstsq's rcond) is computed once, each step is one product
    J_pinv = np.linalg.pinv(J, rcond=1e-9)
    for _ in range(max(iterations, 1)):
        e = matrix_to_rotvec(RaT @ X @ Rb @ Y, assume_valid=True)  # (N, 3); rotations (fit_rotation_pair)
        step = -(J_pinv @ e.reshape(3 * N))
        E = rotvec_to_matrix(step.reshape(-1, 3))  # both updates in one call
        X = E[0] @ X
        if body_offset:
            Y = Y @ E[1]
        if np.linalg.norm(step) < 1e-12:
            break
    return X, Y


def fit_rotation_pair(R_a, R_b, *, body_offset: bool = True, outlier_factor: float | None = 5.0,
                      iterations: int = 10, min_pair_angle: float = np.deg2rad(5.0),
                      require_motion: bool | None = None) -> RotationPairFit:
    """Fixed rotations between time-matched attitude pairs ``R_a, R_b (N, 3, 3)`` (module docstring).

    body_offset : also estimate ``Y`` (else ``Y = I``). outlier_factor : None = no outlier round.
    require_motion : insist on relative motion about two axes before fitting (default: when
    ``body_offset``); without it and without motion, ``X`` starts from the chordal mean.
    """
    # proper rotations from here on (matrices off by more than rounding are projected once), so the
    # solver's many log maps may skip scipy's per-call orthonormalisation
    Ra = ensure_rotation(R_a)
    Rb = ensure_rotation(R_b)
    eye = np.eye(3)
    N = len(Ra)

    def fail(status, msg):
        return RotationPairFit(eye, eye, np.zeros(N), np.zeros(N, bool), False, status, msg)

    if N < (3 if body_offset else 1):
        return fail("too_few_samples", f"need >= {3 if body_offset else 1} time-matched pairs, got {N}")
    require_motion = body_offset if require_motion is None else require_motion
    X, Y = eye, eye
    if body_offset or require_motion:
        a, b = relative_rotvec_pairs(Ra, Rb, min_angle=min_pair_angle, valid=True)
        two_axes = False
        if len(b) >= 2:
            sv = np.linalg.svd(b, compute_uv=False)
            two_axes = sv[1] > 1e-3 * sv[0]
        if two_axes:
            X = wahba(a, b)  # a ≈ X b
        elif require_motion:
            return fail("degenerate_rotation",
                        "the motion turns about fewer than two axes: the fixed rotations are not observable")
        elif body_offset:
            # too little motion to separate X from Y: start from Y = I (X takes the whole offset;
            # the pair is then determined up to the gauge the data cannot see)
            X = chordal_mean(Ra @ np.swapaxes(Rb, -1, -2))
    if body_offset:
        Y = chordal_mean(np.swapaxes(Rb, -1, -2) @ X.T @ Ra)
    inl = np.ones(N, bool)
    rounds = 2 if outlier_factor is not None else 1
    for rnd in range(rounds):
        X, Y = _gauss_newton(Ra[inl], Rb[inl], X, Y, body_offset, iterations)
        d = attitude_error(Ra, X @ Rb @ Y)
        if rnd == 0 and rounds == 2:
            inl = d <= max(outlier_factor * float(np.median(d)), 1e-9)
    n_out = int((~inl).sum())
    cov = _fit_covariance(Ra[inl], Rb[inl], X, Y, body_offset)
    return RotationPairFit(X, Y, d, inl, True, "ok",
                           f"{N} pairs, {n_out} outliers, rms {np.degrees(np.sqrt(np.mean(d[inl] ** 2))):.3g} deg",
                           cov)


def _fit_covariance(Ra, Rb, X, Y, body_offset):
    N = len(Ra)
    RaT = np.swapaxes(Ra, -1, -2)
    e = matrix_to_rotvec(RaT @ X @ Rb @ Y, assume_valid=True)
    p = 6 if body_offset else 3
    if 3 * N <= p:
        return None
    J = (np.concatenate([RaT, np.broadcast_to(np.eye(3), (N, 3, 3))], axis=-1) if body_offset else RaT).reshape(3 * N, p)
    s2 = float(np.sum(e ** 2)) / (3 * N - p)
    return s2 * np.linalg.pinv(J.T @ J, rcond=1e-12)
