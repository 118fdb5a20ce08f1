"""Core CLI: outputs equal the library on the same inputs; bad input gives a clear message."""
import json

import numpy as np
import pytest
from click.testing import CliRunner

from layoutkit.cli import main
from layoutkit.dop import pose_dop
from layoutkit.geometry import rotvec_to_matrix
from layoutkit.layout import save_layout
from layoutkit.shapes import chen_target


@pytest.fixture
def chen_layout(tmp_path):
    p = tmp_path / "chen.json"
    save_layout(chen_target()[1], p)
    return p


def test_dop_json_equals_library(chen_layout):
    """`layoutkit dop --lit all --json` == pose_dop on the same pose (deg → rad at the edge)."""
    r = CliRunner().invoke(main, ["dop", "--layout", str(chen_layout), "--rotvec-deg", "10", "-20", "5",
                                  "--translation-m", "0.1", "0.2", "2.5", "--lit", "all", "--rho", "0.5", "--json"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    ref = pose_dop(chen_target()[1].positions, rotvec_to_matrix(np.radians([10, -20, 5])), [0.1, 0.2, 2.5], rho=0.5)
    assert out["adop_deg_per_rad"] == pytest.approx(float(ref.adop), rel=1e-12)
    assert out["pdop_m_per_rad"] == pytest.approx(float(ref.pdop), rel=1e-12)
    assert out["n_lit"] == 12


def test_simulate_then_solve_recovers_truth_noise_free(chen_layout, tmp_path):
    """Round trip through the frame file: with zero noise and no quantisation the solve is exact."""
    f = tmp_path / "frames.csv"
    r = CliRunner().invoke(main, ["simulate", "--layout", str(chen_layout), "--frames", "50", "--seed", "3",
                                  "--sigma-arcsec", "0", "--no-quantize", "--out", str(f)])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, ["solve", str(f), "--layout", str(chen_layout), "--sigma-arcsec", "0", "--json"])
    assert r.exit_code == 0, r.output  # noise-free frames: told so, no two poses tie (no 'ambiguous')
    out = json.loads(r.stdout)
    assert out["solved"] == 50
    assert out["rms_rot_deg"] < 1e-6 and out["rms_trans_m"] < 1e-8


@pytest.mark.parametrize("content, message", [
    ("not json", "not valid JSON"),
    ('{"units": "m", "sensors": []}', "'sensors' must be a non-empty list"),
])
def test_bad_layout_clear_message_no_traceback(tmp_path, content, message):
    p = tmp_path / "bad.json"
    p.write_text(content)
    r = CliRunner().invoke(main, ["dop", "--layout", str(p)])
    assert r.exit_code == 2
    assert message in r.output and "Traceback" not in r.output


def test_unknown_sensor_id_message(chen_layout):
    r = CliRunner().invoke(main, ["dop", "--layout", str(chen_layout), "--lit", "T1,ZZ"])
    assert r.exit_code == 2 and "--lit: unknown sensor ids ['ZZ']" in r.output


def test_frame_file_with_foreign_ids(chen_layout, tmp_path):
    f = tmp_path / "f.csv"
    f.write_text("t,th_x_Q9,th_y_Q9\n0,1.5,1.5\n")
    r = CliRunner().invoke(main, ["solve", str(f), "--layout", str(chen_layout)])
    assert r.exit_code == 2 and "sensor id(s) ['Q9'] (columns th_x_Q9, ...) are not in the layout" in r.output
