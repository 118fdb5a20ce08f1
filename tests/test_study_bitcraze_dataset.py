"""`layoutkit study bitcraze-dataset` on a dataset folder written like the public one
(bitcraze/positioning_dataset: ``<set>/logNN`` cfusdlog with the real logs' conventions —
tests/_cf_events_sim.simulate_uart_log —, ``mocapNN.npy`` at 300 Hz in its own frame and clock with
NaN rows, ``system-config.yaml``), with known truth.

Proof kinds: closed forms (the jitter of i.i.d. noise is sigma sqrt(6); an error of i.i.d. noise
sigma per axis has RMS sigma sqrt(3)); the simulated motion capture's own clock rate and rigid
transform recovered by the alignment; simulator truth for our poses.
"""
import json

import numpy as np
import pytest
from click.testing import CliRunner

from layoutkit.cli import main
from layoutkit.geometry import rotvec_to_matrix
from layoutkit.layout import load_layout
from layoutkit.studies.bitcraze_dataset import align_to_mocap, coverage, discover, jitter, run_study, write_outputs

from _cf_events_sim import simulate_uart_log, truth_position
from _cf_joint_sim import DECK, flying_motion, static_motion
from cf_helpers import LOG_RATE

MARKERS = [("mode", "B")]
CB = [("x", "f"), ("y", "f"), ("z", "f"), ("delta", "f")]
FIXED = [("stateEstimate.x", "f"), ("stateEstimate.y", "f"), ("stateEstimate.z", "f")]
R_MOCAP = rotvec_to_matrix([0.0, 0.0, np.radians(30.0)])
T_MOCAP = np.array([0.4, -1.2, 0.05])
SIGMA_CB = 2e-4      # the firmware crossing beam's simulated noise per axis (m)
SIGMA_EKF = 2e-3     # the firmware EKF's (m)


def _mocap(sim, t_on, t_off, rng, t0_ms=812345.0):
    """300 Hz motion capture of the truth in its own frame (R_MOCAP, T_MOCAP) and clock (real time:
    the log clock runs LOG_RATE), 0.1 mm noise, ~20 % NaN rows in runs, first sample at markers on."""
    dur = (t_off - t_on) / LOG_RATE
    tm = np.linspace(0.0, dur, int(dur * 300) + 1)     # the last sample at markers off
    p = truth_position(sim, t_on + tm * LOG_RATE) @ R_MOCAP.T + T_MOCAP + rng.normal(0, 1e-4, (len(tm), 3))
    hole = np.zeros(len(tm), bool)
    for s in rng.integers(1, len(tm) - 40, max(1, len(tm) // 150)):
        hole[s:s + 30] = True
    p[hole] = np.nan
    return np.column_stack([t0_ms + 1000 * tm, p])


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("bitcraze")
    rng = np.random.default_rng(7)
    static = _make(root / "lh2_crossingBeam_jitter", rng, mode="crossing_beam", motion=None, duration=2.0, fw="cb")
    moving = _make(root / "lh2_kalman_move", rng, mode="kalman", motion=flying_motion(0.5), duration=3.0, fw="ekf")
    np.save(root / "lh2_kalman_move" / "mocap01.npy", np.zeros((10, 4)))           # no log01: skipped
    (root / "flowv2_move_floor").mkdir()
    (root / "flowv2_move_floor" / "log00").write_bytes(b"\xbc")                     # not a Lighthouse set
    return root, static, moving


def _make(folder, rng, *, mode, motion, duration, fw, name="log00", setup_seed=None):
    """One log with markers, the firmware's estimates (truth + noise) and the motion capture;
    setup_seed : the station calibrations' seed (logs of one set-up share it)."""
    seed = int(rng.integers(1000))
    t_on = 10.9
    t_off = 10.78 + duration * LOG_RATE - 0.1
    t = np.arange(t_on, t_off, 0.01 if fw == "ekf" else 0.07)
    # the truth is a function of the log clock (the simulator's motion of the deck's centre)
    truth = truth_position({"motion": motion or static_motion(), "layout": load_layout(DECK)}, t)
    extra = {"activeMarkerModeChanged": (MARKERS, [t_on, t_off], [(1,), (0,)])}
    if fw == "ekf":
        extra["fixedFrequency"] = (FIXED, t, [tuple(map(float, q)) for q in truth + rng.normal(0, SIGMA_EKF, truth.shape)])
    else:
        q = truth + rng.normal(0, SIGMA_CB, truth.shape)
        extra["lhCrossingBeam"] = (CB, t, [(*map(float, v), 0.01) for v in q])
    log, yml, sim = simulate_uart_log(folder, seed=seed, duration=duration, motion=motion, mode=mode, extra=extra,
                                      name=name, setup_seed=setup_seed)
    yml.rename(folder / "system-config.yaml")
    np.save(folder / name.replace("log", "mocap"), _mocap(sim, t_on, t_off, rng))
    return sim


def test_jitter_and_coverage_closed_forms():
    """Jitter of i.i.d. N(0, s^2 I3) positions is s sqrt(6) (E|dp|^2 = 6 s^2); NaN rows are left out;
    coverage counts 100 ms intervals holding an estimate."""
    rng = np.random.default_rng(0)
    p = rng.normal(0, 1e-3, (200000, 3))
    assert abs(jitter(p) / (1e-3 * np.sqrt(6)) - 1) < 0.01
    q = np.array([[0, 0, 0], [np.nan, 0, 0], [3, 4, 0.0]])
    assert jitter(q) == 5.0
    assert coverage([0.05, 0.07, 0.25, 0.95], 0.0, 1.0) == 0.3


def test_discover_says_what_it_cannot_use(dataset):
    root, *_ = dataset
    items, skipped = discover(root)
    assert sorted(i.name for i in items) == ["lh2_crossingBeam_jitter/log00", "lh2_kalman_move/log00"]
    reasons = {s["file"].split("/")[-1]: s["reason"] for s in skipped}
    assert "not a Lighthouse set" in reasons["flowv2_move_floor"]
    assert "no log with its number" in reasons["mocap01.npy"]


def test_alignment_recovers_clock_rate_and_rigid_transform(dataset):
    """The firmware EKF stream (truth + 2 mm per axis) aligned onto the simulated motion capture: the
    clock rate 1 / LOG_RATE (to the 1 ms steps of the end search), the 30 deg frame rotation, zero end offsets; the error RMS is the
    noise's sigma sqrt(3) (+ the motion capture's 0.1 mm)."""
    root, _, moving = dataset
    from layoutkit.studies.bitcraze_dataset import firmware_series

    fw = firmware_series(root / "lh2_kalman_move" / "log00")
    t, p = fw["ekf"]
    a = align_to_mocap(t, p, np.load(root / "lh2_kalman_move" / "mocap00.npy"), *fw["markers"])
    assert a["status"] == "ok" and a["samples"] > 150
    dur = fw["markers"][1] - fw["markers"][0]
    assert abs(a["rate"] - 1 / LOG_RATE) < 2e-3 / dur        # the ends are searched in 1 ms steps
    assert abs(a["rotation_deg"] - 30.0) < 0.5
    assert abs(a["start_ms"]) <= 10 and abs(a["end_ms"]) <= 10
    assert abs(a["rms_m"] / (SIGMA_EKF * np.sqrt(3)) - 1) < 0.15


def test_study_end_to_end(dataset, tmp_path):
    """run_study → table.md, results.json, figures: the firmware crossing beam's jitter is its noise's
    sigma sqrt(6); our joint poses on the moving log are within 2 mm RMS of the motion capture after
    alignment and cover >= 90 % of the 100 ms intervals; the unusable files are listed with why."""
    root, static, moving = dataset
    res = run_study(root, methods=("joint",))
    s = res["sets"]
    cb = s["lh2_crossingBeam_jitter"]["methods"]["fw_crossing_beam"]
    assert abs(cb["jitter_median_m"] / (SIGMA_CB * np.sqrt(6)) - 1) < 0.35       # ~25 samples
    ours = s["lh2_kalman_move"]["methods"]["ours_joint"]
    assert ours["error_rms_m"] < 2e-3 and ours["coverage_median"] >= 0.9, ours
    ekf = s["lh2_kalman_move"]["methods"]["fw_ekf"]
    assert ekf["error_rms_m"] > 2e-3
    paths = write_outputs(res, tmp_path / "out")
    table = open(paths["table"]).read()
    assert "## lh2_kalman_move" in table and "firmware EKF" in table and "ours joint" in table
    assert "flowv2_move_floor" in table and "mocap01.npy" in table
    assert len(paths["figures"]) == 2 and all(open(f, "rb").read(4) == b"\x89PNG" for f in paths["figures"])
    doc = json.load(open(paths["results"]))
    assert doc["sets"]["lh2_kalman_move"]["methods"]["ours_joint"]["logs"] == 1


def test_cli_json_and_bad_folder(dataset, tmp_path):
    """The exact interface: ``study bitcraze-dataset --data DIR --out OUT --json`` (synchronous
    scheduler here); a folder without any usable log is one ``error:`` line naming it, exit 2."""
    root, *_ = dataset
    r = CliRunner().invoke(main, ["study", "bitcraze-dataset", "--data", str(root), "--out", str(tmp_path / "o"),
                                  "--json", "--scheduler", "synchronous"])
    assert r.exit_code == 0, r.output[-2000:]
    doc = json.loads(r.stdout)
    assert set(doc["sets"]) == {"lh2_crossingBeam_jitter", "lh2_kalman_move"}
    assert {"ours_joint", "ours_filter", "ours_per_station_0"} <= set(doc["sets"]["lh2_kalman_move"]["methods"])
    assert (tmp_path / "o" / "table.md").is_file()
    empty = tmp_path / "empty"
    empty.mkdir()
    r = CliRunner().invoke(main, ["study", "bitcraze-dataset", "--data", str(empty), "--out", str(tmp_path / "o2")])
    lines = [x for x in r.output.splitlines() if x.strip()]
    assert r.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error:") and "empty" in lines[0], r.output


def test_bad_files_in_the_folder_are_listed_not_fatal(dataset, tmp_path):
    """Fault injection: in a copy of the dataset folder, one log emptied, one motion capture file
    replaced by binary junk, a truncated copy of the other: the study still runs on what it can read,
    lists each bad file with why (no traceback), and a folder where no log can be read is one
    ``error:`` line, exit 2."""
    import shutil

    root, *_ = dataset
    bad = tmp_path / "bad"
    shutil.copytree(root, bad)
    (bad / "lh2_crossingBeam_jitter" / "log00").write_bytes(b"")
    (bad / "lh2_kalman_move" / "mocap00.npy").write_bytes(bytes(range(256)) * 4)
    r = CliRunner().invoke(main, ["study", "bitcraze-dataset", "--data", str(bad), "--out", str(tmp_path / "o"),
                                  "--json", "--scheduler", "synchronous"])
    assert r.exit_code == 0, r.output[-2000:]
    doc = json.loads(r.stdout)
    why = {s["file"]: s["reason"] for s in doc["skipped"]}
    assert "not a Crazyflie microSD log" in why["lh2_crossingBeam_jitter/log00"]
    assert "not a NumPy .npy array" in why["lh2_kalman_move/mocap00.npy"]
    assert set(doc["sets"]) == {"lh2_kalman_move"}
    data = (root / "lh2_kalman_move" / "log00").read_bytes()
    (bad / "lh2_kalman_move" / "log00").write_bytes(data[:50])                      # header cut short
    r = CliRunner().invoke(main, ["study", "bitcraze-dataset", "--data", str(bad), "--out", str(tmp_path / "o2"),
                                  "--scheduler", "synchronous"])
    lines = [x for x in r.output.splitlines() if x.strip()]
    assert r.exit_code == 2 and lines[-1].startswith("error:") and "no log could be read" in lines[-1], r.output
    assert "Traceback" not in r.output


def test_table_with_a_decode_check_that_reproduced_nothing():
    """A decoding check with no reproduced frame (max difference None) is written as '–', not a crash."""
    from layoutkit.studies.bitcraze_dataset import _table

    d = {"firmware_frames": 10, "matched": 0, "matched_share": 0.0, "max_abs_diff_rad": None, "rotations": 0,
         "rotations_per_s": 0.0, "repeats_dropped": 0}
    res = {"sets": {}, "skipped": [], "logs": [{"log": "x/log00", "decode": {"status": "ok", "firmware": d, "phase": d,
                                                                            "clock": {"rate_ppm": -10940.0}}}]}
    assert "| x/log00 | 10 | 0 / 0 | – |" in _table(res)


def test_stations_refined_once_per_setup_from_its_static_logs(tmp_path):
    """One set-up (two sets sharing one system-config.yaml whose station 1 is 40 mm and 0.6 deg off the
    simulated truth): the study refines the stations once from the three static logs (the deck at rest in
    three places) and replays every log with them. Proof against the simulator's truth: the refined
    station 1 is back within 5 mm / 0.1 deg of the true one; with the system config's stations every
    static window is high_residual (no ok pose) and the moving log keeps < 50 % of its 100 ms intervals,
    with the refined ones the moving log (not used by the refinement) is ok in >= 80 % of them and
    within 3 mm RMS of the motion capture; the table says which stations each set-up used."""
    import yaml

    from layoutkit.io.systemconfig import system_config_dict
    from layoutkit.lighthouse import Station
    from _cf_joint_sim import TARGET

    rng = np.random.default_rng(11)
    root = tmp_path / "data"
    places = [TARGET + d for d in ([0, 0, 0], [0.35, -0.2, 0.1], [-0.3, 0.25, -0.1])]
    for k, c in enumerate(places):
        sim = _make(root / "lh2_crossingBeam_jitter", rng, mode="crossing_beam", motion=static_motion(c=c),
                    duration=1.5, fw="cb", name=f"log0{k}", setup_seed=5)
    _make(root / "lh2_crossingBeam_move", rng, mode="crossing_beam", motion=flying_motion(0.5), duration=3.0,
          fw="cb", setup_seed=5)
    s0, s1 = sim["stations"]
    off = Station(id=s1.id, rotation=rotvec_to_matrix([0.0, np.radians(0.6), 0.0]) @ s1.rotation,
                  translation=s1.translation + [0.03, -0.02, 0.0173], kind=s1.kind, calibration=s1.calibration)
    text = yaml.safe_dump(system_config_dict({0: s0, 1: off}, sim["cals"], system_type=2))
    for d in ("lh2_crossingBeam_jitter", "lh2_crossingBeam_move"):
        (root / d / "system-config.yaml").write_text(text)
    res = run_study(root, methods=("joint", "joint-config"), work_dir=tmp_path / "out")
    (key, g), = res["setups"].items()
    assert g["refinement"]["applied"], g["refinement"]
    assert len(g["refinement"]["logs"]) == 3 and (tmp_path / "out" / "stations" / f"{key}.json").is_file()
    from layoutkit.io.stations import read_stations
    from layoutkit.geometry import matrix_to_rotvec

    r1 = read_stations(g["refinement"]["stations_file"])[1]
    assert np.linalg.norm(r1.translation - s1.translation) < 5e-3
    assert np.degrees(np.linalg.norm(matrix_to_rotvec(r1.rotation @ s1.rotation.T))) < 0.1
    st = res["sets"]["lh2_crossingBeam_jitter"]["methods"]
    assert st["ours_joint"]["coverage_min"] == 1.0 and not st["ours_joint_config"]["per_s_median"]
    mv = res["sets"]["lh2_crossingBeam_move"]["methods"]
    assert mv["ours_joint"]["coverage_median"] >= 0.8 and mv["ours_joint_config"]["coverage_median"] < 0.5, mv
    assert mv["ours_joint"]["error_rms_m"] < 3e-3
    paths = write_outputs(res, tmp_path / "out")
    table = open(paths["table"]).read()
    assert "## Station set-ups" in table and f"| {key} |" in table and "system config stations" in table
    assert str(root) not in open(paths["results"]).read()           # logs named relative to the data folder
