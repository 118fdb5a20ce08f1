"""Fast ADOP/PDOP of ONE layout over many poses (dense envelopes, ``layoutkit score``, the optimiser).

Same metric as :func:`layoutkit.dop.pose_dop` (Chen eqs. 18–22 with the same-rotor correlation
rho of eq. 19, lit sensors only, all stations), computed by a fused per-pose kernel instead of
batched 6 × 6 matrix algebra: for every pose the kernel accumulates the 21 entries of
``A = J^T J`` and the common-mode rows ``b_c = sum_i v_i j_{i,c}`` (one per station and axis)
directly from the sensor geometry, exploiting the structure of each Jacobian row
(``theta_x`` rows have no ``t_y`` entry, ``theta_y`` rows no ``t_x`` entry, in the station frame),
factors ``A`` by a Jacobi-scaled Cholesky and reads the covariance traces without forming H:

    H = (1 - rho) A^-1 + rho sum_c u_c u_c^T,   u_c = A^-1 b_c      (Chen eq. 18, closed form)
    ADOP = (180/pi) sqrt(tr H_rot),  PDOP = sqrt(tr H_t)              (Chen eq. 22)

The pose batch is processed in bounded chunks (memory O(chunk)); there is no Python loop over poses
(the kernel is compiled with numba on first use and cached on disk).

Accumulation happens in each station's frame (``l_s = R_s^T R p``, ``p_s = R_s^T (R p + t - t_s)``)
and is rotated into the world frame with ``blockdiag(R_s, R_s)`` when stations are given; for the
single station at the origin no rotation is needed (the traces are invariant).

Singular geometry: A is scaled to unit diagonal; a Cholesky pivot below ``1e-12`` (relative) marks the
pose singular (status 2). :func:`layoutkit.dop.pose_dop` uses a relative-eigenvalue test with the same
threshold; both agree except on poses within a factor ~6 of the threshold.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._validate import as_array, check_finite
from .units import RAD2DEG

__all__ = ["BatchDop", "batch_dop", "DEFAULT_CHUNK"]

#: poses per kernel call (bounded working memory: the outputs of one chunk)
DEFAULT_CHUNK = 65536
_PIVOT = 1e-12


@dataclass(frozen=True)
class BatchDop:
    """ADOP/PDOP of one layout at P poses.

    adop : (P,) deg/rad (inf where status != 0); pdop : (P,) m/rad; n_visible : (P,) int, lit
    (station, sensor) pairs; status : (P,) int, 0 ok, 1 fewer than 3 lit pairs, 2 singular geometry;
    success : (P,) bool (status == 0).
    """

    adop: np.ndarray
    pdop: np.ndarray
    n_visible: np.ndarray
    status: np.ndarray

    @property
    def success(self) -> np.ndarray:
        return self.status == 0

    @property
    def message(self) -> str:
        s = self.status
        if np.all(s == 0):
            return "ok"
        return (f"{int(np.sum(s == 1))} pose(s) with fewer than 3 lit sensors, "
                f"{int(np.sum(s == 2))} with singular geometry")


_KERNEL = None


def _kernel():
    """Compile (once, cached on disk) and return the numba kernel."""
    global _KERNEL  # a compiled-function cache, not state: the kernel is pure
    if _KERNEL is None:
        import numba

        _KERNEL = numba.njit(cache=True, fastmath=False, nogil=True)(_dop_kernel)
    return _KERNEL


def _dop_kernel(pos, R, t, vis, Rs, ts, rotate, rho, adop, pdop, nvis, status):  # pragma: no cover - compiled
    """Per-pose fused DOP (see module docstring). pos (n,3); R (P,3,3); t (P,3); vis (P,S,n) uint8;
    Rs (S,3,3), ts (S,3); rotate: rotate station-frame information into the world frame."""
    P = R.shape[0]
    S = Rs.shape[0]
    n = pos.shape[0]
    C = 2 * S
    A = np.zeros((6, 6))
    As = np.zeros((6, 6))
    b = np.zeros((C, 6))
    L = np.zeros((6, 6))
    M = np.zeros((6, 6))
    d = np.zeros(6)
    T = np.zeros((6, 6))
    g = np.zeros(6)
    Ms = np.zeros((3, 3))
    cs = np.zeros(3)
    y = np.zeros(6)
    u = np.zeros(6)
    for p in range(P):
        for i in range(6):
            for j in range(6):
                A[i, j] = 0.0
        for c in range(C):
            for j in range(6):
                b[c, j] = 0.0
        cnt = 0
        for s in range(S):
            # M = Rs^T R, c = Rs^T (t - ts)
            for i in range(3):
                for j in range(3):
                    acc = 0.0
                    for q in range(3):
                        acc += Rs[s, q, i] * R[p, q, j]
                    Ms[i, j] = acc
                acc = 0.0
                for q in range(3):
                    acc += Rs[s, q, i] * (t[p, q] - ts[s, q])
                cs[i] = acc
            for i in range(6):
                for j in range(6):
                    As[i, j] = 0.0
            bx0 = 0.0; bx1 = 0.0; bx2 = 0.0; bx3 = 0.0; bx5 = 0.0
            by0 = 0.0; by1 = 0.0; by2 = 0.0; by4 = 0.0; by5 = 0.0
            for k in range(n):
                if vis[p, s, k] == 0:
                    continue
                cnt += 1
                px = pos[k, 0]; py = pos[k, 1]; pz = pos[k, 2]
                lx = Ms[0, 0] * px + Ms[0, 1] * py + Ms[0, 2] * pz
                ly = Ms[1, 0] * px + Ms[1, 1] * py + Ms[1, 2] * pz
                lz = Ms[2, 0] * px + Ms[2, 1] * py + Ms[2, 2] * pz
                x = lx + cs[0]; yy = ly + cs[1]; z = lz + cs[2]
                # theta_x row: a = (-z, 0, x)/(x²+z²), rot = l x a  (Chen eqs. 10–14)
                dx = 1.0 / (x * x + z * z)
                a1 = -z * dx; a3 = x * dx
                g0 = ly * a3; g1 = lz * a1 - lx * a3; g2 = -ly * a1
                As[0, 0] += g0 * g0; As[0, 1] += g0 * g1; As[0, 2] += g0 * g2; As[0, 3] += g0 * a1; As[0, 5] += g0 * a3
                As[1, 1] += g1 * g1; As[1, 2] += g1 * g2; As[1, 3] += g1 * a1; As[1, 5] += g1 * a3
                As[2, 2] += g2 * g2; As[2, 3] += g2 * a1; As[2, 5] += g2 * a3
                As[3, 3] += a1 * a1; As[3, 5] += a1 * a3
                As[5, 5] += a3 * a3
                bx0 += g0; bx1 += g1; bx2 += g2; bx3 += a1; bx5 += a3
                # theta_y row: a = (0, -z, y)/(y²+z²)
                dy = 1.0 / (yy * yy + z * z)
                e2 = -z * dy; e3 = yy * dy
                h0 = ly * e3 - lz * e2; h1 = -lx * e3; h2 = lx * e2
                As[0, 0] += h0 * h0; As[0, 1] += h0 * h1; As[0, 2] += h0 * h2; As[0, 4] += h0 * e2; As[0, 5] += h0 * e3
                As[1, 1] += h1 * h1; As[1, 2] += h1 * h2; As[1, 4] += h1 * e2; As[1, 5] += h1 * e3
                As[2, 2] += h2 * h2; As[2, 4] += h2 * e2; As[2, 5] += h2 * e3
                As[4, 4] += e2 * e2; As[4, 5] += e2 * e3
                As[5, 5] += e3 * e3
                by0 += h0; by1 += h1; by2 += h2; by4 += e2; by5 += e3
            for i in range(6):
                for j in range(i + 1, 6):
                    As[j, i] = As[i, j]
            b[2 * s, 0] = bx0; b[2 * s, 1] = bx1; b[2 * s, 2] = bx2; b[2 * s, 3] = bx3; b[2 * s, 4] = 0.0; b[2 * s, 5] = bx5
            b[2 * s + 1, 0] = by0; b[2 * s + 1, 1] = by1; b[2 * s + 1, 2] = by2; b[2 * s + 1, 3] = 0.0
            b[2 * s + 1, 4] = by4; b[2 * s + 1, 5] = by5
            if rotate:
                # A += B As B^T, b_c <- B b_c with B = blockdiag(Rs, Rs)
                for i in range(6):
                    for j in range(6):
                        acc = 0.0
                        bi = (i // 3) * 3
                        for q in range(3):
                            acc += Rs[s, i - bi, q] * As[bi + q, j]
                        T[i, j] = acc
                for i in range(6):
                    for j in range(6):
                        acc = 0.0
                        bj = (j // 3) * 3
                        for q in range(3):
                            acc += T[i, bj + q] * Rs[s, j - bj, q]
                        A[i, j] += acc
                for c in range(2 * s, 2 * s + 2):
                    for i in range(6):
                        g[i] = b[c, i]
                    for i in range(6):
                        bi = (i // 3) * 3
                        acc = 0.0
                        for q in range(3):
                            acc += Rs[s, i - bi, q] * g[bi + q]
                        b[c, i] = acc
            else:
                for i in range(6):
                    for j in range(6):
                        A[i, j] += As[i, j]
        nvis[p] = cnt
        if cnt < 3:
            status[p] = 1
            adop[p] = np.inf
            pdop[p] = np.inf
            continue
        # Jacobi scaling, Cholesky of D A D, L^-1
        sing = False
        for i in range(6):
            if A[i, i] <= 0.0:
                sing = True
                break
            d[i] = 1.0 / np.sqrt(A[i, i])
        if not sing:
            for j in range(6):
                acc = A[j, j] * d[j] * d[j]
                for q in range(j):
                    acc -= L[j, q] * L[j, q]
                if acc <= _PIVOT:
                    sing = True
                    break
                L[j, j] = np.sqrt(acc)
                for i in range(j + 1, 6):
                    acc = A[i, j] * d[i] * d[j]
                    for q in range(j):
                        acc -= L[i, q] * L[j, q]
                    L[i, j] = acc / L[j, j]
        if sing:
            status[p] = 2
            adop[p] = np.inf
            pdop[p] = np.inf
            continue
        for j in range(6):
            M[j, j] = 1.0 / L[j, j]
            for i in range(j + 1, 6):
                acc = 0.0
                for q in range(j, i):
                    acc += L[i, q] * M[q, j]
                M[i, j] = -acc / L[i, i]
        # (A^-1)_ii = d_i² sum_{j>=i} M_ji²
        tr_r = 0.0
        tr_t = 0.0
        for i in range(6):
            acc = 0.0
            for j in range(i, 6):
                acc += M[j, i] * M[j, i]
            if i < 3:
                tr_r += acc * d[i] * d[i]
            else:
                tr_t += acc * d[i] * d[i]
        tr_r *= (1.0 - rho)
        tr_t *= (1.0 - rho)
        if rho != 0.0:
            for c in range(C):
                # u = A^-1 b = D M^T M D b
                for i in range(6):
                    acc = 0.0
                    for q in range(i + 1):
                        acc += M[i, q] * d[q] * b[c, q]
                    y[i] = acc
                for i in range(6):
                    acc = 0.0
                    for q in range(i, 6):
                        acc += M[q, i] * y[q]
                    u[i] = acc * d[i]
                tr_r += rho * (u[0] * u[0] + u[1] * u[1] + u[2] * u[2])
                tr_t += rho * (u[3] * u[3] + u[4] * u[4] + u[5] * u[5])
        status[p] = 0
        adop[p] = RAD2DEG * np.sqrt(max(tr_r, 0.0))  # a module constant: numba freezes it at compile time
        pdop[p] = np.sqrt(max(tr_t, 0.0))


def batch_dop(points_body, rotations, translations, *, rho: float = 0.0, visible=None, stations=None,
              chunk: int = DEFAULT_CHUNK) -> BatchDop:
    """ADOP/PDOP of one layout at many poses (fused kernel; same values as ``pose_dop``).

    points_body : (n, 3) float, m, sensor positions in the body frame.
    rotations : (P, 3, 3), translations : (P, 3) m — body pose ``p = R p_body + t`` in the frame of
        the single station at the origin (``stations=None``) or in the world frame of ``stations``
        (sequence of :class:`layoutkit.lighthouse.Station`).
    rho : same-rotor correlation in [0, 1) (Chen eq. 19). visible : (P, n) for one station or
        (P, S, n) bool, lit sensors; default all. chunk : poses per kernel call.
    Returns :class:`BatchDop` with (P,) arrays.
    """
    pos = np.ascontiguousarray(as_array(points_body, "points_body", (None, 3)), float)
    R = np.ascontiguousarray(as_array(rotations, "rotations", (None, 3, 3)), float)
    P = R.shape[0]
    t = np.ascontiguousarray(as_array(translations, "translations", (P, 3)), float)
    for a, nm in ((pos, "points_body"), (R, "rotations"), (t, "translations")):
        check_finite(a, nm)
    if not 0.0 <= float(rho) < 1.0:
        raise ValueError(f"rho: expected 0 <= rho < 1, got {rho}")
    if stations is None:
        Rs = np.eye(3)[None]
        ts = np.zeros((1, 3))
        rotate = False
    else:
        Rs = np.ascontiguousarray(np.stack([np.asarray(s.rotation, float) for s in stations]))
        ts = np.ascontiguousarray(np.stack([np.asarray(s.translation, float) for s in stations]))
        rotate = not all(np.allclose(r, np.eye(3), atol=0, rtol=0) for r in Rs)
    S, n = len(Rs), len(pos)
    if visible is None:
        vis = np.ones((P, S, n), np.uint8)
    else:
        vis = np.asarray(visible, bool)
        if vis.shape == (P, n) and S == 1:
            vis = vis[:, None, :]
        if vis.shape != (P, S, n):
            raise ValueError(f"visible: expected shape ({P}, {n}) or ({P}, {S}, {n}), got {vis.shape}")
        vis = vis.view(np.uint8)
    adop = np.empty(P)
    pdop = np.empty(P)
    nvis = np.empty(P, np.int64)
    status = np.empty(P, np.int64)
    k = _kernel()
    step = max(1, int(chunk))
    for a in range(0, P, step):
        sl = slice(a, a + step)
        k(pos, R[sl], t[sl], np.ascontiguousarray(vis[sl]), Rs, ts, rotate, float(rho),
          adop[sl], pdop[sl], nvis[sl], status[sl])
    return BatchDop(adop, pdop, nvis, status)
