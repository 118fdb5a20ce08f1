"""Fresh-eyes usability pass: bad input ends with one clear ``error: ...`` line and a non-zero
exit, never a traceback (regressions for the rough edges found following the README tour)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest
from click.testing import CliRunner

from layoutkit.cli import main

REPO = Path(__file__).resolve().parents[1]
MESH = str(REPO / "models" / "chen_target.stl")
LAYOUT = str(REPO / "models" / "chen_target.layout.json")


def _run(args):
    r = CliRunner().invoke(main, [str(a) for a in args])
    assert "Traceback" not in r.output
    assert not isinstance(r.exception, Exception) or isinstance(r.exception, SystemExit), r.exception
    return r


def _error_lines(r):
    return [ln for ln in r.output.splitlines() if ln.startswith("error: ")]


@pytest.fixture(scope="module")
def frames_csv(tmp_path_factory):
    path = tmp_path_factory.mktemp("frames") / "frames.csv"
    r = _run(["simulate", "--layout", LAYOUT, "--frames", "20", "--out", path])
    assert r.exit_code == 0, r.output
    return path


def _edit_cell(src, dst, line, col, value):
    lines = src.read_text().splitlines()
    cells = lines[line].split(",")
    cells[col] = value
    lines[line] = ",".join(cells)
    dst.write_text("\n".join(lines) + "\n")
    return dst


# --- output into a folder that does not exist: an error line, not a FileNotFoundError traceback


def test_simulate_out_in_missing_folder(tmp_path):
    out = tmp_path / "nodir" / "f.csv"
    r = _run(["simulate", "--layout", LAYOUT, "--frames", "5", "--out", out])
    assert r.exit_code == 2
    assert _error_lines(r) == [f"error: {out}: No such file or directory"]


def test_solve_out_in_missing_folder(tmp_path, frames_csv):
    out = tmp_path / "nodir" / "p.csv"
    r = _run(["solve", frames_csv, "--layout", LAYOUT, "--out", out])
    assert r.exit_code == 2
    assert _error_lines(r) == [f"error: {out}: No such file or directory"]


def test_candidates_out_in_missing_folder(tmp_path):
    out = tmp_path / "nodir" / "c.json"
    r = _run(["candidates", MESH, "--spacing-mm", "30", "--out", out])
    assert r.exit_code == 2
    assert _error_lines(r) == [f"error: {out}: No such file or directory"]


# --- frame files: NaN / inf / text / wrong shape are named with the file and the frame or line


def test_nan_time_in_frames_csv(tmp_path, frames_csv):
    bad = _edit_cell(frames_csv, tmp_path / "nan_t.csv", 3, 0, "nan")
    r = _run(["solve", bad, "--layout", LAYOUT])
    assert r.exit_code == 2
    assert _error_lines(r) == [f"error: {bad}: frame 2 (line 4), column 't': time is empty, NaN or infinite"]


def test_nan_truth_in_frames_csv(tmp_path, frames_csv):
    bad = _edit_cell(frames_csv, tmp_path / "nan_truth.csv", 2, -1, "nan")
    r = _run(["solve", bad, "--layout", LAYOUT])
    assert r.exit_code == 2
    assert _error_lines(r) == [f"error: {bad}: frame 1 (line 3): truth translation is empty, NaN or infinite"]


def test_nan_angle_means_not_lit(tmp_path, frames_csv):
    """NaN in an angle column is documented as 'not lit': still solved."""
    ok = _edit_cell(frames_csv, tmp_path / "nan_angle.csv", 1, 1, "nan")
    r = _run(["solve", ok, "--layout", LAYOUT])
    assert r.exit_code == 0, r.output
    assert "solved 20 / 20 frames" in r.output


def test_inf_angle_in_frames_csv(tmp_path, frames_csv):
    """An infinite angle is a frame status (invalid angle), not a lost batch (issue 10)."""
    bad = _edit_cell(frames_csv, tmp_path / "inf.csv", 2, 1, "inf")
    r = _run(["solve", bad, "--layout", LAYOUT])
    assert r.exit_code == 0, r.output
    assert "solved 19 / 20 frames" in r.output and "invalid angle" in r.output


def test_text_in_frames_csv(tmp_path, frames_csv):
    bad = _edit_cell(frames_csv, tmp_path / "abc.csv", 4, 2, "abc")
    r = _run(["solve", bad, "--layout", LAYOUT])
    assert r.exit_code == 2
    assert _error_lines(r) == [f"error: {bad}: line 5, column 'th_y_T1': 'abc' is not a number"]


def test_short_row_in_frames_csv(tmp_path, frames_csv):
    bad = tmp_path / "short.csv"
    bad.write_text("\n".join(frames_csv.read_text().splitlines()[:3] + ["0.5,1.0"]) + "\n")
    r = _run(["solve", bad, "--layout", LAYOUT])
    assert r.exit_code == 2
    n = len(frames_csv.read_text().splitlines()[0].split(","))
    assert _error_lines(r) == [f"error: {bad}: line 4: 2 fields, the header has {n}"]


def test_header_only_frames_csv(tmp_path, frames_csv):
    bad = tmp_path / "empty.csv"
    bad.write_text(frames_csv.read_text().splitlines()[0] + "\n")
    r = _run(["solve", bad, "--layout", LAYOUT])
    assert r.exit_code == 2
    assert _error_lines(r) == [f"error: {bad}: no frames"]


def test_binary_frames_csv(tmp_path):
    bad = tmp_path / "bin.csv"
    bad.write_bytes(b"t,\xff\xfe\x80" + os.urandom(200))
    r = _run(["solve", bad, "--layout", LAYOUT])
    assert r.exit_code == 2
    assert _error_lines(r) == [f"error: {bad}: not a text (CSV) frame file"]


def test_corrupt_npz_frames(tmp_path):
    bad = tmp_path / "c.npz"
    bad.write_bytes(os.urandom(3000))
    r = _run(["solve", bad, "--layout", LAYOUT])
    assert r.exit_code == 2
    assert _error_lines(r) == [f"error: {bad}: not a readable .npz frame file"]


def test_npz_missing_array(tmp_path):
    import numpy as np

    bad = tmp_path / "m.npz"
    np.savez(bad, t=np.zeros(3))
    r = _run(["solve", bad, "--layout", LAYOUT])
    assert r.exit_code == 2
    assert _error_lines(r) == [f"error: {bad}: frame .npz lacks array(s) angles, ids; expected t, angles, ids"]


# --- replay of something that is not a capture


def test_replay_random_bytes(tmp_path):
    cap = tmp_path / "corrupt.lkcap"
    cap.write_bytes(os.urandom(5000))
    r = _run(["replay", cap, "--layout", LAYOUT])
    assert r.exit_code == 2
    assert _error_lines(r) == [f"error: {cap}: no valid layoutkit frame in 5000 byte(s); not a capture file, "
                               "or recorded with another --protocol?"]


def test_replay_empty_capture(tmp_path):
    cap = tmp_path / "empty.lkcap"
    cap.write_bytes(b"")
    r = _run(["replay", cap, "--layout", LAYOUT])
    assert r.exit_code == 2
    assert _error_lines(r) == [f"error: {cap}: empty capture (0 bytes)"]


# --- dop at a pose where the layout faces away


def test_dop_undefined_is_an_error_line():
    r = _run(["dop", "--layout", LAYOUT, "--rotvec-deg", "0", "0", "0"])
    assert r.exit_code == 1
    assert _error_lines(r) == ["error: DOP undefined at this pose: fewer than 3 sensors lit; the body may face away "
                               "from the station (try another --rotvec-deg, or --lit all) (lit: none)"]


# --- optimize: impossible request and a wrong-unit mesh



def test_optimize_infeasible_is_an_error_line(tmp_path, small_envelope):
    r = _run(["optimize", MESH, "--sensors", "3", "--envelope", small_envelope, "--out", tmp_path / "x.json",
              "--spacing-mm", "12", "--no-render"])
    assert r.exit_code == 1
    lines = _error_lines(r)
    assert len(lines) == 1
    assert lines[0].startswith("error: infeasible: 3 sensors cannot keep 4 lit at every required pose")


def test_optimize_wrong_units_warns_in_one_line(tmp_path, small_envelope):
    r = _run(["optimize", MESH, "--sensors", "12", "--envelope", small_envelope, "--out", tmp_path / "x.json",
              "--units", "mm", "--spacing-mm", "20", "--no-render", "--allow-odd-size"])
    assert r.exit_code == 2
    assert (f"warning: {MESH}: largest extent is 0.125 mm with units='mm'; if the file is in metres pass units='m'"
            in r.output.splitlines())
    assert "MeshWarning" not in r.output and "load_mesh(" not in r.output
    assert _error_lines(r) == ["error: k: expected 1 <= k <= 1 (number of candidates), got 12"]


@pytest.mark.slow
def test_optimize_summary_starts_on_first_line(tmp_path, small_envelope):
    """The progress bar goes to stderr: stdout is the summary alone (no stray blank first line)."""
    r = CliRunner().invoke(main, ["optimize", MESH, "--sensors", "12", "--envelope", small_envelope,
                                  "--out", str(tmp_path / "x.json"), "--spacing-mm", "12", "--no-render",
                                  "--dense-poses", "0", "--method", "greedy"])
    assert r.exit_code == 0, r.output
    assert r.stdout.splitlines()[0].startswith("12 of ")


def test_optimize_refuses_a_mesh_at_the_wrong_scale(tmp_path):
    """A metre model read as millimetres (0.125 mm target) used to run for minutes of badly scaled
    conic solves; it now stops at once with the unit hint."""
    r = _run(["optimize", MESH, "--sensors", "12", "--envelope",
              str(REPO / "models" / "chen_envelope.toml"), "--out", str(tmp_path / "l.json"), "--no-render", "--units", "mm"])
    assert r.exit_code == 2
    assert "largest extent is 0.125 mm" in r.output and "--allow-odd-size" in r.output
    assert "Traceback" not in r.output


def test_replay_motion_compensation_flag(tmp_path):
    """--motion-compensation reaches the pipeline: a fast spin (20 deg/s about the line of sight,
    trajectory CSV through fake-fpga) biases the uncompensated solve; compensated, the RMS error
    is back at the DOP prediction (Monte-Carlo error of ~600 frames ≈ 3 %)."""
    import json

    import numpy as np
    from scipy.spatial.transform import Rotation

    tt = np.arange(0, 10.01, 0.01)
    rot = Rotation.from_rotvec(np.outer(np.radians(20.0) * tt, [0, 0, 1])) * Rotation.from_rotvec([np.pi, 0, 0])
    traj = tmp_path / "spin.csv"
    rows = np.column_stack([tt, rot.as_rotvec(), np.tile([0.1, 0.1, 2.0], (len(tt), 1))])
    np.savetxt(traj, rows, delimiter=",", header="t,rx,ry,rz,tx,ty,tz", comments="")
    cap, truth = tmp_path / "c.lkcap", tmp_path / "t.csv"
    r = _run(["fake-fpga", "--layout", LAYOUT, "--out", cap, "--truth", truth, "--duration", "10", "--seed", "2",
              "--motion", traj])
    assert r.exit_code == 0, r.output
    out = {}
    for flag in ([], ["--motion-compensation"]):
        r = _run(["replay", cap, "--layout", LAYOUT, "--truth", truth, "--json", *flag])
        assert r.exit_code == 0, r.output
        out[bool(flag)] = json.loads(r.stdout)["truth"]
    assert out[False]["ratio_rot"] > 1.2
    assert abs(out[True]["ratio_rot"] - 1) < 0.1


def test_live_on_a_port_that_never_opens():
    """A missing device used to wait silently and exit 0; now it exits 2 saying the port never opened."""
    r = _run(["live", "--port", "/dev/nonexistent-layoutkit", "--layout", LAYOUT, "--duration", "1", "--no-dashboard"])
    assert r.exit_code == 2
    assert "error: /dev/nonexistent-layoutkit: the port never opened" in r.output
