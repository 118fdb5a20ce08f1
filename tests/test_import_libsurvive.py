"""libsurvive import on the two real sample recordings (tests/data/libsurvive, no network).

Proof kinds: real recordings (residual levels of real devices); libsurvive's own calibrated
lighthouse poses as the independent reference for the angle and frame conventions; a truncated
copy of a real .gz.
"""
import json
import shutil

import numpy as np
import pytest
from click.testing import CliRunner

from layoutkit.cli import main
from layoutkit.importers.libsurvive import (FLIP, device_frames, layout_of, lh2_to_sweep_angles,
                                            read_lighthouse_config, read_recording,
                                            station_rotation_from_quaternion)
from layoutkit.io.frames import read_frame_table
from layoutkit.io.stations import read_stations
from layoutkit.layout import load_layout
from layoutkit.lighthouse import CALIBRATION_PARAMS, lh2_sweep_angles, sweep_angles
from layoutkit.pnp import solve_pnp


@pytest.fixture(scope="module")
def lh1(libsurvive_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("lh1")
    r = CliRunner().invoke(main, ["import", "libsurvive", str(libsurvive_dir / "lh1_test_cal_first4s.rec.gz"),
                                  "--out", str(out), "--json"])
    assert r.exit_code == 0, r.output
    return out, json.loads(r.stdout)


def _solve(d, dev, *extra):
    r = CliRunner().invoke(main, ["solve", str(d / dev / "frames.csv"), "--layout", str(d / dev / "layout.json"),
                                  "--json", *extra])
    return r


def test_lh1_import_files_and_columns(lh1):
    """The interface: DIR/<device>/layout.json, frames.csv (t, station, th_x_<id>, th_y_<id> for every
    layout id), DIR/stations.json with both stations' poses and calibration."""
    d, s = lh1
    assert set(s["devices"]) == {"HMD", "T20"} and not s["truncated"]
    for dev, n in (("HMD", 32), ("T20", 24)):
        lay = load_layout(d / dev / "layout.json")
        assert lay.n == n
        header = (d / dev / "frames.csv").read_text().splitlines()[0].split(",")
        assert header == ["t", "station"] + [f"th_{a}_{i}" for i in lay.ids for a in "xy"]
    st = read_stations(d / "stations.json")
    # ids from libsurvive's lighthouse index (unique, stable); libsurvive's serials kept as source_id
    assert [x.id for x in st] == ["LH0", "LH1"] and all(x.kind == "lh1" for x in st)
    assert [x.source_id for x in st] == ["178605925", "-142728717"]
    # libsurvive fcalphase (lighthouse_gen1: a = ideal - phase) is layoutkit's phase with the sign flipped
    phase = CALIBRATION_PARAMS.index("phase")
    np.testing.assert_allclose(st[0].calibration.params[:, phase], [-0.058624, -0.062164])
    info = s["stations"]["stations"]
    assert all(i["pose_known"] for i in info) and info[1]["calibration_fcal"]["gibmag"] == [0.020615, -0.012276]
    for x in st:
        np.testing.assert_allclose(x.rotation @ x.rotation.T, np.eye(3), atol=1e-6)


@pytest.mark.parametrize("dev", ["HMD", "T20"])
def test_lh1_solve_real_residuals(lh1, dev):
    """Real LH1 frames: exit 0, every frame with >= 4 sensors on both axes solved, median angle
    residual at the ~1e-4 rad level of uncalibrated real stations (< 3e-4 rad)."""
    d, _ = lh1
    r = _solve(d, dev)
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    assert out["frames_with_4_lit_solved"] == out["frames_with_4_lit"] > 150
    assert 3e-5 < out["residual_rms_median"] < 3e-4
    res = [row for row in out["sensor_residuals"] if row["n_x"]]
    assert all(abs(row["mean_x"]) < 2e-3 for row in res)


def test_convention_against_libsurvive_lighthouse_poses(libsurvive_dir):
    """theta = pi/2 + a and station = diag(1,-1,-1) lighthouse frame, checked against libsurvive's own
    calibrated lighthouse poses: the static HMD solved from each station separately lands on the same
    world pose (to the ~cm left by the phase-only calibration), while the other sign conventions put
    the two stations' answers metres apart."""
    f = libsurvive_dir / "lh1_test_cal_first4s.rec.gz"
    rec = read_recording(f)
    cfg = read_lighthouse_config(str(f) + ".json")
    lay = layout_of(rec, "HMD")
    fr, _ = device_frames(rec.light["HMD"], lay.n, lambda g, ch: ch)
    A = fr.angles.copy()
    for s in (0, 1):  # first-order factory phase: a_ideal = a_meas + phase (lighthouse_gen1.py)
        A[fr.station == s] += np.asarray(cfg[s]["calibration"]["phase"])

    def between(angles, flip):
        sol = solve_pnp(lay.positions, angles, ~np.isnan(angles))
        assert np.median(sol.residual_rms[sol.success]) < 2e-4
        world = []
        for s in (0, 1):
            k = sol.success & (fr.stations() == s)
            Rs = station_rotation_from_quaternion(cfg[s]["pose"][3:])
            if not flip:
                Rs = Rs @ FLIP
            world.append(np.median(sol.translation[k] @ Rs.T + cfg[s]["pose"][:3], 0))
        return np.linalg.norm(world[0] - world[1])

    assert between(A, True) < 0.08
    assert between(A, False) > 1.0                 # without the frame turn
    assert between(np.pi - A, True) > 0.3          # pi/2 - a: the image turned 180 deg about boresight


def test_lh2_conversion_matches_plane_model():
    """lh2_to_sweep_angles inverts libsurvive's uncalibrated gen2 plane model exactly (closed form),
    checked on random directions against layoutkit's own LH1 angles of the same points."""
    rng = np.random.default_rng(0)
    p = rng.normal(size=(500, 3)) * [0.7, 0.7, 0.2] + [0, 0, 2.0]   # station frame, z = boresight
    X, Y, D = p[:, 0], -p[:, 1], p[:, 2]                             # libsurvive: y up, looks along -z
    B = np.arctan2(D, X)
    s = np.arcsin(np.tan(np.pi / 6) * Y / np.hypot(X, D))
    a0, a1 = B - s - np.pi / 2, B + s - np.pi / 2                    # lighthouse_gen2.py, no calibration
    np.testing.assert_allclose(lh2_to_sweep_angles(a0, a1), sweep_angles(p), atol=1e-12)
    assert lh2_sweep_angles(p).shape == (500, 2)


def test_lh2_import_and_solve(libsurvive_dir, tmp_path):
    """Real LH2 tracker: both planes of one rotation give a frame; every frame with >= 4 sensors is
    solved; residuals below 3e-4 rad; the two stations' world poses agree to < 0.15 m."""
    out = tmp_path / "lh2"
    r = CliRunner().invoke(main, ["import", "libsurvive", str(libsurvive_dir / "lh2_test_cal_first4s.rec.gz"),
                                  "--out", str(out), "--json"])
    assert r.exit_code == 0, r.output
    s = json.loads(r.stdout)
    assert s["devices"]["T20"]["frames_per_station"] == {"0": 170, "1": 145} or s["devices"]["T20"]["frames"] > 250
    r = _solve(out, "T20", "--stations", str(out / "stations.json"), "--static", "--solve", "per-station")
    assert r.exit_code == 0, r.output
    o = json.loads(r.stdout)
    assert o["frames_with_4_lit_solved"] == o["frames_with_4_lit"] > 250
    assert o["residual_rms_median"] < 3e-4
    assert o["world_between_stations"]["translation_m"] < 0.15
    for st in o["static"].values():  # the same lit set: scatter within 3x of the DOP prediction
        m = st["same_lit_set"]
        assert 0.2 < m["measured_sigma_rot_deg"] / m["predicted_sigma_rot_deg"] < 3.0


def test_static_hmd_scatter_vs_dop(lh1):
    """The static HMD: sigma and rho estimated from the angles; with the same lit set the measured
    pose scatter is within a factor 3 of the DOP prediction (Chen eqs. 18-24)."""
    d, _ = lh1
    o = json.loads(_solve(d, "HMD", "--static").stdout)
    for st in o["static"].values():
        assert 1e-5 < st["sigma_rad"] < 1e-4 and 0.0 <= st["rho_used"] < 1.0
        m = st["same_lit_set"]
        assert 0.33 < m["measured_sigma_rot_deg"] / m["predicted_sigma_rot_deg"] < 3.0
        assert 0.33 < m["measured_sigma_trans_m"] / m["predicted_sigma_trans_m"] < 3.0


def test_truncated_gz_imports_what_is_there(libsurvive_dir, tmp_path):
    """A .gz cut in the middle (as real recordings end) imports the complete lines and says where it ended."""
    src = (libsurvive_dir / "lh2_test_cal_first4s.rec.gz").read_bytes()
    cut = tmp_path / "cut.rec.gz"
    cut.write_bytes(src[: len(src) // 2])
    shutil.copy(libsurvive_dir / "lh2_test_cal_first4s.rec.gz.json", str(cut) + ".json")
    r = CliRunner().invoke(main, ["import", "libsurvive", str(cut), "--out", str(tmp_path / "o"), "--json"])
    assert r.exit_code == 0, r.output
    s = json.loads(r.stdout)
    assert s["truncated"] and "truncated" in s["ended"] and "complete line(s)" in s["ended"]
    fr = read_frame_table(tmp_path / "o" / "T20" / "frames.csv")
    assert 50 < fr.n_frames < 250 and np.isfinite(fr.t).all()


def test_not_a_recording_clear_error(tmp_path):
    p = tmp_path / "x.rec"
    p.write_text("hello world\n")
    r = CliRunner().invoke(main, ["import", "libsurvive", str(p), "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "not a libsurvive recording" in r.output and "Traceback" not in r.output


def test_calibrated_solve_lowers_residuals_and_joins_stations(lh1, tmp_path):
    """--solve per-station goes through each station's factory calibration by default (the recording's
    fcal*, layoutkit.lighthouse model; --ignore-calibration = the ideal model): per-station median
    residuals fall from 1.41e-4 / 1.88e-4 rad to 4.4e-5 / 1.3e-4 rad (real recording), the two stations'
    world poses of the static HMD come closer (libsurvive's own lighthouse poses as the independent
    reference), and every written residual_rms equals an independent re-evaluation of measure() at the
    written pose (the residual is through the forward model, not of pre-corrected angles)."""
    from layoutkit.geometry import rotvec_to_matrix
    from layoutkit.io.poses import read_poses
    from layoutkit.lighthouse import measure

    d, _ = lh1
    st = ["--stations", str(d / "stations.json"), "--solve", "per-station"]
    raw = json.loads(_solve(d, "HMD", *st, "--ignore-calibration").stdout)
    r = _solve(d, "HMD", *st, "--out", str(tmp_path / "p.csv"))
    assert r.exit_code == 0, r.output
    cal = json.loads(r.stdout)
    assert json.loads(_solve(d, "HMD", *st, "--calibrated").stdout)["residual_rms_median"] == cal["residual_rms_median"]
    assert raw["calibrated_stations"] == [] and cal["calibrated_stations"] == [0, 1]
    assert cal["solved"] >= raw["solved"] - 1
    rm, cm = raw["residual_rms_median_per_station"], cal["residual_rms_median_per_station"]
    assert 1.2e-4 < rm["0"] < 1.6e-4 and 1.6e-4 < rm["1"] < 2.1e-4
    assert 3.5e-5 < cm["0"] < 5.5e-5 and 1.1e-4 < cm["1"] < 1.5e-4
    assert cal["world_between_stations"]["translation_m"] < 0.5 * raw["world_between_stations"]["translation_m"]
    # independent re-evaluation through measure() at the written (world-frame) poses
    lay = load_layout(d / "HMD" / "layout.json")
    fr = read_frame_table(d / "HMD" / "frames.csv", lay.ids)
    stations = read_stations(d / "stations.json")
    tab = read_poses(tmp_path / "p.csv")
    ok = tab.status == 0
    Rw, tw = rotvec_to_matrix(tab.rotvec[ok]), tab.translation[ok]
    for q, S in enumerate(stations):
        k = fr.stations()[ok] == q
        pw = np.einsum("fij,nj->fni", Rw[k], lay.positions) + tw[k][:, None]
        r_ = fr.angles[ok][k] - measure((pw - S.translation) @ S.rotation, S.calibration)
        rms = np.sqrt(np.nanmean(r_.reshape(len(r_), -1) ** 2, 1))
        np.testing.assert_allclose(rms, tab.residual_rms[ok][k], rtol=2e-5)  # the table keeps 6 digits

def test_station_ids_unique_from_the_config_order(libsurvive_dir, tmp_path):
    """Issue 26 item 3. nan_crash_windows' real config (MIT) names all three LH2 lighthouses
    2147483647: the import gives them the ids of libsurvive's lighthouse index (LH0, LH1, LH2: the
    calibration file's order), keeps 2147483647 as source_id, maps each channel (mode 11, 3, 8) to its
    own station, and the stations file it writes is read back."""
    rec = tmp_path / "nan_crash_windows.rec"
    shutil.copy(libsurvive_dir / "nan_crash_windows.rec.gz.json", str(rec) + ".json")
    # three B lines per channel (two planes) and a CONFIG-less device: enough to find the stations
    lines = [f"0.{k:03d} T20 B {ch} 0 {1000 * k} {k % 2} 0.1" for k, ch in enumerate([11, 11, 3, 3, 8, 8])]
    rec.write_text("\n".join(lines) + "\n")
    r = CliRunner().invoke(main, ["import", "libsurvive", str(rec), "--out", str(tmp_path / "o"), "--json"])
    assert r.exit_code == 0, r.output
    info = json.loads(r.stdout)["stations"]["stations"]
    st = read_stations(tmp_path / "o" / "stations.json")
    assert [x.id for x in st] == ["LH0", "LH1", "LH2"]
    assert [x.source_id for x in st] == ["2147483647"] * 3
    assert [i["channel"] for i in info] == [11, 3, 8]
    # each channel's rotor speed from libsurvive's channel table
    np.testing.assert_allclose([x.rotor_rpm / 60 for x in st], [52.6894, 50.5796, 51.2273])


def test_duplicate_station_ids_refused(tmp_path):
    """Anywhere else a duplicate id is refused with a message naming the file and the id."""
    d = {"stations": [{"id": "2147483647", "rotation": np.eye(3).tolist(), "translation": [0, 0, 0]},
                      {"id": "2147483647", "rotation": np.eye(3).tolist(), "translation": [1, 0, 0]}]}
    p = tmp_path / "st.json"
    p.write_text(json.dumps(d))
    with pytest.raises(ValueError, match=r"st\.json.*'2147483647' used by more than one station"):
        read_stations(p)


def test_lh2_rotor_speed_of_each_channel_matches_the_sweep_rate(libsurvive_dir):
    """LH2_CHANNEL_HZ against the real recording: within one sweep the angle grows with the device's
    48 MHz timecode at 2 pi f of the channel (median slope between consecutive hits, 0.2 %)."""
    from layoutkit.importers.libsurvive import LH2_CHANNEL_HZ, TICK_HZ

    rec = read_recording(libsurvive_dir / "lh2_test_cal_first4s.rec.gz")
    d = rec.light["T20"]
    tc, a = np.asarray(d.timecode, float), np.asarray(d.angle)
    ch, ax = np.asarray(d.station), np.asarray(d.axis)
    for c in np.unique(ch):
        same = (ch[1:] == c) & (ch[:-1] == c) & (ax[1:] == ax[:-1]) & (np.abs(np.diff(tc)) < 4800) & (np.diff(tc) != 0)
        slope = np.median(np.diff(a)[same] / (np.diff(tc)[same] / TICK_HZ))
        assert slope == pytest.approx(2 * np.pi * LH2_CHANNEL_HZ[c], rel=2e-3)


def test_imu_samples_read_one_g_at_rest_on_the_light_clock(libsurvive_dir):
    """Real IMU lines: the HMD (±4 g) and the Knuckles (±8 g) read 9.81 m/s² at rest within 1.5 % once
    the range is taken from the data and the CONFIG's bias (m/s²) applied; the samples sit on the light's
    clock (inside its time span); the HMD's first samples, written before the light starts with a
    timecode 16.5 s behind, are dropped."""
    from layoutkit.importers.libsurvive_imu import imu_samples

    rec = read_recording(libsurvive_dir / "lh1_test_cal_first4s.rec.gz")
    for dev, cpg in (("HMD", 8192.0), ("T20", 4096.0)):
        s = imu_samples(rec, dev)
        assert s["scales"]["acc_counts_per_g"] == cpg
        assert np.median(np.linalg.norm(s["acc"], axis=1)) == pytest.approx(9.80665, rel=0.015)
        light_t = device_frames(rec.light[dev], 64, lambda g, c: c)[0].t
        assert light_t.min() - 0.5 < s["t"].min() and s["t"].max() < light_t.max() + 0.5
    assert imu_samples(rec, "HMD")["dropped"] >= 1


def test_lh2_sweeps_repeat_at_the_channel_rate(libsurvive_dir):
    """device_sweeps on the real LH2 recording: each plane of a channel comes back once per rotor turn,
    1 / LH2_CHANNEL_HZ (median interval, 0.5 %)."""
    from layoutkit.importers.libsurvive import LH2_CHANNEL_HZ, device_sweeps

    rec = read_recording(libsurvive_dir / "lh2_test_cal_first4s.rec.gz")
    sw = device_sweeps(rec.light["T20"], 32, lambda g, c: c)
    for ch in np.unique(sw["station"]):
        for plane in (0, 1):
            t = sw["t"][(sw["station"] == ch) & (sw["axis"] == plane)]
            d = np.diff(t)
            assert np.median(d[d < 0.03]) == pytest.approx(1 / LH2_CHANNEL_HZ[ch], rel=5e-3)


def test_import_imu_filter_agrees_with_the_joint_solve_at_rest(lh1, libsurvive_dir, tmp_path):
    """``import libsurvive --imu-filter`` on the real lh1 recording (the HMD sits still): the HMD has no
    CONFIG ``imu`` block, so its IMU axes are chosen from gravity (a half turn about z; the accelerometer
    then reads the world's vertical, which libsurvive's calibrated lighthouse poses define, within 3 deg);
    the filter's accepted per-sweep poses agree with the independent joint solve of the same recording's
    frames (nearest window) within 1 mm / 0.2 deg (median). --stations without --imu-filter is refused."""
    from scipy.spatial.transform import Rotation

    from layoutkit.io.poses import read_poses

    out = tmp_path / "o"
    r = CliRunner().invoke(main, ["import", "libsurvive", str(libsurvive_dir / "lh1_test_cal_first4s.rec.gz"),
                                  "--out", str(out), "--imu-filter", "--json"])
    assert r.exit_code == 0, r.output
    f = json.loads(r.stdout)["imu_filter"]["HMD"]
    assert f["imu_frame_from"].startswith("no CONFIG imu block: half turn about z")
    assert f["gravity_from_minus_z_deg"] < 3.0
    assert f["sweeps"]["accepted"] > 0.9 * f["sweeps"]["sweeps"]
    d, _ = lh1
    r = _solve(d, "HMD", "--stations", str(d / "stations.json"), "--solve", "joint", "--out", str(tmp_path / "j.csv"))
    assert r.exit_code == 0, r.output
    a, b = read_poses(out / "HMD" / "imu_filter_poses.csv"), read_poses(tmp_path / "j.csv")
    ka, kb = a.status == 0, b.status == 0
    j = np.searchsorted(b.t[kb], a.t[ka]).clip(0, kb.sum() - 1)
    dp = np.linalg.norm(a.translation[ka] - b.translation[kb][j], axis=1)
    dr = (Rotation.from_rotvec(a.rotvec[ka]) * Rotation.from_rotvec(b.rotvec[kb][j]).inv()).magnitude()
    assert np.median(dp) < 1e-3 and np.degrees(np.median(dr)) < 0.2
    r = CliRunner().invoke(main, ["import", "libsurvive", str(libsurvive_dir / "lh1_test_cal_first4s.rec.gz"),
                                  "--out", str(tmp_path / "p"), "--stations", str(d / "stations.json")])
    assert r.exit_code == 2 and "--stations needs --imu-filter" in r.output
