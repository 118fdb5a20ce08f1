"""Compiled joint solve: the Levenberg–Marquardt of :mod:`layoutkit.joint` per frame in numba.

The same model and steps as :func:`layoutkit.joint._lm` and its start selection, which stay the
reference the tests hold this kernel to (``tests/test_joint_compiled.py``): every station's
forward model (:func:`layoutkit.lighthouse.measure_jacobian` — LH1 sweeps or LH2 light planes,
with the calibration's phase, tilt, curve, gib and ogee terms and their derivatives with respect
to the point, docs/calibration.md eqs. C1, C2), optional motion compensation (each station and axis
at its own time: ``R' = exp([omega dt]x) R``, ``t' = t + v dt``), the wrapped angle residuals, the
damped normal equations ``A + lam (diag A + 1e-12 tr A)`` and the same acceptance, convergence and
damping rules. Per frame the residuals, gradient and Gram matrix come from one pass over the
stations and sensors. The status decisions (singular, behind, redundancy) stay in
:mod:`layoutkit.joint`, on the Gram matrix and depths this kernel returns.

Imported on first use only; compiled once and cached on disk (``cache=True``).
"""
from __future__ import annotations

import math

import numba
import numpy as np
from numba import prange

_JIT = dict(cache=True, fastmath=False, nogil=True, error_model="numpy")

_F0, _F1, _F2, _F3 = -8.0108022e-06, 0.0028679863, 5.3685255000000001e-06, 0.0076069798000000001  # lighthouse._LH2_CURVE_SERIES
_LH2_TILT = math.pi / 6.0


@numba.njit(**_JIT)
def _asin_clip(u):
    """asin(clip(u, -1, 1)) and the factor of its derivative (0 where clipped)."""
    uc = min(max(u, -1.0), 1.0)
    return math.asin(uc), (1.0 / math.sqrt(1.0 - uc * uc) if abs(u) < 1.0 else 0.0)


@numba.njit(**_JIT)
def _lh1_axis(x, y, z, k, c, corrected, grad):
    """LH1 axis k at the station-frame point (x, y, z): the angle, grad (3,) = d angle / d point
    (lighthouse._lh1_axis, eq. C1). Derivatives in the axis' own coordinates (a: swept, o: other)."""
    a, o = (x, y) if k == 0 else (y, x)
    den = z * z + a * a
    theta = math.atan2(z, a)
    dth_a, dth_z = -z / den, a / den              # d theta = (a dz - z da) / (z² + a²)
    rho2 = a * a + z * z
    rho = math.sqrt(rho2)
    tt = math.tan(c[1])
    u = tt * o / rho
    tilt, fu = _asin_clip(u)
    q = tt * o / (rho2 * rho)
    du_a, du_o, du_z = -q * a, tt / rho, -q * z
    dp = o * o + z * z
    psi = math.atan2(o, z)
    dpsi_o, dpsi_z = z / dp, -o / dp              # (z do - o dz) / (o² + z²)
    corr = theta + c[0] + tilt
    base = corr + c[2] * psi * psi
    xi = corr if corrected else theta
    arg = xi + c[3]
    v = base + c[4] * math.sin(arg)
    gc = c[4] * math.cos(arg)
    k2 = 2.0 * c[2] * psi
    # a-component, o-component, z-component
    dc_a, dc_o, dc_z = dth_a + fu * du_a, fu * du_o, dth_z + fu * du_z
    g_a = dc_a + gc * (dc_a if corrected else dth_a)
    g_o = dc_o + k2 * dpsi_o + gc * (dc_o if corrected else 0.0)
    g_z = dc_z + k2 * dpsi_z + gc * (dc_z if corrected else dth_z)
    if k == 0:
        grad[0], grad[1] = g_a, g_o
    else:
        grad[0], grad[1] = g_o, g_a
    grad[2] = g_z
    return v


@numba.njit(**_JIT)
def _lh2_axis(x, y, z, k, c, corrected, grad):
    """LH2 plane k at the station-frame point (x, y, z): the light-plane angle and grad (3,)
    (lighthouse._lh2_axis, eq. C2)."""
    t = (-_LH2_TILT if k == 0 else _LH2_TILT) - c[1]
    rho2 = x * x + z * z
    rho = math.sqrt(rho2)
    az = math.atan2(x, z)
    daz = (z / rho2, 0.0, -x / rho2)
    r3 = math.sqrt(rho2 + y * y)
    tn, ct, st = math.tan(t), math.cos(t), math.sin(t)
    A1 = tn * y / rho
    q = tn * y / (rho2 * rho)
    dA1 = (-q * x, tn / rho, -q * z)
    s1, f1 = _asin_clip(A1)
    alpha1 = az + s1
    og = alpha1 - c[5]
    K = c[2] + c[6] * math.cos(og)
    so = c[6] * math.sin(og)
    w = -y / (r3 * ct)
    s, fs = _asin_clip(w)
    P = ((((_F0 * s + _F1) * s + _F2) * s + _F3) * s) * s
    dP = (((5 * _F0 * s + 4 * _F1) * s + 3 * _F2) * s + 2 * _F3) * s
    ddP = ((20 * _F0 * s + 12 * _F1) * s + 6 * _F2) * s + 2 * _F3
    den = ct + dP * K * st
    A2 = min(max(A1, -1.0), 1.0) + P * K / den
    s2, f2 = _asin_clip(A2)
    beta = az + s2
    inside1 = 1.0 if abs(A1) < 1.0 else 0.0
    pt = (x, y, z)
    for j in range(3):
        ds1 = f1 * dA1[j]
        dK = -so * (daz[j] + ds1)
        dr3 = pt[j] / r3
        dw = (-1.0 / (r3 * ct) if j == 1 else 0.0) + (y / (r3 * r3 * ct)) * dr3
        ds = fs * dw
        dden = (dP * st) * dK + (K * st) * (ddP * ds)
        dA2 = inside1 * dA1[j] + (K / den) * (dP * ds) + (P / den) * dK - (P * K / (den * den)) * dden
        grad[j] = daz[j] + f2 * dA2                   # d beta
    base = beta + c[0]
    xi = beta if corrected else az
    arg = xi + c[3]
    v = base + c[4] * math.sin(arg)
    gc = c[4] * math.cos(arg)
    for j in range(3):
        grad[j] = grad[j] + gc * (grad[j] if corrected else daz[j])
    return v


@numba.njit(**_JIT)
def _exp_rot(x, y, z, E):
    """E (3, 3) = exp([phi]x) (Rodrigues; series for small angles)."""
    th2 = x * x + y * y + z * z
    if th2 < 1e-8:
        a = 1.0 - th2 / 6.0 + th2 * th2 / 120.0
        b = 0.5 - th2 / 24.0 + th2 * th2 / 720.0
    else:
        th = math.sqrt(th2)
        a = math.sin(th) / th
        b = (1.0 - math.cos(th)) / (th * th)
    E[0, 0] = 1.0 - b * (y * y + z * z)
    E[0, 1] = b * x * y - a * z
    E[0, 2] = b * x * z + a * y
    E[1, 0] = b * x * y + a * z
    E[1, 1] = 1.0 - b * (x * x + z * z)
    E[1, 2] = b * y * z - a * x
    E[2, 0] = b * x * z - a * y
    E[2, 1] = b * y * z + a * x
    E[2, 2] = 1.0 - b * (x * x + y * y)


@numba.njit(**_JIT)
def _model_pass(P, R, t, SR, ST, kinds, cals, corrected, meas, mask, dt, omega, vel, motion, mode, A, g, zsum, sc):
    """Cost of the pose (R (3, 3), t (3,)) over every station and seen angle; mode 1 also the
    gradient g (6,) = J^T r and the Gram matrix A (6, 6) = J^T J (:func:`layoutkit.joint.model_angles_jacobian`
    rows ``[l x (E^T a), a]``). zsum (S, n): the station-frame z of each point, summed over the two axes
    (their mean is the reference's depth for the behind test)."""
    S, n = mask.shape[0], mask.shape[1]
    E, lev, grad, aw, awr = sc
    for p in range(6):
        g[p] = 0.0
        for q in range(6):
            A[p, q] = 0.0
    for i in range(n):
        for j in range(3):
            lev[i, j] = R[j, 0] * P[i, 0] + R[j, 1] * P[i, 1] + R[j, 2] * P[i, 2]
    cost = 0.0
    for s in range(S):
        for i in range(n):
            zsum[s, i] = 0.0
        for k in range(2):
            if motion:
                d = dt[s, k]
                _exp_rot(omega[0] * d, omega[1] * d, omega[2] * d, E)
                tw0, tw1, tw2 = t[0] + vel[0] * d, t[1] + vel[1] * d, t[2] + vel[2] * d
            else:
                for a in range(3):
                    for b in range(3):
                        E[a, b] = 1.0 if a == b else 0.0
                tw0, tw1, tw2 = t[0], t[1], t[2]
            for i in range(n):
                l0, l1, l2 = lev[i, 0], lev[i, 1], lev[i, 2]
                pw0 = E[0, 0] * l0 + E[0, 1] * l1 + E[0, 2] * l2 + tw0 - ST[s, 0]
                pw1 = E[1, 0] * l0 + E[1, 1] * l1 + E[1, 2] * l2 + tw1 - ST[s, 1]
                pw2 = E[2, 0] * l0 + E[2, 1] * l1 + E[2, 2] * l2 + tw2 - ST[s, 2]
                x = pw0 * SR[s, 0, 0] + pw1 * SR[s, 1, 0] + pw2 * SR[s, 2, 0]   # R_s^T (p_w - T_s)
                y = pw0 * SR[s, 0, 1] + pw1 * SR[s, 1, 1] + pw2 * SR[s, 2, 1]
                z = pw0 * SR[s, 0, 2] + pw1 * SR[s, 1, 2] + pw2 * SR[s, 2, 2]
                zsum[s, i] += z
                if not mask[s, i, k]:
                    continue
                if kinds[s] == 0:
                    v = _lh1_axis(x, y, z, k, cals[s, k], corrected[s], grad)
                else:
                    v = _lh2_axis(x, y, z, k, cals[s, k], corrected[s], grad)
                e = meas[s, i, k] - v
                e = (e + math.pi) % (2.0 * math.pi) - math.pi
                cost += e * e
                if mode == 0:
                    continue
                for j in range(3):   # d angle / d p_world = R_s grad, rotation part through E^T
                    aw[j] = SR[s, j, 0] * grad[0] + SR[s, j, 1] * grad[1] + SR[s, j, 2] * grad[2]
                for j in range(3):
                    awr[j] = E[0, j] * aw[0] + E[1, j] * aw[1] + E[2, j] * aw[2]
                J0 = l1 * awr[2] - l2 * awr[1]
                J1 = l2 * awr[0] - l0 * awr[2]
                J2 = l0 * awr[1] - l1 * awr[0]
                Jr = (J0, J1, J2, aw[0], aw[1], aw[2])
                for p in range(6):
                    g[p] += Jr[p] * e
                    for q in range(p, 6):
                        A[p, q] += Jr[p] * Jr[q]
    if mode == 1:
        for p in range(6):
            for q in range(p):
                A[p, q] = A[q, p]
    return cost


@numba.njit(**_JIT)
def _solve6(M, g, L, step):
    """step = M^-1 g for a symmetric positive definite M (Cholesky); False if not."""
    for c in range(6):
        s = M[c, c]
        for k in range(c):
            s -= L[c, k] * L[c, k]
        if not s > 0.0:
            return False
        L[c, c] = math.sqrt(s)
        for i in range(c + 1, 6):
            s2 = M[i, c]
            for k in range(c):
                s2 -= L[i, k] * L[c, k]
            L[i, c] = s2 / L[c, c]
    y = np.empty(6)
    for i in range(6):
        s = g[i]
        for k in range(i):
            s -= L[i, k] * y[k]
        y[i] = s / L[i, i]
    for i in range(5, -1, -1):
        s = y[i]
        for k in range(i + 1, 6):
            s -= L[k, i] * step[k]
        step[i] = s / L[i, i]
    return True


@numba.njit(**_JIT)
def _frame(P, SR, ST, kinds, cals, corrected, meas, mask, dt, omega, vel, motion, R, t, max_iterations,
           rtol, atol, A_out, zsum_out):
    """LM of one frame from (R, t), updated in place (joint._lm). Returns (cost, done, iterations);
    A_out (6, 6) and zsum_out (S, n) at the final pose."""
    S, n = mask.shape[0], mask.shape[1]
    sc = (np.empty((3, 3)), np.empty((n, 3)), np.empty(3), np.empty(3), np.empty(3))
    A = np.empty((6, 6))
    g = np.empty(6)
    A2 = np.empty((6, 6))
    g2 = np.empty(6)
    zs2 = np.empty((S, n))
    M = np.empty((6, 6))
    L = np.empty((6, 6))
    step = np.empty(6)
    E = np.empty((3, 3))
    Rn = np.empty((3, 3))
    tn = np.empty(3)
    m = 0.0
    for s in range(S):
        for i in range(n):
            for k in range(2):
                if mask[s, i, k]:
                    m += 1.0
    mm = m if m > 1.0 else 1.0
    cost = _model_pass(P, R, t, SR, ST, kinds, cals, corrected, meas, mask, dt, omega, vel, motion, 1, A, g,
                       zsum_out, sc)
    lam = 1e-3
    done = False
    its = 0
    for _ in range(max_iterations):
        if done:
            break
        tr = A[0, 0] + A[1, 1] + A[2, 2] + A[3, 3] + A[4, 4] + A[5, 5]
        for p in range(6):
            for q in range(6):
                M[p, q] = A[p, q]
            M[p, p] += lam * (A[p, p] + 1e-12 * tr)
        if not _solve6(M, g, L, step):
            for p in range(6):
                step[p] = np.nan
        _exp_rot(step[0], step[1], step[2], E)
        for a in range(3):
            for b in range(3):
                Rn[a, b] = E[a, 0] * R[0, b] + E[a, 1] * R[1, b] + E[a, 2] * R[2, b]
            tn[a] = t[a] + step[3 + a]
        cn = _model_pass(P, Rn, tn, SR, ST, kinds, cals, corrected, meas, mask, dt, omega, vel, motion, 1, A2, g2,
                         zs2, sc)
        better = cn < cost
        its += 1
        gain = cost - cn
        conv = better and (gain <= rtol * cost or gain <= atol * mm)
        snorm = math.sqrt(step[0] ** 2 + step[1] ** 2 + step[2] ** 2 + step[3] ** 2 + step[4] ** 2 + step[5] ** 2)
        tiny = (better and snorm < 1e-9) or ((not better) and cost <= atol * mm)
        if better:
            for a in range(3):
                for b in range(3):
                    R[a, b] = Rn[a, b]
                t[a] = tn[a]
            cost = cn
            for p in range(6):
                g[p] = g2[p]
                for q in range(6):
                    A[p, q] = A2[p, q]
            for s in range(S):
                for i in range(n):
                    zsum_out[s, i] = zs2[s, i]
            lam = max(lam / 10.0, 1e-9)
        else:
            lam = lam * 10.0
        if conv or tiny or lam > 1e8:
            done = True
    for p in range(6):
        for q in range(6):
            A_out[p, q] = A[p, q]
    return cost, done, its


@numba.njit(parallel=True, **_JIT)
def solve_frames(P, SR, ST, kinds, cals, corrected, meas, mask, dt, omega, vel, motion, R0, t0, go, max_iterations,
                 rtol, atol, R_out, t_out, cost, done, its, A_out, zsum):
    """Every frame with ``go`` from its start (R0 (F, 3, 3), t0 (F, 3)); outputs in place.

    P (n, 3) body; SR (S, 3, 3), ST (S, 3) station poses; kinds (S,) 0 LH1 / 1 LH2; cals (S, 2, 7);
    corrected (S,) gib argument; meas (F, S, n, 2) rad, mask (F, S, n, 2); dt (F, S, 2) s, omega,
    vel (F, 3) (used with ``motion``)."""
    F = meas.shape[0]
    for f in prange(F):
        if not go[f]:
            continue
        R = R0[f].copy()
        t = t0[f].copy()
        c, d, it = _frame(P, SR, ST, kinds, cals, corrected, meas[f], mask[f], dt[f], omega[f], vel[f], motion,
                          R, t, max_iterations, rtol, atol, A_out[f], zsum[f])
        R_out[f] = R
        t_out[f] = t
        cost[f] = c
        done[f] = d
        its[f] = it


@numba.njit(parallel=True, **_JIT)
def start_costs(P, SR, ST, kinds, cals, corrected, meas, mask, dt, omega, vel, motion, Rs, ts, ok, out):
    """Cost of each start candidate (K, F) (the reference's start selection); inf where not ok or
    not finite."""
    K, F = Rs.shape[0], Rs.shape[1]
    S, n = mask.shape[1], mask.shape[2]
    for f in prange(F):
        sc = (np.empty((3, 3)), np.empty((n, 3)), np.empty(3), np.empty(3), np.empty(3))
        A = np.empty((6, 6))
        g = np.empty(6)
        zs = np.empty((S, n))
        for c in range(K):
            if not ok[c, f]:
                out[c, f] = np.inf
                continue
            v = _model_pass(P, Rs[c, f], ts[c, f], SR, ST, kinds, cals, corrected, meas[f], mask[f], dt[f], omega[f],
                            vel[f], motion, 0, A, g, zs, sc)
            out[c, f] = v if math.isfinite(v) else np.inf
