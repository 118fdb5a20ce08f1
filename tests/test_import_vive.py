"""`layoutkit import vive-config`: a device calibration JSON in the real format (written from a
layout by the test) → layout JSON; round trip exact; malformed files give one clear error.
The real format's field names are checked against the CONFIG line of a real recording."""
import gzip
import json

import numpy as np
from click.testing import CliRunner

from layoutkit.cli import main
from layoutkit.importers.vive import config_from_layout
from layoutkit.layout import load_layout
from layoutkit.shapes import chen_target


def test_round_trip(tmp_path):
    lay = chen_target()[1]
    cfg = config_from_layout(lay, device_class="tracker", model_number="Test Tracker")
    f = tmp_path / "dev.json"
    f.write_text(json.dumps(cfg))
    out = tmp_path / "layout.json"
    r = CliRunner().invoke(main, ["import", "vive-config", str(f), "--out", str(out), "--json"])
    assert r.exit_code == 0, r.output
    back = load_layout(out)
    np.testing.assert_allclose(back.positions, lay.positions, atol=1e-15)
    np.testing.assert_allclose(back.normals, lay.normals, atol=1e-12)
    assert back.ids == tuple(str(i) for i in range(lay.n))
    assert back.metadata["device_class"] == "tracker" and json.loads(r.stdout)["sensors"] == lay.n


def test_real_config_line(libsurvive_dir, tmp_path):
    """The HMD CONFIG JSON of the real recording imports as a 32-sensor layout with unit normals."""
    with gzip.open(libsurvive_dir / "lh1_test_cal_first4s.rec.gz", "rt") as fh:
        line = next(x for x in fh if " HMD CONFIG " in x)
    f = tmp_path / "hmd.json"
    f.write_text(line.split(" CONFIG ", 1)[1])
    r = CliRunner().invoke(main, ["import", "vive-config", str(f), "--out", str(tmp_path / "hmd_layout.json")])
    assert r.exit_code == 0, r.output
    lay = load_layout(tmp_path / "hmd_layout.json")
    assert lay.n == 32 and lay.metadata["device_class"] == "hmd"
    assert np.ptp(lay.positions, 0).max() < 0.3  # metres: an HMD is ~0.2 m wide


def test_bad_config_clear_error(tmp_path):
    f = tmp_path / "bad.json"
    f.write_text(json.dumps({"lighthouse_config": {"modelPoints": [[0, 0]], "modelNormals": [[0, 0, 1]]}}))
    r = CliRunner().invoke(main, ["import", "vive-config", str(f), "--out", str(tmp_path / "o.json")])
    assert r.exit_code == 2 and "modelPoints: expected n × 3" in r.output and "Traceback" not in r.output
    f.write_text("{}")
    r = CliRunner().invoke(main, ["import", "vive-config", str(f), "--out", str(tmp_path / "o.json")])
    assert r.exit_code == 2 and "no 'lighthouse_config'" in r.output
