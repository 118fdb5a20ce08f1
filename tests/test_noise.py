"""Angle noise of Chen §3.3: the sampled correlation equals eq. (19)."""
import numpy as np
import pytest

from layoutkit.noise import angle_correlation, sample_angle_noise
from layoutkit.units import RHO_PAPER, SIGMA_THETA_PAPER


def test_correlation_matrix_eq19():
    """1 on the diagonal, rho where 1-based i != j and i + j even, else 0."""
    R = angle_correlation(3, 0.5)
    expect = np.array([
        [1, 0, .5, 0, .5, 0], [0, 1, 0, .5, 0, .5], [.5, 0, 1, 0, .5, 0],
        [0, .5, 0, 1, 0, .5], [.5, 0, .5, 0, 1, 0], [0, .5, 0, .5, 0, 1]])
    np.testing.assert_array_equal(R, expect)


def test_sampled_noise_has_eq19_correlation(rng):
    """Monte-Carlo: empirical correlation within 5 standard errors of eq. (19); sigma matches."""
    N, n = 60000, 5
    e = sample_angle_noise((N, n), SIGMA_THETA_PAPER, RHO_PAPER, rng).reshape(N, -1)
    C = np.corrcoef(e.T)
    se = (1 - RHO_PAPER**2) / np.sqrt(N)
    np.testing.assert_allclose(C, angle_correlation(n, RHO_PAPER), atol=5 * max(se, 1 / np.sqrt(N)))
    assert e.std() == pytest.approx(SIGMA_THETA_PAPER, rel=0.01)


def test_reproducible_from_seed():
    a = sample_angle_noise((10, 4), 1e-5, 0.3, np.random.default_rng(7))
    b = sample_angle_noise((10, 4), 1e-5, 0.3, np.random.default_rng(7))
    np.testing.assert_array_equal(a, b)


def test_rho_out_of_range_message():
    with pytest.raises(ValueError, match=r"rho: expected a value in \[0, 1\], got 1.5"):
        sample_angle_noise((2, 4), 1e-5, 1.5, np.random.default_rng(0))
