"""Sweep-angle noise: sigma, same-rotor correlation rho, quantisation (Chen §3.3, design §3).

The paper's values (``SIGMA_THETA_PAPER``, ``RHO_PAPER``) live in :mod:`layoutkit.units`.
"""
from __future__ import annotations

import numpy as np

__all__ = ["angle_correlation", "sample_angle_noise"]


def angle_correlation(n: int, rho: float) -> np.ndarray:
    """Correlation matrix ``R_theta`` of Chen eq. (19) for ``n`` sensors, ``(2n, 2n)``.

    Angle order ``[th1x, th1y, th2x, th2y, ...]`` (eq. 14). 1-based indices i != j with
    i + j even (same axis, hence same rotor sweep) are correlated with ``rho``.
    """
    idx = np.arange(1, 2 * n + 1)
    same = (idx[:, None] + idx[None, :]) % 2 == 0
    R = np.where(same, rho, 0.0)
    np.fill_diagonal(R, 1.0)
    return R


def sample_angle_noise(shape, sigma: float, rho: float, rng: np.random.Generator) -> np.ndarray:
    """Correlated angle noise of shape ``shape + (2,)`` (rad).

    ``shape`` is ``(..., n)``: the last axis is the sensor, the axes before it index frames
    (and stations). Per frame and axis a common term ``c`` and per angle an own term ``e``:
    ``noise = sigma * (sqrt(rho) c + sqrt(1 - rho) e)`` gives eq. (19)'s correlation.
    """
    if not 0.0 <= rho <= 1.0:
        raise ValueError(f"rho: expected a value in [0, 1], got {rho}")
    shape = tuple(shape)
    common = rng.standard_normal(shape[:-1] + (1, 2))
    own = rng.standard_normal(shape + (2,))
    return sigma * (np.sqrt(rho) * common + np.sqrt(1.0 - rho) * own)
