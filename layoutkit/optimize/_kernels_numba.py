"""numba implementations of :mod:`layoutkit.optimize.kernels` (imported on first use only: importing
numba and compiling is not work for import time of the package)."""
import numba
import numpy as np


@numba.njit(cache=True, fastmath=False, nogil=True)
def value6(A, b, rho, w, cond_max, L, Li, y):
    """Squared weighted DOP of one pose from A (6, 6) and b (C, 6); scratch L, Li (6, 6), y (6,)."""
    tr = 0.0
    for i in range(6):
        tr += A[i, i]
    tr /= 6.0
    if not tr > 0.0:
        tr = 1.0
    dmin = np.inf
    dmax = 0.0
    for j in range(6):
        s = A[j, j] / tr
        for q in range(j):
            s -= L[j, q] * L[j, q]
        if not s > 0.0:
            return np.inf
        d = np.sqrt(s)
        L[j, j] = d
        if s < dmin:
            dmin = s
        if s > dmax:
            dmax = s
        for i in range(j + 1, 6):
            s2 = A[i, j] / tr
            for q in range(j):
                s2 -= L[i, q] * L[j, q]
            L[i, j] = s2 / d
    if not dmin > dmax / cond_max:
        return np.inf
    # Li = L^-1 (lower triangular), column by column
    for c in range(6):
        for i in range(6):
            if i < c:
                Li[i, c] = 0.0
                continue
            s = 1.0 if i == c else 0.0
            for q in range(c, i):
                s -= L[i, q] * Li[q, c]
            Li[i, c] = s / L[i, i]
    val = 0.0
    for i in range(6):
        acc = 0.0
        for j in range(i, 6):
            acc += Li[j, i] * Li[j, i]
        val += w[i] * acc
    val *= (1.0 - rho) / tr
    if rho != 0.0:
        C = b.shape[0]
        for c in range(C):
            for i in range(6):  # y = L^-1 b_c
                s = 0.0
                for q in range(i + 1):
                    s += Li[i, q] * b[c, q]
                y[i] = s
            rt = 0.0
            for i in range(6):  # u = L^-T y / tr
                s = 0.0
                for q in range(i, 6):
                    s += Li[q, i] * y[q]
                s /= tr
                rt += w[i] * s * s
            val += rho * rt
    return val


@numba.njit(cache=True, fastmath=False, nogil=True)
def pose_values_kernel(A, b, rho, w, cond_max, out):
    """out[m] = value of A[m] (M, 6, 6), b[m] (M, C, 6)."""
    L = np.zeros((6, 6))
    Li = np.zeros((6, 6))
    y = np.zeros(6)
    for m in range(A.shape[0]):
        out[m] = value6(A[m], b[m], rho, w, cond_max, L, Li, y)


@numba.njit(cache=True, fastmath=False, nogil=True)
def move_values_kernel(Ab, bb, G, U, poses, outs, ins, rho, w, cond_max, out):
    """out[l, q] = value at pose p = poses[q] of ``A = Ab[p] - sum_r G[p, outs[l, r]] + sum_j G[p, ins[l, j]]``
    (b likewise with U); Ab (P, 6, 6), bb (P, C, 6), G (P, N, 6, 6), U (P, N, C, 6)."""
    C = bb.shape[1]
    A = np.zeros((6, 6))
    b = np.zeros((C, 6))
    L = np.zeros((6, 6))
    Li = np.zeros((6, 6))
    y = np.zeros(6)
    for q in range(poses.shape[0]):
        p = poses[q]
        for l in range(outs.shape[0]):
            for i in range(6):
                for j in range(6):
                    A[i, j] = Ab[p, i, j]
                for c in range(C):
                    b[c, i] = bb[p, c, i]
            for r in range(outs.shape[1]):
                n = outs[l, r]
                for i in range(6):
                    for j in range(6):
                        A[i, j] -= G[p, n, i, j]
                    for c in range(C):
                        b[c, i] -= U[p, n, c, i]
            for r in range(ins.shape[1]):
                n = ins[l, r]
                for i in range(6):
                    for j in range(6):
                        A[i, j] += G[p, n, i, j]
                    for c in range(C):
                        b[c, i] += U[p, n, c, i]
            out[l, q] = value6(A, b, rho, w, cond_max, L, Li, y)
