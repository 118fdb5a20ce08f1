"""Bad input gives a clear message or an honest status, never a silent wrong result (issue 14,
items 7, 8, 9). Regression tests through the real CLI: each input below used to run silently
(or with a numpy traceback); the exact error/warning line is checked.
"""
from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from layoutkit.cli import main

REPO = Path(__file__).resolve().parents[1]
LAYOUT = REPO / "models" / "chen_target.layout.json"
MESH = str(REPO / "models" / "chen_target.stl")


def _run(args):
    return CliRunner().invoke(main, [str(a) for a in args])


def _layout_with(tmp_path, edit):
    d = json.loads(LAYOUT.read_text())
    edit(d)
    p = tmp_path / "l.json"
    p.write_text(json.dumps(d))
    return p


# ---------------------------------------------------------------- item 7: units vs numbers
def test_layout_in_metres_labelled_mm_is_refused(tmp_path):
    """Metres labelled mm gave ADOP 2.5 M and 2.4 m pose errors with status ok; now one error line
    naming the file, the span and --allow-odd-size, which lets it through with a warning."""
    p = _layout_with(tmp_path, lambda d: d.update(units="mm"))
    r = _run(["dop", "--layout", p])
    assert r.exit_code == 2
    assert r.output.startswith(f"error: {p}: layout: the sensors span 0.000125 m read as 'mm'")
    assert "--allow-odd-size" in r.output and "Traceback" not in r.output
    r = _run(["dop", "--layout", p, "--allow-odd-size", "--lit", "all"])
    assert r.exit_code == 0 and "warning:" in r.output


@pytest.mark.parametrize("cmd", [
    ["simulate", "--layout", "{p}", "--frames", "5", "--out", "{d}/f.csv"],
    ["fake-fpga", "--layout", "{p}", "--out", "{d}/c.lkcap", "--duration", "0.1"],
])
def test_every_command_taking_a_layout_checks_its_size(tmp_path, cmd):
    p = _layout_with(tmp_path, lambda d: d.update(units="mm"))
    r = _run([c.format(p=p, d=tmp_path) for c in cmd])
    assert r.exit_code == 2 and "read as 'mm'" in r.output and "--allow-odd-size" in r.output
    assert not list(tmp_path.glob("f.csv")) and not list(tmp_path.glob("c.lkcap"))


def test_candidates_on_a_mesh_at_the_wrong_scale_is_refused(tmp_path):
    """`candidates` on a metre mesh read as mm wrote 399,544 sites; now it stops like optimize."""
    out = tmp_path / "c.json"
    r = _run(["candidates", MESH, "--units", "mm", "--spacing-mm", "6", "--out", out])
    assert r.exit_code == 2 and "largest extent is 0.125 mm" in r.output and "--allow-odd-size" in r.output
    assert not out.exists()
    r = _run(["candidates", MESH, "--units", "mm", "--spacing-mm", "6", "--out", out, "--allow-odd-size"])
    assert r.exit_code == 0 and out.exists()


# ---------------------------------------------------------------- item 8: dop, envelope, objective
def test_dop_with_three_lit_is_underdetermined():
    """3 lit sensors: a finite DOP, but the pose is not unique (P3P) — it used to say ok."""
    r = _run(["dop", "--layout", LAYOUT, "--lit", "T1,T2,T3"])
    assert r.exit_code == 1 and "error: underdetermined: 3 lit sensors" in r.output
    r = _run(["dop", "--layout", LAYOUT, "--lit", "T1,T2,T3", "--json"])
    assert r.exit_code == 1 and json.loads(r.stdout)["status"] == "underdetermined"
    assert _run(["dop", "--layout", LAYOUT, "--lit", "T1,T2,T3,C1"]).exit_code == 0


def test_dop_nan_rotvec_is_an_error():
    r = _run(["dop", "--layout", LAYOUT, "--rotvec-deg", "nan", "0", "0"])
    assert r.exit_code == 2 and r.output.startswith("error: Invalid value for '--rotvec-deg': 'nan' is not a finite number")
    assert "Traceback" not in r.output


@pytest.mark.parametrize("toml, message", [
    ("", "envelope: the file sets nothing (empty)"),
    ("# only a comment\n", "envelope: the file sets nothing (empty)"),
    ('range_m = [1.0, 2.0]\n[[station]]\nfov_deg = 0\n', "station 0.fov_deg: expected a full field of view in (0, 180]"),
])
def test_envelope_that_would_run_silently_wrong_is_refused(tmp_path, toml, message):
    p = tmp_path / "e.toml"
    p.write_text(toml)
    r = _run(["visibility", MESH, "--layout", LAYOUT, "--envelope", p])
    assert r.exit_code == 2 and f"error: {p}: {message}" in r.output, r.output


def test_worst_weighted_needs_weights(tmp_path, small_envelope):
    """`worst-weighted` without --weights silently ran as worst-adop-like (1, 1) weights."""
    r = _run(["optimize", MESH, "--sensors", "4", "--envelope", small_envelope, "--objective", "worst-weighted",
              "--out", tmp_path / "l.json", "--no-render"])
    assert r.exit_code == 2 and "error: --objective worst-weighted: needs --weights A,B" in r.output
    assert not (tmp_path / "l.json").exists()


# ---------------------------------------------------------------- item 9: layout JSON
@pytest.mark.parametrize("edit, message", [
    (lambda d: d["sensors"][2].update(position=[0.01, 0.02]),
     "layout sensor 2 (id 'T3'): 'position': expected 3 numbers [x, y, z], got 2: [0.01, 0.02]"),
    (lambda d: d["sensors"][5].update(position=d["sensors"][1]["position"]),
     "layout sensors 1 (id 'T2') and 5 (id 'C2') have the same position"),
])
def test_layout_errors(tmp_path, edit, message):
    """A 2-number position gave numpy's 'inhomogeneous shape'; duplicate positions passed."""
    p = _layout_with(tmp_path, edit)
    r = _run(["dop", "--layout", p])
    assert r.exit_code == 2 and r.output.startswith(f"error: {p}: {message}"), r.output
    assert "inhomogeneous" not in r.output


def test_layout_warnings_missing_id_and_unknown_keys(tmp_path):
    """A missing id (became "0") and unknown per-sensor keys (typos) passed silently: one warning
    line each; extra top-level keys are metadata and pass."""
    def edit(d):
        del d["sensors"][0]["id"]
        d["sensors"][1]["normals"] = d["sensors"][1]["normal"]
        d["colour"] = "red"
        d["x-mine"] = 1  # the user's own key: no warning
    p = _layout_with(tmp_path, edit)
    r = _run(["dop", "--layout", p, "--lit", "all"])
    assert r.exit_code == 0
    warn = [ln for ln in r.output.splitlines() if ln.startswith("warning:")]
    assert f"warning: {p}: layout sensor 0: no 'id'; named '0' after its index" in warn
    assert any("layout sensor 1 (id 'T2'): unknown key 'normals'" in w for w in warn)
    assert not any("colour" in w for w in warn)  # top-level keys are open metadata (importers add theirs)
    assert len(warn) == 2
