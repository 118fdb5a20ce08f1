"""Batched perspective-n-point from lighthouse sweep angles (Chen §2, design §4).

Given the body coordinates of n sensors and their LH1 sweep angles in F frames, find per frame
the pose ``p_lh = R p_body + t`` that minimises the sum of squared **angle** residuals
``theta_meas - theta_pred`` over the lit sensors (maximum likelihood for the noise of Chen §3.3).

Method (all vectorised over frames, processed in bounded chunks):

1. Sweep angles are a pinhole camera: normalised image coordinates ``(x/z, y/z) = cot(theta)``
   (Chen eq. 2).
2. Start, non-coplanar lit sets: scaled-orthographic linear solve with perspective correction
   (POSIT, DeMenthon & Davis 1995), a few fixed-point iterations.
3. Start, coplanar / near-coplanar lit sets (or a poor first solution): the two weak-perspective
   poses of the dominant plane (the planar two-fold ambiguity, as in IPPE, Collins & Bartoli 2014),
   each corrected for perspective; both are refined and the one with the lower residual and all
   lit sensors in front of the station wins.
4. Refinement: Levenberg–Marquardt on the angle residuals with the analytic Jacobian of
   :func:`layoutkit.dop.angle_jacobian` (left perturbation ``R <- exp([dphi]x) R``,
   ``t <- t + dt``; Chen eqs. 6–12), batched 6 × 6 normal equations.

Status codes (``PnPResult.status``): see :data:`STATUS_NAMES`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Protocol

import numpy as np

from ._validate import as_array
from .dop import angle_jacobian

__all__ = [
    "PnPResult",
    "PnPSolver",
    "PNP_SOLVERS",
    "STATUS_OK",
    "STATUS_TOO_FEW",
    "STATUS_DEGENERATE",
    "STATUS_NOT_CONVERGED",
    "STATUS_BEHIND",
    "STATUS_NAMES",
    "solve_pnp",
    "solve_pnp_lm",
]

STATUS_OK = 0
STATUS_TOO_FEW = 1          # fewer than 4 lit sensors with finite angles
STATUS_DEGENERATE = 2       # lit sensors (nearly) collinear, or singular normal equations
STATUS_NOT_CONVERGED = 3    # refinement hit max_iterations without meeting the tolerance
STATUS_BEHIND = 4           # best pose puts a lit sensor at z <= 0 (behind the station)
STATUS_NAMES = {
    STATUS_OK: "ok",
    STATUS_TOO_FEW: "too few lit sensors (< 4)",
    STATUS_DEGENERATE: "degenerate geometry (collinear sensors or singular normal equations)",
    STATUS_NOT_CONVERGED: "not converged",
    STATUS_BEHIND: "behind the station (a lit sensor at z <= 0)",
}

DEFAULT_CHUNK = 32768
# Lit sets whose centred body points have sqrt(lambda_min / lambda_max) below this get the two
# planar candidates in addition to the POSIT start.
PLANARITY_THRESHOLD = 0.2
# A refined solution whose angle-residual RMS exceeds this (rad) is retried from the planar
# candidates (a wrong basin has residuals far above lighthouse noise, ~4e-5 rad).
RETRY_RESIDUAL = 1e-3


@dataclass(frozen=True)
class PnPResult:
    """Poses of F frames.

    rotation : (F, 3, 3), translation : (F, 3) m — ``p_lh = R p_body + t`` (NaN where no pose).
    success : (F,) bool, ``status == STATUS_OK``.
    status : (F,) int, codes in :data:`STATUS_NAMES`.
    residual_rms : (F,) rad, RMS angle residual over the lit sensors' 2 n angles.
    iterations : (F,) int, refinement iterations of the returned solution.
    """

    rotation: np.ndarray
    translation: np.ndarray
    success: np.ndarray
    status: np.ndarray
    residual_rms: np.ndarray
    iterations: np.ndarray

    @property
    def message(self) -> str:
        s = np.asarray(self.status)
        if s.size and np.all(s == STATUS_OK):
            return f"ok ({s.size} frame(s))"
        parts = [f"{int(np.sum(s == k))} {name}" for k, name in STATUS_NAMES.items() if np.any(s == k)]
        return f"{s.size} frame(s): " + ", ".join(parts)


class PnPSolver(Protocol):
    """A batched PnP solver working on one chunk of frames.

    points_body (F, n, 3) m, angles (F, n, 2) rad, lit (F, n) bool (already cleaned: only finite
    angles in (0, pi) and finite points are lit), initial ``(R (F,3,3), t (F,3))`` or None.
    Returns a :class:`PnPResult` for the F frames.
    """

    def __call__(self, points_body: np.ndarray, angles: np.ndarray, lit: np.ndarray,
                 initial, max_iterations: int) -> PnPResult: ...


# ----------------------------------------------------------------------------------- helpers

def _rodrigues(phi: np.ndarray) -> np.ndarray:
    """exp([phi]x) for phi (F, 3) → (F, 3, 3), stable for small angles."""
    th2 = np.einsum("fi,fi->f", phi, phi)
    th = np.sqrt(th2)
    small = th < 1e-4
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th2 / 6.0 + th2 * th2 / 120.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th2 / 24.0 + th2 * th2 / 720.0, (1.0 - np.cos(ths)) / (ths * ths))
    x, y, z = phi[:, 0], phi[:, 1], phi[:, 2]
    K = np.zeros(phi.shape[:1] + (3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -z, y, -x
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = z, -y, x
    return np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)


def _orthonormal_pair(a: np.ndarray, b: np.ndarray):
    """Symmetric orthonormalisation of two 3-vectors per frame (F, 3) → (r1, r2) unit, orthogonal."""
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    m = a + b
    d = a - b
    m /= np.linalg.norm(m, axis=-1, keepdims=True)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return (m + d) / np.sqrt(2.0), (m - d) / np.sqrt(2.0)


def _residuals(P, ang, w, R, t):
    """Angle residuals (F, n, 2) weighted by lit mask, points in the station frame and lever."""
    lever = np.matmul(P, np.swapaxes(R, -1, -2))  # R p_body, (F, n, 3)
    p = lever + t[:, None, :]
    pred = np.stack([np.arctan2(p[..., 2], p[..., 0]), np.arctan2(p[..., 2], p[..., 1])], -1)
    r = (ang - pred) * w[..., None]
    return r, p, lever


def _refine(P, ang, w, R, t, max_iterations):
    """Batched Levenberg–Marquardt on the angle residuals.

    Returns R, t, cost (sum of squared residuals), iterations, converged, ok (normal equations
    solvable), min depth of lit sensors.
    """
    F = P.shape[0]
    R = R.copy()
    t = t.copy()
    m = 2.0 * w.sum(1)
    r, p, lever = _residuals(P, ang, w, R, t)
    cost = np.einsum("fna,fna->f", r, r)
    lam = np.full(F, 1e-6)
    iters = np.zeros(F, int)
    conv = np.zeros(F, bool)
    ok = np.ones(F, bool)
    active = np.arange(F)
    eye = np.eye(6)
    for _ in range(max_iterations):
        if active.size == 0:
            break
        a = active
        J = angle_jacobian(p[a], lever[a]) * w[a][..., None, None]  # (A, n, 2, 6), Chen eqs. 10-14
        J = J.reshape(a.size, -1, 6)
        A = np.matmul(np.swapaxes(J, 1, 2), J)
        g = np.matmul(np.swapaxes(J, 1, 2), r[a].reshape(a.size, -1, 1))[..., 0]
        diag = np.einsum("fii->fi", A)
        scale = np.maximum(diag.max(1), 1e-300)
        M = A + (lam[a][:, None] * np.maximum(diag, 1e-12 * scale[:, None]))[:, :, None] * eye
        bad = ~np.all(np.isfinite(M), axis=(1, 2))
        M[bad] = eye
        try:
            step = np.linalg.solve(M, g[..., None])[..., 0]
        except np.linalg.LinAlgError:  # pragma: no cover - singular only with exact zeros
            step = np.stack([np.linalg.lstsq(Mi, gi, rcond=None)[0] for Mi, gi in zip(M, g)])
        ok[a[bad]] = False
        Rn = np.matmul(_rodrigues(step[:, :3]), R[a])
        tn = t[a] + step[:, 3:]
        rn, pn, levn = _residuals(P[a], ang[a], w[a], Rn, tn)
        cn = np.einsum("fna,fna->f", rn, rn)
        acc = (cn <= cost[a]) & ~bad
        ia = a[acc]
        R[ia], t[ia], r[ia], p[ia], lever[ia], cost[ia] = Rn[acc], tn[acc], rn[acc], pn[acc], levn[acc], cn[acc]
        lam[ia] = np.maximum(lam[ia] * 0.1, 1e-12)
        lam[a[~acc]] *= 10.0
        iters[a] += 1
        # converged: the step changes the cost by a negligible amount (or is itself negligible)
        dl = np.einsum("fi,fi->f", step, g)
        small = (np.abs(dl) <= 1e-8 * cost[a] + m[a] * 1e-24) | (
            (np.linalg.norm(step[:, :3], axis=1) < 1e-13)
            & (np.linalg.norm(step[:, 3:], axis=1) < 1e-13 * (1.0 + np.linalg.norm(t[a], axis=1))))
        done = small | bad | (lam[a] > 1e12)
        conv[a[small]] = True
        active = a[~done]
    depth = np.where(w > 0, p[..., 2], np.inf).min(1)
    return R, t, cost, iters, conv, ok, depth


def _centred(P, w):
    nl = w.sum(1)
    c = (P * w[..., None]).sum(1) / np.maximum(nl, 1)[:, None]
    Q = (P - c[:, None, :]) * w[..., None]
    S = np.matmul(np.swapaxes(Q, 1, 2), Q)
    return c, Q, S


def _posit(Q, c, u, w, iterations=4):
    """Scaled-orthographic start with perspective correction (POSIT) for non-coplanar lit sets.

    Q (F, n, 3) centred lit body points (zero where unlit), c (F, 3) their centroid,
    u (F, n, 2) normalised image coordinates, w (F, n) lit mask. Returns R (F,3,3), t (F,3).
    """
    F = Q.shape[0]
    S = np.matmul(np.swapaxes(Q, 1, 2), Q)
    Sinv = np.linalg.pinv(S)
    nl = np.maximum(w.sum(1), 1)
    eps = np.zeros(w.shape)
    for _ in range(iterations):
        uu = u * (1.0 + eps)[..., None] * w[..., None]
        x0 = uu.sum(1) / nl[:, None]  # (F, 2): image of the centroid times depth ratio
        IJ = np.matmul(Sinv, np.matmul(np.swapaxes(Q, 1, 2), uu))  # (F, 3, 2)
        I, J = IJ[..., 0], IJ[..., 1]
        s = 0.5 * (np.linalg.norm(I, axis=1) + np.linalg.norm(J, axis=1))
        Z = 1.0 / np.maximum(s, 1e-300)
        r1, r2 = _orthonormal_pair(I, J)
        r3 = np.cross(r1, r2)
        eps = np.einsum("fnk,fk->fn", Q, r3) / Z[:, None]
    R = np.stack([r1, r2, r3], 1)
    t = np.concatenate([x0 * Z[:, None], Z[:, None]], 1) - np.einsum("fij,fj->fi", R, c)
    return R, t


def _ippe_pair(Q, c, u, w):
    """The two poses of the planar ambiguity for the dominant plane of the lit set (IPPE).

    Fits the homography from in-plane coordinates (principal axes of the centred lit body points
    ``Q``) to the normalised image coordinates ``u``, takes its Jacobian at the lit centroid ``c``
    and decomposes it in closed form into the two plane poses (Collins & Bartoli 2014, IPPE).
    Exact for noise-free coplanar points; a start for near-coplanar ones.
    Returns ``[(R_a, t_a), (R_b, t_b)]``, each (F, 3, 3), (F, 3).
    """
    F = Q.shape[0]
    S = np.matmul(np.swapaxes(Q, 1, 2), Q)
    _, V = np.linalg.eigh(S)  # ascending
    e1, e2 = V[..., 2], V[..., 1]
    e0 = np.cross(e1, e2)  # completes a proper body basis
    E = np.stack([e1, e2, e0], -1)
    nl = np.maximum(w.sum(1), 1)
    # Hartley normalisation of both point sets
    sa = np.einsum("fnk,fk->fn", Q, e1)
    sb = np.einsum("fnk,fk->fn", Q, e2)
    m = np.sqrt(((sa * sa + sb * sb) * w).sum(1) / nl)[:, None]
    m = np.maximum(m, 1e-300)
    sa, sb = sa / m, sb / m
    ubar = (u * w[..., None]).sum(1) / nl[:, None]
    du = (u - ubar[:, None, :]) * w[..., None]
    k = np.maximum(np.sqrt((du * du).sum((1, 2)) / nl), 1e-300)[:, None]
    ux, uy = du[..., 0] / k, du[..., 1] / k
    # homography with h33 = 1: [h11 h12 h13 h21 h22 h23 h31 h32] (linear least squares)
    z = np.zeros_like(sa)
    one = w
    rx = np.stack([sa * w, sb * w, one, z, z, z, -ux * sa, -ux * sb], -1)
    ry = np.stack([z, z, z, sa * w, sb * w, one, -uy * sa, -uy * sb], -1)
    Arows = np.concatenate([rx, ry], 1)  # (F, 2n, 8)
    rhs = np.concatenate([ux, uy], 1)
    AtA = np.matmul(np.swapaxes(Arows, 1, 2), Arows) + 1e-14 * np.eye(8)
    h = np.linalg.solve(AtA, np.matmul(np.swapaxes(Arows, 1, 2), rhs[..., None]))[..., 0]
    vx_, vy_ = h[:, 2], h[:, 5]
    # Jacobian of the (normalised) homography at the plane origin, then de-normalised
    j00 = (h[:, 0] - vx_ * h[:, 6]) * k[:, 0] / m[:, 0]
    j01 = (h[:, 1] - vx_ * h[:, 7]) * k[:, 0] / m[:, 0]
    j10 = (h[:, 3] - vy_ * h[:, 6]) * k[:, 0] / m[:, 0]
    j11 = (h[:, 4] - vy_ * h[:, 7]) * k[:, 0] / m[:, 0]
    p = ubar[:, 0] + k[:, 0] * vx_
    q = ubar[:, 1] + k[:, 0] * vy_
    # Rv: rotation taking e_z to the ray (p, q, 1)
    nr = np.sqrt(p * p + q * q + 1.0)
    axis = np.stack([-q, p, np.zeros(F)], -1)
    an = np.linalg.norm(axis, axis=1)
    angle = np.arccos(np.clip(1.0 / nr, -1.0, 1.0))
    axis = axis / np.where(an > 0, an, 1.0)[:, None]
    Rv = _rodrigues(axis * angle[:, None])
    b00 = Rv[:, 0, 0] - p * Rv[:, 2, 0]
    b01 = Rv[:, 0, 1] - p * Rv[:, 2, 1]
    b10 = Rv[:, 1, 0] - q * Rv[:, 2, 0]
    b11 = Rv[:, 1, 1] - q * Rv[:, 2, 1]
    det = b00 * b11 - b01 * b10
    det = np.where(np.abs(det) > 1e-300, det, 1e-300)
    i00, i01, i10, i11 = b11 / det, -b01 / det, -b10 / det, b00 / det
    a00, a01 = i00 * j00 + i01 * j10, i00 * j01 + i01 * j11
    a10, a11 = i10 * j00 + i11 * j10, i10 * j01 + i11 * j11
    t00, t01, t11 = a00 * a00 + a10 * a10, a00 * a01 + a10 * a11, a01 * a01 + a11 * a11
    gamma = np.sqrt(np.maximum(0.5 * (t00 + t11 + np.sqrt((t00 - t11) ** 2 + 4 * t01 * t01)), 1e-300))
    r00, r01, r10, r11 = a00 / gamma, a01 / gamma, a10 / gamma, a11 / gamma
    b0 = np.sqrt(np.maximum(1.0 - r00 * r00 - r10 * r10, 0.0))
    b1 = np.sqrt(np.maximum(1.0 - r01 * r01 - r11 * r11, 0.0))
    b1 = np.where(r00 * r01 + r10 * r11 > 0, -b1, b1)  # columns orthogonal
    tz = 1.0 / gamma
    out = []
    for sgn in (1.0, -1.0):
        c1 = np.stack([r00, r10, sgn * b0], -1)
        c2 = np.stack([r01, r11, sgn * b1], -1)
        c1, c2 = _orthonormal_pair(c1, c2)
        Rt = np.stack([c1, c2, np.cross(c1, c2)], -1)
        R = np.matmul(np.matmul(Rv, Rt), np.swapaxes(E, 1, 2))
        t = np.stack([p * tz, q * tz, tz], -1) - np.einsum("fij,fj->fi", R, c)
        out.append((R, t))
    return out


# ----------------------------------------------------------------------------------- solver

def solve_pnp_lm(points_body, angles, lit, initial=None, max_iterations: int = 20) -> PnPResult:
    """Levenberg–Marquardt PnP on one chunk (see module docstring). Shapes as :class:`PnPSolver`."""
    P = np.asarray(points_body, float)
    ang = np.asarray(angles, float)
    lit = np.asarray(lit, bool)
    F, n = lit.shape
    w = lit.astype(float)
    P = np.where(lit[..., None], P, 0.0)
    ang = np.where(lit[..., None], ang, np.pi / 2)
    u = np.cos(ang) / np.sin(ang) * w[..., None]  # Chen eq. (2): (x/z, y/z) = cot(theta)
    nl = lit.sum(1)
    c, Q, S = _centred(P, w)
    ev = np.linalg.eigvalsh(S)  # ascending
    ev = np.maximum(ev, 0.0)
    big = np.maximum(ev[:, 2], 1e-300)
    collinear = ev[:, 1] <= 1e-10 * big
    planarity = np.sqrt(ev[:, 0] / big)

    status = np.full(F, STATUS_TOO_FEW)
    valid = nl >= 4
    status[valid & collinear] = STATUS_DEGENERATE
    todo = valid & ~collinear

    best_R = np.full((F, 3, 3), np.nan)
    best_t = np.full((F, 3), np.nan)
    best_cost = np.full(F, np.inf)
    best_it = np.zeros(F, int)
    best_status = np.full(F, STATUS_DEGENERATE)

    def consider(idx, R0, t0):
        R, t, cost, it, conv, ok, depth = _refine(P[idx], ang[idx], w[idx], R0, t0, max_iterations)
        st = np.where(~ok, STATUS_DEGENERATE, np.where(depth <= 0, STATUS_BEHIND,
                      np.where(conv, STATUS_OK, STATUS_NOT_CONVERGED)))
        # rank: ok first, then lower cost
        better = (st == STATUS_OK) & ((best_status[idx] != STATUS_OK) | (cost < best_cost[idx]))
        better |= (best_status[idx] != STATUS_OK) & (st != STATUS_OK) & (cost < best_cost[idx]) & ok
        j = idx[better]
        best_R[j], best_t[j], best_cost[j] = R[better], t[better], cost[better]
        best_it[j], best_status[j] = it[better], st[better]

    def poor(idx):
        rms = np.sqrt(best_cost[idx] / np.maximum(2 * nl[idx], 1))
        return (best_status[idx] != STATUS_OK) | ~(rms <= RETRY_RESIDUAL)

    if initial is not None:
        R0, t0 = initial
        idx = np.flatnonzero(todo & np.all(np.isfinite(R0), (1, 2)) & np.all(np.isfinite(t0), 1))
        if idx.size:
            consider(idx, R0[idx], t0[idx])
        cold = todo.copy()
        cold[idx[~poor(idx)]] = False
    else:
        cold = todo

    idx = np.flatnonzero(cold & (planarity > 1e-6))
    if idx.size:
        R0, t0 = _posit(Q[idx], c[idx], u[idx], w[idx])
        consider(idx, R0, t0)
    tried = np.flatnonzero(cold)
    need = np.zeros(F, bool)
    need[tried] = (planarity[tried] < PLANARITY_THRESHOLD) | poor(tried)
    idx = np.flatnonzero(need)
    if idx.size:
        for R0, t0 in _ippe_pair(Q[idx], c[idx], u[idx], w[idx]):
            consider(idx, R0, t0)

    status[todo] = best_status[todo]
    res = np.sqrt(best_cost / np.maximum(2 * nl, 1))
    res[~todo] = np.nan
    return PnPResult(rotation=best_R, translation=best_t, success=status == STATUS_OK,
                     status=status, residual_rms=res, iterations=best_it)


PNP_SOLVERS: "dict[str, Callable[..., PnPResult]]" = {"lm": solve_pnp_lm}


def solve_pnp(points_body, angles, visible=None, *, initial=None, max_iterations: int = 20,
              method: str = "lm", chunk_size: int = DEFAULT_CHUNK) -> PnPResult:
    """Poses of a rigid sensor body from LH1 sweep angles, batched over frames.

    points_body : (n, 3) or (F, n, 3) float, m, sensor positions in the body frame.
    angles : (F, n, 2) or (n, 2) float, rad, ``[theta_x, theta_y]`` as from
        :func:`layoutkit.lighthouse.sweep_angles`. NaN (or outside (0, pi)) means not lit.
    visible : (F, n) bool, optional; lit sensors (default: all with finite angles).
    initial : optional ``(rotation (F, 3, 3), translation (F, 3))`` start, e.g. the previous frame
        when tracking; frames where it does not give a good solution fall back to the cold start.
    max_iterations : Levenberg–Marquardt iteration cap per start.
    method : key of :data:`PNP_SOLVERS`.
    chunk_size : frames per chunk; memory stays bounded for any F.

    Returns a :class:`PnPResult` with a leading frame axis F (F = 1 for (n, 2) angles).
    Degenerate input (fewer than 4 lit sensors, collinear sensors, NaN) gives a status, not an
    exception; inconsistent shapes raise ``ValueError``.
    """
    if method not in PNP_SOLVERS:
        raise ValueError(f"method: expected one of {sorted(PNP_SOLVERS)}, got {method!r}")
    ang = as_array(angles, "angles", (..., None, 2))
    if ang.ndim == 2:
        ang = ang[None]
    if ang.ndim != 3:
        raise ValueError(f"angles: expected shape (F, n, 2) or (n, 2), got {ang.shape}")
    F, n = ang.shape[:2]
    P = as_array(points_body, "points_body", (..., None, 3))
    if P.ndim == 2:
        if P.shape[0] != n:
            raise ValueError(f"points_body: expected shape ({n}, 3) or ({F}, {n}, 3), got {P.shape}")
    elif P.ndim != 3 or P.shape[:2] != (F, n):
        raise ValueError(f"points_body: expected shape ({n}, 3) or ({F}, {n}, 3), got {P.shape}")
    if visible is None:
        vis = np.ones((F, n), bool)
    else:
        vis = np.asarray(visible, bool)
        if vis.shape != (F, n):
            raise ValueError(f"visible: expected shape ({F}, {n}), got {vis.shape}")
    R0 = t0 = None
    if initial is not None:
        R0 = as_array(initial[0], "initial rotation", (..., 3, 3))
        t0 = as_array(initial[1], "initial translation", (..., 3))
        if R0.shape != (F, 3, 3) or t0.shape != (F, 3):
            raise ValueError(f"initial: expected shapes ({F}, 3, 3) and ({F}, 3), got {R0.shape} and {t0.shape}")
    solver = PNP_SOLVERS[method]
    parts = []
    for s in range(0, F, max(int(chunk_size), 1)):
        e = min(F, s + int(chunk_size))
        a = ang[s:e]
        p = np.broadcast_to(P, (e - s, n, 3)) if P.ndim == 2 else P[s:e]
        lit = (vis[s:e] & np.all(np.isfinite(a), -1) & np.all((a > 0) & (a < np.pi), -1)
               & np.all(np.isfinite(p), -1))
        ini = None if R0 is None else (R0[s:e], t0[s:e])
        parts.append(solver(p, a, lit, ini, max_iterations))
    if not parts:
        z = np.zeros(0)
        return PnPResult(np.zeros((0, 3, 3)), np.zeros((0, 3)), z.astype(bool), z.astype(int), z, z.astype(int))
    return PnPResult(*(np.concatenate([getattr(r, f) for r in parts]) for f in
                       ("rotation", "translation", "success", "status", "residual_rms", "iterations")))
