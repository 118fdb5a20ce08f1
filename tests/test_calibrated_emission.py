"""`simulate --stations` and `fake-fpga --stations`: calibrated (distorted) angles from given stations.

Proof kinds: bit-identity with the ideal emission for a station without calibration; independent
re-evaluation of the forward model (layoutkit.lighthouse.measure) at the written truth poses; a
noise-free round trip through `solve --solve joint` (truth to 1e-9); the bias of an uncalibrated
solve against its first-order closed form (one Gauss-Newton step from the truth on the
calibrated-minus-ideal angle difference); the joint DOP prediction for the noisy scatter.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from _calib_sim import random_calibration
from layoutkit.cli import main
from layoutkit.geometry import rotvec_to_matrix, transform_points
from layoutkit.io.frames import read_frame_table
from layoutkit.io.poses import read_poses
from layoutkit.io.stations import read_stations, write_stations
from layoutkit.layout import load_layout, save_layout
from layoutkit.lighthouse import Station, measure
from layoutkit.shapes import chen_target
from layoutkit.simulate import stations_looking_at

LAYOUT = "tests/data/chen_layout.json"


def _stations(rng, scale=1.0):
    """Station 0 at the origin (the simulator's frame: poses in front of it), station 1 2 m to the
    side looking at the same area; both with factory-size LH1 calibrations (times ``scale``)."""
    from layoutkit.lighthouse import Calibration

    s1 = stations_looking_at([[2.0, -0.4, 0.8]], (0.0, 0.3, 2.0))[0]
    cals = [random_calibration(rng, "lh1", "corrected"), random_calibration(rng, "lh1")]
    cals = [Calibration(c.params * scale, c.kind, c.gib_argument) for c in cals]
    return [Station(id="0", calibration=cals[0]),
            Station(id="1", rotation=s1.rotation, translation=s1.translation, calibration=cals[1])]


def _simulate(tmp_path, layout, stations, *extra, name="f.csv"):
    sp = tmp_path / f"st_{name}.json"
    write_stations(sp, stations)
    out = tmp_path / name
    r = CliRunner().invoke(main, ["simulate", "--layout", str(layout), "--frames", "60", "--seed", "3",
                                  "--out", str(out), "--stations", str(sp), "--json", *extra])
    assert r.exit_code == 0, r.output
    return out, sp, json.loads(r.stdout)


@pytest.fixture
def chen(tmp_path):
    p = tmp_path / "chen.json"
    save_layout(chen_target()[1], p)
    return p


def test_simulate_station_without_calibration_is_bit_identical(tmp_path, chen):
    """One uncalibrated station at the origin: angles, times and truth bit-identical to `simulate`
    without --stations (the file only gains the station column)."""
    plain = tmp_path / "plain.csv"
    r = CliRunner().invoke(main, ["simulate", "--layout", str(chen), "--frames", "60", "--seed", "3",
                                  "--out", str(plain)])
    assert r.exit_code == 0, r.output
    out, _, summ = _simulate(tmp_path, chen, [Station(id="0")])
    a, b = read_frame_table(plain), read_frame_table(out)
    assert summ["calibrated_stations"] == [] and a.station is None and np.all(b.station == 0)
    assert np.array_equal(a.t, b.t) and np.array_equal(a.angles, b.angles, equal_nan=True)
    assert np.array_equal(a.truth_rotation, b.truth_rotation) and np.array_equal(a.truth_translation, b.truth_translation)


def test_simulate_stations_emits_each_stations_forward_model(tmp_path, chen, rng):
    """Noise-free, unquantised: every row's angles == measure(points at the row's truth pose,
    that station's calibration) to 1e-12, rows of one pose within one 20 ms window; and the summary
    records the stations with their calibration."""
    from layoutkit.joint import group_windows

    st = _stations(rng)
    out, sp, summ = _simulate(tmp_path, chen, st, "--sigma-arcsec", "0", "--no-quantize")
    fr = read_frame_table(out)
    lay = load_layout(chen)
    assert summ["rows"] == 120 and summ["calibrated_stations"] == [0, 1]
    assert [s["calibration"]["phase"] for s in summ["stations"]] == [list(s.calibration.params[:, 0]) for s in st]
    for q, s in enumerate(st):
        k = fr.station == q
        pred = measure(transform_points(fr.truth_rotation[k], fr.truth_translation[k], lay.positions), s.calibration)
        seen = np.isfinite(fr.angles[k])
        np.testing.assert_allclose(fr.angles[k][seen], pred[seen], rtol=0, atol=1e-12)
        ideal = measure(transform_points(fr.truth_rotation[k], fr.truth_translation[k], lay.positions))
        assert np.nanmax(np.abs(fr.angles[k] - ideal)) > 1e-3          # really distorted
    rows, _ = group_windows(fr.t, fr.station, 2)
    assert rows.shape == (60, 2) and np.all(rows >= 0)


def _world_truth(fr, stations):
    """The world pose of every station-0 row (station 0 is at the origin: its frame is the world)."""
    k = fr.station == 0
    return fr.truth_rotation[k], fr.truth_translation[k]


def test_joint_solve_recovers_truth_noise_free_and_bias_without_calibration(tmp_path, chen, rng):
    """Noise-free frames from `simulate --stations` solved by `solve --solve joint` with the same
    stations: the truth to 1e-9 (rad, m). Solved with the calibration dropped (--ignore-calibration):
    biased, and the bias equals its first-order closed form — one Gauss-Newton step of the ideal
    model from the truth on d = measure(calibrated) - measure(ideal) — to 10 %; the residual RMS equals
    the part of d no pose change explains (``|(I - J J^+) d| / sqrt(m)``) to 10 %. (Calibrations of a
    tenth of factory size, where first order holds; at full size the two stations disagree by ~1e-2 rad
    and the uncalibrated joint fit does not even converge.)"""
    from layoutkit.joint import model_angles_jacobian

    st = _stations(rng, scale=0.1)
    out, sp, _ = _simulate(tmp_path, chen, st, "--sigma-arcsec", "0", "--no-quantize")
    fr = read_frame_table(out)
    lay = load_layout(chen)
    Rt, tt = _world_truth(fr, st)
    got = {}
    for flag in ((), ("--ignore-calibration",)):
        poses = tmp_path / f"p{len(flag)}.csv"
        r = CliRunner().invoke(main, ["solve", str(out), "--layout", str(chen), "--stations", str(sp), "--solve", "joint",
                                      "--json", "--out", str(poses), *flag])
        assert r.exit_code == 0, r.output
        tab = read_poses(poses)
        assert len(tab) == 60 and np.all(tab.status == 0), (flag, r.output[:300])
        got[bool(flag)] = tab
    tab = got[False]
    assert np.abs(tab.translation - tt).max() < 1e-9
    dR = np.einsum("fji,fjk->fik", rotvec_to_matrix(tab.rotvec), Rt)
    assert np.abs(dR - np.eye(3)).max() < 1e-9
    # the uncalibrated solve: first-order prediction of its bias from the truth
    ideal = [Station(id=s.id, rotation=s.rotation, translation=s.translation) for s in st]
    A_cal, _, _ = model_angles_jacobian(lay.positions, Rt, tt, st, jacobian=False)
    A_id, J, _ = model_angles_jacobian(lay.positions, Rt, tt, ideal)
    ang = np.stack([fr.angles[fr.station == q] for q in range(2)], 1)
    seen = np.isfinite(ang)
    d = np.where(seen, A_cal - A_id, 0.0).reshape(60, -1)
    Jm = (J * seen[..., None]).reshape(60, -1, 6)
    step = np.stack([np.linalg.lstsq(Jm[f], d[f], rcond=None)[0] for f in range(60)])
    bias = np.linalg.norm(got[True].translation - tt, axis=1)
    pred = np.linalg.norm(step[:, 3:], axis=1)
    assert np.median(bias) > 1e-3                                    # a real bias (mm and more)
    np.testing.assert_allclose(bias, pred, rtol=0.1)
    left = d - np.einsum("fkj,fj->fk", Jm, step)
    rms_pred = np.sqrt(np.sum(left * left, 1) / seen.reshape(60, -1).sum(1))
    np.testing.assert_allclose(got[True].residual_rms, rms_pred, rtol=0.1)


def test_noisy_joint_scatter_follows_joint_dop(tmp_path, chen, rng):
    """With noise (8.28", rho 0) the joint solve's position error RMS vs truth is within 30 % of the
    joint DOP prediction `solve` reports (300 poses); per-station solving of the same file
    (--solve per-station, through each calibration) is unbiased too: median error below 3x its own
    per-frame prediction."""
    st = _stations(rng)
    sp = tmp_path / "st.json"
    write_stations(sp, st)
    out = tmp_path / "n.csv"
    r = CliRunner().invoke(main, ["simulate", "--layout", str(chen), "--frames", "300", "--seed", "5", "--out", str(out),
                                  "--stations", str(sp), "--rho", "0"])
    assert r.exit_code == 0, r.output
    fr = read_frame_table(out)
    Rt, tt = _world_truth(fr, st)
    r = CliRunner().invoke(main, ["solve", str(out), "--layout", str(chen), "--stations", str(sp), "--solve", "joint",
                                  "--json", "--out", str(tmp_path / "p.csv"), "--rho", "0"])
    assert r.exit_code == 0, r.output
    summ = json.loads(r.stdout)
    tab = read_poses(tmp_path / "p.csv")
    ok = tab.status == 0
    assert ok.mean() > 0.97
    err = np.sqrt(np.mean(np.sum((tab.translation[ok] - tt[ok]) ** 2, 1)))
    assert 0.7 < err / summ["predicted_position_sigma_m"] < 1.3, (err, summ["predicted_position_sigma_m"])
    r = CliRunner().invoke(main, ["solve", str(out), "--layout", str(chen), "--stations", str(sp), "--solve",
                                  "per-station", "--json", "--rho", "0", "--sigma-arcsec", "8.28"])
    assert r.exit_code == 0, r.output
    ps = json.loads(r.stdout)
    assert ps["calibrated_stations"] == [0, 1] and ps["solved"] > 0.9 * 600
    assert ps["rms_trans_m_without_gross"] < 3 * ps["predicted_rms_trans_m"]


def test_fake_fpga_station_without_calibration_is_bit_identical(tmp_path):
    """`fake-fpga --stations` with one uncalibrated LH1 station at the origin: the capture bytes equal
    those of `fake-fpga` without --stations."""
    sp = tmp_path / "s.json"
    write_stations(sp, [Station(id="0")])
    caps = []
    for extra in ((), ("--stations", str(sp))):
        cap = tmp_path / f"c{len(extra)}.lkcap"
        r = CliRunner().invoke(main, ["fake-fpga", "--layout", LAYOUT, "--out", str(cap), "--duration", "1",
                                      "--seed", "4", "--json", *extra])
        assert r.exit_code == 0, r.output
        caps.append(cap.read_bytes())
    assert caps[0] == caps[1] and len(caps[0]) > 1000


def test_fake_fpga_emits_calibrated_angles_and_records_the_stations(tmp_path, rng):
    """A calibrated station: the decoded angles (quantised hits) equal measure(points at the truth
    pose, calibration) within half a 50 MHz tick, not the ideal angles; the capture sidecar holds the
    stations with their calibration (read back as the same parameters)."""
    from layoutkit.live.capture import read_sidecar
    from layoutkit.workflows.fake import fake_fpga_stream

    lay = load_layout(LAYOUT)
    cal = random_calibration(rng, "lh1", "corrected")
    st = [Station(id="A", calibration=cal)]
    fs = fake_fpga_stream(lay, duration_s=1.0, seed=2, sigma=0.0, stations=st)
    sw = fs.sweeps
    p = transform_points(rotvec_to_matrix(sw.rotvec), sw.translation, lay.positions)
    ref = np.take_along_axis(measure(p, cal), sw.axis[:, None, None], -1)[..., 0]
    ideal = np.take_along_axis(measure(p), sw.axis[:, None, None], -1)[..., 0]
    got = sw.measured_angles()
    seen = np.isfinite(got)
    tick = 2 * np.pi * 60 / 50e6
    assert seen.sum() > 500
    assert np.abs(got[seen] - ref[seen]).max() <= tick / 2 + 1e-12
    assert np.abs(got[seen] - ideal[seen]).max() > 100 * tick
    sp = tmp_path / "s.json"
    write_stations(sp, st)
    cap = tmp_path / "c.lkcap"
    r = CliRunner().invoke(main, ["fake-fpga", "--layout", LAYOUT, "--out", str(cap), "--duration", "1", "--seed", "2",
                                  "--stations", str(sp), "--json"])
    assert r.exit_code == 0, r.output
    side = read_sidecar(cap)
    back = read_stations_list(side["stations"])
    np.testing.assert_allclose(back[0].calibration.params, cal.params, atol=1e-15)
    bad = CliRunner().invoke(main, ["fake-fpga", "--layout", LAYOUT, "--out", str(tmp_path / "d.lkcap"),
                                    "--stations", str(tmp_path / "nope.json")])
    assert bad.exit_code == 2 and "nope.json" in bad.output and "Traceback" not in bad.output


def read_stations_list(items):
    from layoutkit.io.stations import stations_from_list

    return stations_from_list(items)


def test_read_stations_roundtrip_keeps_calibration(tmp_path, rng):
    """The stations JSON the commands read carries the calibration exactly (the emission's input)."""
    st = _stations(rng)
    write_stations(tmp_path / "s.json", st)
    back = read_stations(tmp_path / "s.json")
    for a, b in zip(st, back):
        np.testing.assert_array_equal(a.calibration.params, b.calibration.params)
        assert a.calibration.gib_argument == b.calibration.gib_argument


def test_per_station_calibrated_solve_keeps_the_planar_ambiguity_status():
    """A 4-sensor planar deck (3 x 1.5 cm) at up to 3.5 m: the same poses and noise draws emitted by an
    ideal and by a calibrated station; solved per station (the calibrated one through its model) the
    planar two-fold ambiguity is the same property of the geometry — the same frames come back
    'ambiguous' (not 'ok'), and the errors vs truth of the ok frames agree within 25 %."""
    from layoutkit.layout import Layout
    from layoutkit.pnp import STATUS_AMBIGUOUS
    from layoutkit.workflows.frames import simulate_frames, solve_frames

    deck = np.array([[-0.015, 0.0075, 0.0], [-0.015, -0.0075, 0.0], [0.015, 0.0075, 0.0], [0.015, -0.0075, 0.0]])
    lay = Layout(deck, np.tile([0.0, 0.0, 1.0], (4, 1)), ("a", "b", "c", "d"))
    cal = random_calibration(np.random.default_rng(1), "lh1", "corrected")
    out = []
    for st in ([Station(id="0")], [Station(id="0", calibration=cal)]):
        fr = simulate_frames(lay, 400, seed=2, sigma=4e-5, rho=0.0, stations=st, half_angle_deg=80)
        out.append(solve_frames(fr, lay, sigma=4e-5, rho=0.0, stations=dict(enumerate(st))))
    ideal, calib = out
    assert calib["calibrated_stations"] == [0] and ideal["calibrated_stations"] == []
    amb_i, amb_c = ideal["status"] == STATUS_AMBIGUOUS, calib["status"] == STATUS_AMBIGUOUS
    assert amb_i.sum() > 100 and np.mean(amb_i == amb_c) >= 0.95
    r = calib["rms_trans_m_without_gross"] / ideal["rms_trans_m_without_gross"]
    assert 0.8 < r < 1.25, r
