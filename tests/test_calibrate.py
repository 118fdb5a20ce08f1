"""layoutkit calibrate (bundle adjustment): Monte-Carlo coverage of the reported standard deviations
against the simulation truth (proof by simulation with known parameters), agreement of the Schur LM
with scipy's least_squares on the sparse problem, unobservable parameters reported as such, and the
CLI end to end (files written, residuals down, joint solve through the adjusted stations)."""
import csv
import json

import numpy as np
import pytest
from click.testing import CliRunner

from _calib_sim import capture, z_scores
from layoutkit.calibrate import bundle_adjust
from layoutkit.cli import main
from layoutkit.io.stations import write_stations
from layoutkit.joint import solve_joint
from layoutkit.layout import Layout


def _adjust(cap, **kw):
    ini = solve_joint(cap["P"], cap["angles"], stations=cap["start"])
    return bundle_adjust(cap["P"], cap["angles"], cap["start"], sigma=cap["sigma"],
                         initial_poses=(ini.rotation, ini.translation), **kw)


@pytest.mark.slow
def test_recovery_within_three_sigma_small_monte_carlo():
    """3 simulated captures (LH1 and LH2, with sensor offsets of 0.5 mm RMS): >= 95 % of the observable
    parameters within 3 reported sigma of the truth, and the residuals fall to the noise (|r| median
    about 0.67 sigma). The 100-trial version is benchmarks/bench_calibrate.py --recovery."""
    ss = np.random.SeedSequence(11)
    z = []
    for k, child in enumerate(ss.spawn(3)):
        rng = np.random.default_rng(child)
        kind = "lh1" if k % 2 == 0 else "lh2"
        cap = capture(rng, kind=kind, n=16, samples=60, offset_rms=0.5e-3)
        res = _adjust(cap, sensor_offsets=True)
        assert res.success, res.message
        assert np.nanmedian(np.abs(res.residual_after)) < 0.8 * cap["sigma"]
        assert np.nanmedian(np.abs(res.residual_before)) > 10 * cap["sigma"]
        z.append(z_scores(res, cap, kind))
    z = np.concatenate(z)
    assert z.size > 100
    assert np.mean(np.abs(z) < 3) >= 0.95, np.sort(np.abs(z))[-10:]


@pytest.mark.slow
def test_schur_lm_agrees_with_least_squares_on_the_sparse_problem(rng):
    """Same cost, two optimisers: the Schur-complement LM and scipy.optimize.least_squares (trf, exact
    trust-region steps on the analytic Jacobian) find the same calibration to a quarter of its sigma."""
    cap = capture(rng, kind="lh1", n=8, samples=12)
    a = _adjust(cap)
    b = _adjust(cap, solver="least_squares", max_nfev=300)
    assert abs(a.extra["cost"] - b.extra["cost"]) <= 1e-4 * b.extra["cost"]
    for pa, pb in zip(a.parameters, b.parameters):
        assert pa.name == pb.name
        if pa.status == "ok" and "axis" in pa.name and pb.std:
            assert abs(pa.value - pb.value) < 0.25 * pa.std, (pa, pb)


@pytest.mark.parametrize("kind", ["lh1", "lh2"])
def test_analytic_jacobian_equals_finite_differences_within_the_sparsity(rng, kind):
    """The bundle-adjustment Jacobian (poses, station poses, calibration columns, sensor offsets,
    reference rows) == central differences to 1e-6 relative, and no difference falls outside the
    jac_sparsity pattern handed to least_squares."""
    from layoutkit.calibrate import _Problem, jacobian_sparsity, station_to_ba

    cap = capture(rng, kind=kind, n=8, samples=6, offset_rms=0.5e-3)
    ini = solve_joint(cap["P"], cap["angles"], stations=cap["start"])
    ok = np.isfinite(ini.translation).all(1)
    R0, t0 = np.where(ok[:, None, None], ini.rotation, np.eye(3)), np.where(ok[:, None], ini.translation, 0.0)
    RS0 = np.stack([s.rotation for s in cap["start"]])
    TS0 = np.stack([s.translation for s in cap["start"]])
    cal0 = np.stack([station_to_ba(s.calibration.params, kind) for s in cap["truth"]])
    free = [(s, ax, j) for s in range(2) for ax in range(2) for j in range(5 if kind == "lh1" else 7)]
    pb = _Problem(cap["P"], np.where(ok[:, None, None, None], cap["angles"], np.nan), cap["start"], sigma=2e-5,
                  free_cal=free, free_station=[1], offsets=True, offset_prior=1e-3, calibration_prior=np.full(7, 0.1),
                  cal_start=cal0, reference=(R0, t0, ok), reference_sigma=(1e-3, 1e-3))
    base = (R0, t0, RS0, TS0)
    x = rng.normal(0, 0.01, pb.N)
    for (s, ax, j), c in pb.cal_col.items():
        x[c] = cal0[s, ax, j] + rng.normal(0, 0.003)
    J = pb.jacobian(x, base).toarray()
    h = 1e-7
    fd = np.stack([(pb.residual(x + h * e, base) - pb.residual(x - h * e, base)) / (2 * h) for e in np.eye(pb.N)], 1)
    scale = np.abs(fd).max()
    np.testing.assert_allclose(J, fd, rtol=1e-6, atol=1e-6 * scale)
    assert np.abs(fd[jacobian_sparsity(pb).toarray() == 0]).max() <= 1e-9 * scale


def test_unobservable_parameters_are_reported_not_fitted(rng):
    """LH2: the common phase is the station's yaw, and curve/ogee are below the noise at these angles:
    they come back 'unobservable', without a standard deviation, at their starting values."""
    cap = capture(rng, kind="lh2", n=16, samples=60)
    res = _adjust(cap)
    by = {p.name: p for p in res.parameters}
    for nm in ("station 0 axis 0 phase_common", "station 1 axis 0 phase_common", "station 0 axis 0 curve"):
        assert by[nm].status == "unobservable" and by[nm].std is None and by[nm].value == by[nm].start
    assert by["station 1 axis 1 phase_diff"].status == "ok"
    assert by["station 0 axis 0 tilt"].status == "ok"


@pytest.mark.slow
def test_layout_consider_sd_matches_monte_carlo_scatter():
    """Monte-Carlo vs predicted covariance: sensor offsets of 0.3 mm per coordinate that are NOT adjusted;
    the reported sds (noise + the layout consider term, layout_sigma = 0.3 mm) match the scatter of
    the calibration estimates about the truth (RMS z-score ~1, >= 95 % within 3 sigma) — without the
    consider term the same estimates are 1.5x+ outside their noise-only sds."""
    rms_z = {}
    for lsig in (0.3e-3, 0.0):
        z = []
        for child in np.random.SeedSequence(5).spawn(4):
            cap = capture(np.random.default_rng(child), kind="lh1", n=16, samples=60, offset_rms=0.3e-3 * np.sqrt(3))
            z.append(z_scores(_adjust(cap, layout_sigma=lsig), cap, "lh1"))
        z = np.concatenate(z)
        assert z.size > 60
        rms_z[lsig] = float(np.sqrt(np.mean(z * z)))
        if lsig:
            assert np.mean(np.abs(z) < 3) >= 0.95
    assert 0.7 < rms_z[0.3e-3] < 1.3, rms_z
    assert rms_z[0.0] > 1.4, rms_z


def _static_capture(rng, K=60):
    """One body pose seen K times (a body at rest, like the real HMD sample), 32 sensors with 0.5 mm
    unknown offsets; the start ("factory") calibration is the truth."""
    from layoutkit.lighthouse import Station
    from layoutkit.simulate import simulate_station_angles

    cap = capture(rng, kind="lh1", n=32, samples=1, offset_rms=0.5e-3)
    R, t = np.repeat(cap["R"], K, 0), np.repeat(cap["t"], K, 0)
    a = simulate_station_angles(cap["P"] + cap["offsets"], R, t, cap["truth"], sigma=cap["sigma"], rho=0.0, rng=rng)
    a[np.isnan(np.repeat(cap["angles"], K, 0))] = np.nan
    start = [Station(id=s.id, rotation=s0.rotation, translation=s0.translation, kind=s.kind, calibration=s.calibration)
             for s, s0 in zip(cap["truth"], cap["start"])]
    return cap, a, start


@pytest.mark.slow
def test_static_capture_calibration_is_held_not_fitted(rng):
    """One static pose cannot separate tilt, curve and gib from the station pose and sensor offsets
    (the real HMD sample's situation): every calibration parameter comes back unobservable or
    weakly_observable, without an sd, at its factory value — never as a fitted number."""
    cap, a, start = _static_capture(rng)
    ini = solve_joint(cap["P"], a, stations=start)
    res = bundle_adjust(cap["P"], a, start, sigma=cap["sigma"], initial_poses=(ini.rotation, ini.translation))
    assert res.success, res.message
    cal = [p for p in res.parameters if "axis" in p.name]
    assert cal and all(p.status in ("unobservable", "weakly_observable") for p in cal), \
        [(p.name, p.status) for p in cal if p.status not in ("unobservable", "weakly_observable")]
    assert all(p.std is None and p.value == pytest.approx(p.start, abs=1e-12) for p in cal if "gib_" not in p.name)
    assert any(p.status == "weakly_observable" for p in cal)
    from layoutkit.calibrate import to_ba

    for h, s in zip(res.stations, start):  # the same model (gib as cos/sin: sign/phase representation free)
        np.testing.assert_allclose(to_ba(h.calibration.params), to_ba(s.calibration.params), atol=1e-12)


@pytest.mark.slow
def test_parameter_far_from_its_factory_value_is_suspect(rng):
    """A moving capture whose factory calibration has station 0's axis-0 phase 0.02 rad off (20+ sd):
    the fit recovers the truth within 3 sd and flags exactly that kind of parameter 'suspect'; with
    the true factory values nothing is suspect."""
    from layoutkit.lighthouse import Calibration, Station

    cap = capture(rng, kind="lh1", n=16, samples=60, offset_rms=0.5e-3)
    ini = solve_joint(cap["P"], cap["angles"], stations=cap["start"])
    for shift in (0.0, 0.02):
        st = []
        for s, tr in zip(cap["start"], cap["truth"]):
            p = tr.calibration.params.copy()
            if s.id == "0":
                p[0, 0] += shift
            st.append(Station(id=s.id, rotation=s.rotation, translation=s.translation, kind=s.kind,
                              calibration=Calibration(p, "lh1", tr.calibration.gib_argument)))
        res = bundle_adjust(cap["P"], cap["angles"], st, sigma=cap["sigma"],
                            initial_poses=(ini.rotation, ini.translation), sensor_offsets=True)
        by = {p.name: p for p in res.parameters}
        suspect = [p.name for p in res.parameters if p.status == "suspect"]
        ph = by["station 0 axis 0 phase"]
        if shift:
            assert "station 0 axis 0 phase" in suspect, suspect
            assert abs(ph.value - cap["truth"][0].calibration.params[0, 0]) < 3 * ph.std
        else:
            assert suspect == [], suspect


def _write_frames(path, cap, ids):
    """One row per station and sample (station 1 8 ms after station 0), empty cells where not seen."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "station"] + [f"th_{ax}_{i}" for i in ids for ax in "xy"])
        for k in range(cap["angles"].shape[0]):
            for s in range(2):
                a = cap["angles"][k, s].ravel()
                w.writerow([repr(0.1 * k + 0.008 * s), str(s)] + ["" if not np.isfinite(x) else repr(float(x)) for x in a])


@pytest.mark.slow
def test_cli_calibrate_then_joint_solve(tmp_path, rng):
    """`layoutkit calibrate FRAMES --layout L --stations S --out DIR` writes stations.json, layout.json,
    report.json; residuals fall from the uncalibrated level to the noise; `layoutkit solve --stations
    DIR/stations.json --solve joint` then gives `joint` poses within a few sigma-mm of the truth."""
    cap = capture(rng, kind="lh1", n=16, samples=80)
    lay = Layout(cap["P"], cap["N"], tuple(f"s{i}" for i in range(16)))
    (tmp_path / "layout.json").write_text(json.dumps(lay.to_dict()))
    write_stations(tmp_path / "stations.json", cap["start"])
    _write_frames(tmp_path / "frames.csv", cap, lay.ids)
    out = tmp_path / "cal"
    # the simulated layout is exact: say so (10 um), else the default 1 mm layout uncertainty holds
    # the station-1 tilts as weakly observable (confounded with sensor offsets of that size)
    r = CliRunner().invoke(main, ["calibrate", str(tmp_path / "frames.csv"), "--layout", str(tmp_path / "layout.json"),
                                  "--stations", str(tmp_path / "stations.json"), "--out", str(out),
                                  "--sigma-arcsec", str(cap["sigma"] / 4.84813681109536e-06), "--json",
                                  "--offset-prior-mm", "0.01"])
    assert r.exit_code == 0, r.output
    rep = json.loads(r.stdout)
    for f in ("stations.json", "layout.json", "report.json", "residuals.png"):
        assert (out / f).exists()
    med = rep["median_sample_residual_rms_rad"]
    assert med["start"] > 20 * med["after"] and med["after"] < 1.5 * cap["sigma"]
    assert rep["residuals_after"]["per_station"]["1"]["rms_rad"] < 1.5 * cap["sigma"]
    assert all(set(p) >= {"name", "value", "std", "status"} for p in rep["parameters"])
    r = CliRunner().invoke(main, ["solve", str(tmp_path / "frames.csv"), "--layout", str(tmp_path / "layout.json"),
                                  "--stations", str(out / "stations.json"), "--solve", "joint", "--json",
                                  "--out", str(tmp_path / "poses.csv")])
    assert r.exit_code == 0, r.output
    summ = json.loads(r.stdout)
    assert summ["mode"] == "joint" and summ["poses"] == 80
    from layoutkit.io.poses import read_poses

    tab = read_poses(tmp_path / "poses.csv")
    assert np.all(tab.station == -1)
    assert "joint" in (tmp_path / "poses.csv").read_text().splitlines()[1]
    ok = tab.status == 0
    err = np.linalg.norm(tab.translation[ok] - cap["t"][ok], axis=1)
    raw = solve_joint(cap["P"], cap["angles"], stations=cap["start"])
    err_raw = np.linalg.norm(raw.translation - cap["t"], axis=1)
    # the world frame is held by station 0's pose, its phases known to ~2e-4 rad: ~1 mm at 3 m
    assert ok.mean() > 0.95 and np.median(err) < 3e-3 and np.median(err) < np.nanmedian(err_raw) / 5


def test_cli_calibrate_bad_input_is_one_error_line(tmp_path):
    """A missing stations file: exit 2 and one `error:` line naming it."""
    lay = tmp_path / "l.json"
    lay.write_text(json.dumps({"units": "m", "sensors": [{"id": "a", "position": [0, 0, 0], "normal": [0, 0, 1]}]}))
    (tmp_path / "f.csv").write_text("t,station,th_x_a,th_y_a\n0,0,1.5,1.5\n")
    r = CliRunner().invoke(main, ["calibrate", str(tmp_path / "f.csv"), "--layout", str(lay), "--stations",
                                  str(tmp_path / "nope.json"), "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "nope.json" in r.output and "Traceback" not in r.output


def test_consider_term_equals_dense_full_inverse():
    """Closed form vs brute force: the Schur-reduced consider covariance (sample poses eliminated in
    chunks) equals [H^-1 J^T J_o][H^-1 J^T J_o]^T of the dense full information matrix, restricted
    to the global columns, for any chunk size."""
    from scipy.sparse import csr_matrix

    from layoutkit.calibrate import _consider_covariance

    rng = np.random.default_rng(3)
    K, G, n = 9, 5, 4
    J = rng.normal(size=(400, 6 * K + G)) * (rng.random((400, 6 * K + G)) < 0.6)
    own = np.arange(400) % K                        # each angle belongs to one sample: H_pp block-diagonal
    J[:, : 6 * K] *= (np.arange(6 * K)[None] // 6 == own[:, None])
    Jo = rng.normal(size=(400, 3 * n))
    H = J.T @ J
    Hinv = np.linalg.inv(H)
    cov = Hinv[6 * K:, 6 * K:]                      # the marginal = inverse Schur complement
    full = (Hinv @ J.T @ Jo)[6 * K:]
    ref = full @ full.T
    for chunk in (1, 4, 100):
        got = _consider_covariance(csr_matrix(J), csr_matrix(Jo), K, cov, chunk=chunk)
        np.testing.assert_allclose(got, ref, rtol=1e-8, atol=1e-12 * np.abs(ref).max())


def test_cli_calibrate_that_determines_nothing_says_why(tmp_path):
    """issue 29: 8 simulated frames without a station column and a one-station JSON (its pose is the
    gauge, its calibration terms unobservable from 8 frames) used to end in "zero-size array to
    reduction operation maximum". Now: exit 2, one error naming the frame file, the missing 'station'
    column, the stations file, and what to give instead; nothing written."""
    from layoutkit.resources import model_path

    lay = str(model_path("chen_target.layout.json"))
    r = CliRunner().invoke(main, ["simulate", "--layout", lay, "--frames", "8", "--out", str(tmp_path / "f.csv")])
    assert r.exit_code == 0, r.output
    (tmp_path / "st1.json").write_text(json.dumps({"stations": [
        {"id": "A", "kind": "lh1", "translation": [0, 0, 0], "rotation": np.eye(3).tolist()}]}))
    r = CliRunner().invoke(main, ["calibrate", str(tmp_path / "f.csv"), "--layout", lay, "--stations",
                                  str(tmp_path / "st1.json"), "--out-dir", str(tmp_path / "D")])
    assert r.exit_code == 2, r.output
    assert r.exception is None or isinstance(r.exception, SystemExit), r.exception
    msg = r.output
    assert msg.startswith("error:") and "f.csv" in msg and "nothing to calibrate" in msg
    assert "'station'" in msg and "st1.json" in msg and "determine none of the 10 free parameter(s)" in msg
    assert not (tmp_path / "D" / "stations.json").exists()


def test_cli_calibrate_without_stations_is_a_usage_error(tmp_path):
    """issue 29: `calibrate FRAMES --layout L --out-dir D` without --stations (required) was a TypeError."""
    (tmp_path / "f.csv").write_text("t,th_x_a,th_y_a\n0,1.5,1.5\n")
    (tmp_path / "l.json").write_text(json.dumps({"units": "m", "sensors": [{"id": "a", "position": [0, 0, 0],
                                                                             "normal": [0, 0, 1]}]}))
    r = CliRunner().invoke(main, ["calibrate", str(tmp_path / "f.csv"), "--layout", str(tmp_path / "l.json"),
                                  "--out-dir", str(tmp_path / "D")])
    assert r.exit_code == 2 and "Missing option '--stations'" in r.output and "Traceback" not in r.output
