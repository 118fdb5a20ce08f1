"""numba kernels of the IMU-aided sweep filter (:mod:`layoutkit.filter.imu_tracker`; imported on first use).

The same propagation and update as :class:`layoutkit.filter.imu.ImuEskf` (Solà 2017; the numpy
reference the tests compare with), in place on the nominal state ``R (3, 3), p, v, ba, bg (3,)`` and
the error-state covariance ``P (15, 15)`` ordered ``[dp, dv, dtheta, dba, dbg]``; the sweep's forward
model is the lighthouse filter's compiled one (:func:`layoutkit.filter._kernels_numba.sweep_rows`).
"""
import math

import numba
import numpy as np

from ._kernels_numba import sweep_rows

_JIT = dict(cache=True, fastmath=False, nogil=True)


@numba.njit(**_JIT)
def _expm(a0, a1, a2, E):
    """Rodrigues: E = exp([a]x)."""
    th = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    if th < 1e-9:
        A = 1.0 - th * th / 6.0
        B = 0.5 - th * th / 24.0
    else:
        A = math.sin(th) / th
        B = (1.0 - math.cos(th)) / (th * th)
    E[0, 0] = 1.0 - B * (a1 * a1 + a2 * a2)
    E[1, 1] = 1.0 - B * (a0 * a0 + a2 * a2)
    E[2, 2] = 1.0 - B * (a0 * a0 + a1 * a1)
    E[0, 1] = -A * a2 + B * a0 * a1
    E[1, 0] = A * a2 + B * a0 * a1
    E[0, 2] = A * a1 + B * a0 * a2
    E[2, 0] = -A * a1 + B * a0 * a2
    E[1, 2] = -A * a0 + B * a1 * a2
    E[2, 1] = A * a0 + B * a1 * a2


@numba.njit(**_JIT)
def _correct(R, p, v, ba, bg, P, Pn, dx):
    """The end of a Joseph-form update, in place: ``P`` <- the symmetric part of ``Pn``, and the error
    state ``dx = [dp, dv, dtheta, dba, dbg]`` injected into the nominal state (``R <- R exp([dtheta]x)``)."""
    for a in range(15):
        for b in range(15):
            P[a, b] = 0.5 * (Pn[a, b] + Pn[b, a])
    for i in range(3):
        p[i] += dx[i]
        v[i] += dx[3 + i]
        ba[i] += dx[9 + i]
        bg[i] += dx[12 + i]
    E = np.empty((3, 3))
    _expm(dx[6], dx[7], dx[8], E)
    Rn = R @ E
    R[:, :] = Rn


@numba.njit(**_JIT)
def _error_transition(R, ba, bg, f, w, dt, fa, E, F):
    """The error transition of one IMU step (Solà 2017 eqs. 269-270) into ``F`` (15, 15), given as the
    identity: ``fa (3,) <- f - ba``, ``E (3, 3) <- exp([(w - bg) dt]x)``, and F's blocks ``dp/dv = I dt``,
    ``dv/dtheta = -R [fa]x dt``, ``dv/dba = -R dt``, ``dtheta/dtheta = E^T``, ``dtheta/dbg = -I dt``."""
    for i in range(3):
        fa[i] = f[i] - ba[i]
    _expm((w[0] - bg[0]) * dt, (w[1] - bg[1]) * dt, (w[2] - bg[2]) * dt, E)
    for i in range(3):
        F[i, 3 + i] = dt
        F[6 + i, 12 + i] = -dt
        for j in range(3):
            F[3 + i, 9 + j] = -R[i, j] * dt
            F[6 + i, 6 + j] = E[j, i]
    # -R [fa]x dt
    S = np.array([[0.0, -fa[2], fa[1]], [fa[2], 0.0, -fa[0]], [-fa[1], fa[0], 0.0]])
    for i in range(3):
        for j in range(3):
            F[3 + i, 6 + j] = -(R[i, 0] * S[0, j] + R[i, 1] * S[1, j] + R[i, 2] * S[2, j]) * dt


@numba.njit(**_JIT)
def propagate(R, p, v, ba, bg, g, P, f, w, dt, qa, qg, qba, qbg):
    """Advance by ``dt`` s with specific force ``f`` (m/s²) and rate ``w`` (rad/s), IMU frame;
    ``qa, qg, qba, qbg``: the noise densities squared (acc, gyro, acc bias walk, gyro bias walk)."""
    if dt <= 0.0:
        return
    fa = np.empty(3)
    a = np.empty(3)
    E = np.empty((3, 3))
    F = np.eye(15)
    _error_transition(R, ba, bg, f, w, dt, fa, E, F)
    for i in range(3):
        a[i] = R[i, 0] * fa[0] + R[i, 1] * fa[1] + R[i, 2] * fa[2] + g[i]
    FP = F @ P
    P[:, :] = FP @ F.T
    for i in range(3):
        P[3 + i, 3 + i] += qa * dt
        P[6 + i, 6 + i] += qg * dt
        P[9 + i, 9 + i] += qba * dt
        P[12 + i, 12 + i] += qbg * dt
    for i in range(3):
        p[i] += v[i] * dt + 0.5 * a[i] * dt * dt
        v[i] += a[i] * dt
    Rn = R @ E
    R[:, :] = Rn


@numba.njit(**_JIT)
def sample_at(T, gyro, acc, t, w, f):
    """``w``, ``f`` (3,) <- gyro, acc linearly interpolated at ``t`` (held beyond the ends), as
    the IMU filter's one interpolation (its propagation and its late sweeps)."""
    N = T.shape[0]
    j = np.searchsorted(T, t, side="right") - 1
    if j < 0:
        for i in range(3):
            w[i], f[i] = gyro[0, i], acc[0, i]
        return
    if j >= N - 1:
        for i in range(3):
            w[i], f[i] = gyro[N - 1, i], acc[N - 1, i]
        return
    u = (t - T[j]) / (T[j + 1] - T[j]) if T[j + 1] > T[j] else 0.0
    for i in range(3):
        w[i] = gyro[j, i] + u * (gyro[j + 1, i] - gyro[j, i])
        f[i] = acc[j, i] + u * (acc[j + 1, i] - acc[j, i])


@numba.njit(**_JIT)
def propagate_span(R, p, v, ba, bg, g, P, T, gyro, acc, a, t, gap, q_sat, acc_noise, acc_noise_per_acc, qg, qba,
                   qbg, Fc, record, gap_from, gap_dt):
    """Integrate the IMU samples ``T (N,)`` s, ``gyro``, ``acc (N, 3)`` from ``a`` to ``t`` s: each stretch
    between sample times with its midpoint's interpolated sample (:func:`sample_at`), the accelerometer
    noise ``(acc_noise + acc_noise_per_acc |R (f - ba) + g|)²`` (``q_sat`` when ``gap``: no IMU data there),
    :func:`propagate`. ``record``: each stretch's error transition accumulated into ``Fc``
    (:func:`transition`), and the integration stops early at a sample time ``b < t`` with
    ``b - gap_from >= gap_dt`` (the smoother's pose inside a gap between sweeps). Returns the time
    reached (``t``, or that sample time)."""
    w = np.empty(3)
    f = np.empty(3)
    N = T.shape[0]
    j = np.searchsorted(T, a, side="right")
    while True:
        b = min(t, T[j]) if j < N else t
        if b > a:
            sample_at(T, gyro, acc, 0.5 * (a + b), w, f)
            if gap:
                qa = q_sat
            else:  # the accelerometer's error grows with the motion (scale, axes, timing, filtering)
                s = 0.0
                for i in range(3):
                    ad = R[i, 0] * (f[0] - ba[0]) + R[i, 1] * (f[1] - ba[1]) + R[i, 2] * (f[2] - ba[2]) + g[i]
                    s += ad * ad
                qa = (acc_noise + acc_noise_per_acc * math.sqrt(s)) ** 2
            if record:
                transition(R, ba, bg, f, w, b - a, Fc)
            propagate(R, p, v, ba, bg, g, P, f, w, b - a, qa, qg, qba, qbg)
            a = b
            if record and b < t and b - gap_from >= gap_dt:
                return b
        if a >= t:
            return a
        j += 1


@numba.njit(**_JIT)
def update(R, p, v, ba, bg, P, pb, idx, z, Rs, ts, lh2, axis, c, corrected, sigma2, q1, qm, out):
    """One sweep: angles ``z (m,)`` rad of the sensors ``idx`` at ``pb (n, 3)`` (IMU frame) on ``axis`` of
    the station ``Rs, ts`` (kind flag ``lh2``, calibration ``c (7,)``, ``corrected``); angle noise
    variance ``sigma2``. Angles whose ``y_i² / S_ii`` exceeds ``q1`` are dropped, then the sweep is
    rejected when its NIS exceeds ``qm[m_kept]``. ``out``: [accepted, nis, m kept, y·y / m, trace(H P
    H^T) / m, angles dropped] (the last two over the kept angles)."""
    m = idx.shape[0]
    zp = np.empty(m)
    rows = np.empty((m, 6))
    sweep_rows(pb, idx, R, p, Rs, ts, lh2, axis, c, corrected, zp, rows)
    H = np.zeros((m, 15))
    y = np.empty(m)
    for r in range(m):
        for j in range(3):
            H[r, j] = rows[r, 3 + j]
            # d/dtheta (local) = d/dphi (world) R
            H[r, 6 + j] = rows[r, 0] * R[0, j] + rows[r, 1] * R[1, j] + rows[r, 2] * R[2, j]
        d = z[r] - zp[r] + math.pi
        y[r] = d - 2.0 * math.pi * math.floor(d / (2.0 * math.pi)) - math.pi
    HP = H @ P
    S = HP @ H.T
    keep = np.empty(m, np.bool_)
    k = 0
    for r in range(m):
        keep[r] = y[r] * y[r] / (S[r, r] + sigma2) <= q1
        if keep[r]:
            k += 1
    out[0] = 0.0
    out[1] = np.nan
    out[2] = k
    out[5] = m - k
    if k < 2:
        return
    ki = np.empty(k, np.int64)
    j = 0
    for r in range(m):
        if keep[r]:
            ki[j] = r
            j += 1
    Hk = H[ki]
    yk = y[ki]
    HPk = HP[ki]
    Sk = np.empty((k, k))
    tr = 0.0
    for a in range(k):
        for b in range(k):
            Sk[a, b] = S[ki[a], ki[b]]
        tr += Sk[a, a]
        Sk[a, a] += sigma2
    Si = np.linalg.inv(Sk)
    Siy = Si @ yk
    nis = 0.0
    yy = 0.0
    for a in range(k):
        nis += yk[a] * Siy[a]
        yy += yk[a] * yk[a]
    out[1] = nis
    out[3] = yy / k
    out[4] = tr / k
    if nis > qm[k]:
        return
    out[0] = 1.0
    K = HPk.T @ Si                      # (15, k)
    dx = K @ yk
    IKH = np.eye(15) - K @ Hk
    _correct(R, p, v, ba, bg, P, IKH @ P @ IKH.T + sigma2 * (K @ K.T), dx)


@numba.njit(**_JIT)
def matrix_to_quat(R, q):
    """Rotation matrix → unit quaternion ``q = [x, y, z, w]`` with ``w >= 0`` (Shepperd's method; the order
    and sign of :func:`layoutkit.rotations.matrix_to_quaternion`, which the tests compare with)."""
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr >= R[0, 0] and tr >= R[1, 1] and tr >= R[2, 2]:
        w = 0.5 * math.sqrt(max(1.0 + tr, 0.0))
        s = 0.25 / w
        x, y, z = (R[2, 1] - R[1, 2]) * s, (R[0, 2] - R[2, 0]) * s, (R[1, 0] - R[0, 1]) * s
    elif R[0, 0] >= R[1, 1] and R[0, 0] >= R[2, 2]:
        x = 0.5 * math.sqrt(max(1.0 + R[0, 0] - R[1, 1] - R[2, 2], 0.0))
        s = 0.25 / x
        w, y, z = (R[2, 1] - R[1, 2]) * s, (R[0, 1] + R[1, 0]) * s, (R[0, 2] + R[2, 0]) * s
    elif R[1, 1] >= R[2, 2]:
        y = 0.5 * math.sqrt(max(1.0 - R[0, 0] + R[1, 1] - R[2, 2], 0.0))
        s = 0.25 / y
        w, x, z = (R[0, 2] - R[2, 0]) * s, (R[0, 1] + R[1, 0]) * s, (R[1, 2] + R[2, 1]) * s
    else:
        z = 0.5 * math.sqrt(max(1.0 - R[0, 0] - R[1, 1] + R[2, 2], 0.0))
        s = 0.25 / z
        w, x, y = (R[1, 0] - R[0, 1]) * s, (R[0, 2] + R[2, 0]) * s, (R[1, 2] + R[2, 1]) * s
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if w < 0.0:
        n = -n
    q[0], q[1], q[2], q[3] = x / n, y / n, z / n, w / n


@numba.njit(**_JIT)
def body_cov(R, P, p_ib, out):
    """(12, 12) covariance ``out`` of the body pose in the lighthouse filter's layout ``(dphi world, dw,
    dp, dv)`` from the IMU filter's ``P (15, 15)`` (``[dp, dv, dtheta, dba, dbg]``, local attitude
    error): ``dphi = R dtheta``, ``dw = R dbg`` (the rate's uncertainty is the gyro bias's), ``dp_body
    = dp + R [p_ib]x dtheta`` (the IMU at ``p_ib`` in the body), ``dv``."""
    B = np.zeros((12, 15))
    S = np.array([[0.0, -p_ib[2], p_ib[1]], [p_ib[2], 0.0, -p_ib[0]], [-p_ib[1], p_ib[0], 0.0]])
    RS = R @ S
    for i in range(3):
        B[6 + i, i] = 1.0
        B[9 + i, 3 + i] = 1.0
        for j in range(3):
            B[i, 6 + j] = R[i, j]
            B[3 + i, 12 + j] = R[i, j]
            B[6 + i, 6 + j] = RS[i, j]
    out[:, :] = B @ P @ B.T


@numba.njit(**_JIT)
def zero_velocity(R, p, v, ba, bg, P, sigma2):
    """Zero-velocity pseudo-measurement ``v = 0`` with noise variance ``sigma2`` per axis (the IMU says
    the body is at rest), Joseph form; in place."""
    S = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            S[i, j] = P[3 + i, 3 + j]
        S[i, i] += sigma2
    Si = np.linalg.inv(S)
    K = np.ascontiguousarray(P[:, 3:6]) @ Si  # (15, 3)
    dx = K @ (-v)
    IKH = np.eye(15)
    for a in range(15):
        for j in range(3):
            IKH[a, 3 + j] -= K[a, j]
    _correct(R, p, v, ba, bg, P, IKH @ P @ IKH.T + sigma2 * (K @ K.T), dx)


@numba.njit(**_JIT)
def transition(R, ba, bg, f, w, dt, Fc):
    """The error transition ``F (15, 15)`` of :func:`propagate` over ``dt`` s with ``f``, ``w`` from the
    nominal state ``R, ba, bg`` *before* that propagation (the same formula, Solà eqs. 269-270),
    accumulated in place: ``Fc <- F Fc`` (the smoother's transition between two recorded steps)."""
    if dt <= 0.0:
        return
    F = np.eye(15)
    _error_transition(R, ba, bg, f, w, dt, np.empty(3), np.empty((3, 3)), F)
    Fn = F @ Fc
    Fc[:, :] = Fn


@numba.njit(**_JIT)
def _logm(R, out):
    """Rotation vector ``out (3,)`` of ``R`` (angle below pi; small angles to second order)."""
    c = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    c = min(1.0, max(-1.0, c))
    th = math.acos(c)
    k = 0.5 + th * th / 12.0 if th < 1e-4 else 0.5 * th / math.sin(th)
    out[0] = k * (R[2, 1] - R[1, 2])
    out[1] = k * (R[0, 2] - R[2, 0])
    out[2] = k * (R[1, 0] - R[0, 1])


@numba.njit(**_JIT)
def rts_backward(Rf, xf, Pf, Rp, xp, Pp, F, n, Rs, xs, Ps):
    """Rauch-Tung-Striebel backward pass of the error-state filter over steps ``0..n-1`` of one chain
    (no restart in between), in place on ``Rs (K, 3, 3)``, ``xs (K, 12)``, ``Ps (K, 15, 15)``.

    Per step k: ``Rf, xf = [p, v, ba, bg], Pf`` the filtered nominal state and error covariance after
    its update; ``Rp, xp, Pp`` the predicted ones before it; ``F[k]`` the error transition from step
    k-1's filtered state to step k's prediction (I for a step without propagation); index 0's
    ``Rp, xp, Pp, F`` are not used. Error state ``[dp, dv, dtheta (local), dba, dbg]``.
    The step ``n-1`` is smoothed = filtered; backwards:
    ``C = Pf[k] F[k+1]^T Pp[k+1]^-1``, ``dx = C (x_s[k+1] ⊟ xp[k+1])``, ``x_s[k] = xf[k] ⊞ dx``
    (``R_s = R_f exp([dtheta]x)``, ``⊟``: ``log(R_p^T R_s)`` for the attitude), ``P_s[k] = Pf[k] +
    C (P_s[k+1] - Pp[k+1]) C^T`` (symmetrised)."""
    last = n - 1
    Rs[last] = Rf[last]
    xs[last] = xf[last]
    Ps[last] = Pf[last]
    d = np.empty(15)
    r = np.empty(3)
    E = np.empty((3, 3))
    for k in range(last - 1, -1, -1):
        A = F[k + 1] @ Pf[k]                          # (15, 15) = F Pf
        CT = np.linalg.solve(Pp[k + 1], A)            # C^T = Pp^-1 F Pf (Pp, Pf symmetric)
        C = CT.T.copy()
        for i in range(3):
            d[i] = xs[k + 1, i] - xp[k + 1, i]
            d[3 + i] = xs[k + 1, 3 + i] - xp[k + 1, 3 + i]
            d[9 + i] = xs[k + 1, 6 + i] - xp[k + 1, 6 + i]
            d[12 + i] = xs[k + 1, 9 + i] - xp[k + 1, 9 + i]
        D = Rp[k + 1].T @ Rs[k + 1]
        _logm(D, r)
        for i in range(3):
            d[6 + i] = r[i]
        dx = C @ d
        for i in range(3):
            xs[k, i] = xf[k, i] + dx[i]
            xs[k, 3 + i] = xf[k, 3 + i] + dx[3 + i]
            xs[k, 6 + i] = xf[k, 6 + i] + dx[9 + i]
            xs[k, 9 + i] = xf[k, 9 + i] + dx[12 + i]
        _expm(dx[6], dx[7], dx[8], E)
        Rs[k] = Rf[k] @ E
        M = C @ (Ps[k + 1] - Pp[k + 1]) @ CT
        for a in range(15):
            for b in range(15):
                Ps[k, a, b] = Pf[k, a, b] + 0.5 * (M[a, b] + M[b, a])


@numba.njit(**_JIT)
def record_state(R, p, v, ba, bg, P, Rd, xd, Pd):
    """Copy the nominal state and covariance into a recorder's slots: ``Rd (3, 3)``, ``xd (12,) = [p, v,
    ba, bg]``, ``Pd (15, 15)``."""
    for i in range(3):
        for j in range(3):
            Rd[i, j] = R[i, j]
        xd[i] = p[i]
        xd[3 + i] = v[i]
        xd[6 + i] = ba[i]
        xd[9 + i] = bg[i]
    for a in range(15):
        for b in range(15):
            Pd[a, b] = P[a, b]


@numba.njit(**_JIT)
def body_outputs(Rs, xs, Ps, n, p_ib, cov, q, pb):
    """Per smoothed step ``k < n`` the body pose of an output: ``cov[k] (12, 12)`` (:func:`body_cov`),
    ``q[k]`` the attitude quaternion (:func:`matrix_to_quat`), ``pb[k] = p - R p_ib`` (m, world)."""
    for k in range(n):
        body_cov(Rs[k], Ps[k], p_ib, cov[k])
        matrix_to_quat(Rs[k], q[k])
        for i in range(3):
            pb[k, i] = xs[k, i] - (Rs[k, i, 0] * p_ib[0] + Rs[k, i, 1] * p_ib[1] + Rs[k, i, 2] * p_ib[2])
