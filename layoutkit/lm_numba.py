"""The Levenberg–Marquardt core of the compiled pose solvers (single-station PnP and joint).

One compiled LM serves :mod:`layoutkit.pnp_numba` (one ideal LH1 station) and :mod:`layoutkit.joint_numba`
(several calibrated LH1 / LH2 stations, motion compensation): the same rotation update
(:func:`exp_rot`, Rodrigues, left perturbation ``R <- exp([dphi]x) R``, ``t <- t + dt``, design §2),
the same damped normal equations (unrolled 6 × 6 LDL^T factor of ``A + lam diag(A)``, :func:`factor`,
:func:`apply`) and the same damping and stop rule (:func:`refine`: a step is first tried with the
previous iteration's factor; converged when the Gauss–Newton step's predicted decrease is below
``rtol cost + atol m / 2``, that last step taken without a new evaluation; damping ×0.1 on an
accepted step (floor 1e-12), ×10 on a rejected one, given up above 1e10). The numpy references of
the rule are :func:`layoutkit.pnp_lh1._refine` and :func:`layoutkit.joint._lm`.

A solver plugs its model in as a compiled function ``pass_fn(ctx, r, t, mode, A, g, aux) -> cost``:
the sum of squared residuals at the pose (r (9,) row-major rotation, t (3,) m); mode >= 1 also the
gradient g (6,) = J^T e, mode 2 also the upper triangle of the Gram matrix A (6, 6) = J^T J (J the
residuals' Jacobian with respect to the perturbation (dphi, dt), sign such that the step is
A^-1 g); ``aux`` (k,) a per-pose by-product (depths) the caller reads back. ``ctx`` is the model's
data (a tuple). numba compiles :func:`refine` once per ``pass_fn`` (one specialisation per solver).

Imported on first use only (by the two kernels); compiled once and cached on disk (``cache=True``).
"""
from __future__ import annotations

import math

import numba

# fastmath: fused multiply-add, reciprocals and signed zeros only (no NaN / infinity assumptions: NaN
# marks unseen sensors and failed frames). Functions here allocate nothing and keep no array: compiled
# without the reference-counting runtime (numba's private ``_nrt`` flag), so a call does not
# incref/decref each array argument (27 % of the PnP kernel's time at n = 12 before, measured with perf).
JIT = dict(cache=True, fastmath={"contract", "arcp", "nsz"}, nogil=True, error_model="numpy")
LEAF = dict(JIT, _nrt=False)

#: rows of the LM's small-vector scratch ``B`` (at least (8, 9)): 1 / diag(L), gradient, trial
#: gradient, forward-substitution vector, step, exp([dphi]x), trial rotation, trial translation.
B_INV, B_G, B_G2, B_Y, B_STEP, B_E, B_RN, B_TN = range(8)


@numba.njit(**LEAF)
def exp_rot(x, y, z, E):
    """E (9,) = exp([phi]x), phi = (x, y, z) rad, row-major (Rodrigues, series for small angles)."""
    th2 = x * x + y * y + z * z
    if th2 < 1e-8:
        a = 1.0 - th2 / 6.0 + th2 * th2 / 120.0
        b = 0.5 - th2 / 24.0 + th2 * th2 / 720.0
    else:
        th = math.sqrt(th2)
        a = math.sin(th) / th
        b = (1.0 - math.cos(th)) / (th * th)
    bxy, bxz, byz = b * x * y, b * x * z, b * y * z
    ax, ay, az = a * x, a * y, a * z
    E[0] = 1.0 - b * (y * y + z * z)
    E[1] = bxy - az
    E[2] = bxz + ay
    E[3] = bxy + az
    E[4] = 1.0 - b * (x * x + z * z)
    E[5] = byz - ax
    E[6] = bxz - ay
    E[7] = byz + ax
    E[8] = 1.0 - b * (x * x + y * y)


@numba.njit(**LEAF)
def compose(E, r, out):
    """out = E @ R, all (9,) row-major."""
    for i in range(3):
        e0, e1, e2 = E[3 * i], E[3 * i + 1], E[3 * i + 2]
        for j in range(3):
            out[3 * i + j] = e0 * r[j] + e1 * r[3 + j] + e2 * r[6 + j]


@numba.njit(**LEAF)
def factor(A, lam, L, inv):
    """LDL^T factor of A + lam diag(A) (upper triangle of A read), unrolled, without square roots (the
    Cholesky factor of pnp_lh1._cholesky_factor is L sqrt(D); the pivots d_c are its L[c, c]^2): L[i, c]
    (i > c) the unit lower factor, L[c, i] = L[i, c] d_c, inv[c] = 1 / d_c; False where a pivot is not
    above 1e-14 max diag(A) (singular or rank-deficient normal equations).
    Unrolled in scalars (the loops' operations in the same order; the loop form went through memory, a
    chain of store / load latencies: factor + apply were 14 % of a PnP solve at n = 12, perf). Not inlined:
    inlined (factor, apply, compose) the kernel loaded from numba's disk cache measured 6 % slower than
    the loops (freshly compiled, 7 % faster), called 2.7 % faster both ways (in-process A/B, one core)."""
    scale = A[0, 0]
    for i in range(1, 6):
        if A[i, i] > scale:
            scale = A[i, i]
    if not scale > 1e-300:  # np.maximum(.., 1e-300) (NaN propagates there: keep NaN)
        scale = 1e-300 if scale == scale else scale
    ok = True
    f = 1.0 + lam
    lim = 1e-14 * scale
    # column 0
    s = A[0, 0] * f
    if not s > lim:
        ok = False
        s = scale
    i0 = 1.0 / s
    u01 = A[0, 1]
    l10 = u01 * i0
    u02 = A[0, 2]
    l20 = u02 * i0
    u03 = A[0, 3]
    l30 = u03 * i0
    u04 = A[0, 4]
    l40 = u04 * i0
    u05 = A[0, 5]
    l50 = u05 * i0
    # column 1
    s = A[1, 1] * f
    s -= l10 * u01
    if not s > lim:
        ok = False
        s = scale
    i1 = 1.0 / s
    s2 = A[1, 2]
    s2 -= l20 * u01
    u12 = s2
    l21 = u12 * i1
    s2 = A[1, 3]
    s2 -= l30 * u01
    u13 = s2
    l31 = u13 * i1
    s2 = A[1, 4]
    s2 -= l40 * u01
    u14 = s2
    l41 = u14 * i1
    s2 = A[1, 5]
    s2 -= l50 * u01
    u15 = s2
    l51 = u15 * i1
    # column 2
    s = A[2, 2] * f
    s -= l20 * u02
    s -= l21 * u12
    if not s > lim:
        ok = False
        s = scale
    i2 = 1.0 / s
    s2 = A[2, 3]
    s2 -= l30 * u02
    s2 -= l31 * u12
    u23 = s2
    l32 = u23 * i2
    s2 = A[2, 4]
    s2 -= l40 * u02
    s2 -= l41 * u12
    u24 = s2
    l42 = u24 * i2
    s2 = A[2, 5]
    s2 -= l50 * u02
    s2 -= l51 * u12
    u25 = s2
    l52 = u25 * i2
    # column 3
    s = A[3, 3] * f
    s -= l30 * u03
    s -= l31 * u13
    s -= l32 * u23
    if not s > lim:
        ok = False
        s = scale
    i3 = 1.0 / s
    s2 = A[3, 4]
    s2 -= l40 * u03
    s2 -= l41 * u13
    s2 -= l42 * u23
    u34 = s2
    l43 = u34 * i3
    s2 = A[3, 5]
    s2 -= l50 * u03
    s2 -= l51 * u13
    s2 -= l52 * u23
    u35 = s2
    l53 = u35 * i3
    # column 4
    s = A[4, 4] * f
    s -= l40 * u04
    s -= l41 * u14
    s -= l42 * u24
    s -= l43 * u34
    if not s > lim:
        ok = False
        s = scale
    i4 = 1.0 / s
    s2 = A[4, 5]
    s2 -= l50 * u04
    s2 -= l51 * u14
    s2 -= l52 * u24
    s2 -= l53 * u34
    u45 = s2
    l54 = u45 * i4
    # column 5
    s = A[5, 5] * f
    s -= l50 * u05
    s -= l51 * u15
    s -= l52 * u25
    s -= l53 * u35
    s -= l54 * u45
    if not s > lim:
        ok = False
        s = scale
    i5 = 1.0 / s
    L[0, 1], L[1, 0] = u01, l10
    L[0, 2], L[2, 0] = u02, l20
    L[0, 3], L[3, 0] = u03, l30
    L[0, 4], L[4, 0] = u04, l40
    L[0, 5], L[5, 0] = u05, l50
    L[1, 2], L[2, 1] = u12, l21
    L[1, 3], L[3, 1] = u13, l31
    L[1, 4], L[4, 1] = u14, l41
    L[1, 5], L[5, 1] = u15, l51
    L[2, 3], L[3, 2] = u23, l32
    L[2, 4], L[4, 2] = u24, l42
    L[2, 5], L[5, 2] = u25, l52
    L[3, 4], L[4, 3] = u34, l43
    L[3, 5], L[5, 3] = u35, l53
    L[4, 5], L[5, 4] = u45, l54
    inv[0], inv[1], inv[2], inv[3], inv[4], inv[5] = i0, i1, i2, i3, i4, i5
    return ok


@numba.njit(**LEAF)
def apply(L, inv, g, y, x):
    """x (6,) = (L D L^T)^-1 g with a factor from :func:`factor`, unrolled in scalars (y (6,) unused, kept
    for the callers' signature)."""
    y0 = g[0]
    y1 = g[1]
    y1 -= L[1, 0] * y0
    y2 = g[2]
    y2 -= L[2, 0] * y0
    y2 -= L[2, 1] * y1
    y3 = g[3]
    y3 -= L[3, 0] * y0
    y3 -= L[3, 1] * y1
    y3 -= L[3, 2] * y2
    y4 = g[4]
    y4 -= L[4, 0] * y0
    y4 -= L[4, 1] * y1
    y4 -= L[4, 2] * y2
    y4 -= L[4, 3] * y3
    y5 = g[5]
    y5 -= L[5, 0] * y0
    y5 -= L[5, 1] * y1
    y5 -= L[5, 2] * y2
    y5 -= L[5, 3] * y3
    y5 -= L[5, 4] * y4
    x5 = y5 * inv[5]
    x4 = y4 * inv[4]
    x4 -= L[5, 4] * x5
    x3 = y3 * inv[3]
    x3 -= L[4, 3] * x4
    x3 -= L[5, 3] * x5
    x2 = y2 * inv[2]
    x2 -= L[3, 2] * x3
    x2 -= L[4, 2] * x4
    x2 -= L[5, 2] * x5
    x1 = y1 * inv[1]
    x1 -= L[2, 1] * x2
    x1 -= L[3, 1] * x3
    x1 -= L[4, 1] * x4
    x1 -= L[5, 1] * x5
    x0 = y0 * inv[0]
    x0 -= L[1, 0] * x1
    x0 -= L[2, 0] * x2
    x0 -= L[3, 0] * x3
    x0 -= L[4, 0] * x4
    x0 -= L[5, 0] * x5
    x[0], x[1], x[2], x[3], x[4], x[5] = x0, x1, x2, x3, x4, x5


def make_refine(pass_fn, name, trial_gram=False):
    """The LM core compiled for one model ``pass_fn`` (a compiled function, see the module docstring),
    cached on disk under ``refine_<name>``: the model is a constant of the closure, so its calls are
    direct (a compiled function passed as an argument would be a runtime address, which numba cannot
    cache). Inlined into its caller at numba's IR level (``inline="always"``; the caller is the one
    place each solver calls it): as a separate function the PnP kernel was ~6-9 % slower per frame at
    n = 12 (interleaved A/B, one thread). ``trial_gram``: the trial poses are evaluated with the Gram
    matrix (mode 2, into M6[2]), kept when the step is accepted — for models whose residuals cost far
    more than the Gram matrix (the joint solve's calibrated forward models), where a second pass at the
    accepted pose would cost a whole model evaluation; the same steps and results.
    """

    def refine(ctx, r, t, na, rtol, atol, max_iterations, M6, B, aux, aux2, out):
        """Levenberg–Marquardt from (r (9,), t (3,)), updated in place (the rule in the module docstring;
        numpy reference :func:`layoutkit.pnp_lh1._refine`). na: number of residuals (for ``atol``).
        M6 (2, 6, 6) scratch (Gram matrix, factor; (3, 6, 6) with ``trial_gram``), B (8, >= 9) scratch (rows :data:`B_INV` ...), aux / aux2
        the pass's by-product at the current / trial pose (aux: that of the last evaluated accepted pose).
        out[0:4] = cost, iterations, converged, ok (normal equations solvable). At the end A = M6[0] is the
        Gram matrix of the last accepted evaluated pose when ``trial_gram`` (aux's pose)."""
        A, L = M6[0], M6[1]
        A2 = M6[2] if trial_gram else M6[0]
        inv, g, g2, y, step, E, rn, tn = B[B_INV], B[B_G], B[B_G2], B[B_Y], B[B_STEP], B[B_E], B[B_RN], B[B_TN]
        cost = pass_fn(ctx, r, t, 2, A, g, aux)
        gram_here = True  # A is the Gram matrix at the current pose
        lam = 1e-6
        iters = 0
        conv = False
        ok = True
        have_fac = False
        for _ in range(max_iterations):
            tol = rtol * cost + atol * 0.5 * na
            small = False
            okc = True
            if have_fac:
                apply(L, inv, g, y, step)
                dl = 0.0
                for k in range(6):
                    dl += step[k] * g[k]
                small = dl <= tol
            if not small:
                if not gram_here:
                    pass_fn(ctx, r, t, 2, A, g, aux2)
                    gram_here = True
                okc = factor(A, lam, L, inv)
                apply(L, inv, g, y, step)
                dl = 0.0
                for k in range(6):
                    dl += step[k] * g[k]
                small = okc and dl <= tol
                have_fac = True
            exp_rot(step[0], step[1], step[2], E)
            compose(E, r, rn)
            for k in range(3):
                tn[k] = t[k] + step[3 + k]
            acc = False
            if okc and not small:
                if trial_gram:
                    cn = pass_fn(ctx, rn, tn, 2, A2, g2, aux2)
                else:
                    cn = pass_fn(ctx, rn, tn, 1, A, g2, aux2)
                if cn <= cost:
                    acc = True
                    cost = cn
                    for k in range(6):
                        g[k] = g2[k]
                    for k in range(aux.shape[0]):
                        aux[k] = aux2[k]
                    if trial_gram:
                        for p in range(6):
                            for q in range(p, 6):
                                A[p, q] = A2[p, q]
                    gram_here = trial_gram
            if small:
                c2 = cost - dl
                cost = c2 if c2 > 0.0 else 0.0
            if acc or small:
                for k in range(9):
                    r[k] = rn[k]
                for k in range(3):
                    t[k] = tn[k]
            if acc:
                lnew = lam * 0.1
                if lnew < 1e-12:
                    lnew = 1e-12
            elif okc and not small:
                lnew = lam * 10.0
            else:
                lnew = lam
            lam = lnew
            iters += 1
            if small:
                conv = True
            if not okc:
                ok = False
            if small or not okc or lnew > 1e10:
                break
        out[0] = cost
        out[1] = iters
        out[2] = 1.0 if conv else 0.0
        out[3] = 1.0 if ok else 0.0

    refine.__name__ = refine.__qualname__ = "refine_" + name
    return numba.njit(inline="always", **LEAF)(refine)
