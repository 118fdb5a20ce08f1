"""Temporal filtering of attitude streams on SO(3) (Zhai et al. suggest filtering their output).

A causal constant-rate alpha–beta filter in the tangent space: predict with the current rate,
correct with the rotation-vector innovation. Left perturbations as in :mod:`layoutkit.geometry`
(``R = exp([phi]x) R_ref``).
"""
from __future__ import annotations

import numpy as np

from .._validate import as_array
from ..geometry import matrix_to_rotvec, rotvec_to_matrix

__all__ = ["alpha_beta_so3"]


def alpha_beta_so3(times, rotations, alpha: float = 0.2, beta: float = 0.02, gate_rad: float | None = None,
                   valid=None, max_rejects: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Causal alpha–beta filter of a rotation stream.

    Parameters
    ----------
    times : (T,) s, increasing. rotations : (T, 3, 3) measured rotations (NaN allowed where
        invalid), or (T, K, 3, 3) candidate measurements per frame (e.g. both IPPE branches times
        the corner-labelling symmetries): the one nearest the prediction is used (the first
        valid candidate initialises the filter) — temporal continuity inside the filter.
    alpha, beta : position and rate gains in (0, 1] (alpha=1, beta=0: no filtering).
    gate_rad : innovations larger than this (rad) are treated as outliers and skipped (prediction
        only); None = no gate. After ``max_rejects`` consecutive rejections the filter restarts at
        the measurement with zero rate (it had lost track, e.g. after a branch flip).
    valid : (T,) bool, measurements to use (default: finite rotations).

    Returns
    -------
    (R_filtered (T, 3, 3), rate (T, 3) rad/s) — the filtered attitude and the estimated angular
    rate (left / space-frame rotation vector rate). Before the first valid measurement the output is NaN.
    """
    t = as_array(times, "times", (None,))
    R = np.asarray(rotations, dtype=float)
    if R.ndim == 3:
        R = R[:, None]
    R = as_array(R, "rotations", (None, None, 3, 3))
    if len(t) != len(R):
        raise ValueError(f"times: expected {len(R)} values (one per rotation), got {len(t)}")
    fin = np.all(np.isfinite(R), axis=(2, 3))  # (T, K)
    ok = fin.any(1) if valid is None else np.asarray(valid, bool) & fin.any(1)
    out = np.full((len(t), 3, 3), np.nan)
    rate = np.full((len(t), 3), np.nan)
    est, w, t_prev, rejects = None, np.zeros(3), None, 0
    for k in range(len(t)):
        if est is not None:
            dt = t[k] - t_prev
            est = rotvec_to_matrix(w * dt) @ est  # predict
            t_prev = t[k]
            if ok[k]:
                cand = R[k][fin[k]]
                rs = matrix_to_rotvec(cand @ est.T)  # innovations of all candidates
                j = int(np.argmin(np.linalg.norm(rs, axis=-1)))  # the one nearest the prediction
                r = rs[j]
                if gate_rad is None or np.linalg.norm(r) <= gate_rad:
                    est = rotvec_to_matrix(alpha * r) @ est
                    if dt > 0:
                        w = w + beta * r / dt
                    rejects = 0
                else:
                    rejects += 1
                    if rejects >= max_rejects:
                        est, w, rejects = cand[j].copy(), np.zeros(3), 0
        elif ok[k]:
            est, t_prev = R[k][fin[k]][0].copy(), t[k]
        if est is not None:
            out[k], rate[k] = est, w
    return out, rate
