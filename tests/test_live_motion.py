"""Motion compensation of the live pipeline (LiveConfig.motion_compensation, docs/live.md).

The hardware simulator draws every sweep's angles from the pose at that sweep's own sync time, so
a frame pairs an X sweep at t and a Y sweep at t + 8.33 ms. Without compensation the PnP fits one
pose to both, biased for fast motion; with it the Y angles are moved to the X time with the body
velocity of the recent poses.
"""
from __future__ import annotations

import numpy as np
import pytest

from layoutkit.dop import pose_errors, rms
from layoutkit.geometry import rotvec_to_matrix
from layoutkit.live.frames import SweepMeasurement
from layoutkit.live.pipeline import LiveConfig, PosePipeline
from layoutkit.live.simulator import simulate_sweeps, spin_motion
from layoutkit.units import SIGMA_THETA_PAPER
from layoutkit.shapes import chen_target
from layoutkit.status import OK as STATUS_OK

WARM_UP_S = 0.5  # frames before this have no (or a start-up) velocity estimate; not evaluated


@pytest.fixture(scope="module")
def layout():
    return chen_target()[1]




def solve(layout, sw, chunk_frames=256, **cfg):
    """Feed the simulated sweeps through the pipeline; per frame: t, R, t, status, adop, pdop, truth."""
    ang = sw.measured_angles()
    sweeps = [SweepMeasurement(float(sw.t[k]), int(sw.station[k]), int(sw.axis[k]), ang[k], int(sw.seq[k]))
              for k in range(sw.t.size)]
    pipe = PosePipeline(layout.positions, LiveConfig(n_sensors=layout.n, chunk_frames=chunk_frames, **cfg))
    chunks = pipe.feed(sweeps) + pipe.flush(end_of_stream=True)
    c = {k: np.concatenate([getattr(ch, k) for ch in chunks])
         for k in ("t", "rotation", "translation", "status", "adop", "pdop")}
    x = sw.axis == 0  # a frame's t is its X sweep's sync time, a TRUTH row
    i = np.searchsorted(sw.t[x], c["t"])
    assert np.array_equal(sw.t[x][i], c["t"])
    c["R_true"], c["t_true"] = rotvec_to_matrix(sw.rotvec[x][i]), sw.translation[x][i]
    return c


def ratios(c):
    """RMS attitude / position error vs truth over the good frames after the warm-up, each divided
    by its prediction sqrt(mean ADOP²)·σθ, sqrt(mean PDOP²)·σθ (Chen eq. 24)."""
    g = (c["status"] == STATUS_OK) & (c["t"] >= WARM_UP_S)
    e_r, e_t = pose_errors(c["rotation"][g], c["translation"][g], c["R_true"][g], c["t_true"][g])
    pred_r = np.sqrt(np.mean(c["adop"][g] ** 2)) * SIGMA_THETA_PAPER
    pred_t = np.sqrt(np.mean(c["pdop"][g] ** 2)) * SIGMA_THETA_PAPER
    return np.degrees(rms(e_r)) / pred_r, rms(e_t) / pred_t, int(g.sum())


def test_fast_tumble_error_matches_dop_only_with_compensation(layout):
    """20°/s constant rotation + 0.2 m/s translation, paper noise + 50 MHz quantisation, 30 s
    (1800 frames, 1770 after the 0.5 s warm-up). Without compensation the RMS attitude error is
    ~2× the DOP prediction (asserted > 1.2×); with it, attitude and position are within 7 % of the
    prediction. Tolerance: the relative standard error of an RMS over N independent frames is
    ~1/sqrt(2N) = 1.7 % here, so 7 % is ~4 standard errors (measured: without 2.05 / 2.09,
    with 1.006 / 0.999)."""
    sw = simulate_sweeps(layout, duration=30.0, seed=11, motion=spin_motion(20.0, 0.2))
    off = ratios(solve(layout, sw))
    on = ratios(solve(layout, sw, motion_compensation=True))
    assert off[2] > 1700 and on[2] > 1700  # practically every frame is good either way
    assert off[0] > 1.2 and off[1] > 1.2
    assert abs(on[0] - 1) < 0.07 and abs(on[1] - 1) < 0.07


def test_noise_free_constant_velocity_is_removed(layout):
    """Proof of the model: no noise, no quantisation (1 THz clock), constant 60°/s rotation. After
    the warm-up every compensated pose is within 0.05 predicted σ of the truth, while the
    uncompensated poses are off by several σ (the whole error is the X/Y time skew)."""
    sw = simulate_sweeps(layout, duration=3.0, seed=2, motion=spin_motion(60.0, 0.0), sigma=0.0, clock_hz=1e12)
    out = {}
    for on in (False, True):
        c = solve(layout, sw, chunk_frames=64, motion_compensation=on)
        g = c["t"] >= WARM_UP_S
        assert np.all(c["status"][g] == STATUS_OK)
        e_r, e_t = pose_errors(c["rotation"][g], c["translation"][g], c["R_true"][g], c["t_true"][g])
        out[on] = (np.degrees(e_r) / (c["adop"][g] * SIGMA_THETA_PAPER), e_t / (c["pdop"][g] * SIGMA_THETA_PAPER))
    assert np.median(out[False][0]) > 3 and np.median(out[False][1]) > 2
    assert out[True][0].max() < 0.05 and out[True][1].max() < 0.05


@pytest.mark.slow
def test_compensation_chunking_and_gaps(layout):
    """1-frame chunks (live) and 500-frame chunks (replay) agree far below the noise (0.02 σ); the
    first frames of the stream and of the track after a 1 s gap (no velocity yet) are not
    corrected (equal to the uncompensated poses, to the LM tolerance)."""
    sw = simulate_sweeps(layout, duration=4.0, seed=5, motion=spin_motion(20.0, 0.2))
    keep = (sw.t < 1.5) | (sw.t > 2.5)  # a 1 s gap: no good pose for longer than motion_window_s
    sw_gap = type(sw)(**{k: (getattr(sw, k)[keep] if isinstance(getattr(sw, k), np.ndarray) else getattr(sw, k))
                         for k in sw.__dataclass_fields__})
    a = solve(layout, sw_gap, chunk_frames=1, motion_compensation=True)
    b = solve(layout, sw_gap, chunk_frames=500, motion_compensation=True)
    off = solve(layout, sw_gap, chunk_frames=500)
    e_r, e_t = pose_errors(a["rotation"], a["translation"], b["rotation"], b["translation"])
    assert np.degrees(e_r).max() < 0.02 * (a["adop"] * SIGMA_THETA_PAPER).min()
    assert e_t.max() < 0.02 * (a["pdop"] * SIGMA_THETA_PAPER).min()
    after = np.flatnonzero(b["t"] > 2.5)[:3]
    for k in np.concatenate([[0, 1, 2], after]):  # fewer than 3 earlier poses in the window
        np.testing.assert_allclose(b["rotation"][k], off["rotation"][k], atol=1e-8)  # LM tolerance
    k = after[-1] + 1
    assert np.abs(b["rotation"][k] - off["rotation"][k]).max() > 1e-5  # corrected from here on
