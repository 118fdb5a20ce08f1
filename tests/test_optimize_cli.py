"""`layoutkit optimize` end to end on the bundled Chen target (small envelope, fast method)."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from layoutkit.cli import main
from layoutkit.layout import load_layout
from layoutkit.mesh import load_mesh, mesh_hash
from layoutkit.optimize import METHODS

REPO = Path(__file__).resolve().parents[1]
MESH = str(REPO / "models" / "chen_target.stl")



def test_cli_choices_come_from_registry():
    """The --method choices offered by the command are the method registry (no copied list)."""
    opt = next(p for p in main.commands["optimize"].params if p.name == "method")
    assert tuple(opt.type.choices) == tuple(sorted(METHODS))


def test_optimize_writes_layout_with_metadata(tmp_path, small_envelope):
    """Layout JSON round-trips; its metadata carries the mesh hash, objective, value >= bound."""
    out = tmp_path / "lay.json"
    r = CliRunner().invoke(main, ["optimize", MESH, "-k", "12", "--envelope", small_envelope, "--out", str(out),
                                  "--report", str(tmp_path / "rep"), "--method", "greedy", "--spacing-mm", "12",
                                  "--no-render", "--json", "--dense-poses", "0"])
    assert r.exit_code == 0, r.output
    s = json.loads(r.stdout)
    lay = load_layout(out)
    assert lay.n == 12
    assert lay.metadata["mesh_sha256"] == mesh_hash(load_mesh(MESH))
    assert lay.metadata["objective"] == "worst-adop"
    assert lay.metadata["value"] >= lay.metadata["bound"] > 0
    assert s["stats"]["adop_deg_per_rad"]["max"] == pytest.approx(s["value"], rel=1e-12)
    assert (tmp_path / "rep" / "dop_over_envelope.png").is_file()
    assert (tmp_path / "rep" / "summary.json").is_file()


def test_impossible_request_message(tmp_path, small_envelope):
    """Too few sensors: exit 1 with the smallest k named."""
    r = CliRunner().invoke(main, ["optimize", MESH, "-k", "3", "--envelope", small_envelope, "--out",
                                  str(tmp_path / "x.json"), "--spacing-mm", "12", "--dense-poses", "0"])
    assert r.exit_code == 1
    assert "infeasible: 3 sensors cannot keep 4 lit at every required pose: the smallest k that works is" in r.output
    assert not (tmp_path / "x.json").exists()


def test_bad_objective_is_a_clear_error(tmp_path, small_envelope):
    r = CliRunner().invoke(main, ["optimize", MESH, "-k", "8", "--envelope", small_envelope, "--out",
                                  str(tmp_path / "x.json"), "--objective", "best-adop"])
    assert r.exit_code == 2
    assert "error: objective: expected '<worst|mean|pNN>-<adop|pdop|weighted>'" in r.output
    assert "Traceback" not in r.output
