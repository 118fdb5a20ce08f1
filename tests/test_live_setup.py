"""A replay's inputs are read once and its configuration is one frozen object (issue 24, item 3).

Proof kinds: (1) the system config is read once — a replay given the loaded object after its file
was deleted writes the same ``poses.csv`` byte for byte as one given the path (anything reading it
again would fail); (2) ``poses.csv`` is written once with the firmware's estimates joined in — its
``firmware_*`` columns equal an independent ``np.interp`` of the log's own estimate rows at the
pose times; (3) a reference comparison needs no pose file — the same errors with and without a
report folder, and nothing written outside it; (4) the capture sidecar records the run
(:meth:`RunSetup.sidecar`) and a replay rebuilds the same run from it.
"""
import json

import numpy as np
import pytest

from layoutkit.io.poses import read_poses
from layoutkit.io.sidecar import CaptureSidecar
from layoutkit.io.systemconfig import read_system_config
from layoutkit.live.pipeline import LiveConfig
from layoutkit.live.session import RunSetup
from layoutkit.shapes import chen_target
from layoutkit.workflows.live import replay_capture

from _cf_events_sim import simulate_events, truth_position, write_event_log


@pytest.fixture(scope="module")
def event_log(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("cflog")
    sim = simulate_events("lh2", duration=2.0, seed=7)
    t = np.arange(12.6, 14.4, 0.01)
    truth = truth_position(sim, t)
    log, yml = write_event_log(sim, tmp, firmware={"estPosition": (t, truth + [0.02, 0.0, 0.0]),
                                                   "fixedFrequency": (t, truth)})
    return log, yml, t, truth


def test_system_config_is_read_once(event_log, tmp_path):
    log, yml, _, _ = event_log
    a = replay_capture(log, system_config=yml, solve="joint", report_dir=tmp_path / "a")
    copy = tmp_path / "sys.yaml"
    copy.write_text(yml.read_text())
    cfg = read_system_config(copy)
    copy.unlink()  # from here on only the object exists
    b = replay_capture(log, system_config=cfg, solve="joint", report_dir=tmp_path / "b")
    assert a["good"] == b["good"] > 50
    assert (tmp_path / "a" / "poses.csv").read_bytes() == (tmp_path / "b" / "poses.csv").read_bytes()


def test_firmware_columns_are_joined_as_the_poses_are_written(event_log, tmp_path):
    log, yml, t_fw, truth = event_log
    s = replay_capture(log, system_config=yml, solve="joint", report_dir=tmp_path / "rep")
    tb = read_poses(tmp_path / "rep" / "poses.csv")
    inside = (tb.t > t_fw[0]) & (tb.t < t_fw[-1])
    assert inside.sum() > 50
    for k, ax in enumerate("xyz"):
        want = np.interp(tb.t[inside], t_fw, truth[:, k] + (0.02 if ax == "x" else 0.0))
        np.testing.assert_allclose(tb.extras[f"firmware_crossing_beam_{ax}"][inside], want, atol=1e-9)
    assert np.all(np.isnan(tb.extras["firmware_crossing_beam_x"][tb.t < t_fw[0]]))
    fw = s["firmware_vs_ours"]["crossing_beam"]
    ok = tb.ok & inside
    d = np.linalg.norm(tb.translation[ok] - np.column_stack(
        [tb.extras[f"firmware_crossing_beam_{ax}"][ok] for ax in "xyz"]), axis=1)
    assert fw["compared_poses"] == ok.sum()
    assert fw["rms_distance_m"] == pytest.approx(np.sqrt(np.mean(d ** 2)), rel=1e-6)


def test_reference_needs_no_pose_file(tmp_path, monkeypatch):
    """A replay with a motion-capture reference and no report folder writes no file; its errors are
    those of the same replay with a report folder."""
    from click.testing import CliRunner

    from layoutkit.cli import main
    from layoutkit.layout import save_layout

    lay = chen_target()[1]
    save_layout(lay, tmp_path / "layout.json")
    cap, truth = tmp_path / "run.lkcap", tmp_path / "TRUTH.csv"
    r = CliRunner().invoke(main, ["fake-fpga", "--layout", str(tmp_path / "layout.json"), "--out", str(cap),
                                  "--truth", str(truth), "--duration", "6", "--seed", "3", "--tumble-rate-deg-s", "20"])
    assert r.exit_code == 0, r.output
    work = tmp_path / "cwd"
    work.mkdir()
    monkeypatch.chdir(work)
    a = replay_capture(cap, lay, reference=truth)
    assert list(work.iterdir()) == []
    b = replay_capture(cap, lay, reference=truth, report_dir=tmp_path / "rep")
    assert a["reference"]["errors"]["n"] == b["reference"]["errors"]["n"] > 100
    for k in ("rms_rot_deg", "rms_trans_m"):
        assert a["reference"]["errors"][k] == pytest.approx(b["reference"]["errors"][k], rel=1e-9)


def test_sidecar_records_the_run_and_replay_rebuilds_it(event_log):
    _, yml, _, _ = event_log
    cfg = read_system_config(yml)
    lay = chen_target()[1]
    setup = RunSetup(lay, "bitcraze-lh2", {"time_offset_s": 1.5}, tuple(cfg.station_list()), cfg,
                     LiveConfig(solve="joint", sigma_theta=5e-5))
    sc = CaptureSidecar.from_dict(json.loads(json.dumps(setup.sidecar(source="live").to_dict())))
    assert sc.protocol_options == {"time_offset_s": 1.5, "system_config": str(yml)}
    assert sc.extra["live_config"]["solve"] == "joint" and sc.extra["live_config"]["sigma_theta"] == 5e-5
    again = RunSetup.from_sidecar(sc, lay)
    assert again.protocol == "bitcraze-lh2" and again.protocol_options == {"time_offset_s": 1.5}
    assert [s.id for s in again.stations] == [s.id for s in setup.stations]
    assert again.system_config.calibs == cfg.calibs
    assert again.config == LiveConfig()  # the recorded settings are a record: the command's own apply
