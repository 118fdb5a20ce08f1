"""THE FRAME TABLE (layoutkit.io.frames) and `solve` on bad frames.

Proof kinds: round trips (write → read, exact); malformed files must give a ValueError naming file
and column (never KeyError); a frame file with NaN rows, 3-lit rows and out-of-range angles must
solve with statuses by reason (exit 0) while the good frames stay exact (noise-free closed form).
"""
import json

import numpy as np
import pytest
from click.testing import CliRunner

from layoutkit.cli import main
from layoutkit.geometry import random_rotations, transform_points
from layoutkit.io.frames import Frames, read_frame_table, write_frame_table
from layoutkit.layout import load_layout, save_layout
from layoutkit.lighthouse import sweep_angles
from layoutkit.pnp import STATUS_INVALID_ANGLE, STATUS_NO_START, STATUS_OK, STATUS_TOO_FEW, solve_pnp
from layoutkit.shapes import chen_target


@pytest.fixture
def chen_layout(tmp_path):
    p = tmp_path / "chen.json"
    save_layout(chen_target()[1], p)
    return p


def _frames(lay, F, rng, station=None):
    R = random_rotations(F, rng) @ np.diag([1.0, -1.0, -1.0])
    t = np.column_stack([rng.uniform(-0.3, 0.3, F), rng.uniform(-0.3, 0.3, F), rng.uniform(1.5, 2.5, F)])
    ang = sweep_angles(transform_points(R, t, lay.positions))
    return Frames(np.arange(F) / 60.0, ang, lay.ids, R, t, station)


@pytest.mark.parametrize("suffix", [".csv", ".npz"])
def test_round_trip_with_station_and_one_axis(chen_layout, tmp_path, rng, suffix):
    """Exact round trip; a sensor seen on one axis keeps that axis (one empty cell, not a dropped sensor)."""
    lay = load_layout(chen_layout)
    fr = _frames(lay, 7, rng, station=np.array([0, 1, 0, 1, 1, 0, 2]))
    ang = fr.angles.copy()
    ang[2, 3, 1] = np.nan
    ang[4, :, :] = np.nan
    fr = Frames(fr.t, ang, fr.ids, fr.truth_rotation, fr.truth_translation, fr.station)
    p = tmp_path / f"f{suffix}"
    write_frame_table(fr, p)
    back = read_frame_table(p, lay.ids)
    np.testing.assert_array_equal(back.station, fr.station)
    np.testing.assert_array_equal(np.isnan(back.angles), np.isnan(ang))
    np.testing.assert_allclose(back.angles, ang, rtol=0, atol=1e-15)
    assert not np.isnan(back.angles[2, 3, 0])
    np.testing.assert_allclose(back.truth_translation, fr.truth_translation, atol=1e-15)


@pytest.mark.parametrize("text, needle", [
    ("time,th_x_T1,th_y_T1\n0,1,1\n", "first column is 'time', expected 't' (renamed?"),
    ("t,th_x_T1\n0,1\n", "column 'th_y_T1' is missing (column 'th_x_T1' is present"),
    ("t,th_x_T1,th_y_T1,theta_x_T2\n0,1,1,1\n", "unknown column(s) ['theta_x_T2']"),
    ("t,th_x_T1,th_y_T1\n0,1,abc\n", "line 2, column 'th_y_T1': 'abc' is not a number"),
    ("t,th_x_T1,th_y_T1\n0,1\n", "line 2: 2 fields, the header has 3"),
    ("t,station,th_x_T1,th_y_T1\n0,1.5,1,1\n", "column 'station': 1.5 is not a station index"),
    ("t,th_x_T1,th_y_T1,true_rx\n0,1,1,0\n", "truth column(s)"),
    ("", "empty file"),
])
def test_malformed_frame_tables_name_file_and_column(chen_layout, tmp_path, text, needle):
    """Missing / renamed / unknown columns and text cells: one clear error naming the file and column."""
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(ValueError) as e:
        read_frame_table(p, load_layout(chen_layout).ids)
    assert str(p) in str(e.value) and needle in str(e.value)
    r = CliRunner().invoke(main, ["solve", str(p), "--layout", str(chen_layout)])
    assert r.exit_code == 2 and needle in r.output and "Traceback" not in r.output
    assert r.output.count("error:") == 1


def test_solve_bad_rows_statuses_by_reason(chen_layout, tmp_path, rng):
    """NaN rows, 3-lit rows, 2-lit rows, inf, 100 rad and degree-valued angles: exit 0, each frame its
    status and reason, the good frames exact (noise-free), a pose table with residual_rms."""
    lay = load_layout(chen_layout)
    F = 40
    fr = _frames(lay, F, rng)
    vis = np.ones((F, lay.n), bool)
    ang = fr.angles.copy()
    # keep only sensors in front (a body rotated at random hides half of them; the solver needs no
    # visibility model here — all angles of a noise-free pose are consistent)
    ang[0] = np.nan                        # NaN row
    ang[1, 3:] = np.nan                    # 3 lit on both axes
    ang[2, 2:] = np.nan                    # 2 lit
    ang[3, 0, 0] = np.inf                  # inf
    ang[4, 1, 1] = 100.0                   # 100 rad
    ang[5] = np.degrees(ang[5])            # degrees
    ang[6, :, 1] = np.nan                  # x only: 12 angles, no y at all
    ang[6, :3, 1] = fr.angles[6, :3, 1]
    del vis
    p = tmp_path / "bad_rows.csv"
    write_frame_table(Frames(fr.t, ang, lay.ids), p)
    out = tmp_path / "poses.csv"
    r = CliRunner().invoke(main, ["solve", str(p), "--layout", str(chen_layout), "--json", "--out", str(out)])
    assert r.exit_code == 0, r.output
    s = json.loads(r.stdout)
    assert s["status_counts"][str(STATUS_TOO_FEW)] == 2            # NaN row, 2 lit
    assert s["status_counts"][str(STATUS_INVALID_ANGLE)] == 3      # inf, 100 rad, degrees
    assert s["input"]["infinite angles"] == 1 and s["input"]["angles outside (0, pi) rad"] >= 2
    # the 3-lit row and the x-only row meet the minimum rule (>= 6 angles from >= 3 sensors): they
    # are solved from the nearest good frame (a different random pose, so they may not converge)
    assert s["solved"] >= F - 7
    header = out.read_text().splitlines()[0].split(",")
    assert header[:10] == ["t", "station", "status", "rx", "ry", "rz", "tx", "ty", "tz", "residual_rms"]
    rows = [line.split(",") for line in out.read_text().splitlines()[1:]]
    good = [r_ for r_ in rows if r_[2] == str(STATUS_OK)]
    assert max(float(r_[9]) for r_ in good) < 1e-9


def test_solve_all_bad_exits_nonzero_with_reason(chen_layout, tmp_path, rng):
    """A run with no good pose exits 1 and names the most common reason."""
    lay = load_layout(chen_layout)
    fr = _frames(lay, 5, rng)
    ang = fr.angles.copy()
    ang[:, 1:] = np.nan
    p = tmp_path / "one_lit.csv"
    write_frame_table(Frames(fr.t, ang, lay.ids), p)
    r = CliRunner().invoke(main, ["solve", str(p), "--layout", str(chen_layout)])
    assert r.exit_code == 1 and "most common reason: too few angles" in r.output


def test_one_axis_sensors_contribute(chen_layout, rng):
    """Per-angle masks (F, n, 2): with 3 sensors on both axes plus sensors seen on one axis only, the
    solver (from a nearby start) recovers the exact pose; the cold path needs 4 both-axis sensors."""
    lay = load_layout(chen_layout)
    fr = _frames(lay, 20, rng)
    seen = np.zeros((20, lay.n, 2), bool)
    seen[:, :3] = True
    seen[:, 3:6, 0] = True          # x only
    seen[:, 6:9, 1] = True          # y only
    cold = solve_pnp(lay.positions, fr.angles, seen)
    assert (cold.status == STATUS_NO_START).all()
    warm = solve_pnp(lay.positions, fr.angles, seen,
                     initial=(fr.truth_rotation, fr.truth_translation + 0.02))
    assert warm.success.all()
    np.testing.assert_allclose(warm.translation, fr.truth_translation, atol=1e-8)
    # the one-axis angles carry information: the per-angle DOP is below the both-axes-only DOP
    from layoutkit.dop import pose_dop

    d_angle = pose_dop(lay.positions, fr.truth_rotation, fr.truth_translation, visible=seen)
    d_sensor = pose_dop(lay.positions, fr.truth_rotation, fr.truth_translation, visible=seen.all(-1))
    assert d_angle.success.all() and (d_angle.adop < d_sensor.adop).all() and (d_angle.n_visible == 9).all()
