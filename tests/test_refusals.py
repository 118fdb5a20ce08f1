"""Issue 29's findings, each re-run through the real CLI: a command refuses what it cannot honour
(exit 2, one ``error:`` line naming the option or file and field) instead of a traceback, a silent
wrong result or work without end.

Proof kind: regression tests on the exact inputs the QA run found (each one used to trace back,
run forever or exit 0 with garbage); the expected line is checked, and where a run must still
work its output is checked against an independent count.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from layoutkit.cli import main

REPO = Path(__file__).resolve().parents[1]
LAYOUT = REPO / "models" / "chen_target.layout.json"


def _run(args):
    return CliRunner().invoke(main, [str(a) for a in args])


def _layout(tmp_path, keep=None, flip=False):
    d = json.loads(LAYOUT.read_text())
    if keep is not None:
        d["sensors"] = d["sensors"][:keep]
    if flip:  # two sensors face +z, two -z: never 4 within 60 deg of one station direction
        d["sensors"] = d["sensors"][:4]
        for i, s in enumerate(d["sensors"]):
            s["normal"] = [0.0, 0.0, 1.0 if i < 2 else -1.0]
    p = tmp_path / "l.json"
    p.write_text(json.dumps(d))
    return p


@pytest.mark.parametrize("keep, flip, message", [
    (3, False, "the layout has 3 sensors: no pose can light the 4 a frame needs"),
    (None, True, "lights 4 sensors of this layout"),
])
def test_simulate_with_a_layout_that_cannot_light_four_says_so_at_once(tmp_path, keep, flip, message):
    """It used to loop forever (3 sensors); now an error within seconds."""
    t0 = time.perf_counter()
    r = _run(["simulate", "--layout", _layout(tmp_path, keep, flip), "--frames", 10, "--out", tmp_path / "f.csv"])
    assert r.exit_code == 2 and r.output.startswith("error: ") and message in r.output, r.output
    assert time.perf_counter() - t0 < 20
    assert not (tmp_path / "f.csv").exists()


def test_truncated_binary_stl_names_the_cut(tmp_path):
    """A binary STL cut short said "no faces"; the header's triangle count gives the real reason."""
    p = tmp_path / "cut.stl"
    p.write_bytes((REPO / "models" / "chen_target.stl").read_bytes()[:500])
    r = _run(["mesh-info", p])
    assert r.exit_code == 2
    assert r.output.startswith(f"error: {p}: truncated binary STL: the header announces 20 triangles (1084 bytes), "
                               "the file has 500 bytes (8 whole triangles)"), r.output
    assert _run(["mesh-info", REPO / "models" / "chen_target.stl"]).exit_code == 0


def test_envelope_range_in_millimetres_is_refused_naming_file_and_unit(tmp_path, small_envelope):
    """``range_m = [1000, 3000]`` (mm written as m) was scored without a word (PDOP 1.8e7)."""
    p = tmp_path / "env_mm.toml"
    p.write_text(Path(small_envelope).read_text().replace("range_m = [1.0, 2.0]", "range_m = [1000.0, 3000.0]"))
    r = _run(["score", LAYOUT, "--envelope", p, "--json"])
    assert r.exit_code == 2
    assert r.output.startswith(f"error: {p}: range_m [1000.0, 3000.0]: 3000 m is farther than any lighthouse "
                               "reaches (<= 30 m): the numbers are probably millimetres (3 m?)"), r.output
    ok = _run(["score", LAYOUT, "--envelope", p, "--json", "--allow-odd-size"])
    assert ok.exit_code == 0 and "warning:" in ok.output  # let through on request, still said
