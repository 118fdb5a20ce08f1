"""Fused per-pose 6 × 6 kernels of the selection search (numba, compiled on first use, cached on disk).

The search evaluates the exact squared DOP ``trace(W H_p)`` of many candidate selections at many
poses, ``H_p = (1 - rho) A^-1 + rho sum_c u_c u_c^T``, ``u_c = A^-1 b_c`` (Chen eq. 18 rewritten, see
:func:`layoutkit.optimize.problem.pose_values_from_info`). Batched numpy spends most of its time
in ``np.linalg.inv``/``cholesky`` dispatch on tiny matrices and in materialising the gathered
``A = A_base - sum G_out + sum G_in`` arrays. These kernels do the same algebra per pose in
registers: trace scaling ``An = A / (tr A / 6)``, Cholesky ``An = L L^T`` (a non-positive pivot or
``min L_ii^2 <= max L_ii^2 / cond_max`` marks the pose singular: value inf, the same test as the
numpy path), ``L^-1`` by forward substitution, ``(A^-1)_ii = sum_j (L^-1)_ji^2 / tr`` and
``u_c = L^-T (L^-1 b_c) / tr``. No Python loop over poses; single-threaded (no prange).
"""
from __future__ import annotations

import numpy as np

__all__ = ["pose_values", "move_values"]

def pose_values(A, b, rho, w, cond_max=1e12):
    """Squared weighted DOP ``trace(W H)`` per pose: A (..., 6, 6), b (..., C, 6) -> (...,), inf where
    A is singular (module docstring). Same values as the numpy path of
    :func:`layoutkit.optimize.problem.pose_values_from_info` (to rounding)."""
    from ._kernels_numba import pose_values_kernel

    A = np.asarray(A, float)
    b = np.asarray(b, float)
    batch = A.shape[:-2]
    Af = np.ascontiguousarray(A.reshape(-1, 6, 6))
    bf = np.ascontiguousarray(np.broadcast_to(b, batch + b.shape[-2:]).reshape(len(Af), -1, 6))
    out = np.empty(len(Af))
    pose_values_kernel(Af, bf, float(rho), np.ascontiguousarray(w, float), float(cond_max), out)
    return out.reshape(batch)


def move_values(A_base, b_base, G, U, poses, outs, ins, rho, w, cond_max=1e12):
    """Squared values ``(L, Pc)`` of L moves at poses ``poses (Pc,)``: move l removes candidates
    ``outs[l] (L, r)`` and adds ``ins[l] (L, a)`` to the selection whose information at pose p is
    ``A_base[p] (P, 6, 6)``, ``b_base[p] (P, C, 6)``; G (P, N, 6, 6), U (P, N, C, 6) per candidate
    (:class:`layoutkit.optimize.problem.Problem`). Nothing of size L × Pc × 36 is materialised."""
    from ._kernels_numba import move_values_kernel

    poses = np.ascontiguousarray(poses, np.int64)
    outs = np.ascontiguousarray(np.asarray(outs, np.int64).reshape(len(outs), -1))
    ins = np.ascontiguousarray(np.asarray(ins, np.int64).reshape(len(ins), -1))
    if len(outs) != len(ins):
        raise ValueError(f"outs and ins: expected the same number of moves, got {len(outs)} and {len(ins)}")
    out = np.empty((len(outs), len(poses)))
    move_values_kernel(_c(A_base), _c(b_base), _c(G), _c(U), poses, outs, ins, float(rho),
                       np.ascontiguousarray(w, float), float(cond_max), out)
    return out


def _c(a):
    a = np.asarray(a, float)
    return a if a.flags.c_contiguous else np.ascontiguousarray(a)
