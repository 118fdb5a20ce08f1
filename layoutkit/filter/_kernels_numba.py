"""numba kernels of the tracking filter (:mod:`layoutkit.filter.imm`; imported on first use only:
importing numba and compiling is not work for the package's import time).

Why one module of ~790 lines: the forward model, the predict/update, the gates and the IMM mixing
run inside one compiled call per sweep and share its argument layout (``PAR_*``, ``OUT_*``). Every function works on one sweep
with scalars and small arrays in registers; the numpy references they are tested against are
:func:`layoutkit.lighthouse.measure_jacobian` (forward model) and
:class:`layoutkit.filter.ekf.ErrorStateEKF` (predict / update).
"""
import math

import numba
import numpy as np

_JIT = dict(cache=True, fastmath=False, nogil=True)
LH2_TILT = math.pi / 6.0
# libsurvive's LH2 curve series (layoutkit.lighthouse._LH2_CURVE_SERIES; the test checks they agree)
F0, F1, F2, F3 = -8.0108022e-06, 0.0028679863, 5.3685255000000001e-06, 0.0076069798000000001


@numba.njit(**_JIT)
def _asin_d(u):
    """asin(clip(u, -1, 1)) and d/du (0 where clipped)."""
    if u >= 1.0:
        return math.pi / 2, 0.0
    if u <= -1.0:
        return -math.pi / 2, 0.0
    return math.asin(u), 1.0 / math.sqrt(1.0 - u * u)


@numba.njit(**_JIT)
def lh1_axis(x, y, z, k, c, corrected, g):
    """LH1 axis ``k`` of a point (x, y, z) in the station frame with calibration ``c`` (7,)
    (phase, tilt, curve, gib_phase, gib_mag, ...): the angle, and its gradient in ``g`` (3,)
    (lighthouse._lh1_axis)."""
    if k == 0:
        a, o = x, y
    else:
        a, o = y, x
    # gradients kept as (d/da, d/do, d/dz)
    r2 = a * a + z * z
    theta = math.atan2(z, a)
    ta, to, tz = -z / r2, 0.0, a / r2
    rho = math.sqrt(r2)
    tt = math.tan(c[1])
    u = tt * o / rho
    ua = -tt * o * a / (r2 * rho)
    uo = tt / rho
    uz = -tt * o * z / (r2 * rho)
    tilt, ds = _asin_d(u)
    q2 = o * o + z * z
    psi = math.atan2(o, z)
    pa, po, pz = 0.0, z / q2, -o / q2
    corr = theta + c[0] + tilt
    ca, co, cz = ta + ds * ua, to + ds * uo, tz + ds * uz
    base = corr + c[2] * psi * psi
    ba, bo, bz = ca + 2.0 * c[2] * psi * pa, co + 2.0 * c[2] * psi * po, cz + 2.0 * c[2] * psi * pz
    if corrected:
        xi, xa, xo, xz = corr, ca, co, cz
    else:
        xi, xa, xo, xz = theta, ta, to, tz
    arg = xi + c[3]
    v = base + c[4] * math.sin(arg)
    cg = c[4] * math.cos(arg)
    ga, go, gz = ba + cg * xa, bo + cg * xo, bz + cg * xz
    if k == 0:
        g[0], g[1], g[2] = ga, go, gz
    else:
        g[0], g[1], g[2] = go, ga, gz
    return v


@numba.njit(**_JIT)
def lh2_axis(x, y, z, k, c, corrected, g):
    """LH2 light plane ``k`` (0: t = -30°, 1: t = +30°) of a point in the station frame with
    calibration ``c`` (7,): the angle, and its gradient in ``g`` (3,) (lighthouse._lh2_axis)."""
    t = (-LH2_TILT if k == 0 else LH2_TILT) - c[1]
    r2 = x * x + z * z
    az = math.atan2(x, z)
    azx, azz = z / r2, -x / r2
    rho = math.sqrt(r2)
    r3 = math.sqrt(r2 + y * y)
    tn, ct, st = math.tan(t), math.cos(t), math.sin(t)
    A1 = tn * y / rho
    a1x = -tn * y * x / (r2 * rho)
    a1y = tn / rho
    a1z = -tn * y * z / (r2 * rho)
    s1, d1 = _asin_d(A1)
    og = az + s1 - c[5]
    K = c[2] + c[6] * math.cos(og)
    kk = -c[6] * math.sin(og)
    Kx, Ky, Kz = kk * (azx + d1 * a1x), kk * (d1 * a1y), kk * (azz + d1 * a1z)
    w = -y / (r3 * ct)
    f = y / (r3 * r3 * ct)
    wx = f * x / r3
    wy = -1.0 / (r3 * ct) + f * y / r3
    wz = f * z / r3
    s, dsw = _asin_d(w)
    sx, sy, sz = dsw * wx, dsw * wy, dsw * wz
    P = ((((F0 * s + F1) * s + F2) * s + F3) * s) * s
    dP = (((5 * F0 * s + 4 * F1) * s + 3 * F2) * s + 2 * F3) * s
    ddP = ((20 * F0 * s + 12 * F1) * s + 6 * F2) * s + 2 * F3
    den = ct + dP * K * st
    dnx = dP * st * Kx + K * st * ddP * sx
    dny = dP * st * Ky + K * st * ddP * sy
    dnz = dP * st * Kz + K * st * ddP * sz
    if A1 >= 1.0:
        A1c, inside = 1.0, 0.0
    elif A1 <= -1.0:
        A1c, inside = -1.0, 0.0
    else:
        A1c, inside = A1, 1.0
    A2 = A1c + P * K / den
    e1, e2, e3 = K / den, P / den, P * K / (den * den)
    A2x = inside * a1x + e1 * dP * sx + e2 * Kx - e3 * dnx
    A2y = inside * a1y + e1 * dP * sy + e2 * Ky - e3 * dny
    A2z = inside * a1z + e1 * dP * sz + e2 * Kz - e3 * dnz
    s2, d2 = _asin_d(A2)
    beta = az + s2
    bx, by, bz = azx + d2 * A2x, d2 * A2y, azz + d2 * A2z
    if corrected:
        xi, xx, xy, xz = beta, bx, by, bz
    else:
        xi, xx, xy, xz = az, azx, 0.0, azz
    arg = xi + c[3]
    v = beta + c[0] + c[4] * math.sin(arg)
    cg = c[4] * math.cos(arg)
    g[0], g[1], g[2] = bx + cg * xx, by + cg * xy, bz + cg * xz
    return v


@numba.njit(**_JIT)
def sweep_rows(pb, idx, R, p, Rs, ts, lh2, axis, c, corrected, z_pred, rows):
    """Predicted angles ``z_pred (m,)`` of sensors ``idx`` (m,) on ``axis`` of one station and
    their rows ``(m, 6)`` of d angle / d (left world rotation, world position) at the body pose
    ``R (3, 3), p (3,)``; station ``Rs`` (station → world), ``ts`` (3,), ``lh2`` kind flag,
    calibration ``c`` (7,) of that axis, ``corrected`` gib argument (filter.models + lighthouse)."""
    _sweep_rows(pb, idx, R, p, Rs, ts, lh2, axis, c, corrected, z_pred, rows, np.empty(3))


@numba.njit(**_JIT)
def _sweep_rows(pb, idx, R, p, Rs, ts, lh2, axis, c, corrected, z_pred, rows, g):
    """:func:`sweep_rows` with the caller's scratch ``g`` (3,)."""
    for r in range(idx.shape[0]):
        i = idx[r]
        lx = R[0, 0] * pb[i, 0] + R[0, 1] * pb[i, 1] + R[0, 2] * pb[i, 2]
        ly = R[1, 0] * pb[i, 0] + R[1, 1] * pb[i, 1] + R[1, 2] * pb[i, 2]
        lz = R[2, 0] * pb[i, 0] + R[2, 1] * pb[i, 1] + R[2, 2] * pb[i, 2]
        wx, wy, wz = lx + p[0] - ts[0], ly + p[1] - ts[1], lz + p[2] - ts[2]
        x = Rs[0, 0] * wx + Rs[1, 0] * wy + Rs[2, 0] * wz
        y = Rs[0, 1] * wx + Rs[1, 1] * wy + Rs[2, 1] * wz
        z = Rs[0, 2] * wx + Rs[1, 2] * wy + Rs[2, 2] * wz
        if lh2:
            z_pred[r] = lh2_axis(x, y, z, axis, c, corrected, g)
        else:
            z_pred[r] = lh1_axis(x, y, z, axis, c, corrected, g)
        ax = Rs[0, 0] * g[0] + Rs[0, 1] * g[1] + Rs[0, 2] * g[2]
        ay = Rs[1, 0] * g[0] + Rs[1, 1] * g[1] + Rs[1, 2] * g[2]
        az = Rs[2, 0] * g[0] + Rs[2, 1] * g[1] + Rs[2, 2] * g[2]
        rows[r, 0] = ly * az - lz * ay
        rows[r, 1] = lz * ax - lx * az
        rows[r, 2] = lx * ay - ly * ax
        rows[r, 3], rows[r, 4], rows[r, 5] = ax, ay, az


@numba.njit(**_JIT)
def quat_to_matrix(q, R):
    x, y, z, w = q[0], q[1], q[2], q[3]
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    R[0, 0], R[0, 1], R[0, 2] = 1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)
    R[1, 0], R[1, 1], R[1, 2] = 2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)
    R[2, 0], R[2, 1], R[2, 2] = 2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)


@numba.njit(**_JIT)
def quat_left_mul_rotvec(phi0, phi1, phi2, q):
    """``q <- exp(phi) ⊗ q`` in place, normalised with w >= 0 (filter.so3)."""
    th = math.sqrt(phi0 * phi0 + phi1 * phi1 + phi2 * phi2)
    if th < 1e-6:
        s = 0.5 - th * th / 48.0
        c = 1.0 - th * th / 8.0
    else:
        s = math.sin(0.5 * th) / th
        c = math.cos(0.5 * th)
    ax, ay, az, aw = s * phi0, s * phi1, s * phi2, c
    bx, by, bz, bw = q[0], q[1], q[2], q[3]
    x = aw * bx + ax * bw + ay * bz - az * by
    y = aw * by - ax * bz + ay * bw + az * bx
    z = aw * bz + ax * by - ay * bx + az * bw
    w = aw * bw - ax * bx - ay * by - az * bz
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if w < 0:
        n = -n
    q[0], q[1], q[2], q[3] = x / n, y / n, z / n, w / n


@numba.njit(**_JIT)
def quat_left_error(qa, qb, e):
    """``e = log(qa ⊗ qb^-1)`` (3,) rad: the left (world) rotation from b to a."""
    # qb^-1 = conj(qb)
    bx, by, bz, bw = -qb[0], -qb[1], -qb[2], qb[3]
    ax, ay, az, aw = qa[0], qa[1], qa[2], qa[3]
    x = aw * bx + ax * bw + ay * bz - az * by
    y = aw * by - ax * bz + ay * bw + az * bx
    z = aw * bz + ax * by - ay * bx + az * bw
    w = aw * bw - ax * bx - ay * by - az * bz
    if w < 0:
        x, y, z, w = -x, -y, -z, -w
    s = math.sqrt(x * x + y * y + z * z)
    k = 2.0 / w if s < 1e-12 else 2.0 * math.atan2(s, w) / s
    e[0], e[1], e[2] = k * x, k * y, k * z


@numba.njit(**_JIT)
def cv_predict(q, w, p, v, P, dt, qrot, qpos, T, dq, Ph):
    """Constant-velocity prediction of one model over ``dt`` s (ErrorStateEKF.predict): nominal
    ``q <- exp(w dt) q``, ``p <- p + v dt``; ``P <- F P F^T + Q`` with the error-state transition
    ``F`` (identity but the attitude block ``Phi = exp([w dt]x)`` and the dt couplings attitude/rate,
    position/velocity) and the white-acceleration Q of PSDs ``qrot``, ``qpos`` (Bar-Shalom et al.
    2001 eq. 6.2.2-12). ``T`` (12, 12), ``dq`` (4,), ``Ph`` (3, 3) scratch."""
    if dt <= 0.0:
        return
    phi0, phi1, phi2 = w[0] * dt, w[1] * dt, w[2] * dt
    dq[0], dq[1], dq[2], dq[3] = 0.0, 0.0, 0.0, 1.0
    quat_left_mul_rotvec(phi0, phi1, phi2, dq)
    quat_left_mul_rotvec(phi0, phi1, phi2, q)
    for k in range(3):
        p[k] += v[k] * dt
    quat_to_matrix(dq, Ph)
    # T = F P: rows 0-2 = Phi P[0:3] + dt P[3:6]; rows 6-8 = P[6:9] + dt P[9:12]; others as P
    # (row by row: the inner loop runs along contiguous rows)
    for i in range(3):
        h0, h1, h2 = Ph[i, 0], Ph[i, 1], Ph[i, 2]
        for j in range(12):
            T[i, j] = h0 * P[0, j] + h1 * P[1, j] + h2 * P[2, j] + dt * P[3 + i, j]
    for i in range(3):
        for j in range(12):
            T[3 + i, j] = P[3 + i, j]
            T[6 + i, j] = P[6 + i, j] + dt * P[9 + i, j]
            T[9 + i, j] = P[9 + i, j]
    # P = T F^T: columns likewise
    for i in range(12):
        for j in range(3):
            P[i, j] = T[i, 0] * Ph[j, 0] + T[i, 1] * Ph[j, 1] + T[i, 2] * Ph[j, 2] + dt * T[i, 3 + j]
            P[i, 3 + j] = T[i, 3 + j]
            P[i, 6 + j] = T[i, 6 + j] + dt * T[i, 9 + j]
            P[i, 9 + j] = T[i, 9 + j]
    d3, d2, d1 = dt * dt * dt / 3.0, dt * dt / 2.0, dt
    for k in range(3):
        P[k, k] += qrot * d3
        P[k, 3 + k] += qrot * d2
        P[3 + k, k] += qrot * d2
        P[3 + k, 3 + k] += qrot * d1
        P[6 + k, 6 + k] += qpos * d3
        P[6 + k, 9 + k] += qpos * d2
        P[9 + k, 6 + k] += qpos * d2
        P[9 + k, 9 + k] += qpos * d1


@numba.njit(**_JIT)
def sweep_innovation(pb, idx, z, q, w, p, v, P, Rs, ts, lh2, axis, c, corrected, dl, sigma2, rho, y, H, HP, S,
                     zp, rows, qrot, qpos, R, g):
    """Innovations ``y (m,)``, rows ``H (m, 12)``, ``HP = H P (m, 12)`` and the innovation covariance
    ``S (m, m)`` of one sweep for one model (ErrorStateEKF.update_sweep before the gates): each
    angle predicted at its own hit time ``dl`` s after the state time (first order in the
    velocity), ``S`` with the model's process noise over those offsets
    (:func:`hit_time_noise`; ``qrot`` rad²/s³, ``qpos`` m²/s³). ``zp (m,)``, ``rows (m, 6)``, ``R (3, 3)``,
    ``g (3,)`` scratch."""
    m = idx.shape[0]
    quat_to_matrix(q, R)
    _sweep_rows(pb, idx, R, p, Rs, ts, lh2, axis, c, corrected, zp, rows, g)
    for r in range(m):
        jw = rows[r, 0] * w[0] + rows[r, 1] * w[1] + rows[r, 2] * w[2]
        jv = rows[r, 3] * v[0] + rows[r, 4] * v[1] + rows[r, 5] * v[2]
        d = z[r] - (zp[r] + dl[r] * (jw + jv)) + math.pi
        y[r] = d - 2.0 * math.pi * math.floor(d / (2.0 * math.pi)) - math.pi
        for k in range(3):
            H[r, k] = rows[r, k]
            H[r, 3 + k] = rows[r, k] * dl[r]
            H[r, 6 + k] = rows[r, 3 + k]
            H[r, 9 + k] = rows[r, 3 + k] * dl[r]
    # HP[r, j] = sum_k H[r, k] P[k, j], summed over k in order (0.0 + ...), a row of P at a time
    for r in range(m):
        for j in range(12):
            HP[r, j] = 0.0
        for k in range(12):
            h = H[r, k]
            for j in range(12):
                HP[r, j] += h * P[k, j]
    for a in range(m):
        for b in range(a + 1):
            s = 0.0
            for k in range(12):
                s += HP[a, k] * H[b, k]
            s += sigma2 * (rho + (1.0 - rho if a == b else 0.0))
            if qrot > 0.0 or qpos > 0.0:
                cab = hit_time_noise(dl[a], dl[b])
                if cab > 0.0:
                    s += cab * (qrot * (rows[a, 0] * rows[b, 0] + rows[a, 1] * rows[b, 1] + rows[a, 2] * rows[b, 2])
                                + qpos * (rows[a, 3] * rows[b, 3] + rows[a, 4] * rows[b, 4] + rows[a, 5] * rows[b, 5]))
            S[a, b] = s
            S[b, a] = s


@numba.njit(**_JIT)
def hit_time_noise(da, db):
    """s³, covariance factor of the white-acceleration process noise between the state time and
    two hit times ``da``, ``db`` s after it: the integrated motion ``x(d) = int_0^d (d - s) a(s) ds``
    of a white acceleration of unit PSD has ``Cov(x(da), x(db)) = lo² hi / 2 - lo³ / 6`` with
    ``lo = min(|da|, |db|)``, ``hi = max`` (``d³ / 3`` for ``da = db``; Bar-Shalom, Li & Kirubarajan
    2001 eq. 6.2.2-12's position term); 0 when the two lie on opposite sides of the state time
    (independent noise). The extrapolation of a sweep's angles to their hit times (first order in
    the velocity) misses this motion; with it in ``S`` the innovations of a moving body are not
    taken for angle noise."""
    if da * db <= 0.0:
        return 0.0
    x, y = abs(da), abs(db)
    lo, hi = (x, y) if x < y else (y, x)
    return lo * lo * hi / 2.0 - lo * lo * lo / 6.0


@numba.njit(**_JIT)
def _chol_solve(ix, k, y, HP, S, L, X):
    """Cholesky ``L`` of ``S`` over the kept angles ``ix[:k]`` and ``X = S^-1 [y, HP]`` (k, 13) of them.
    Returns ``(k, nis, log det S)``; ``k = -1`` when S is not positive definite."""
    for a in range(k):
        for b in range(a + 1):
            s = S[ix[a], ix[b]]
            for c in range(b):
                s -= L[a, c] * L[b, c]
            if a == b:
                if not s > 0.0:
                    return -1, np.nan, np.nan
                L[a, a] = math.sqrt(s)
            else:
                L[a, b] = s / L[b, b]
    # the 13 right-hand sides together (row by row; each element's terms subtracted in the same order)
    # forward: L u = rhs
    for a in range(k):
        X[a, 0] = y[ix[a]]
        for col in range(1, 13):
            X[a, col] = HP[ix[a], col - 1]
        for c in range(a):
            l = L[a, c]
            for col in range(13):
                X[a, col] -= l * X[c, col]
        d = L[a, a]
        for col in range(13):
            X[a, col] = X[a, col] / d
    # back: L^T x = u
    for a in range(k - 1, -1, -1):
        for c in range(a + 1, k):
            l = L[c, a]
            for col in range(13):
                X[a, col] -= l * X[c, col]
        d = L[a, a]
        for col in range(13):
            X[a, col] = X[a, col] / d
    nis = 0.0
    logdet = 0.0
    for a in range(k):
        nis += y[ix[a]] * X[a, 0]
        logdet += 2.0 * math.log(L[a, a])
    return k, nis, logdet


@numba.njit(**_JIT)
def _apply(ix, k, HP, X, q, w, p, v, P, dx, acc):
    """``dx = (HP)^T S^-1 y``, ``P -= (HP)^T S^-1 HP`` over the kept angles ``ix[:k]``, injected into the
    nominal. acc (12,) scratch."""
    for i in range(12):
        s = 0.0
        for a in range(k):
            s += HP[ix[a], i] * X[a, 0]
        dx[i] = s
    for i in range(12):
        # acc[j] = sum_a HP[ix[a], i] X[a, 1 + j], summed over a in order (0.0 + ...), j <= i together
        for j in range(i + 1):
            acc[j] = 0.0
        for a in range(k):
            h = HP[ix[a], i]
            for j in range(i + 1):
                acc[j] += h * X[a, 1 + j]
        for j in range(i + 1):
            P[i, j] -= acc[j]
            if i != j:
                P[j, i] = P[i, j]
    quat_left_mul_rotvec(dx[0], dx[1], dx[2], q)
    for a in range(3):
        w[a] += dx[3 + a]
        p[a] += dx[6 + a]
        v[a] += dx[9 + a]


@numba.njit(**_JIT)
def imm_sweep(Q, W, Pn, V, P, mu, qrot, qpos, Pi, t_state, t, pb, idx, z, Rs, ts, lh2, axis, c, corrected,
              omega, sigma2, rho, q1, qm, mix, out, qc, wc, pc, vc, Pc, sweep_dt, freeze, hit_noise, ws, iw):
    """One sweep through an interacting-multiple-model bank of ``r`` constant-velocity filters
    (Blom & Bar-Shalom 1988): mix (when ``mix``), predict each model to ``t`` with its own PSDs,
    gate, update every model with the kept angles, re-weight ``mu`` by the likelihoods, and write
    the combined state into ``qc`` (4,), ``wc``, ``pc``, ``vc`` (3,), ``Pc`` (12, 12). Arrays per
    model: Q (r, 4), W, Pn, V (r, 3), P (r, 12, 12); Pi (r, r) the per-sweep mode transition
    matrix. Gates: an angle is kept when its normalised innovation is within the chi²(1) quantile
    ``q1`` in at least one model; the sweep is rejected when its NIS exceeds ``qm[k]`` (chi²(k)
    quantile) in every model. ``out`` (10,) <- used, rejected, sweep_rejected (0/1), NIS of the most
    probable model, the combined pose correction (6,) (left rotation rad, position m). sweep_dt : s,
    the sweep's own time minus ``t`` (<= 0: a sweep that arrives slightly out of time order is
    applied at ``t`` with its hit times moved back by that much). freeze : keep ``mu`` (a body the
    static detector says is at rest stays in the mode it was put in). hit_noise : each model's
    white acceleration over the angles' hit-time offsets in ``S`` (:func:`hit_time_noise`). ws : float
    scratch of :func:`_scratch_size` (r, m) and iw : int64 scratch of max(r, m) (their contents are not
    read: every piece is written before use)."""
    r = Q.shape[0]
    m = idx.shape[0]
    q_prev = ws[0:4]
    p_prev = ws[4:7]
    er = ws[7:10]
    dq = ws[10:14]
    Ph = ws[14:23].reshape(3, 3)
    T = ws[23:167].reshape(12, 12)
    rest = ws[167:]  # the mixing, update and combination scratch (used one after the other)
    for a in range(4):
        q_prev[a] = qc[a]
    for a in range(3):
        p_prev[a] = pc[a]
    if mix and r > 1:
        _imm_mix_ws(Q, W, Pn, V, P, mu, Pi, rest, iw)
    for j in range(r):
        cv_predict(Q[j], W[j], Pn[j], V[j], P[j], t - t_state, qrot[j], qpos[j], T, dq, Ph)
    for a in range(10):
        out[a] = 0.0
    out[3] = np.nan
    if m > 0:
        _imm_update(Q, W, Pn, V, P, mu, pb, idx, z, Rs, ts, lh2, axis, c, corrected, omega, sigma2, rho, q1, qm, out,
                    sweep_dt, freeze, qrot, qpos, hit_noise, rest, iw)
    _imm_combine_ws(Q, W, Pn, V, P, mu, qc, wc, pc, vc, Pc, rest, iw)
    if out[0] > 0:
        quat_left_error(qc, q_prev, er)
        for a in range(3):
            out[4 + a] = er[a]
            out[7 + a] = pc[a] - p_prev[a]


@numba.njit(**_JIT)
def _imm_update(Q, W, Pn, V, P, mu, pb, idx, z, Rs, ts, lh2, axis, c, corrected, omega, sigma2, rho, q1, qm, out,
                sweep_dt, freeze, qrot, qpos, hit_noise, ws, iw):
    r = Q.shape[0]
    m = idx.shape[0]
    o = 0
    dl = ws[o:o + m]
    o += m
    Y = ws[o:o + r * m].reshape(r, m)
    o += r * m
    H = ws[o:o + r * m * 12].reshape(r, m, 12)
    o += r * m * 12
    HP = ws[o:o + r * m * 12].reshape(r, m, 12)
    o += r * m * 12
    S = ws[o:o + r * m * m].reshape(r, m, m)
    o += r * m * m
    zp = ws[o:o + m]
    o += m
    rows = ws[o:o + 6 * m].reshape(m, 6)
    o += 6 * m
    R3 = ws[o:o + 9].reshape(3, 3)
    o += 9
    g3 = ws[o:o + 3]
    o += 3
    nis = ws[o:o + r]
    o += r
    logdet = ws[o:o + r]
    o += r
    ll = ws[o:o + r]
    o += r
    dx = ws[o:o + 12]
    o += 12
    acc = ws[o:o + 12]
    o += 12
    for a in range(m):
        if lh2:
            dl[a] = (z[a] + math.pi + (-math.pi / 3.0 if axis == 0 else math.pi / 3.0)) / omega + sweep_dt
        else:
            dl[a] = z[a] / omega + sweep_dt
    keep = np.zeros(m, np.bool_)
    for j in range(r):
        sweep_innovation(pb, idx, z, Q[j], W[j], Pn[j], V[j], P[j], Rs, ts, lh2, axis, c, corrected, dl, sigma2,
                         rho, Y[j], H[j], HP[j], S[j], zp, rows, qrot[j] if hit_noise else 0.0,
                         qpos[j] if hit_noise else 0.0, R3, g3)
        for a in range(m):
            if Y[j, a] * Y[j, a] <= q1 * S[j, a, a]:
                keep[a] = True
    k = 0
    for a in range(m):
        if keep[a]:
            k += 1
    out[1] = m - k
    if k == 0:
        out[2] = 1.0
        return
    ix = iw[0:k]
    k = 0
    for a in range(m):
        if keep[a]:
            ix[k] = a
            k += 1
    L = ws[o:o + k * k].reshape(k, k)
    o += k * k
    X = ws[o:o + r * k * 13].reshape(r, k, 13)
    o += r * k * 13
    for j in range(r):
        nis[j] = np.inf
        logdet[j] = 0.0
    any_ok = False
    for j in range(r):
        kk, nis[j], logdet[j] = _chol_solve(ix, k, Y[j], HP[j], S[j], L, X[j])
        if kk < 0:
            nis[j] = np.inf
        elif nis[j] <= qm[k]:
            any_ok = True
    jm = 0
    for j in range(r):
        if mu[j] > mu[jm]:
            jm = j
    out[3] = nis[jm]
    if not any_ok:
        out[2] = 1.0
        return
    for j in range(r):
        if np.isfinite(nis[j]):
            _apply(ix, k, HP[j], X[j], Q[j], W[j], Pn[j], V[j], P[j], dx, acc)
    if r > 1 and not freeze:
        # mode probabilities: mu_j ∝ mu_j Λ_j, Λ_j = N(y_j; 0, S_j) over the kept angles
        lmax = -np.inf
        for j in range(r):
            ll[j] = -0.5 * (nis[j] + logdet[j]) if np.isfinite(nis[j]) else -np.inf
            if ll[j] > lmax:
                lmax = ll[j]
        tot = 0.0
        for j in range(r):
            mu[j] = max(mu[j] * math.exp(ll[j] - lmax), 1e-12)
            tot += mu[j]
        for j in range(r):
            mu[j] /= tot
        jm = 0
        for j in range(r):
            if mu[j] > mu[jm]:
                jm = j
        out[3] = nis[jm]
    out[0] = k


@numba.njit(**_JIT)
def _bounded(Q, W, Pn, V, P):
    """Every model's state and covariance within +-1e100 (so no NaN/inf): a term of weight
    exactly 0 then adds exactly +-0 to the sums of :func:`_imm_mix` and :func:`imm_combine`
    (their differences and products stay finite), and skipping it changes no bit of the result
    (the sums start at +0 and never become -0). A bank held in one model (``hold_static``:
    probabilities exactly 1 and 0) thus mixes and combines only that model."""
    r = Q.shape[0]
    for i in range(r):
        for a in range(4):
            if not abs(Q[i, a]) < 1e100:
                return False
        for a in range(3):
            if not (abs(W[i, a]) < 1e100 and abs(Pn[i, a]) < 1e100 and abs(V[i, a]) < 1e100):
                return False
        for a in range(12):
            for b in range(12):
                if not abs(P[i, a, b]) < 1e100:
                    return False
    return True


@numba.njit(**_JIT)
def _moment_match(Q, W, Pn, V, P, wt, ref, skip_zero, e, er, use, mean, C):
    """Weighted mean and covariance of the models in model ``ref``'s error state: deviations
    ``e[i] = [left attitude error of i about ref, w_i - w_ref, p_i - p_ref, v_i - v_ref]``, into
    ``mean`` (12,) ``= sum wt_i e_i`` and ``C`` (12, 12) ``= sum wt_i (P_i + (e_i - mean)(e_i - mean)^T)``.
    With ``skip_zero`` (:func:`_bounded`) the models of weight 0 are left out: they add exactly +-0.
    e (r, 12), er (3,), use (r,) scratch."""
    r = Q.shape[0]
    nu = 0
    for i in range(r):
        if skip_zero and wt[i] == 0.0:
            continue
        use[nu] = i
        nu += 1
        quat_left_error(Q[i], Q[ref], er)
        for a in range(3):
            e[i, a] = er[a]
            e[i, 3 + a] = W[i, a] - W[ref, a]
            e[i, 6 + a] = Pn[i, a] - Pn[ref, a]
            e[i, 9 + a] = V[i, a] - V[ref, a]
    for a in range(12):
        mean[a] = 0.0
    for u in range(nu):
        i = use[u]
        for a in range(12):
            mean[a] += wt[i] * e[i, a]
    # C[a, b] = sum_u wt_i (P_i[a, b] + d_i[a] d_i[b]), summed over u in order (0.0 + ...), b <= a together
    for a in range(12):
        for b in range(a + 1):
            C[a, b] = 0.0
        for u in range(nu):
            i = use[u]
            wi = wt[i]
            da = e[i, a] - mean[a]
            for b in range(a + 1):
                C[a, b] += wi * (P[i, a, b] + da * (e[i, b] - mean[b]))
        for b in range(a):
            C[b, a] = C[a, b]


@numba.njit(**_JIT)
def _imm_mix(Q, W, Pn, V, P, mu, Pi):
    """IMM mixing step in the error state: model j starts from the mixture of all models with
    weights ``mu_{i|j} ∝ Pi[i, j] mu_i``, attitudes mixed as left errors about model j's own."""
    r = Q.shape[0]
    _imm_mix_ws(Q, W, Pn, V, P, mu, Pi, np.empty(_scratch_size(r, 0)), np.empty(r, np.int64))


@numba.njit(**_JIT)
def _imm_mix_ws(Q, W, Pn, V, P, mu, Pi, ws, use):
    """:func:`_imm_mix` with the caller's scratch: ws >= 171 r + 15 floats, use (r,) int64."""
    r = Q.shape[0]
    o = 0
    cbar = ws[o:o + r]
    o += r
    Q0 = ws[o:o + 4 * r].reshape(r, 4)
    o += 4 * r
    W0 = ws[o:o + 3 * r].reshape(r, 3)
    o += 3 * r
    Pn0 = ws[o:o + 3 * r].reshape(r, 3)
    o += 3 * r
    V0 = ws[o:o + 3 * r].reshape(r, 3)
    o += 3 * r
    P0 = ws[o:o + 144 * r].reshape(r, 12, 12)
    o += 144 * r
    e = ws[o:o + 12 * r].reshape(r, 12)
    o += 12 * r
    wij = ws[o:o + r]
    o += r
    er = ws[o:o + 3]
    o += 3
    mean = ws[o:o + 12]
    for j in range(r):
        cbar[j] = 0.0
    for j in range(r):
        for i in range(r):
            cbar[j] += Pi[i, j] * mu[i]
    Q0[:] = Q
    W0[:] = W
    Pn0[:] = Pn
    V0[:] = V
    P0[:] = P
    skip_zero = _bounded(Q0, W0, Pn0, V0, P0)
    for j in range(r):
        for i in range(r):
            wij[i] = Pi[i, j] * mu[i] / cbar[j]
        _moment_match(Q0, W0, Pn0, V0, P0, wij, j, skip_zero, e, er, use, mean, P[j])
        Q[j] = Q0[j]
        quat_left_mul_rotvec(mean[0], mean[1], mean[2], Q[j])
        for a in range(3):
            W[j, a] = W0[j, a] + mean[3 + a]
            Pn[j, a] = Pn0[j, a] + mean[6 + a]
            V[j, a] = V0[j, a] + mean[9 + a]
    for j in range(r):
        mu[j] = cbar[j]


@numba.njit(**_JIT)
def imm_combine(Q, W, Pn, V, P, mu, q, w, p, v, Pc):
    """The bank's output: the ``mu``-weighted mixture of the models (attitude about the most
    probable model's), into ``q`` (4,), ``w``, ``p``, ``v`` (3,), ``Pc`` (12, 12)."""
    r = Q.shape[0]
    _imm_combine_ws(Q, W, Pn, V, P, mu, q, w, p, v, Pc, np.empty(_scratch_size(r, 0)), np.empty(r, np.int64))


@numba.njit(**_JIT)
def _imm_combine_ws(Q, W, Pn, V, P, mu, q, w, p, v, Pc, ws, use):
    """:func:`imm_combine` with the caller's scratch: ws >= 12 r + 15 floats, use (r,) int64."""
    r = Q.shape[0]
    jm = 0
    for j in range(r):
        if mu[j] > mu[jm]:
            jm = j
    mean = ws[0:12]
    er = ws[12:15]
    e = ws[15:15 + 12 * r].reshape(r, 12)
    _moment_match(Q, W, Pn, V, P, mu, jm, _bounded(Q, W, Pn, V, P), e, er, use, mean, Pc)
    for a in range(4):
        q[a] = Q[jm, a]
    quat_left_mul_rotvec(mean[0], mean[1], mean[2], q)
    for a in range(3):
        w[a] = W[jm, a] + mean[3 + a]
        p[a] = Pn[jm, a] + mean[6 + a]
        v[a] = V[jm, a] + mean[9 + a]


@numba.njit(**_JIT)
def _scratch_size(r, m):
    """Floats of scratch for :func:`imm_sweep` after its own 167: the larger of the mixing's
    (171 r + 15), the combination's (12 r + 15) and the update's with ``m`` angles (at most ``m`` kept)."""
    upd = m * (8 + r * (38 + m)) + m * m + 3 * r + 36
    return max(171 * r + 15, 12 * r + 15, upd)


#: layout of the per-call parameter vector of :func:`imm_step`
PAR_T_STATE, PAR_T, PAR_SIGMA2, PAR_RHO, PAR_Q1, PAR_OMEGA, PAR_LH2, PAR_AXIS, PAR_CORRECTED, PAR_MIX = range(10)
PAR_CAL, PAR_RS, PAR_TS, PAR_SWEEP_DT, PAR_FREEZE, PAR_HIT_NOISE, PAR_SIZE = 10, 17, 26, 29, 30, 31, 32
#: layout of :func:`imm_step`'s output vector
OUT_STATE, OUT_P, OUT_SIG, OUT_SIZE = 10, 23, 167, 173


@numba.njit(**_JIT)
def imm_step(X, P, M, Pi, pb, idx, z, par, qm, out):
    """:func:`imm_sweep` with packed arguments (a compiled call's cost grows with its argument
    count): X (r, 13) per-model nominal ``[q (4), w, p, v]``, P (r, 12, 12), M (r, 3)
    ``[mu, psd_rot, psd_pos]`` (mu updated), Pi (r, r), par (PAR_SIZE,) (``PAR_*``: times, noise,
    gate, rotor rate, kind, axis, gib argument, mix flag, calibration (7), station rotation (9,
    row-major), translation (3)), qm (n + 1,) chi² quantiles per dof; out (OUT_SIZE,) <- the counts
    and correction (10), the combined nominal (13) and covariance (144, row-major), and the pose
    1-sigma ``(dphi rad, dp m)`` (6,) before the step (``sqrt(max(diag P, 0))`` of the incoming
    covariance, NaN kept). The combined state of the previous call is read from ``out`` too (the
    correction is relative to it)."""
    for k in range(6):
        x = out[OUT_P + 13 * (k if k < 3 else k + 3)]
        out[OUT_SIG + k] = math.sqrt(x if (x >= 0.0 or x != x) else 0.0)
    r = X.shape[0]
    m = idx.shape[0]
    # one scratch allocation per call: the per-model copies and every work array are pieces of it
    ws = np.empty(16 * r + 176 + 167 + _scratch_size(r, m))
    iw = np.empty(max(r, m, 1), np.int64)
    Q = ws[0:4 * r].reshape(r, 4)
    W = ws[4 * r:7 * r].reshape(r, 3)
    Pn = ws[7 * r:10 * r].reshape(r, 3)
    V = ws[10 * r:13 * r].reshape(r, 3)
    mu = ws[13 * r:14 * r]
    qrot = ws[14 * r:15 * r]
    qpos = ws[15 * r:16 * r]
    o = 16 * r
    for j in range(r):
        for a in range(4):
            Q[j, a] = X[j, a]
        for a in range(3):
            W[j, a] = X[j, 4 + a]
            Pn[j, a] = X[j, 7 + a]
            V[j, a] = X[j, 10 + a]
        mu[j], qrot[j], qpos[j] = M[j, 0], M[j, 1], M[j, 2]
    c = ws[o:o + 7]
    Rs = ws[o + 7:o + 16].reshape(3, 3)
    ts = ws[o + 16:o + 19]
    qc = ws[o + 19:o + 23]
    wc = ws[o + 23:o + 26]
    pc = ws[o + 26:o + 29]
    vc = ws[o + 29:o + 32]
    Pc = ws[o + 32:o + 176].reshape(12, 12)
    for a in range(7):
        c[a] = par[PAR_CAL + a]
    for a in range(3):
        for b in range(3):
            Rs[a, b] = par[PAR_RS + 3 * a + b]
        ts[a] = par[PAR_TS + a]
        pc[a] = out[OUT_STATE + 7 + a]
    for a in range(4):
        qc[a] = out[OUT_STATE + a]
    imm_sweep(Q, W, Pn, V, P, mu, qrot, qpos, Pi, par[PAR_T_STATE], par[PAR_T], pb, idx, z, Rs, ts,
              par[PAR_LH2] > 0.5, int(par[PAR_AXIS]), c, par[PAR_CORRECTED] > 0.5, par[PAR_OMEGA], par[PAR_SIGMA2],
              par[PAR_RHO], par[PAR_Q1], qm, par[PAR_MIX] > 0.5, out, qc, wc, pc, vc, Pc, par[PAR_SWEEP_DT],
              par[PAR_FREEZE] > 0.5, par[PAR_HIT_NOISE] > 0.5, ws[o + 176:], iw)
    for j in range(r):
        for a in range(4):
            X[j, a] = Q[j, a]
        for a in range(3):
            X[j, 4 + a] = W[j, a]
            X[j, 7 + a] = Pn[j, a]
            X[j, 10 + a] = V[j, a]
        M[j, 0] = mu[j]
    for a in range(4):
        out[OUT_STATE + a] = qc[a]
    for a in range(3):
        out[OUT_STATE + 4 + a] = wc[a]
        out[OUT_STATE + 7 + a] = pc[a]
        out[OUT_STATE + 10 + a] = vc[a]
    for a in range(12):
        for b in range(12):
            out[OUT_P + 12 * a + b] = Pc[a, b]
