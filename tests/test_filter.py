"""Tracking filter (layoutkit.filter, issue 12): forward-model Jacobians, the EKF's information
bookkeeping, tracking under dropout / hidden station / reflections / loss, NEES-NIS consistency.

Kinds of proof: finite differences (Jacobians), scipy (quaternions), closed form (the static
filter's covariance equals the summed Fisher information of its sweeps), Monte Carlo against the
filter's own covariance (NEES / NIS chi² bands), and the live pipeline's frame-by-frame PnP on the
same simulated sweeps (share of time with a pose).
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from layoutkit.filter import EkfConfig, ErrorStateEKF, PlainSweepModel, SweepTracker
from layoutkit.filter.consistency import chi2_band, nees, pose_error, run_sweeps
from layoutkit.filter.models import angle_gradient
from layoutkit.filter.so3 import quat_from_matrix, quat_from_rotvec, quat_mul, quat_to_matrix, quat_to_rotvec
from layoutkit.lighthouse import lh2_to_lh1_angles as lh2_planes_to_lh1
from layoutkit.geometry import rotvec_to_matrix
from layoutkit.layout import load_layout
from layoutkit.lighthouse import Station, lh2_sweep_angles, sweep_angles
from layoutkit.live.simulator import simulate_sweeps
from layoutkit.studies import filter_scenarios as wf

LAYOUT = "tests/data/chen_layout.json"


@pytest.fixture(scope="module")
def layout():
    return load_layout(LAYOUT)


def _station_b():
    return Station("B", rotvec_to_matrix([0.1, -0.5, 0.2]), np.array([1.1, 0.2, 0.3]))


@pytest.mark.parametrize("kind", ["lh1", "lh2"])
def test_forward_model_jacobian_matches_finite_differences(layout, kind):
    """Finite differences: the analytic (dphi, dt) Jacobian of the plain models, world perturbation,
    rotated/offset station, both code paths (generic and the LH1 hot path)."""
    st = Station("B", _station_b().rotation, _station_b().translation, kind=kind)
    R = rotvec_to_matrix([0.3, 2.0, -0.4])
    t = st.rotation @ np.array([0.05, -0.1, 2.0]) + st.translation
    m = PlainSweepModel()
    ang, J = m.angles_and_jacobian(layout.positions, R, t, st)
    J2 = m.jacobian(layout.positions, R, t, st)
    np.testing.assert_allclose(J, J2, atol=1e-12)
    np.testing.assert_allclose(ang, m(layout.positions, R, t, st), atol=1e-15)
    h = 1e-7
    num = np.zeros_like(J)
    for i in range(6):
        d = np.zeros(6)
        d[i] = h
        Rp, tp = rotvec_to_matrix(d[:3]) @ R, t + d[3:]
        Rm, tm = rotvec_to_matrix(-d[:3]) @ R, t - d[3:]
        num[..., i] = (m(layout.positions, Rp, tp, st) - m(layout.positions, Rm, tm, st)) / (2 * h)
    np.testing.assert_allclose(J, num, atol=1e-6, rtol=1e-5)


def test_lh2_gradient_and_plane_inversion():
    """Finite differences for the LH2 angle gradient; lh2_planes_to_lh1 inverts lh2_sweep_angles."""
    p = np.array([[0.3, -0.2, 2.0], [-0.5, 0.4, 1.5]])
    g = angle_gradient(p, "lh2")
    h = 1e-7
    for i in range(3):
        d = np.zeros(3)
        d[i] = h
        num = (lh2_sweep_angles(p + d) - lh2_sweep_angles(p - d)) / (2 * h)
        np.testing.assert_allclose(g[..., i], num, atol=1e-7)
    np.testing.assert_allclose(lh2_planes_to_lh1(lh2_sweep_angles(p)), sweep_angles(p), atol=1e-12)


def test_quaternion_helpers_match_scipy():
    """scipy Rotation as the reference for exp, product, matrix and log."""
    rng = np.random.default_rng(4)
    for _ in range(20):
        a, b = rng.normal(size=3), rng.normal(size=3) * 1e-3
        qa, qb = quat_from_rotvec(a), quat_from_rotvec(b)
        ref = Rotation.from_rotvec(b) * Rotation.from_rotvec(a)
        np.testing.assert_allclose(quat_to_matrix(quat_mul(qb, qa)), ref.as_matrix(), atol=1e-12)
        np.testing.assert_allclose(quat_to_rotvec(quat_mul(qb, qa)), ref.as_rotvec(), atol=1e-10)
    np.testing.assert_allclose(quat_to_matrix(quat_from_rotvec([1e-9, 0, 0])), np.eye(3), atol=1e-9)


def test_quaternion_orders_have_one_owner():
    """The filter's closed-form quat_to_matrix agrees with the rotations core's pair (both orders),
    and a libsurvive [w, x, y, z] quaternion means the same rotation as its [x, y, z, w] reordering
    (scipy as the reference)."""
    from layoutkit.rotations import matrix_to_quaternion, quaternion_to_matrix

    q = Rotation.random(50, random_state=7).as_quat()
    R = Rotation.from_quat(q).as_matrix()
    np.testing.assert_allclose(np.stack([quat_to_matrix(x) for x in q]), R, atol=1e-15)
    np.testing.assert_allclose(quaternion_to_matrix(q), R, atol=1e-15)
    np.testing.assert_allclose(quaternion_to_matrix(q[:, [3, 0, 1, 2]], scalar_first=True), R, atol=1e-15)
    back = matrix_to_quaternion(R)
    assert np.all(back[:, 3] >= 0)
    np.testing.assert_allclose(np.abs(np.sum(back * q, 1)), 1.0, atol=1e-12)  # same rotation, either sign
    np.testing.assert_allclose(matrix_to_quaternion(R, scalar_first=True), back[:, [3, 0, 1, 2]])
    np.testing.assert_allclose(quat_from_matrix(R[0]), back[0])


def test_static_covariance_equals_summed_fisher_information(layout):
    """Closed form: with no process noise and zero-velocity pseudo-measurements the pose covariance
    after N sweeps equals (P0^-1 + sum_k J_k^T R_k^-1 J_k)^-1 of the sweeps' angle Jacobians with
    the Chen eq. 19 correlation (information adds up; this is what makes the static precision the
    frame bound / sqrt(frames))."""
    from layoutkit.noise import angle_correlation

    st = [Station()]
    R = rotvec_to_matrix([2.6, 0.3, -0.2])
    t = np.array([0.1, -0.05, 2.0])
    cfg = EkfConfig(motion="fixed", psd_rot=0.0, psd_pos=0.0, hit_timing=False, rho=0.6, init_sigma_rate=0.05,
                    init_sigma_speed=0.05)
    ekf = ErrorStateEKF(layout.positions, st, cfg)
    P0 = np.eye(6) * 1e-6
    ekf.initialize(0.0, R, t, P0)
    ang = PlainSweepModel()(layout.positions, R, t, st[0])
    lit = np.flatnonzero(np.all(np.isfinite(ang), -1) & (ang[:, 0] > 0.6) & (ang[:, 0] < 2.5))[:6]
    info = np.linalg.inv(P0)
    for k in range(40):
        ekf.predict((k + 1) / 120.0)
        ekf.zero_velocity_update()
        ax = k % 2
        u = ekf.update_sweep(0, ax, lit, ang[lit, ax])  # noise-free angles: the state stays put
        assert u.used == lit.size and not u.sweep_rejected
        J = PlainSweepModel().jacobian(layout.positions[lit], R, t, st[0])[:, ax, :]
        Rm = angle_correlation(lit.size, cfg.rho)[0::2, 0::2] * cfg.sigma_theta ** 2
        info += J.T @ np.linalg.solve(Rm, J)
    np.testing.assert_allclose(ekf.pose_covariance(), np.linalg.inv(info), rtol=2e-3, atol=1e-16)
    np.testing.assert_allclose(ekf.rotation, R, atol=1e-9)


def test_filter_keeps_a_pose_under_dropout_where_pnp_cannot(layout):
    """Against the live pipeline on the same sweeps: tumble with 60 % of the lit hits dropped —
    the filter is ok >= 99 % of the sweeps, frame-by-frame PnP < 50 % of the frames; the filter's
    RMS error is within 2x its own predicted 1-sigma (Monte Carlo vs covariance)."""
    r = wf.dropout_scenario(layout, seed=5, duration=12.0, dropout=0.6)
    f, p = r["filter"], r["pnp"]
    assert f["share_with_pose"] >= 0.99
    assert p["share_with_pose"] < 0.5
    assert f["rms_rot_deg"] < 2 * f["predicted_rot_deg"]
    assert f["rms_pos_m"] < 2 * f["predicted_pos_m"]


def test_hidden_station_and_reflections(layout):
    """Two stations, one hidden 2 s, one sensor reflecting (1 % of its hits off by 5-50 mrad, here
    raised to 5 % to have enough of them in a short run): every reflection is rejected, no update
    moves the pose by more than 3 prior sigma per axis, the pose stays ok throughout."""
    r = wf.hidden_station_scenario(layout, seed=3, duration=12.0, hide_at=4.0, reflect_share=0.05)
    assert r["outliers_injected"] >= 5
    assert r["outliers_rejected"] == r["outliers_injected"]
    assert r["good_angles_rejected"] <= 3
    assert r["corrections_over_3_prior_sigma"] == 0
    assert r["share_with_pose"] > 0.99
    assert r["sigma_pos_m_max_hidden"] > r["sigma_pos_m_before_hidden"]  # one station less: less certain


@pytest.mark.slow
def test_nees_nis_consistency_small(layout):
    """Monte Carlo vs the filter's covariance: over 8 tumbles the time-averaged ANEES (6 dof) and the
    NIS per dof are inside generous bands (the full 50-run check is benchmarks/bench_filter.py)."""
    r = wf.consistency_scenario(layout, runs=8, duration=6.0)
    lo, hi = chi2_band(6 * 8 * 5, 0.999)  # ~5 effectively independent steps per run
    assert lo / 40 <= r["anees_mean"] <= hi / 40
    assert 0.9 <= r["nis_per_dof_mean"] <= 1.1


def test_lost_and_reinitialised_after_a_teleport(layout):
    """The innovations detect a state that is wrong (the body 'teleports': the second half of the
    sweeps comes from another run's pose): the filter declares itself lost, re-initialises from PnP
    and ends within 5 sigma of the new truth."""
    a = simulate_sweeps(layout, duration=4.0, seed=11)
    b = simulate_sweeps(layout, duration=4.0, seed=12)
    half = len(a.t) // 2
    ang = np.concatenate([wf.measured(a)[:half], wf.measured(b)[half:]])
    rv = np.concatenate([a.rotvec[:half], b.rotvec[half:]])
    tr_true = np.concatenate([a.translation[:half], b.translation[half:]])
    trk = SweepTracker(layout.positions, a.stations, EkfConfig(**wf.TUMBLE_CONFIG))
    run = run_sweeps(trk, a.t, a.station, a.axis, ang)
    assert run.counters["losts"] >= 1 and run.counters["inits"] >= 2
    e = pose_error(run.rotvec[-1:], run.translation[-1:], rv[-1:], tr_true[-1:])
    assert nees(e, run.pose_cov[-1:])[0] < 25 * 6
    assert run.ok[-1]


def test_lh2_station_and_constant_acceleration(layout):
    """An LH2 station (slanted planes, 50 Hz) and the constant-acceleration model on a 20 deg/s spin:
    RMS error within 3x the filter's own 1-sigma after warm-up (Monte Carlo vs covariance)."""
    from layoutkit.live.simulator import spin_motion

    for stations, motion, ca in (([Station(kind="lh2", rotor_rpm=3000.0)], "tumble", False),
                                 ([Station()], spin_motion(20.0, 0.05), True)):
        sw = simulate_sweeps(layout, duration=3.0, seed=7, stations=stations, motion=motion)
        cfg = EkfConfig(motion="fixed", hit_timing=False, constant_acceleration=ca, psd_rot=1e-4, psd_pos=1e-6,
                        psd_jerk_rot=1e-3, psd_jerk_pos=1e-4, init_sigma_rate=0.5, init_sigma_speed=0.05)
        run, _ = wf.track(layout, sw, config=cfg)
        w = run.ok & (sw.t > 1.0)
        assert run.ok[sw.t > 1.0].mean() > 0.99
        e = pose_error(run.rotvec[w], run.translation[w], sw.rotvec[w], sw.translation[w])
        s = np.sqrt(np.diagonal(run.pose_cov[w], axis1=1, axis2=2))
        assert np.sqrt(np.mean(e ** 2, 0)).max() / np.sqrt(np.mean(s ** 2, 0)).max() < 3.0


def test_config_validation():
    """Bad tuning is a ValueError naming the field."""
    with pytest.raises(ValueError, match="psd_rot"):
        EkfConfig(psd_rot=-1.0)
    with pytest.raises(ValueError, match="rho"):
        EkfConfig(rho=1.0)
    with pytest.raises(ValueError, match="model"):
        EkfConfig(model="nope")
    with pytest.raises(ValueError, match="time ran backwards"):
        ekf = ErrorStateEKF(np.zeros((4, 3)), [Station()])
        ekf.initialize(1.0, np.eye(3), [0, 0, 2.0], np.eye(6))
        ekf.predict(0.5)


def _calibrated_station(kind="lh1"):
    from layoutkit.lighthouse import Calibration

    p = np.zeros((2, 7))
    p[:, 0] = [0.004, -0.003]   # phase
    p[:, 1] = [0.003, 0.002]    # tilt
    p[:, 2] = [0.002, -0.001]   # curve
    p[:, 3] = [0.4, 1.1]        # gib phase
    p[:, 4] = [0.002, 0.0015]   # gib magnitude
    return Station(kind=kind, calibration=Calibration(p, kind))


def test_calibrated_station_model_jacobian_matches_finite_differences(layout):
    """Finite differences through the calibrated forward model (layoutkit.lighthouse.measure)."""
    from layoutkit.filter import FORWARD_MODELS

    st = _calibrated_station()
    m = FORWARD_MODELS["station"]
    R = rotvec_to_matrix([2.7, 0.2, -0.3])
    t = np.array([0.05, -0.1, 2.0])
    J = m.jacobian(layout.positions, R, t, st)
    a1, r1 = m.sweep_rows(layout.positions, R, t, st, 1)
    np.testing.assert_allclose(r1, J[:, 1, :], atol=1e-14)
    h = 1e-7
    for i in range(6):
        d = np.zeros(6)
        d[i] = h
        num = (m(layout.positions, rotvec_to_matrix(d[:3]) @ R, t + d[3:], st)
               - m(layout.positions, rotvec_to_matrix(-d[:3]) @ R, t - d[3:], st)) / (2 * h)
        np.testing.assert_allclose(J[..., i], num, atol=1e-6)
    assert np.abs(m(layout.positions, R, t, st) - FORWARD_MODELS["plain"](layout.positions, R, t, st)).max() > 1e-3


def test_filter_tracks_through_a_calibrated_station(layout):
    """Angles distorted by a station calibration (phase, tilt, curve, gib): through the station's own
    forward model the filter's RMS error stays within 2x its 1-sigma; the ideal model ('plain') is
    biased far beyond its covariance on the same data (the reference: the true poses)."""
    from layoutkit.lighthouse import measure

    st = _calibrated_station()
    sw = simulate_sweeps(layout, duration=4.0, seed=21)
    K = len(sw.t)
    Rt = rotvec_to_matrix(sw.rotvec)
    ps = np.einsum("kij,nj->kni", Rt, layout.positions) + sw.translation[:, None, :]
    cal = measure(ps, st.calibration)[np.arange(K), :, sw.axis]  # (K, n)
    meas = wf.measured(sw)
    ang = np.where(np.isfinite(meas), cal + (meas - sw.angles_true), np.nan)
    ratios = {}
    for name in ("station", "plain"):
        trk = SweepTracker(layout.positions, [st], EkfConfig(**{**wf.TUMBLE_CONFIG, "model": name}))
        run = run_sweeps(trk, sw.t, sw.station, sw.axis, ang)
        w = run.has_output & (sw.t > 1.0)
        e = pose_error(run.rotvec[w], run.translation[w], sw.rotvec[w], sw.translation[w])
        s = np.sqrt(np.diagonal(run.pose_cov[w], axis1=1, axis2=2))
        ratios[name] = (np.sqrt(np.mean(e ** 2, 0)) / np.sqrt(np.mean(s ** 2, 0))).max()
        if name == "station":
            assert run.ok[w].mean() > 0.99
    assert ratios["station"] < 2.0
    assert ratios["plain"] > 5.0


def test_cli_model_choices_are_the_registry():
    """The --filter-model choices are the forward-model registry's names."""
    import click

    from layoutkit.cli.live import replay_cmd
    from layoutkit.filter import FORWARD_MODELS

    opt = next(p for p in replay_cmd.params if p.name == "filter_model")
    assert isinstance(opt.type, click.Choice) and sorted(opt.type.choices) == sorted(FORWARD_MODELS)


def test_replay_filter_json_lines_through_the_cli(tmp_path):
    """End to end through the CLI on a fake-fpga capture with 60 % dropout: one JSON object per
    sweep with the interface fields (3 values each), mostly "ok"; the poses agree with TRUTH.csv
    within the reported covariance (Monte Carlo vs covariance) and the summary compares with the
    frame-by-frame DOP prediction."""
    import json

    from click.testing import CliRunner

    from layoutkit.cli import main
    from layoutkit.io.poses import read_reference
    from layoutkit.live.reference import PoseTrack

    cap, truth = tmp_path / "cap.bin", tmp_path / "TRUTH.csv"
    r = CliRunner().invoke(main, ["fake-fpga", "--layout", LAYOUT, "--out", str(cap), "--truth", str(truth),
                                  "--duration", "6", "--dropout", "0.6", "--seed", "2"])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, ["replay", str(cap), "--layout", LAYOUT, "--truth", str(truth), "--filter", "ekf",
                                  "--no-filter-hit-timing", "--filter-motion", "fixed", "--filter-psd-rot", "1e-8", "--filter-psd-pos", "3e-9",
                                  "--json-lines", "--json", "--report", str(tmp_path / "new" / "report")])
    assert r.exit_code == 0, r.output
    recs = [json.loads(ln) for ln in r.stdout.splitlines() if ln.startswith('{"t"')]
    assert len(recs) >= 0.99 * 6 * 120
    # --report into a folder that does not exist yet: the filter's pose table is written there too
    # (it was opened before the report folder was made), one row per JSON line
    from layoutkit.io.poses import read_poses

    assert len(read_poses(tmp_path / "new" / "report" / "filter_poses.csv").t) == len(recs)
    for k in ("t", "status", "rotvec", "translation", "cov_pos_m", "cov_rot_deg"):
        assert k in recs[0]
    assert all(len(x["cov_pos_m"]) == 3 and len(x["cov_rot_deg"]) == 3 for x in recs)
    ok = [x for x in recs if x["status"] == "ok"]
    # the start's velocity prior admits a moving body (3 m/s): the first sweeps fix the velocity
    after = [x for x in recs if x["t"] > recs[0]["t"] + 0.5]
    assert sum(x["status"] == "ok" for x in after) / len(after) > 0.98
    tr = PoseTrack.from_reference(read_reference(truth))
    t = np.array([x["t"] for x in ok])
    _, p_true, v = tr.at(t)
    p = np.array([x["translation"] for x in ok])
    s = np.array([x["cov_pos_m"] for x in ok])
    z = np.abs(p[v] - p_true[v]) / s[v]
    assert np.sqrt(np.mean(z ** 2)) < 2.0
    summary = json.loads(r.stderr[r.stderr.index("{"):])  # with --json-lines the summary goes to stderr
    f = summary["filter"]["truth"]
    assert f["frame_dop_predicted_rot_deg"] is not None
    assert f["rms_rot_deg"] < f["frame_by_frame_rms_rot_deg"]


def test_solve_filter_on_a_frame_table(tmp_path):
    """layoutkit solve --filter ekf: a frame table of a tumble (per-frame time stamps) gives a pose
    table of filtered poses, more accurate than frame-by-frame PnP against the table's truth; on
    independent random poses (layoutkit simulate) the filter honestly reports almost nothing as ok."""
    from click.testing import CliRunner

    from layoutkit.cli import main
    from layoutkit.io.poses import read_poses
    from layoutkit.workflows.frames import Frames, write_frames

    lay = load_layout(LAYOUT)
    sw = simulate_sweeps(lay, duration=5.0, seed=4)
    a = sw.measured_angles()
    fr = tmp_path / "frames.csv"
    write_frames(Frames(sw.t[0::2], np.stack([a[0::2], a[1::2]], -1), lay.ids, rotvec_to_matrix(sw.rotvec[0::2]),
                        sw.translation[0::2]), fr)
    out = tmp_path / "poses.csv"
    r = CliRunner().invoke(main, ["solve", str(fr), "--layout", LAYOUT, "--filter", "ekf", "--filter-motion", "fixed", "--filter-psd-rot", "1e-8",
                                  "--filter-psd-pos", "3e-9", "--out", str(out), "--json"])
    assert r.exit_code == 0, r.output
    import json

    s = json.loads(r.stdout)
    assert s["filter"]["ok"] >= 0.98 * s["frames"]
    assert s["filter"]["filter_rms_rot_deg"] < s["rms_rot_deg"]
    tab = read_poses(out)
    assert len(tab) == s["frames"] and "cov_pos_m_x" in tab.extras
    rnd = tmp_path / "random.csv"
    assert CliRunner().invoke(main, ["simulate", "--layout", LAYOUT, "--frames", "30", "--out", str(rnd)]).exit_code == 0
    r = CliRunner().invoke(main, ["solve", str(rnd), "--layout", LAYOUT, "--filter", "ekf", "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["filter"]["ok"] <= 3


def test_real_hmd_at_rest_filtered_jitter_below_frame_by_frame(libsurvive_dir, tmp_path):
    """A real recording (libsurvive sample, HMD at rest, two LH1 stations): per station, the
    filtered pose jitters less than the frame-by-frame PnP poses of the same frames (Chen eq. 23
    precision after a 1 s warm-up), and the filter keeps a pose on nearly every frame."""
    from layoutkit.workflows.importers import import_libsurvive

    import_libsurvive(libsurvive_dir / "lh1_test_cal_first4s.rec.gz", tmp_path)
    r = wf.real_static_jitter(tmp_path / "HMD" / "frames.csv", tmp_path / "HMD" / "layout.json",
                              tmp_path / "stations.json")
    assert len(r["stations"]) == 2
    for row in r["stations"].values():
        assert row["filter_ok"] >= 0.9 * row["frames"]
        assert row["filter_jitter_rot_deg"] < row["pnp_jitter_rot_deg"]
        assert row["filter_jitter_pos_mm"] < row["pnp_jitter_pos_mm"]


def test_json_line_is_json_dumps_of_the_record():
    """filter.jsonline.json_line (the per-sweep JSON line of replay / live --filter ekf) is byte for byte
    json.dumps(record()) — on random states over many magnitudes (exponent spellings 1e-05 / 1e+16,
    -0.0), numpy float times, and the values json spells itself: NaN / infinite floats, a negative
    variance, an infinite NIS (null), odd types (numpy ints are refused by both, bools written as
    true / false), non-ASCII event text."""
    import json

    from layoutkit.filter.jsonline import json_line
    from layoutkit.filter.tracker import FilterOutput

    rng = np.random.default_rng(7)

    def out(**kw):
        q = rng.standard_normal(4)
        P = rng.standard_normal((15, 15))
        P = P @ P.T * 10.0 ** rng.uniform(-20, 20)
        base = dict(t=float(rng.uniform(0, 1e4)), station=int(rng.integers(0, 3)), axis=int(rng.integers(0, 2)),
                    status=str(rng.choice(["ok", "uncertain", "lost"])), quaternion=q / np.linalg.norm(q),
                    translation=rng.standard_normal(3) * 10.0 ** rng.uniform(-8, 17), state_cov=P,
                    used=int(rng.integers(0, 30)), rejected=int(rng.integers(0, 3)), nis=float(rng.exponential(3.0)),
                    dof=int(rng.integers(0, 30)), static=bool(rng.integers(0, 2)), event=str(rng.choice(["", "init"])))
        base.update(kw)
        return FilterOutput(**base)

    cases = [out() for _ in range(500)]
    Pn = np.eye(15)
    Pn[7, 7] = np.nan
    Pneg = np.eye(15)
    Pneg[1, 1] = -1e-9
    Pinf = np.eye(15)
    Pinf[8, 8] = np.inf
    cases += [out(t=np.float64(3.5)), out(t=1e-5), out(t=1e16), out(translation=np.array([-0.0, 0.0, 1e-300])),
              out(state_cov=Pn), out(state_cov=Pneg), out(state_cov=Pinf), out(state_cov=np.zeros((15, 15))),
              out(nis=np.inf), out(nis=np.nan), out(nis=np.float64(2.25)), out(translation=np.array([np.nan, 1.0, 2.0])),
              out(event="ré-init \"x\"\n"), out(used=True),
              out(quaternion=np.array([0.0, 0.0, 0.0, 1.0])), out(t=7)]
    for o in cases:
        with np.errstate(invalid="ignore"):  # record()'s np.sqrt of the negative variance
            assert json_line(o) == json.dumps(o.record())
    for bad in (out(station=np.int64(1)), out(static=np.bool_(True))):
        with pytest.raises(TypeError), np.errstate(invalid="ignore"):
            json.dumps(bad.record())
        with pytest.raises(TypeError):
            json_line(bad)
