"""Running statistics with flat memory (layoutkit.live.stats): streaming results equal the batch
formulas of layoutkit.dop computed in one go."""
from __future__ import annotations

import numpy as np
import pytest

from layoutkit.dop import pose_errors, precision, rms
from layoutkit.geometry import random_rotations, rotvec_to_matrix
from layoutkit.live.stats import DecimatedSeries, ErrorAccumulator, StaticGroupTracker

SIG = 4.014e-5
DEG = np.pi / 180


def noisy_static(R0, t0, n, rng, s_rot, s_t):
    """n poses scattered around (R0, t0) with per-axis rotation s_rot (rad) and translation s_t (m)."""
    R = rotvec_to_matrix(rng.normal(0, s_rot, (n, 3))) @ R0
    t = t0 + rng.normal(0, s_t, (n, 3))
    return R, t


def test_static_groups_streaming_equals_batch_precision():
    """Streaming == batch: three static stretches separated by moves; each group's eq. (23)
    precision equals layoutkit.dop.precision over the same frames (rtol 1e-6), fed in odd chunks."""
    rng = np.random.default_rng(0)
    W = 60
    adop, pdop = 2500.0, 20.0  # deg/rad, m/rad -> predicted 0.1 deg, 0.8 mm
    s_rot = adop * SIG * DEG / np.sqrt(3)
    s_t = pdop * SIG / np.sqrt(3)
    R0s = random_rotations(3, rng)
    parts, truth_groups = [], []
    for g in range(3):
        n = W * (4 + g)
        R, t = noisy_static(R0s[g], np.array([0.1 * g, 0, 2.0]), n, rng, s_rot, s_t)
        parts.append((R, t))
        truth_groups.append((R, t))
        # a move between groups: 30 frames along a geodesic (clearly not static)
        if g < 2:
            steps = np.linspace(0, 1, W)[:, None]
            rv = steps * np.array([0.5, 0.2, 0.0])
            parts.append((rotvec_to_matrix(rv) @ R0s[g], np.array([0.1 * g, 0, 2.0]) + steps * [0.05, 0, 0]))
    R = np.concatenate([p[0] for p in parts])
    t = np.concatenate([p[1] for p in parts])
    times = np.arange(len(R)) / 60.0
    tr = StaticGroupTracker(SIG, window=W, factor=3.0)
    i = 0
    for step in (7, 113, 1, 250, 59) * 100:
        if i >= len(R):
            break
        j = min(len(R), i + step)
        tr.update(times[i:j], R[i:j], t[i:j], np.full(j - i, adop), np.full(j - i, pdop))
        i = j
    groups = tr.finish()
    assert len(groups) == 3
    for g, (Rg, tg) in zip(groups, truth_groups):
        assert g.n == len(Rg)
        s_r, s_tt = precision(Rg, tg)
        np.testing.assert_allclose(g.sigma_rot_deg, s_r / DEG, rtol=1e-6)
        np.testing.assert_allclose(g.sigma_trans_m, s_tt, rtol=1e-9)
        np.testing.assert_allclose(g.predicted_rot_deg, adop * SIG, rtol=1e-12)
        np.testing.assert_allclose(g.predicted_trans_m, pdop * SIG, rtol=1e-12)
        # and the measured scatter is the one we injected (Monte-Carlo, 4 sigma of the estimate)
        assert abs(g.sigma_rot_deg / (adop * SIG) - 1) < 4 / np.sqrt(2 * 3 * g.n) + 0.01


def test_slow_drift_is_not_static():
    """A drift of 0.5 deg/s with noise at the predicted level never forms a static group
    (the half-window drift test catches what the spread test lets through)."""
    rng = np.random.default_rng(1)
    n = 1200
    times = np.arange(n) / 60.0
    adop = 3000.0
    rv = np.column_stack([np.deg2rad(0.5) * times, 0 * times, 0 * times])
    R = rotvec_to_matrix(rv + rng.normal(0, adop * SIG * DEG / np.sqrt(3), (n, 3)))
    t = np.array([0, 0, 2.0]) + rng.normal(0, 1e-4, (n, 3))
    tr = StaticGroupTracker(SIG, window=120)
    tr.update(times, R, t, np.full(n, adop), np.full(n, 20.0))
    assert tr.finish() == [] and tr.windows_moving == 10


def test_error_accumulator_equals_batch_eq25():
    """Streaming == batch: chunked RMS/max/mean errors equal pose_errors over all frames at once."""
    rng = np.random.default_rng(2)
    n = 1000
    Rr = random_rotations(n, rng)
    tr = rng.normal(0, 1, (n, 3))
    Re = rotvec_to_matrix(rng.normal(0, 1e-3, (n, 3))) @ Rr
    te = tr + rng.normal(0, 1e-3, (n, 3))
    a = rng.uniform(1000, 3000, n)
    p = rng.uniform(10, 30, n)
    acc = ErrorAccumulator(SIG, series_capacity=64)
    for s in np.array_split(np.arange(n), 7):
        acc.update(s / 60.0, Re[s], te[s], Rr[s], tr[s], a[s], p[s])
    e_r, e_t = pose_errors(Re, te, Rr, tr)
    s = acc.summary()
    assert s.n == n
    np.testing.assert_allclose(s.rms_rot_deg, rms(e_r) / DEG, rtol=1e-12)
    np.testing.assert_allclose(s.max_rot_deg, e_r.max() / DEG, rtol=1e-12)
    np.testing.assert_allclose(s.rms_trans_m, rms(e_t), rtol=1e-12)
    np.testing.assert_allclose(s.max_trans_m, e_t.max(), rtol=1e-12)
    np.testing.assert_allclose(s.mean_trans_err_m, (te - tr).mean(0), atol=1e-15)
    np.testing.assert_allclose(s.predicted_rot_deg, np.sqrt(np.mean(a ** 2)) * SIG, rtol=1e-12)
    np.testing.assert_allclose(s.ratio_rot, s.rms_rot_deg / s.predicted_rot_deg)
    assert len(acc.series) <= 64


@pytest.mark.parametrize("capacity,total,chunk", [(10, 1000, 7), (16, 16, 16), (5, 3, 1), (64, 10000, 333)])
def test_decimated_series_keeps_every_stride_th_row(capacity, total, chunk):
    """Brute force: the stored rows are exactly rows 0, s, 2s, ... of the stream, fewer than capacity."""
    ds = DecimatedSeries(2, capacity)
    rows = np.column_stack([np.arange(total), -np.arange(total)]).astype(float)
    for i in range(0, total, chunk):
        ds.extend(rows[i:i + chunk])
    out = ds.array()
    assert len(out) <= capacity
    np.testing.assert_array_equal(out, rows[::ds.stride][: len(out)])
    assert len(out) == len(rows[::ds.stride])


def test_bad_arguments():
    with pytest.raises(ValueError, match=r"^window: expected >= 3 frames, got 2$"):
        StaticGroupTracker(window=2)
    with pytest.raises(ValueError, match=r"^capacity: expected >= 2, got 1$"):
        DecimatedSeries(3, 1)
