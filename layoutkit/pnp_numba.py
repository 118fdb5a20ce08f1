"""Compiled batched PnP: the LH1 solver of :mod:`layoutkit.pnp_lh1` as one numba kernel per frame.

Why one module of ~900 lines: the per-frame solver (counts and geometry tests, POSIT and IPPE
starts, Levenberg–Marquardt with the factor reuse, the candidate bookkeeping and the ambiguity
test) is one compiled call graph over shared scratch arrays; split, its parts could not be
compiled together.

The same algorithm, step for step, as :func:`layoutkit.pnp_lh1.solve_pnp_lm` (which stays the
reference the tests hold this kernel to: same poses to rounding, same statuses): per frame the
minimum rule and the collinearity test, the start from ``initial``, the POSIT start in the virtual
camera, the IPPE pair for (near-)coplanar or poorly fitted frames, each refined by the same
Levenberg–Marquardt (unrolled 6 × 6 LDL^T factor of ``A + lam diag(A)``, the previous factor reused to
test convergence, the same tolerances), the best / runner-up bookkeeping and the likelihood-ratio
ambiguity test. Differences: scalar code per frame instead of frames-last arrays (no temporaries),
frames spread over threads (``prange`` over blocks of frames, each block with its own scratch); the
residual / gradient / Gram pass runs branch-free and vectorised over the sensors (:func:`_pass_series`,
the atan series to q^13) whenever every seen residual is in the series' range, the exact pass
otherwise; sums in another order (fused multiply-add, reassociated): poses agree with the reference to
~1e-14, except frames that hit the iteration cap.

Imported on first use only (importing numba and loading the compiled cache is not import-time
work of the package); compiled once and cached on disk (``cache=True``). The entry point is
:func:`layoutkit.pnp_lh1.solve_pnp_compiled` (the ``"lm"`` solver of the registry).
"""
from __future__ import annotations

import math
from collections import namedtuple

import numba
import numpy as np
from numba import prange

from .lm_numba import JIT, LEAF, exp_rot, make_refine

# status codes (layoutkit.status; numba needs plain ints)
OK, TOO_FEW, DEGENERATE, NOT_CONVERGED, BEHIND, AMBIGUOUS, NO_START = 0, 1, 2, 3, 4, 5, 7

# the flags of the LM core (layoutkit.lm_numba): fastmath without NaN / infinity assumptions (NaN marks
# unseen sensors and failed frames; poses move by ~5e-15 against strict IEEE order, 11 % faster); the
# functions below the batch loop allocate nothing and are compiled without the reference-counting
# runtime (_LEAF); only _scratch and the batch loops, which allocate, keep it.
_JIT, _LEAF = JIT, LEAF
_RTOL, _ATOL = 1e-6, 1e-26  # the LM's tolerances: those of the reference, pnp_lh1._RTOL and _ATOL
_VEC = dict(_LEAF, fastmath={"contract", "arcp", "nsz", "reassoc"})
# The per-frame call chain (_frames -> _solve_frame -> _consider -> _refine -> LM core -> _pass, _depth)
# is inlined at numba's IR level (inline="always"; same flags, so the same arithmetic, bit for bit):
# as separate functions each call passed every array as ~7 words (-9 to -14 % per frame at n = 12,
# interleaved A/B on one core; _solve_frame into the frame loop and the sensor arrays as the rows of
# one array down the chain, another -15 to -19 %). _pass_series and _posit stay calls: their
# reassociating flags (vectorised sums) must not spread to the LM's arithmetic.
# Timing note: the same kernel freshly compiled and loaded from numba's disk cache (what every run
# after the first executes) measured up to 14 % apart (same instructions; code / data placement):
# changes here were judged on the cached kernel, in-process A/B against the previous one.
# Inlined code takes its caller's runtime: these functions (and _views) are for the kernel's own
# functions compiled without reference counting (_LEAF) only — inlined into a function with it, the
# views _views hands out would be released without having been held (heap corruption, seen in a test
# harness).


# ------------------------------------------------------------------------------ small helpers

@numba.njit(**_LEAF)
def _atan_ratio(num, den):
    """atan2(num, den), by the series of :func:`layoutkit.pnp_lh1._atan_ratio` when den > 0 and
    |num / den| is small (truncation below 1.2e-19 resp. 2.1e-21)."""
    if den > 0.0:
        q = num / den
        aq = abs(q)
        if aq < 1e-2:
            q2 = q * q
            return q * (1.0 - q2 * (1.0 / 3.0 - q2 * (0.2 - q2 * (1.0 / 7.0))))
        if aq < 0.05:
            q2 = q * q
            return q * (1.0 - q2 * (1.0 / 3.0 - q2 * (0.2 - q2 * (1.0 / 7.0 - q2 * (1.0 / 9.0 - q2 * (
                1.0 / 11.0 - q2 * (1.0 / 13.0)))))))
    return math.atan2(num, den)


@numba.njit(**_LEAF)
def _distinct(Ra, Rb, cos_limit):
    """Attitudes more than DISTINCT_ANGLE apart (NaN counts as distinct), as pnp_lh1."""
    s = 0.0
    for k in range(9):
        s += Ra[k] * Rb[k]
    c = (s - 1.0) / 2.0
    if c > 1.0:
        c = 1.0
    elif c < -1.0:
        c = -1.0
    return not (c > cos_limit)


# ------------------------------------------------------------------------------ evaluation

@numba.njit(**_LEAF)
def _eval(Px, Py, Pz, ux, uy, wx, wy, n, r, t, rx, ry, zz):
    """Residuals rx, ry (n,) and depths zz (n,) of the pose (r (9,), t (3,)); returns the cost."""
    cost = 0.0
    for i in range(n):
        X, Y, Z = Px[i], Py[i], Pz[i]
        x = r[0] * X + r[1] * Y + r[2] * Z + t[0]
        y = r[3] * X + r[4] * Y + r[5] * Z + t[1]
        z = r[6] * X + r[7] * Y + r[8] * Z + t[2]
        zz[i] = z
        if wx[i] > 0.0:
            a = _atan_ratio(x - ux[i] * z, z + ux[i] * x)
        else:
            a = 0.0
        if wy[i] > 0.0:
            b = _atan_ratio(y - uy[i] * z, z + uy[i] * y)
        else:
            b = 0.0
        rx[i] = a
        ry[i] = b
        cost += a * a + b * b
    return cost


@numba.njit(**_VEC)
def _pass_series(SA, n, r, t, mode, A, g):
    """:func:`_pass_exact` without branches, for poses where every seen angle's residual is in the
    series' range (den > 0, |num / den| < 0.05: atan by its odd series to q^13, truncation below
    2e-21): returns (cost, in_range); when not in_range nothing is written and the caller runs the
    exact pass. Branch-free with reassociated sums so that LLVM vectorises it over the sensors;
    the sums' order differs from the exact pass by rounding only."""
    Px, Py, Pz, ux, uy, wx, wy = SA[0], SA[1], SA[2], SA[3], SA[4], SA[5], SA[6]
    r0, r1, r2, r3, r4, r5, r6, r7, r8 = r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7], r[8]
    t0, t1, t2 = t[0], t[1], t[2]
    g0 = g1 = g2 = g3 = g4 = g5 = 0.0
    a00 = a01 = a02 = a03 = a04 = a05 = a11 = a12 = a13 = a14 = a15 = 0.0
    a22 = a23 = a24 = a25 = a33 = a35 = a44 = a45 = a55 = 0.0
    cost = 0.0
    out = 0.0
    for i in range(n):
        hx, hy = wx[i] > 0.0, wy[i] > 0.0
        X, Y, Z = Px[i], Py[i], Pz[i]
        lx = r0 * X + r1 * Y + r2 * Z
        ly = r3 * X + r4 * Y + r5 * Z
        lz = r6 * X + r7 * Y + r8 * Z
        x, y, z = lx + t0, ly + t1, lz + t2
        dx = z + ux[i] * x
        dy = z + uy[i] * y
        qx = (x - ux[i] * z) / dx
        qy = (y - uy[i] * z) / dy
        okx = (dx > 0.0) & (abs(qx) < 0.05)
        oky = (dy > 0.0) & (abs(qy) < 0.05)
        out += (1.0 if (hx and not okx) else 0.0) + (1.0 if (hy and not oky) else 0.0)
        sx = qx * qx
        sy = qy * qy
        ex = qx * (1.0 - sx * (1.0 / 3.0 - sx * (0.2 - sx * (1.0 / 7.0 - sx * (1.0 / 9.0 - sx * (
            1.0 / 11.0 - sx * (1.0 / 13.0)))))))
        ey = qy * (1.0 - sy * (1.0 / 3.0 - sy * (0.2 - sy * (1.0 / 7.0 - sy * (1.0 / 9.0 - sy * (
            1.0 / 11.0 - sy * (1.0 / 13.0)))))))
        ex = ex if hx else 0.0
        ey = ey if hy else 0.0
        cost += ex * ex + ey * ey
        if mode >= 1:
            ix = 1.0 / (x * x + z * z)
            iy = 1.0 / (y * y + z * z)
            a0 = -z * ix if hx else 0.0
            a2 = x * ix if hx else 0.0
            b1 = -z * iy if hy else 0.0
            b2 = y * iy if hy else 0.0
            j0, j1, j2, j3, j5 = ly * a2, lz * a0 - lx * a2, -ly * a0, a0, a2
            k0, k1, k2, k4, k5 = ly * b2 - lz * b1, -lx * b2, lx * b1, b1, b2
            g0 += j0 * ex + k0 * ey
            g1 += j1 * ex + k1 * ey
            g2 += j2 * ex + k2 * ey
            g3 += j3 * ex
            g4 += k4 * ey
            g5 += j5 * ex + k5 * ey
            if mode == 2:
                a00 += j0 * j0 + k0 * k0
                a01 += j0 * j1 + k0 * k1
                a02 += j0 * j2 + k0 * k2
                a03 += j0 * j3
                a04 += k0 * k4
                a05 += j0 * j5 + k0 * k5
                a11 += j1 * j1 + k1 * k1
                a12 += j1 * j2 + k1 * k2
                a13 += j1 * j3
                a14 += k1 * k4
                a15 += j1 * j5 + k1 * k5
                a22 += j2 * j2 + k2 * k2
                a23 += j2 * j3
                a24 += k2 * k4
                a25 += j2 * j5 + k2 * k5
                a33 += j3 * j3
                a35 += j3 * j5
                a44 += k4 * k4
                a45 += k4 * k5
                a55 += j5 * j5 + k5 * k5
    if out > 0.0:
        return cost, False
    if mode >= 1:
        g[0], g[1], g[2], g[3], g[4], g[5] = g0, g1, g2, g3, g4, g5
    if mode == 2:
        A[0, 0], A[0, 1], A[0, 2], A[0, 3], A[0, 4], A[0, 5] = a00, a01, a02, a03, a04, a05
        A[1, 1], A[1, 2], A[1, 3], A[1, 4], A[1, 5] = a11, a12, a13, a14, a15
        A[2, 2], A[2, 3], A[2, 4], A[2, 5] = a22, a23, a24, a25
        A[3, 3], A[3, 4], A[3, 5] = a33, 0.0, a35
        A[4, 4], A[4, 5] = a44, a45
        A[5, 5] = a55
    return cost, True


@numba.njit(inline="always", **_LEAF)
def _pass(SA, n, r, t, mode, A, g):
    """One pass over the sensors at the pose (see :func:`_pass_exact`): the vectorised series pass
    when every seen residual is in its range, else the exact one."""
    cost, ok = _pass_series(SA, n, r, t, mode, A, g)
    if not ok:
        return _pass_exact(SA[0], SA[1], SA[2], SA[3], SA[4], SA[5], SA[6], n, r, t, mode, A, g)
    return cost


@numba.njit(inline="always", **_LEAF)
def _depth(Px, Py, Pz, wx, wy, n, pose, depth):
    """depth (2,) = smallest and largest z of the seen sensors at pose (12,) = (r (9,), t (3,))."""
    r6, r7, r8, t2 = pose[6], pose[7], pose[8], pose[11]
    zmin, zmax = np.inf, -np.inf
    for i in range(n):
        if wx[i] > 0.0 or wy[i] > 0.0:
            z = r6 * Px[i] + r7 * Py[i] + r8 * Pz[i] + t2
            if z < zmin:
                zmin = z
            if z > zmax:
                zmax = z
    depth[0], depth[1] = zmin, zmax


@numba.njit(**_LEAF)
def _pass_exact(Px, Py, Pz, ux, uy, wx, wy, n, r, t, mode, A, g):
    """One pass over the sensors at the pose (r (9,), t (3,)): returns the cost (sum of squared angle
    residuals, as :func:`_eval`); mode >= 1 also the gradient g (6,) = J^T r, mode 2 also the upper
    triangle of A = J^T J (6, 6) — the Jacobian rows of :func:`layoutkit.pnp_lh1._jacobian` (left
    perturbation, Chen eqs. 10-14).
    Fused so that the residuals are computed once per pose; the pose, gradient and Gram matrix are
    held in registers over the loop."""
    r0, r1, r2, r3, r4, r5, r6, r7, r8 = r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7], r[8]
    t0, t1, t2 = t[0], t[1], t[2]
    g0 = g1 = g2 = g3 = g4 = g5 = 0.0
    a00 = a01 = a02 = a03 = a04 = a05 = a11 = a12 = a13 = a14 = a15 = 0.0
    a22 = a23 = a24 = a25 = a33 = a35 = a44 = a45 = a55 = 0.0
    cost = 0.0
    for i in range(n):
        hx, hy = wx[i] > 0.0, wy[i] > 0.0
        X, Y, Z = Px[i], Py[i], Pz[i]
        lx = r0 * X + r1 * Y + r2 * Z
        ly = r3 * X + r4 * Y + r5 * Z
        lz = r6 * X + r7 * Y + r8 * Z
        x, y, z = lx + t0, ly + t1, lz + t2
        ex = _atan_ratio(x - ux[i] * z, z + ux[i] * x) if hx else 0.0
        ey = _atan_ratio(y - uy[i] * z, z + uy[i] * y) if hy else 0.0
        cost += ex * ex + ey * ey
        if mode == 0 or not (hx or hy):
            continue
        ix = 1.0 / (x * x + z * z)
        iy = 1.0 / (y * y + z * z)
        a0 = -z * wx[i] * ix
        a2 = x * wx[i] * ix
        b1 = -z * wy[i] * iy
        b2 = y * wy[i] * iy
        j0, j1, j2, j3, j5 = ly * a2, lz * a0 - lx * a2, -ly * a0, a0, a2          # theta_x row (j4 = 0)
        k0, k1, k2, k4, k5 = ly * b2 - lz * b1, -lx * b2, lx * b1, b1, b2          # theta_y row (k3 = 0)
        g0 += j0 * ex + k0 * ey
        g1 += j1 * ex + k1 * ey
        g2 += j2 * ex + k2 * ey
        g3 += j3 * ex
        g4 += k4 * ey
        g5 += j5 * ex + k5 * ey
        if mode == 2:
            a00 += j0 * j0 + k0 * k0
            a01 += j0 * j1 + k0 * k1
            a02 += j0 * j2 + k0 * k2
            a03 += j0 * j3
            a04 += k0 * k4
            a05 += j0 * j5 + k0 * k5
            a11 += j1 * j1 + k1 * k1
            a12 += j1 * j2 + k1 * k2
            a13 += j1 * j3
            a14 += k1 * k4
            a15 += j1 * j5 + k1 * k5
            a22 += j2 * j2 + k2 * k2
            a23 += j2 * j3
            a24 += k2 * k4
            a25 += j2 * j5 + k2 * k5
            a33 += j3 * j3
            a35 += j3 * j5
            a44 += k4 * k4
            a45 += k4 * k5
            a55 += j5 * j5 + k5 * k5
    if mode >= 1:
        g[0], g[1], g[2], g[3], g[4], g[5] = g0, g1, g2, g3, g4, g5
    if mode == 2:
        A[0, 0], A[0, 1], A[0, 2], A[0, 3], A[0, 4], A[0, 5] = a00, a01, a02, a03, a04, a05
        A[1, 1], A[1, 2], A[1, 3], A[1, 4], A[1, 5] = a11, a12, a13, a14, a15
        A[2, 2], A[2, 3], A[2, 4], A[2, 5] = a22, a23, a24, a25
        A[3, 3], A[3, 4], A[3, 5] = a33, 0.0, a35
        A[4, 4], A[4, 5] = a44, a45
        A[5, 5] = a55
    return cost


@numba.njit(inline="always", **_LEAF)
def _pnp_pass(ctx, r, t, mode, A, g, pose):
    """:func:`_pass` as the LM core's model (:func:`layoutkit.lm_numba.make_refine`): ctx = the frame's
    sensor arrays and their count; the by-product is the evaluated pose, pose (12,) = (r, t), whose
    depths :func:`_refine` computes once, for the last accepted one."""
    SA, n = ctx
    for k in range(9):
        pose[k] = r[k]
    for k in range(3):
        pose[9 + k] = t[k]
    return _pass(SA, n, r, t, mode, A, g)


_lm_refine = make_refine(_pnp_pass, "pnp")


# ------------------------------------------------------------------------------ refinement

@numba.njit(inline="always", **_LEAF)
def _refine(SA, n, na, r, t, max_iterations, wk, out):
    """Levenberg–Marquardt from (r (9,), t (3,)), updated in place: the shared core
    :func:`layoutkit.lm_numba.make_refine` (the per-frame form of :func:`layoutkit.pnp_lh1._refine`: the same
    steps, tolerances and factor reuse) with each pose's residuals, gradient (and Gram matrix) from one
    fused :func:`_pass`. out[0:6] = cost, iterations, converged, ok, zmin, zmax (z of the last
    evaluated pose, as the reference)."""
    sc = _views(wk)
    pose, pose2 = sc.dep, sc.dep2
    _lm_refine((SA, n), r, t, na, _RTOL, _ATOL, max_iterations, wk.M6, wk.LB,
               pose, pose2, out)
    _depth(SA[0], SA[1], SA[2], SA[5], SA[6], n, pose, out[4:6])


# ------------------------------------------------------------------------------ starts

@numba.njit(**_LEAF)
def _sym3_eigvals(S00, S11, S22, S01, S02, S12):
    """Eigenvalues (ascending) of a symmetric 3 x 3 matrix, closed form (pnp_lh1._sym3_eigvals)."""
    p1 = S01 * S01 + S02 * S02 + S12 * S12
    q = (S00 + S11 + S22) / 3.0
    p2 = (S00 - q) ** 2 + (S11 - q) ** 2 + (S22 - q) ** 2 + 2.0 * p1
    p = math.sqrt(p2 / 6.0)
    ps = p if p > 0 else 1.0
    B00, B11, B22 = (S00 - q) / ps, (S11 - q) / ps, (S22 - q) / ps
    B01, B02, B12 = S01 / ps, S02 / ps, S12 / ps
    detB = (B00 * (B11 * B22 - B12 * B12) - B01 * (B01 * B22 - B12 * B02)
            + B02 * (B01 * B12 - B11 * B02))
    h = detB / 2.0
    if h > 1.0:
        h = 1.0
    elif h < -1.0:
        h = -1.0
    phi = math.acos(h) / 3.0
    e_hi = q + 2.0 * p * math.cos(phi)
    e_lo = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
    return e_lo, 3.0 * q - e_hi - e_lo, e_hi


@numba.njit(**_VEC)
def _scatter(Px, Py, Pz, w, n, c, S):
    """Centroid c (3,) and scatter S (6,) = (S00, S11, S22, S01, S02, S12) of the points weighted by
    w (n,) (0/1), as pnp_lh1._scatter (raw moments minus nl c c^T)."""
    nl = 0.0
    sx = sy = sz = 0.0
    m00 = m11 = m22 = m01 = m02 = m12 = 0.0
    for i in range(n):
        wi = w[i]
        X, Y, Z = Px[i], Py[i], Pz[i]
        nl += wi
        sx += wi * X
        sy += wi * Y
        sz += wi * Z
        m00 += wi * X * X
        m11 += wi * Y * Y
        m22 += wi * Z * Z
        m01 += wi * X * Y
        m02 += wi * X * Z
        m12 += wi * Y * Z
    if nl < 1.0:
        nl = 1.0
    c[0], c[1], c[2] = sx / nl, sy / nl, sz / nl
    S[0] = m00 - nl * c[0] * c[0]
    S[1] = m11 - nl * c[1] * c[1]
    S[2] = m22 - nl * c[2] * c[2]
    S[3] = m01 - nl * c[0] * c[1]
    S[4] = m02 - nl * c[0] * c[2]
    S[5] = m12 - nl * c[1] * c[2]


@numba.njit(**_LEAF)
def _unit3(a, b, c):
    nrm = math.sqrt(a * a + b * b + c * c)
    return a / nrm, b / nrm, c / nrm, nrm


@numba.njit(**_VEC)
def _posit(SA, n, nl, c, S, r, t, wk, have_geo):
    """POSIT in the virtual camera (pnp_lh1._posit, two iterations) → r (9,), t (3,). have_geo: the
    centred points and the inverse scatter in ``wk`` are this geometry's (computed here otherwise)."""
    Px, Py, Pz, ux, uy, w = SA[0], SA[1], SA[2], SA[3], SA[4], SA[7]
    sc = _views(wk)
    vxs, vys = sc.rx2, sc.ry2
    Qx, Qy, Qz, Si = sc.px, sc.py, sc.pz, sc.si
    su = sv = 0.0
    for i in range(n):
        su += w[i] * ux[i]
        sv += w[i] * uy[i]
    m0, m1, m2, _ = _unit3(su, sv, nl)
    vx, vy, cz = m1, -m0, m2
    k = 1.0 / (1.0 + cz)
    kxy = k * vx * vy
    Rc0, Rc1, Rc2, Rc3, Rc4, Rc5, Rc6, Rc7, Rc8 = 1.0 - k * vy * vy, kxy, vy, kxy, 1.0 - k * vx * vx, -vx, -vy, vx, cz
    for i in range(n):
        ibz = 1.0 / (Rc6 * ux[i] + Rc7 * uy[i] + cz)
        vxs[i] = w[i] * ((Rc0 * ux[i] + Rc1 * uy[i] + vy) * ibz)
        vys[i] = w[i] * ((Rc3 * ux[i] + Rc4 * uy[i] - vx) * ibz)
    if not have_geo:
        for i in range(n):
            Qx[i] = (Px[i] - c[0]) * w[i]
            Qy[i] = (Py[i] - c[1]) * w[i]
            Qz[i] = (Pz[i] - c[2]) * w[i]
        S00, S11, S22, S01, S02, S12 = S[0], S[1], S[2], S[3], S[4], S[5]
        C00 = S11 * S22 - S12 * S12
        C01 = S02 * S12 - S01 * S22
        C02 = S01 * S12 - S02 * S11
        C11 = S00 * S22 - S02 * S02
        C12 = S01 * S02 - S00 * S12
        C22 = S00 * S11 - S01 * S01
        idet = 1.0 / (S00 * C00 + S01 * C01 + S02 * C02)
        Si[0], Si[1], Si[2] = C00 * idet, C01 * idet, C02 * idet
        Si[3], Si[4], Si[5] = C01 * idet, C11 * idet, C12 * idet
        Si[6], Si[7], Si[8] = C02 * idet, C12 * idet, C22 * idet
    Si0, Si1, Si2, Si3, Si4, Si5, Si6, Si7, Si8 = Si[0], Si[1], Si[2], Si[3], Si[4], Si[5], Si[6], Si[7], Si[8]
    nlm = nl if nl > 1.0 else 1.0
    r10 = r11 = r12 = r20 = r21 = r22 = r30 = r31 = r32 = iZ = 0.0
    sax = say = 0.0
    for it in range(2):
        qa0 = qa1 = qa2 = qb0 = qb1 = qb2 = 0.0
        sax = say = 0.0
        for i in range(n):
            ax, ay = vxs[i], vys[i]
            if it:
                e = 1.0 + (r30 * iZ) * Qx[i] + (r31 * iZ) * Qy[i] + (r32 * iZ) * Qz[i]
                ax, ay = ax * e, ay * e
            sax += ax
            say += ay
            qa0 += Qx[i] * ax
            qa1 += Qy[i] * ax
            qa2 += Qz[i] * ax
            qb0 += Qx[i] * ay
            qb1 += Qy[i] * ay
            qb2 += Qz[i] * ay
        I0, I1, I2, nI = _unit3(Si0 * qa0 + Si1 * qa1 + Si2 * qa2, Si3 * qa0 + Si4 * qa1 + Si5 * qa2,
                                Si6 * qa0 + Si7 * qa1 + Si8 * qa2)
        J0, J1, J2, nJ = _unit3(Si0 * qb0 + Si1 * qb1 + Si2 * qb2, Si3 * qb0 + Si4 * qb1 + Si5 * qb2,
                                Si6 * qb0 + Si7 * qb1 + Si8 * qb2)
        iZ = 0.5 * (nI + nJ)
        mm0, mm1, mm2, _ = _unit3(I0 + J0, I1 + J1, I2 + J2)
        dd0, dd1, dd2, _ = _unit3(I0 - J0, I1 - J1, I2 - J2)
        h = math.sqrt(0.5)
        r10, r11, r12 = (mm0 + dd0) * h, (mm1 + dd1) * h, (mm2 + dd2) * h
        r20, r21, r22 = (mm0 - dd0) * h, (mm1 - dd1) * h, (mm2 - dd2) * h
        r30 = r11 * r22 - r12 * r21
        r31 = r12 * r20 - r10 * r22
        r32 = r10 * r21 - r11 * r20
    Z = 1.0 / iZ
    Rv = (r10, r11, r12, r20, r21, r22, r30, r31, r32)
    tv0 = sax / nlm * Z - (Rv[0] * c[0] + Rv[1] * c[1] + Rv[2] * c[2])
    tv1 = say / nlm * Z - (Rv[3] * c[0] + Rv[4] * c[1] + Rv[5] * c[2])
    tv2 = Z - (Rv[6] * c[0] + Rv[7] * c[1] + Rv[8] * c[2])
    RcT = (Rc0, Rc3, Rc6, Rc1, Rc4, Rc7, Rc2, Rc5, Rc8)
    for i in range(3):
        e0, e1, e2 = RcT[3 * i], RcT[3 * i + 1], RcT[3 * i + 2]
        for j in range(3):
            r[3 * i + j] = e0 * Rv[j] + e1 * Rv[3 + j] + e2 * Rv[6 + j]
    t[0] = RcT[0] * tv0 + RcT[1] * tv1 + RcT[2] * tv2
    t[1] = RcT[3] * tv0 + RcT[4] * tv1 + RcT[5] * tv2
    t[2] = RcT[6] * tv0 + RcT[7] * tv1 + RcT[8] * tv2


@numba.njit(**_LEAF)
def _ippe_pair(Px, Py, Pz, ux, uy, w, n, nl, c, ra, ta, rb, tb, wk):
    """The two poses of the planar ambiguity of the dominant plane (pnp_lh1._ippe_pair, IPPE)."""
    sc = _views(wk)
    Qx, Qy, Qz = sc.qx, sc.qy, sc.qz
    S3 = sc.S3
    for a in range(3):
        for b in range(3):
            S3[a, b] = 0.0
    for i in range(n):
        Qx[i] = (Px[i] * w[i] - c[0]) * w[i]
        Qy[i] = (Py[i] * w[i] - c[1]) * w[i]
        Qz[i] = (Pz[i] * w[i] - c[2]) * w[i]
        q = (Qx[i], Qy[i], Qz[i])
        for a in range(3):
            for b in range(3):
                S3[a, b] += q[a] * q[b]
    # the plane's normal e0: the eigenvector of the smallest eigenvalue (closed form: the largest cross
    # product of two rows of S - lambda_min I); e1, e2 any orthonormal pair in the plane with
    # e1 x e2 = e0 (the reference takes the principal axes; the pose does not depend on the in-plane
    # basis, which may be degenerate — a square face)
    lo, _, _ = _sym3_eigvals(S3[0, 0], S3[1, 1], S3[2, 2], S3[0, 1], S3[0, 2], S3[1, 2])
    best = -1.0
    n0 = n1 = n2 = 0.0
    for ia in range(3):
        for ib in range(ia + 1, 3):
            a0, a1, a2 = S3[ia, 0] - (lo if ia == 0 else 0.0), S3[ia, 1] - (lo if ia == 1 else 0.0), \
                S3[ia, 2] - (lo if ia == 2 else 0.0)
            b0, b1, b2 = S3[ib, 0] - (lo if ib == 0 else 0.0), S3[ib, 1] - (lo if ib == 1 else 0.0), \
                S3[ib, 2] - (lo if ib == 2 else 0.0)
            c0, c1, c2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
            nn = c0 * c0 + c1 * c1 + c2 * c2
            if nn > best:
                best, n0, n1, n2 = nn, c0, c1, c2
    if not best > 0.0:
        n0, n1, n2 = 0.0, 0.0, 1.0
    n0, n1, n2, _ = _unit3(n0, n1, n2)
    # e1: the coordinate axis least aligned with the normal, made orthogonal to it
    if abs(n0) <= abs(n1) and abs(n0) <= abs(n2):
        u0, u1, u2 = 1.0 - n0 * n0, -n0 * n1, -n0 * n2
    elif abs(n1) <= abs(n2):
        u0, u1, u2 = -n1 * n0, 1.0 - n1 * n1, -n1 * n2
    else:
        u0, u1, u2 = -n2 * n0, -n2 * n1, 1.0 - n2 * n2
    u0, u1, u2, _ = _unit3(u0, u1, u2)
    e0 = (n0, n1, n2)
    e1 = (u0, u1, u2)
    e2 = (n1 * u2 - n2 * u1, n2 * u0 - n0 * u2, n0 * u1 - n1 * u0)   # e0 x e1, so e1 x e2 = e0
    nlm = nl if nl > 1.0 else 1.0
    sa, sb = sc.rx2, sc.ry2
    acc = 0.0
    ub0 = ub1 = 0.0
    for i in range(n):
        sa[i] = Qx[i] * e1[0] + Qy[i] * e1[1] + Qz[i] * e1[2]
        sb[i] = Qx[i] * e2[0] + Qy[i] * e2[1] + Qz[i] * e2[2]
        acc += (sa[i] * sa[i] + sb[i] * sb[i]) * w[i]
        ub0 += ux[i] * w[i]
        ub1 += uy[i] * w[i]
    m = math.sqrt(acc / nlm)
    if not m > 1e-300:
        m = 1e-300
    ub0 /= nlm
    ub1 /= nlm
    kk = 0.0
    for i in range(n):
        sa[i] /= m
        sb[i] /= m
        d0 = (ux[i] - ub0) * w[i]
        d1 = (uy[i] - ub1) * w[i]
        kk += d0 * d0 + d1 * d1
    k = math.sqrt(kk / nlm)
    if not k > 1e-300:
        k = 1e-300
    AtA, rhs = sc.A8, sc.b8
    for a in range(8):
        rhs[a] = 0.0
        for b in range(8):
            AtA[a, b] = 1e-14 if a == b else 0.0
    row = sc.row8
    for i in range(n):
        vx_ = (ux[i] - ub0) * w[i] / k
        vy_ = (uy[i] - ub1) * w[i] / k
        for axis in range(2):
            for a in range(8):
                row[a] = 0.0
            if axis == 0:
                row[0], row[1], row[2] = sa[i], sb[i], w[i]
                row[6], row[7] = -vx_ * sa[i], -vx_ * sb[i]
                v = vx_
            else:
                row[3], row[4], row[5] = sa[i], sb[i], w[i]
                row[6], row[7] = -vy_ * sa[i], -vy_ * sb[i]
                v = vy_
            for a in range(8):
                ra_ = row[a]
                if ra_ == 0.0:
                    continue
                rhs[a] += ra_ * v
                for b in range(8):
                    AtA[a, b] += ra_ * row[b]
    h = sc.h8
    for cc in range(8):           # Cholesky of the SPD normal matrix (ridge 1e-14), in place, then solve
        d = AtA[cc, cc]
        for q_ in range(cc):
            d -= AtA[cc, q_] * AtA[cc, q_]
        d = math.sqrt(d) if d > 0.0 else 1e-300
        AtA[cc, cc] = d
        for i in range(cc + 1, 8):
            v = AtA[i, cc]
            for q_ in range(cc):
                v -= AtA[i, q_] * AtA[cc, q_]
            AtA[i, cc] = v / d
    for i in range(8):
        v = rhs[i]
        for q_ in range(i):
            v -= AtA[i, q_] * h[q_]
        h[i] = v / AtA[i, i]
    for i in range(7, -1, -1):
        v = h[i]
        for q_ in range(i + 1, 8):
            v -= AtA[q_, i] * h[q_]
        h[i] = v / AtA[i, i]
    hx, hy = h[2], h[5]
    km = k / m
    j00 = (h[0] - hx * h[6]) * km
    j01 = (h[1] - hx * h[7]) * km
    j10 = (h[3] - hy * h[6]) * km
    j11 = (h[4] - hy * h[7]) * km
    p = ub0 + k * hx
    q = ub1 + k * hy
    nr = math.sqrt(p * p + q * q + 1.0)
    an = math.sqrt(q * q + p * p)
    cosang = 1.0 / nr
    if cosang > 1.0:
        cosang = 1.0
    ang = math.acos(cosang)
    dn = an if an > 0 else 1.0
    E = sc.E
    exp_rot(-q / dn * ang, p / dn * ang, 0.0, E)
    Rv00, Rv01, Rv02, Rv10, Rv11, Rv12, Rv20, Rv21, Rv22 = E[0], E[1], E[2], E[3], E[4], E[5], E[6], E[7], E[8]
    b00 = Rv00 - p * Rv20
    b01 = Rv01 - p * Rv21
    b10 = Rv10 - q * Rv20
    b11 = Rv11 - q * Rv21
    det = b00 * b11 - b01 * b10
    if not abs(det) > 1e-300:
        det = 1e-300
    i00, i01, i10, i11 = b11 / det, -b01 / det, -b10 / det, b00 / det
    a00, a01 = i00 * j00 + i01 * j10, i00 * j01 + i01 * j11
    a10, a11 = i10 * j00 + i11 * j10, i10 * j01 + i11 * j11
    t00, t01, t11 = a00 * a00 + a10 * a10, a00 * a01 + a10 * a11, a01 * a01 + a11 * a11
    gg = 0.5 * (t00 + t11 + math.sqrt((t00 - t11) ** 2 + 4 * t01 * t01))
    gamma = math.sqrt(gg if gg > 1e-300 else 1e-300)
    r00, r01, r10, r11 = a00 / gamma, a01 / gamma, a10 / gamma, a11 / gamma
    v0 = 1.0 - r00 * r00 - r10 * r10
    v1 = 1.0 - r01 * r01 - r11 * r11
    b0 = math.sqrt(v0 if v0 > 0.0 else 0.0)
    b1 = math.sqrt(v1 if v1 > 0.0 else 0.0)
    if r00 * r01 + r10 * r11 > 0:
        b1 = -b1
    tz = 1.0 / gamma
    Ecols = (e1, e2, e0)  # E = [e1 e2 e0] (columns)
    for sol in range(2):
        sgn = 1.0 if sol == 0 else -1.0
        # symmetric orthonormalisation of the two columns (pnp_lh1._orthonormal_pair)
        A0, A1, A2, _ = _unit3(r00, r10, sgn * b0)
        B0, B1, B2, _ = _unit3(r01, r11, sgn * b1)
        M0, M1, M2, _ = _unit3(A0 + B0, A1 + B1, A2 + B2)
        D0, D1, D2, _ = _unit3(A0 - B0, A1 - B1, A2 - B2)
        hh = math.sqrt(0.5)
        c1 = ((M0 + D0) * hh, (M1 + D1) * hh, (M2 + D2) * hh)
        c2 = ((M0 - D0) * hh, (M1 - D1) * hh, (M2 - D2) * hh)
        c3 = (c1[1] * c2[2] - c1[2] * c2[1], c1[2] * c2[0] - c1[0] * c2[2], c1[0] * c2[1] - c1[1] * c2[0])
        Rt = ((c1[0], c2[0], c3[0]), (c1[1], c2[1], c3[1]), (c1[2], c2[2], c3[2]))  # columns c1 c2 c3
        out_r = ra if sol == 0 else rb
        out_t = ta if sol == 0 else tb
        # R = Rv Rt E^T
        for i in range(3):
            RvRt0 = E[3 * i] * Rt[0][0] + E[3 * i + 1] * Rt[1][0] + E[3 * i + 2] * Rt[2][0]
            RvRt1 = E[3 * i] * Rt[0][1] + E[3 * i + 1] * Rt[1][1] + E[3 * i + 2] * Rt[2][1]
            RvRt2 = E[3 * i] * Rt[0][2] + E[3 * i + 1] * Rt[1][2] + E[3 * i + 2] * Rt[2][2]
            for j in range(3):
                out_r[3 * i + j] = RvRt0 * Ecols[0][j] + RvRt1 * Ecols[1][j] + RvRt2 * Ecols[2][j]
        out_t[0] = p * tz - (out_r[0] * c[0] + out_r[1] * c[1] + out_r[2] * c[2])
        out_t[1] = q * tz - (out_r[3] * c[0] + out_r[4] * c[1] + out_r[5] * c[2])
        out_t[2] = tz - (out_r[6] * c[0] + out_r[7] * c[1] + out_r[8] * c[2])


# ------------------------------------------------------------------------------ one frame

@numba.njit(**_LEAF)
def _noise_quadratic(rx, ry, wx, wy, n, sigma, rho):
    """r^T Sigma^-1 r under Chen eq. 19's noise (pnp_lh1._noise_quadratic)."""
    if rho < 0.0:
        rho = 0.0
    if rho > 1.0 - 1e-9:
        rho = 1.0 - 1e-9
    q = 0.0
    for axis in range(2):
        ss = s1 = nw = 0.0
        for i in range(n):
            e = rx[i] if axis == 0 else ry[i]
            ss += e * e
            s1 += e
            nw += wx[i] if axis == 0 else wy[i]
        cc = rho / (1.0 - rho + nw * rho)
        q += ss - cc * s1 * s1
    return q / (sigma * sigma * (1.0 - rho))


@numba.njit(inline="always", **_LEAF)
def _consider(SA, n, na, size, r0, t0, max_iterations, track_alt, cos_d, wk, bs):
    """Refine the start (r0, t0) and keep it as the best or the runner-up (pnp_lh1's consider)."""
    sc = _views(wk)
    r, t, out = sc.rc, sc.tc, sc.out
    for k in range(9):
        r[k] = r0[k]
    for k in range(3):
        t[k] = t0[k]
    _refine(SA, n, na, r, t, max_iterations, wk, out)
    cost, it, conv, ok, zmin, zmax = out[0], out[1], out[2] > 0.5, out[3] > 0.5, out[4], out[5]
    ok = ok and math.isfinite(cost) and zmax <= 1e5 * size
    if not ok:
        st = DEGENERATE
    elif zmin <= 0:
        st = BEHIND
    elif conv:
        st = OK
    else:
        st = NOT_CONVERGED
    best_R, best_t, alt_R, alt_t, best_v = bs.best_R, bs.best_t, bs.alt_R, bs.alt_t, bs.vals
    prev_ok = best_v[3] == OK  # vals: best_cost, best_it, alt_cost, best_status
    if st == OK:
        better = (not prev_ok) or cost < best_v[0]
    else:
        better = (not prev_ok) and ok and cost < best_v[0]
    if better:
        if track_alt and prev_ok:
            for k in range(9):
                sc.oR[k] = best_R[k]
            for k in range(3):
                sc.ot[k] = best_t[k]
            ocost = best_v[0]
        for k in range(9):
            best_R[k] = r[k]
        for k in range(3):
            best_t[k] = t[k]
        best_v[0], best_v[1], best_v[3] = cost, it, st
        if track_alt:
            if math.isfinite(best_v[2]) and not _distinct(alt_R, best_R, cos_d):
                best_v[2] = np.inf
            if prev_ok and ocost < best_v[2] and _distinct(sc.oR, best_R, cos_d):
                for k in range(9):
                    alt_R[k] = sc.oR[k]
                for k in range(3):
                    alt_t[k] = sc.ot[k]
                best_v[2] = ocost
    elif track_alt and st == OK:
        if cost < best_v[2] and _distinct(r, best_R, cos_d):
            for k in range(9):
                alt_R[k] = r[k]
            for k in range(3):
                alt_t[k] = t[k]
            best_v[2] = cost


@numba.njit(inline="always", **_LEAF)
def _solve_frame(SA, n, R0, t0, has_init, max_iterations, sigma, rho,
                 consts, wk, bs, res, same):
    """One frame (pnp_lh1.solve_pnp_lm). SA (9, n): the frame's sensor arrays Px, Py, Pz, ux, uy, wx, wy, w,
    wany as rows (one array through the inlined chain down to the calls of :func:`_pass_series` and
    :func:`_posit`: passed as 7 or 6 arrays, ~45 words of arguments were pushed per call).
    res[:] = status, residual, iterations, alt residual.
    same: the points and lit pattern are those of the previous frame solved with ``wk``, whose
    geometry (counts, centroid, scatter, planarity, collinearity, size, POSIT's centred points and
    inverse scatter) is reused — the same values, computed once per run of such frames."""
    Px, Py, Pz, ux, uy, wx, wy, w, wany = SA[0], SA[1], SA[2], SA[3], SA[4], SA[5], SA[6], SA[7], SA[8]
    sc = _views(wk)
    min_angles, min_sensors, min_start, planar_thr, coplanar_thr, collinear_thr, retry_res, cos_d, amb_lr = (
        consts[0], consts[1], consts[2], consts[3], consts[4], consts[5], consts[6], consts[7], consts[8])
    c, S, Sa, geo = sc.c, sc.S, sc.Sa, sc.geo
    if same:
        nl, na, ns, planarity, collinear, size = geo[0], geo[1], geo[2], geo[3], geo[4] > 0.5, geo[5]
    else:
        nl = na = ns = 0.0
        for i in range(n):
            nl += w[i]
            na += wx[i] + wy[i]
            ns += wany[i]
        _scatter(Px, Py, Pz, w, n, c, S)
        e_lo, _, e_hi = _sym3_eigvals(S[0], S[1], S[2], S[3], S[4], S[5])
        planarity = math.sqrt((e_lo if e_lo > 0.0 else 0.0) / (e_hi if e_hi > 1e-300 else 1e-300))
        if ns == nl:  # every seen sensor has both angles: wany = w, the same scatter
            for k in range(6):
                Sa[k] = S[k]
        else:
            _scatter(Px, Py, Pz, wany, n, sc.c2, Sa)
        minors = Sa[0] * Sa[1] - Sa[3] * Sa[3] + Sa[0] * Sa[2] - Sa[4] * Sa[4] + Sa[1] * Sa[2] - Sa[5] * Sa[5]
        trace = Sa[0] + Sa[1] + Sa[2]
        collinear = minors <= collinear_thr * collinear_thr * trace * trace
        size = math.sqrt((trace if trace > 0.0 else 0.0) / (ns if ns > 1.0 else 1.0))
        geo[0], geo[1], geo[2], geo[3], geo[4], geo[5] = nl, na, ns, planarity, 1.0 if collinear else 0.0, size
        geo[6] = 0.0  # POSIT's centred points / inverse scatter not yet computed for this geometry
    best_R, best_t, alt_R, alt_t, bv = bs.best_R, bs.best_t, bs.alt_R, bs.alt_t, bs.vals
    for k in range(9):
        best_R[k] = np.nan
        alt_R[k] = np.nan
    for k in range(3):
        best_t[k] = np.nan
        alt_t[k] = np.nan
    bv[0], bv[1], bv[2], bv[3] = np.inf, 0.0, np.inf, DEGENERATE
    status = TOO_FEW
    valid = na >= min_angles and ns >= min_sensors
    if valid and collinear:
        status = DEGENERATE
    todo = valid and not collinear
    track_alt = sigma == sigma  # sigma NaN = None: no runner-up, no test
    if todo:
        cold = True
        tried_initial = False
        if has_init:
            _consider(SA, n, na, size, R0, t0, max_iterations, track_alt, cos_d, wk, bs)
            tried_initial = True
            rms = math.sqrt(bv[0] / (na if na > 1.0 else 1.0))
            if bv[3] == OK and rms <= retry_res:
                cold = False
        if cold and nl < min_start:
            if not tried_initial:
                bv[3] = NO_START
            cold = False
        if cold and planarity > coplanar_thr:
            _posit(SA, n, nl, c, S, sc.r0, sc.t0, wk, geo[6] > 0.5)
            geo[6] = 1.0
            _consider(SA, n, na, size, sc.r0, sc.t0, max_iterations, track_alt, cos_d, wk, bs)
        if cold:
            retry = retry_res if not (sigma == sigma and sigma != 0.0) else min(retry_res, 5.0 * sigma)
            rms = math.sqrt(bv[0] / (na if na > 1.0 else 1.0))
            poor = bv[3] != OK or not (rms <= retry)
            if planarity < planar_thr or poor:
                _ippe_pair(Px, Py, Pz, ux, uy, w, n, nl, c, sc.r0, sc.t0, sc.r1, sc.t1, wk)
                _consider(SA, n, na, size, sc.r0, sc.t0, max_iterations, track_alt, cos_d,
                          wk, bs)
                _consider(SA, n, na, size, sc.r1, sc.t1, max_iterations, track_alt, cos_d,
                          wk, bs)
        status = int(bv[3])
    nam = na if na > 1.0 else 1.0
    resid = math.sqrt(bv[0] / nam)
    if not todo or not math.isfinite(bv[0]):
        resid = np.nan
    amb = False
    if todo and status == OK and math.isfinite(bv[2]) and sigma == sigma and sigma > 0:
        _eval(Px, Py, Pz, ux, uy, wx, wy, n, best_R, best_t, sc.rx, sc.ry, sc.zz)
        q1 = _noise_quadratic(sc.rx, sc.ry, wx, wy, n, sigma, rho)
        _eval(Px, Py, Pz, ux, uy, wx, wy, n, alt_R, alt_t, sc.rx, sc.ry, sc.zz)
        q2 = _noise_quadratic(sc.rx, sc.ry, wx, wy, n, sigma, rho)
        if q2 - q1 < amb_lr:
            amb = True
            status = AMBIGUOUS
    res[0] = status
    res[1] = resid
    res[2] = bv[1]
    res[3] = math.sqrt(bv[2] / nam) if amb else np.nan
    return amb


# ------------------------------------------------------------------------------ the batch

Scratch = namedtuple("Scratch", ["rx", "ry", "zz", "rx2", "ry2", "zz2", "qx", "qy", "qz", "A", "L", "inv", "g", "y",
                                 "step", "E", "rn", "tn", "rc", "tc", "out", "oR", "ot", "c", "c2", "S", "Sa", "S3",
                                 "A8", "b8", "row8", "r0", "t0", "r1", "t1", "g2", "dep", "dep2", "h8", "geo", "si",
                                 "px", "py", "pz"])
Best = namedtuple("Best", ["best_R", "best_t", "alt_R", "alt_t", "vals"])
#: The scratch memory of one thread, in six arrays: V (12, n) per-sensor vectors, M6 (2, 6, 6) the
#: normal matrix and its factor, A8 (8, 8) IPPE's normal matrix, S3 (3, 3), B (28, 12) small vectors,
#: LB (8, 9) the LM core's small vectors (layoutkit.lm_numba.refine).
#: Functions take this and name its parts with :func:`_views` (inlined; unused views cost nothing):
#: passing 39 separate arrays by value cost ~300 words of argument copying per call.
Work = namedtuple("Work", ["V", "M6", "A8", "S3", "B", "LB"])


@numba.njit(**_JIT)
def _aligned_rows(k, n):
    """Zeros (k, n) whose data starts on a 64-byte boundary (a cache line, one AVX-512 vector). numba's
    arrays are aligned to less: with rows of a multiple of 8 doubles starting anywhere, every vector load of
    the sensor loops split two cache lines or not by chance of the allocator (a kernel 0.77-0.84 us per
    frame at n = 12 by what the process had allocated before)."""
    buf = np.zeros(k * n + 8)
    off = ((-buf.ctypes.data) % 64) // 8
    return buf[off:off + k * n].reshape((k, n))


@numba.njit(**_JIT)
def _scratch(n):
    return Work(_aligned_rows(12, n), np.zeros((2, 6, 6)), np.zeros((8, 8)), np.zeros((3, 3)), np.zeros((28, 12)),
                np.zeros((8, 9)))


@numba.njit(**_LEAF)
def _views(wk):
    """The named scratch arrays (:data:`Scratch`) as views of ``wk`` (:data:`Work`)."""
    V, M6, B = wk.V, wk.M6, wk.B
    return Scratch(V[0], V[1], V[2], V[3], V[4], V[5], V[6], V[7], V[8], M6[0], M6[1], B[0], B[1], B[2],
                   B[3], B[4], B[5], B[6], B[7], B[8], B[9], B[10], B[11], B[12], B[13], B[14], B[15], wk.S3,
                   wk.A8, B[16], B[17], B[18], B[19], B[20], B[21], B[22], B[23], B[24], B[25], B[26], B[27],
                   V[9], V[10], V[11])


@numba.njit(**_JIT)
def _solve_range(lo, hi, P, shared, cot, lit, R0, t0, has_init, max_iterations, sigma, rho, consts,
                 R_out, t_out, status, resid, iters, altR, altt, altres):
    """Frames lo..hi-1 with one set of scratch arrays (see :func:`solve_batch`): allocates them (this
    function keeps numba's reference counting) and runs :func:`_frames` (compiled without it)."""
    n = cot.shape[1]
    # above 6 sensors the sensor arrays are padded with unseen sensors to a multiple of 8 (weights 0:
    # they add exact zeros everywhere), so that the vectorised pass (8 doubles per AVX-512 vector) has
    # no scalar remainder: n = 12 -12 %, n = 48 -39 % per frame; at n = 4 the padding cost 10 %
    m = (n + 7) // 8 * 8 if n > 6 else n
    wk = _scratch(m)
    bs = Best(np.empty(9), np.empty(3), np.empty(9), np.empty(3), np.empty(4))
    S = _aligned_rows(9, m)  # Px, Py, Pz, ux, uy, wx, wy, w, wany
    r0, tt0 = np.zeros(9), np.zeros(3)
    res = np.empty(4)
    _frames(lo, hi, P, shared, cot, lit, R0, t0, has_init, max_iterations, sigma, rho, consts,
            R_out, t_out, status, resid, iters, altR, altt, altres, m, wk, bs, S, r0, tt0, res)


@numba.njit(**_LEAF)
def _frames(lo, hi, P, shared, cot, lit, R0, t0, has_init, max_iterations, sigma, rho, consts,
            R_out, t_out, status, resid, iters, altR, altt, altres, m, wk, bs, S, r0, tt0, res):
    """The frame loop of :func:`_solve_range` with :func:`_solve_frame` inlined (one call per range: as a
    call per frame, its ~170 words of array arguments were copied every frame). S (9, m): the frame's
    sensor arrays Px, Py, Pz, ux, uy, wx, wy, w, wany (zeros past n)."""
    n = cot.shape[1]
    Px, Py, Pz, ux, uy, wx, wy, w, wany = S[0], S[1], S[2], S[3], S[4], S[5], S[6], S[7], S[8]
    if shared:  # the body's points, once for all frames
        for i in range(n):
            Px[i], Py[i], Pz[i] = P[0, i, 0], P[0, i, 1], P[0, i, 2]
    for f in range(lo, hi):
        # the body's geometry is the previous frame's when the body is shared and the same angles are lit
        same = shared and f > lo
        if same:
            for i in range(n):
                if lit[f, i, 0] != lit[f - 1, i, 0] or lit[f, i, 1] != lit[f - 1, i, 1]:
                    same = False
                    break
        if same:  # the weights are the previous frame's: only the measurements change
            for i in range(n):
                ux[i] = cot[f, i, 0] if wx[i] > 0.0 else 0.0
                uy[i] = cot[f, i, 1] if wy[i] > 0.0 else 0.0
        else:
            for i in range(n):
                lx, ly = lit[f, i, 0], lit[f, i, 1]
                wx[i] = 1.0 if lx else 0.0
                wy[i] = 1.0 if ly else 0.0
                w[i] = wx[i] * wy[i]
                wany[i] = 1.0 if (lx or ly) else 0.0
                ux[i] = cot[f, i, 0] if lx else 0.0
                uy[i] = cot[f, i, 1] if ly else 0.0
                if shared:
                    pass
                elif lx or ly:
                    Px[i], Py[i], Pz[i] = P[f, i, 0], P[f, i, 1], P[f, i, 2]
                else:  # an unseen sensor's (maybe non-finite) point never enters, as pnp_lh1._Frames
                    Px[i] = Py[i] = Pz[i] = 0.0
        hi_ = has_init[f]
        if hi_:
            for a in range(3):
                for c in range(3):
                    r0[3 * a + c] = R0[f, a, c]
                tt0[a] = t0[f, a]
        amb = _solve_frame(S, m, r0, tt0, hi_, max_iterations, sigma, rho,
                           consts, wk, bs, res, same)
        status[f] = int(res[0])
        resid[f] = res[1]
        iters[f] = int(res[2])
        altres[f] = res[3]
        for a in range(3):
            for c in range(3):
                R_out[f, a, c] = bs.best_R[3 * a + c]
                altR[f, a, c] = bs.alt_R[3 * a + c] if amb else np.nan
            t_out[f, a] = bs.best_t[a]
            altt[f, a] = bs.alt_t[a] if amb else np.nan


@numba.njit(**_JIT)
def solve_batch(P, shared, cot, lit, R0, t0, has_init, max_iterations, sigma, rho, consts,
                R_out, t_out, status, resid, iters, altR, altt, altres):
    """Solve F frames on one thread; outputs written in place.

    P : (1, n, 3) shared body (``shared``) or (F, n, 3) m; cot : (F, n, 2) the cotangents of the sweep
    angles (normalised image coordinates, Chen eq. 2; read where lit only); lit : (F, n, 2) bool
    (cleaned as by :func:`layoutkit.pnp_lh1.solve_pnp_lh1`); has_init (F,) which frames have a start,
    R0 (F, 3, 3), t0 (F, 3) the starts (read where has_init only: (1, 3, 3), (1, 3) when none has); sigma NaN for no ambiguity test; consts the thresholds of pnp_lh1 (in the order of
    :func:`layoutkit.pnp_lh1.solve_pnp_compiled`). Outputs as :class:`layoutkit.pnp_result.PnPResult`.
    """
    _solve_range(np.int64(0), cot.shape[0], P, shared, cot, lit, R0, t0, has_init, max_iterations, sigma, rho, consts,
                 R_out, t_out, status, resid, iters, altR, altt, altres)


def solve_batch_parallel(P, shared, cot, lit, R0, t0, has_init, max_iterations, sigma, rho, consts, block,
                         R_out, t_out, status, resid, iters, altR, altt, altres):
    """:func:`solve_batch` with blocks of ``block`` frames spread over numba's threads; on one thread
    :func:`solve_batch` itself (the whole batch as one range: no per-block scratch, the geometry reused
    across blocks; 4 % per frame at n = 12). (The thread count is read here: read inside the kernel it
    is a runtime address, which numba cannot cache.)"""
    if numba.get_num_threads() == 1:
        solve_batch(P, shared, cot, lit, R0, t0, has_init, max_iterations, sigma, rho, consts,
                    R_out, t_out, status, resid, iters, altR, altt, altres)
    else:
        _solve_blocks(P, shared, cot, lit, R0, t0, has_init, max_iterations, sigma, rho, consts, block,
                      R_out, t_out, status, resid, iters, altR, altt, altres)


@numba.njit(parallel=True, **_JIT)
def _solve_blocks(P, shared, cot, lit, R0, t0, has_init, max_iterations, sigma, rho, consts, block,
                  R_out, t_out, status, resid, iters, altR, altt, altres):
    """Blocks of ``block`` frames spread over numba's threads, each with its own scratch."""
    F = cot.shape[0]
    nb = (F + block - 1) // block
    for b in prange(nb):
        _solve_range(b * block, min(F, (b + 1) * block), P, shared, cot, lit, R0, t0, has_init, max_iterations,
                     sigma, rho, consts, R_out, t_out, status, resid, iters, altR, altt, altres)
