"""Compiled joint solve: the model of :mod:`layoutkit.joint` per frame in numba, on the shared LM core.

The same model and steps as :func:`layoutkit.joint._lm` and its start selection, which stay the
reference the tests hold this kernel to (``tests/test_joint_compiled.py``): every station's
forward model (:func:`layoutkit.lighthouse.measure_jacobian` — LH1 sweeps or LH2 light planes,
with the calibration's phase, tilt, curve, gib and ogee terms and their derivatives with respect
to the point, docs/calibration.md eqs. C1, C2), optional motion compensation (each station and axis
at its own time: ``R' = exp([omega dt]x) R``, ``t' = t + v dt``) and the wrapped angle residuals,
plugged into the Levenberg–Marquardt core the single-station PnP kernel uses
(:func:`layoutkit.lm_numba.make_refine`: one rotation update, one damped 6 × 6 LDL^T solve, one damping
and stop rule, with the joint solve's tolerances). Per frame the residuals, gradient (and Gram matrix)
come from one pass over the stations and sensors. The status decisions (singular, behind, redundancy) stay in
:mod:`layoutkit.joint`, on the Gram matrix and depths this kernel returns.

Imported on first use only; compiled once and cached on disk (``cache=True``).
"""
from __future__ import annotations

import math

import numba
import numpy as np
from numba import prange

from .lm_numba import exp_rot, make_refine

# the forward models in strict IEEE order (as the numpy reference); the LM core (layoutkit.lm_numba) has
# its own flags. Functions that allocate nothing are compiled without the reference-counting runtime.
_JIT = dict(cache=True, fastmath=False, nogil=True, error_model="numpy")
_LEAF = dict(_JIT, _nrt=False)

_F0, _F1, _F2, _F3 = -8.0108022e-06, 0.0028679863, 5.3685255000000001e-06, 0.0076069798000000001  # lighthouse._LH2_CURVE_SERIES
_LH2_TILT = math.pi / 6.0


@numba.njit(**_LEAF)
def _asin_clip(u):
    """asin(clip(u, -1, 1)) and the factor of its derivative (0 where clipped)."""
    uc = min(max(u, -1.0), 1.0)
    return math.asin(uc), (1.0 / math.sqrt(1.0 - uc * uc) if abs(u) < 1.0 else 0.0)


@numba.njit(**_LEAF)
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


@numba.njit(**_LEAF)
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


@numba.njit(**_LEAF)
def _model_pass(P, r, t, SR, ST, kinds, cals, corrected, meas, mask, dt, omega, vel, motion, mode, A, g, zsum, sc):
    """Cost of the pose (r (9,) row-major rotation, t (3,)) over every station and seen angle; mode >= 1
    also the gradient g (6,) = J^T e, mode 2 also the upper triangle of the Gram matrix A (6, 6) = J^T J
    (:func:`layoutkit.joint.model_angles_jacobian` rows ``[l x (E^T a), a]``). zsum (S n,): the
    station-frame z of each point (station-major), summed over the two axes (their mean is the
    reference's depth for the behind test)."""
    S, n = mask.shape[0], mask.shape[1]
    E, lev, grad, aw, awr = sc
    for p in range(6):
        g[p] = 0.0
        if mode == 2:   # (the LM core keeps its Gram matrix in A over a mode-1 trial pass)
            for q in range(6):
                A[p, q] = 0.0
    for i in range(n):
        for j in range(3):
            lev[i, j] = r[3 * j] * P[i, 0] + r[3 * j + 1] * P[i, 1] + r[3 * j + 2] * P[i, 2]
    cost = 0.0
    for s in range(S):
        for i in range(n):
            zsum[s * n + i] = 0.0
        for k in range(2):
            if motion:
                d = dt[s, k]
                exp_rot(omega[0] * d, omega[1] * d, omega[2] * d, E)
                tw0, tw1, tw2 = t[0] + vel[0] * d, t[1] + vel[1] * d, t[2] + vel[2] * d
            else:
                for a in range(9):
                    E[a] = 1.0 if a % 4 == 0 else 0.0
                tw0, tw1, tw2 = t[0], t[1], t[2]
            for i in range(n):
                l0, l1, l2 = lev[i, 0], lev[i, 1], lev[i, 2]
                pw0 = E[0] * l0 + E[1] * l1 + E[2] * l2 + tw0 - ST[s, 0]
                pw1 = E[3] * l0 + E[4] * l1 + E[5] * l2 + tw1 - ST[s, 1]
                pw2 = E[6] * l0 + E[7] * l1 + E[8] * l2 + tw2 - ST[s, 2]
                x = pw0 * SR[s, 0, 0] + pw1 * SR[s, 1, 0] + pw2 * SR[s, 2, 0]   # R_s^T (p_w - T_s)
                y = pw0 * SR[s, 0, 1] + pw1 * SR[s, 1, 1] + pw2 * SR[s, 2, 1]
                z = pw0 * SR[s, 0, 2] + pw1 * SR[s, 1, 2] + pw2 * SR[s, 2, 2]
                zsum[s * n + i] += z
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
                    awr[j] = E[j] * aw[0] + E[3 + j] * aw[1] + E[6 + j] * aw[2]
                J0 = l1 * awr[2] - l2 * awr[1]
                J1 = l2 * awr[0] - l0 * awr[2]
                J2 = l0 * awr[1] - l1 * awr[0]
                Jr = (J0, J1, J2, aw[0], aw[1], aw[2])
                for p in range(6):
                    g[p] += Jr[p] * e
                if mode == 2:
                    for p in range(6):
                        for q in range(p, 6):
                            A[p, q] += Jr[p] * Jr[q]
    return cost


@numba.njit(inline="always", **_LEAF)
def _joint_pass(ctx, r, t, mode, A, g, zsum):
    """:func:`_model_pass` as the LM core's model (:func:`layoutkit.lm_numba.make_refine`): ctx = one
    frame's model data and scratch."""
    P, SR, ST, kinds, cals, corrected, meas, mask, dt, omega, vel, motion, sc = ctx
    return _model_pass(P, r, t, SR, ST, kinds, cals, corrected, meas, mask, dt, omega, vel, motion, mode, A, g,
                       zsum, sc)


_lm_refine = make_refine(_joint_pass, "joint", trial_gram=True)


@numba.njit(**_JIT)
def _pass_scratch(n):
    return np.empty(9), np.empty((n, 3)), np.empty(3), np.empty(3), np.empty(3)


@numba.njit(parallel=True, **_JIT)
def solve_frames(P, SR, ST, kinds, cals, corrected, meas, mask, dt, omega, vel, motion, R0, t0, go, max_iterations,
                 rtol, atol, R_out, t_out, cost, done, its, A_out, zsum):
    """Every frame with ``go`` from its start (R0 (F, 3, 3), t0 (F, 3)) by the shared LM core
    (:func:`layoutkit.lm_numba.make_refine`, tolerances rtol, atol); outputs in place: the pose and cost,
    the Gram matrix A_out (F, 6, 6) and the depth sums zsum (F, S, n) of the last accepted evaluated
    pose; done = converged, its = iterations.

    P (n, 3) body; SR (S, 3, 3), ST (S, 3) station poses; kinds (S,) 0 LH1 / 1 LH2; cals (S, 2, 7);
    corrected (S,) gib argument; meas (F, S, n, 2) rad, mask (F, S, n, 2); dt (F, S, 2) s, omega,
    vel (F, 3) (used with ``motion``)."""
    F = meas.shape[0]
    S, n = mask.shape[1], mask.shape[2]
    for f in prange(F):
        if not go[f]:
            continue
        sc = _pass_scratch(n)
        M6, B, out = np.zeros((3, 6, 6)), np.zeros((8, 9)), np.zeros(4)
        aux, aux2 = np.zeros(S * n), np.zeros(S * n)
        r, t = np.empty(9), np.empty(3)
        for a in range(3):
            for b in range(3):
                r[3 * a + b] = R0[f, a, b]
            t[a] = t0[f, a]
        m = 0.0
        for s in range(S):
            for i in range(n):
                for k in range(2):
                    if mask[f, s, i, k]:
                        m += 1.0
        ctx = (P, SR, ST, kinds, cals, corrected, meas[f], mask[f], dt[f], omega[f], vel[f], motion, sc)
        _lm_refine(ctx, r, t, m, rtol, atol, max_iterations, M6, B, aux, aux2, out)
        # the Gram matrix (singular test) and depths (behind test) of the last accepted evaluated pose
        # (the converged step after it is below the tolerance)
        for p in range(6):
            for q in range(6):
                A_out[f, p, q] = M6[0, p, q] if q >= p else M6[0, q, p]
        for s in range(S):
            for i in range(n):
                zsum[f, s, i] = aux[s * n + i]
        for a in range(3):
            for b in range(3):
                R_out[f, a, b] = r[3 * a + b]
            t_out[f, a] = t[a]
        cost[f] = out[0]
        done[f] = out[2] > 0.5
        its[f] = int(out[1])


@numba.njit(parallel=True, **_JIT)
def start_costs(P, SR, ST, kinds, cals, corrected, meas, mask, dt, omega, vel, motion, Rs, ts, ok, out):
    """Cost of each start candidate (K, F) (the reference's start selection); inf where not ok or
    not finite."""
    K, F = Rs.shape[0], Rs.shape[1]
    S, n = mask.shape[1], mask.shape[2]
    for f in prange(F):
        sc = _pass_scratch(n)
        A = np.empty((6, 6))
        g = np.empty(6)
        zs = np.empty(S * n)
        r = np.empty(9)
        for c in range(K):
            if not ok[c, f]:
                out[c, f] = np.inf
                continue
            for a in range(3):
                for b in range(3):
                    r[3 * a + b] = Rs[c, f, a, b]
            v = _model_pass(P, r, ts[c, f], SR, ST, kinds, cals, corrected, meas[f], mask[f], dt[f], omega[f],
                            vel[f], motion, 0, A, g, zs, sc)
            out[c, f] = v if math.isfinite(v) else np.inf
