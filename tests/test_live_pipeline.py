"""Live pose pipeline: sweep pairing, chunked PnP, statuses, LH2 conversion (layoutkit.live.pipeline).

Streams are generated here from the core measurement model (``lighthouse.sweep_angles`` +
``noise.sample_angle_noise``), independent of the protocol decoders and the simulator.
"""
from __future__ import annotations

import numpy as np
import pytest

from layoutkit.dop import pose_dop, pose_errors, rms
from layoutkit.geometry import rotvec_to_matrix
from layoutkit.lighthouse import in_field_of_view, lh2_sweep_angles, sweep_angles
from layoutkit.live.frames import SweepMeasurement
from layoutkit.lighthouse import lh2_to_lh1_angles
from layoutkit.live.pipeline import LiveConfig, PosePipeline, SweepPairer
from layoutkit.status import JUMP as STATUS_JUMP, OK as STATUS_OK, TOO_FEW_LIT as STATUS_TOO_FEW_LIT
from layoutkit.noise import sample_angle_noise
from layoutkit.units import RHO_PAPER, SIGMA_THETA_PAPER
from layoutkit.shapes import chen_target
from layoutkit.visibility import facing_mask

SLOT = 1.0 / 120.0


@pytest.fixture(scope="module")
def layout():
    return chen_target()[1]


def trajectory(F, t0=0.0):
    """A slow tumble ~2 m in front of the station (body top face towards it)."""
    t = t0 + np.arange(F) / 60.0
    rv = np.column_stack([np.pi + 0.3 * np.sin(0.2 * t), 0.2 * np.cos(0.1 * t), 0.005 * t])
    tr = np.column_stack([0.3 * np.sin(0.05 * t), 0.1 + 0 * t, 2 + 0.5 * np.sin(0.03 * t)])
    return t, rotvec_to_matrix(rv), tr


def make_sweeps(layout, F, rng, sigma=SIGMA_THETA_PAPER, rho=RHO_PAPER, station=0):
    """X sweep at t_k, Y sweep at t_k + 1/120 s; returns (sweeps, t, R, tr, lit)."""
    t, R, tr = trajectory(F)
    lit = facing_mask(layout.positions, layout.normals, R, tr)
    ang = sweep_angles(np.einsum("fij,nj->fni", R, layout.positions) + tr[:, None])
    if sigma > 0:
        ang = ang + sample_angle_noise((F, layout.n), sigma, rho, rng)
    ang = np.where(lit[..., None], ang, np.nan)
    sw = []
    for k in range(F):
        sw.append(SweepMeasurement(t[k], station, 0, ang[k, :, 0], 2 * k))
        sw.append(SweepMeasurement(t[k] + SLOT, station, 1, ang[k, :, 1], 2 * k + 1))
    return sw, t, R, tr, lit


def run(layout, sweeps, **cfg):
    pipe = PosePipeline(layout.positions, LiveConfig(n_sensors=layout.n, **cfg))
    chunks = pipe.feed(sweeps) + pipe.flush(end_of_stream=True)
    cat = {k: np.concatenate([getattr(c, k) for c in chunks]) for k in
           ("t", "rotation", "translation", "status", "adop", "pdop", "n_lit")}
    return pipe, chunks, cat


def test_noise_free_stream_recovers_exact_poses(layout):
    """Proof by construction: noise-free angles of known poses give those poses back (1e-9)."""
    sw, t, R, tr, lit = make_sweeps(layout, 300, None, sigma=0.0)
    pipe, _, c = run(layout, sw, chunk_frames=64)
    assert pipe.counters.frames == 300 and pipe.counters.good == 300
    np.testing.assert_allclose(c["t"], t)
    e_r, e_t = pose_errors(c["rotation"], c["translation"], R, tr)
    assert e_r.max() < 1e-8 and e_t.max() < 1e-9
    np.testing.assert_array_equal(c["n_lit"], lit.sum(1))


def test_noisy_stream_rms_error_matches_dop(layout):
    """Monte-Carlo vs prediction: RMS pose error over 3000 frames equals sqrt(mean ADOP²)·σθ
    (Chen eq. 24) within 6 %; the pipeline's ADOP equals pose_dop at the true pose (1 %)."""
    rng = np.random.default_rng(3)
    sw, t, R, tr, lit = make_sweeps(layout, 3000, rng)
    _, _, c = run(layout, sw, chunk_frames=512)
    assert np.all(c["status"] == STATUS_OK)
    e_r, e_t = pose_errors(c["rotation"], c["translation"], R, tr)
    pred_r = np.sqrt(np.mean(c["adop"] ** 2)) * SIGMA_THETA_PAPER  # deg
    pred_t = np.sqrt(np.mean(c["pdop"] ** 2)) * SIGMA_THETA_PAPER
    assert abs(np.degrees(rms(e_r)) / pred_r - 1) < 0.06
    assert abs(rms(e_t) / pred_t - 1) < 0.06
    d = pose_dop(layout.positions, R, tr, rho=RHO_PAPER, visible=lit)
    np.testing.assert_allclose(c["adop"], d.adop, rtol=0.01)


def test_chunk_size_does_not_change_poses(layout):
    """Chunking invariance: 1-frame chunks (live) and 1000-frame chunks (replay) agree to the LM
    stopping tolerance (1e-7, four orders below the noise-induced pose scatter)."""
    rng = np.random.default_rng(4)
    sw, *_ = make_sweeps(layout, 200, rng)
    _, _, a = run(layout, sw, chunk_frames=1)
    _, _, b = run(layout, sw, chunk_frames=1000)
    np.testing.assert_allclose(a["rotation"], b["rotation"], atol=1e-7)
    np.testing.assert_allclose(a["translation"], b["translation"], atol=1e-8)


def test_pairing_with_dropped_sweeps(layout):
    """Brute-force bookkeeping: drop random X and Y sweeps; exactly the frames with both sweeps
    come out, at the right times and poses, and every orphan sweep is counted."""
    rng = np.random.default_rng(5)
    F = 400
    sw, t, R, tr, _ = make_sweeps(layout, F, rng, sigma=0.0)
    keep = rng.random(2 * F) > 0.15
    kept = [s for s, k in zip(sw, keep) if k]
    both = keep[0::2] & keep[1::2]
    pipe, _, c = run(layout, kept, chunk_frames=50)
    np.testing.assert_allclose(c["t"], t[both])
    e_r, _ = pose_errors(c["rotation"], c["translation"], R[both], tr[both])
    assert e_r.max() < 1e-8
    orphans = int(np.sum(keep)) - 2 * int(both.sum())
    assert pipe.counters.unpaired_sweeps == orphans


def test_pairing_rejects_late_and_foreign_sweeps():
    """A Y sweep more than one rotor period after its X, or of another station, is not paired."""
    n = 4
    a = np.full(n, 1.5)
    p = SweepPairer(n)
    assert p.push(SweepMeasurement(0.0, 0, 0, a)) is None
    assert p.push(SweepMeasurement(0.0 + 0.02, 0, 1, a)) is None  # 20 ms > 16.7 ms
    assert p.unpaired == 2
    assert p.push(SweepMeasurement(1.0, 0, 0, a)) is None
    assert p.push(SweepMeasurement(1.0 + SLOT, 1, 1, a)) is None  # station 1 has no X pending
    fr = p.push(SweepMeasurement(1.0 + SLOT, 0, 1, a + 0.1))
    assert fr is not None and fr.t == 1.0 and fr.station == 0
    np.testing.assert_allclose(fr.angles, np.column_stack([a, a + 0.1]))
    assert p.unpaired == 3 and p.paired == 1
    assert p.push(SweepMeasurement(2.0, 0, 1, np.ones(3))) is None and p.wrong_size == 1


def test_too_few_lit_frames_get_status_and_no_record(layout):
    """Frames with 3 lit sensors are reported with STATUS_TOO_FEW_LIT and skipped in --json-lines."""
    rng = np.random.default_rng(6)
    sw, *_ = make_sweeps(layout, 20, rng)
    dark = []
    for s in sw:
        a = s.angles.copy()
        a[3:] = np.nan
        dark.append(SweepMeasurement(s.t, s.station, s.axis, a, s.seq))
    pipe, chunks, c = run(layout, sw[:20] + [SweepMeasurement(s.t + 10, 0, s.axis, s.angles) for s in dark[:10]])
    assert np.sum(c["status"] == STATUS_TOO_FEW_LIT) == 5
    assert pipe.counters.too_few_lit == 5 and pipe.counters.bad == 5
    recs = [r for ch in chunks for r in ch.records()]
    assert len(recs) == 10 and all(r["status"] == "ok" for r in recs)
    assert set(recs[0]) >= {"t", "rotvec", "translation", "n_lit", "status", "adop", "pdop", "residual_rms"}


def test_continuity_gate_flags_a_consistent_but_wrong_pose(layout):
    """Frames 100-102 carry the exact angles of a pose 40° away (a self-consistent wrong basin:
    zero residual): they are reported as STATUS_JUMP, every other frame stays good, and after
    ``reacquire_s`` without a good pose a new pose is accepted again."""
    sw, t, R, tr, _ = make_sweeps(layout, 300, None, sigma=0.0)
    Rw = rotvec_to_matrix([0.0, np.deg2rad(40), 0.0]) @ R[100]
    wrong = sweep_angles(np.einsum("ij,nj->ni", Rw, layout.positions) + tr[100])
    for k in (100, 101, 102):
        for ax in (0, 1):
            m = sw[2 * k + ax]
            sw[2 * k + ax] = SweepMeasurement(m.t, 0, ax, wrong[:, ax], m.seq)
    _, _, c = run(layout, sw, chunk_frames=64)
    jump = np.flatnonzero(c["status"] == STATUS_JUMP)
    np.testing.assert_array_equal(jump, [100, 101, 102])
    assert np.all(c["status"][np.setdiff1d(np.arange(300), jump)] == STATUS_OK)
    # a jump after a gap longer than reacquire_s is a re-acquisition, not a jump; if that pose is
    # the wrong one, the right track is taken back after reacquire_frames consistent poses
    late = [SweepMeasurement(m.t + (1.0 if i >= 200 else 0.0), 0, m.axis, m.angles, m.seq) for i, m in enumerate(sw)]
    _, _, c2 = run(layout, late, chunk_frames=1)
    st = c2["status"]
    assert np.all(st[100:103] == STATUS_OK)  # accepted after the gap (nothing to compare with)
    np.testing.assert_array_equal(st[103:107], STATUS_JUMP)  # 4 frames back on the right track
    assert np.all(st[107:] == STATUS_OK) and np.all(st[:100] == STATUS_OK)


def test_lh2_plane_angles_convert_to_lh1_angles():
    """Closed-form inverse: lh2_to_lh1(lh2_sweep_angles(p)) == sweep_angles(p) over the field of view."""
    rng = np.random.default_rng(7)
    p = np.column_stack([rng.uniform(-1.5, 1.5, 2000), rng.uniform(-1.5, 1.5, 2000), rng.uniform(0.5, 4, 2000)])
    p = p[in_field_of_view(p)]
    assert len(p) > 500
    np.testing.assert_allclose(lh2_to_lh1_angles(lh2_sweep_angles(p)), sweep_angles(p), atol=1e-12)


def test_bad_configuration_messages(layout):
    with pytest.raises(ValueError, match=r"^n_sensors: expected >= 1, got 0$"):
        LiveConfig(n_sensors=0)
    with pytest.raises(ValueError, match=r"^min_lit: expected >= 3, got 2$"):
        LiveConfig(n_sensors=12, min_lit=2)
    with pytest.raises(ValueError, match=r"^points_body: expected shape \(4, 3\), got \(12, 3\)$"):
        PosePipeline(layout.positions, LiveConfig(n_sensors=4))


def test_continuity_gate_equals_its_one_pose_at_a_time_definition():
    """The gate's batched verdicts (every good pose against the one before it, evaluated at once and
    used whenever that is the reference) give the same statuses and jump chain as the rule applied
    one pose at a time (written out here), on random tracks with jumps, chains of consistent jumps
    (re-acquisition), long gaps, time running backwards, non-ok frames, with and without a previous
    good pose or an open chain."""
    from layoutkit.geometry import attitude_error
    from layoutkit.live.continuity import continuity_gate
    from layoutkit import status as st

    cfg = LiveConfig(max_rate_deg_s=60.0, max_speed_m_s=1.0, reacquire_frames=3)
    rate, k_sig = np.deg2rad(cfg.max_rate_deg_s), cfg.gate_sigma * cfg.sigma_theta

    def reference(t, R, tr, status, adop, pdop, last, cand):
        def near(k, ref):
            dt = t[k] - ref[2]
            return bool(attitude_error(R[k], ref[0]) <= rate * dt + k_sig * np.deg2rad(adop[k])) and bool(
                np.linalg.norm(tr[k] - ref[1]) <= cfg.max_speed_m_s * dt + k_sig * pdop[k])
        status = status.copy()
        for k in np.flatnonzero(status == st.OK):
            gap = t[k] - last[2] if last is not None else 0.0
            if last is None or gap > cfg.reacquire_s or gap < 0 or near(k, last):
                last, cand = (R[k], tr[k], t[k]), None
                continue
            status[k] = st.JUMP
            cand = (R[k], tr[k], t[k], cand[3] + 1) if cand is not None and near(k, cand) else (R[k], tr[k], t[k], 1)
            if cand[3] >= cfg.reacquire_frames:
                status[k] = st.OK
                last, cand = (R[k], tr[k], t[k]), None
        return status, cand

    rng = np.random.default_rng(11)
    jumps = 0
    for trial in range(60):
        F = int(rng.integers(1, 40))
        dt = rng.choice([0.01, 0.01, 0.01, 0.7, -0.02], F, p=[0.5, 0.2, 0.2, 0.05, 0.05])
        t = 10.0 + np.cumsum(dt)
        rv = np.cumsum(rng.normal(0, 0.002, (F, 3)), 0)
        tr = np.cumsum(rng.normal(0, 0.002, (F, 3)), 0) + [0, 0, 2.0]
        flip = rng.random(F) < 0.25  # wrong-basin poses, sometimes in runs (a chain that re-acquires)
        rv[flip] += [0.0, 0.8, 0.0]
        tr[flip] += [0.0, 0.0, 0.3 * (trial % 2)]
        R = rotvec_to_matrix(rv)
        status = np.where(rng.random(F) < 0.15, st.TOO_FEW_LIT, st.OK)
        adop, pdop = rng.uniform(1, 3, F), rng.uniform(0.5, 2, F)
        last = None if trial % 3 == 0 else (rotvec_to_matrix(rng.normal(0, 0.3, 3)), np.array([0, 0, 2.0]), 9.99)
        cand = None if trial % 4 else (R[0], tr[0], t[0] - 0.01, int(rng.integers(1, 3)))
        got, gc = continuity_gate(t, R, tr, status, adop, pdop, last, cand, cfg)
        want, wc = reference(t, R, tr, status, adop, pdop, last, cand)
        assert np.array_equal(got, want), trial
        assert (gc is None) == (wc is None) and (gc is None or (gc[3] == wc[3] and gc[2] == wc[2])), trial
        jumps += int((want == st.JUMP).sum())
    assert jumps > 20  # the slow path ran
