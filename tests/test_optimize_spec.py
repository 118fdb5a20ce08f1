"""OptimizeSpec / DesignProblem (issue 24 item 1): one validated settings object, one problem loaded once.

Proof kinds: (1) input checks — every bad value is refused naming its field (NaN included), unknown keys
are refused, the dict form round-trips; (2) one source of defaults — the CLI's and the sweep's defaults are
compared with the spec's own (a default changed in one place only fails here); (3) independent
recomputation — the problem's visibility at the design poses (sliced for a selection) equals a fresh
ray-cast of the selected sensors, and ``solve`` equals ``optimize_stations`` called on the same arrays;
(4) provenance round trip — a layout written by ``layoutkit optimize`` is scored and rendered from the
layout alone with the same numbers as with every input given explicitly.
"""
from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from layoutkit.cli import main
from layoutkit.optimize import DenseSpec, DesignProblem, OptimizeSpec, optimize_stations, solve

REPO = Path(__file__).resolve().parents[1]
MESH = str(REPO / "models" / "chen_target.stl")


@pytest.mark.parametrize("field,value,msg", [
    ("k", 0, "k: expected an integer >= 1"),
    ("rho", math.nan, "rho: expected a finite number, got nan"),
    ("rho", 1.0, r"rho: expected a number in \[0.0, 1.0\)"),
    ("coverage_fraction", 0.0, "coverage_fraction: expected a number in"),
    ("min_spacing_m", -0.001, "min_spacing_m: expected a number >= 0.0"),
    ("half_angle_deg", math.inf, "half_angle_deg: expected a finite number"),
    ("max_tilt_deg", 90.0, r"max_tilt_deg: expected a number in \[0.0, 90.0\)"),
    ("time_limit_s", math.nan, "time_limit_s: expected a finite number"),
    ("method", "magic", r"method: expected one of \["),
    ("coverage", "most", "coverage: expected one of any-station"),
    ("objective", "best-adop", "objective: expected '<worst"),
    ("branch_and_bound", "maybe", r"branch_and_bound: expected one of \['auto', 'off'\]"),
    ("tilt_toward", (0, 0, 0), "tilt_toward: expected a non-zero body axis"),
    ("seed", 1.5, "seed: expected an integer"),
])
def test_bad_values_are_refused_naming_the_field(field, value, msg):
    with pytest.raises(ValueError, match=msg):
        OptimizeSpec(**{"k": 4, field: value})


def test_dict_form_round_trips_and_rejects_unknown_keys():
    spec = OptimizeSpec(k=12, weights=(1.0, 2.0), objective="worst-weighted", tilt_toward=(0, 0, 1),
                        max_tilt_deg=20.0, fixed=("c0001",), dense=DenseSpec(poses=500, range_sweep=True))
    d = json.loads(json.dumps(spec.to_dict()))  # through JSON, as in a layout file
    assert OptimizeSpec.from_dict(d) == spec
    with pytest.raises(ValueError, match=r"spec: unknown key\(s\) \['spacing'\]"):
        OptimizeSpec.from_dict({"k": 4, "spacing": 3})
    with pytest.raises(ValueError, match=r"spec: dense: unknown key\(s\) \['pose'\]"):
        OptimizeSpec.from_dict({"k": 4, "dense": {"pose": 3}})
    with pytest.raises(ValueError, match="weights: objective 'worst-weighted' needs weights"):
        OptimizeSpec(k=4, objective="worst-weighted")
    with pytest.raises(ValueError, match="fixed: 3 fixed sensors exceed k = 2"):
        OptimizeSpec(k=2, fixed=("a", "b", "c"))
    assert DenseSpec(poses=300).coverage_count == 1200 and DenseSpec(poses=3, coverage_poses=0).coverage_count == 0


def test_cli_and_sweep_defaults_are_the_specs():
    """The optimize command's option defaults and the sweep's defaults equal the spec's field defaults."""
    from layoutkit.optimize.spec import SPEC_OPTIONS
    from layoutkit.workflows.sweep_config import defaults, options

    spec_defaults = {f.name: f.default for f in dataclasses.fields(OptimizeSpec)}
    cli = {p.name: p.default for p in main.commands["optimize"].params}
    for field, flag, scale in (("objective", "objective", 1), ("rho", "rho", 1), ("method", "method", 1),
                               ("min_visible", "min_visible", 1), ("coverage_fraction", "coverage_fraction", 1),
                               ("coverage", "coverage", 1), ("min_spacing_m", "min_spacing_mm", 1e-3),
                               ("half_angle_deg", "half_angle_deg", 1), ("max_tilt_deg", "max_tilt_deg", 1),
                               ("seed", "seed", 1), ("time_limit_s", "time_limit_s", 1)):
        v = cli[flag]
        assert (v * scale if isinstance(v, float) else v) == spec_defaults[field], field
    assert cli["bnb"] is True and spec_defaults["branch_and_bound"] == "auto"
    sw = defaults()
    for field, so in SPEC_OPTIONS.items():
        if so.sweep and spec_defaults[field] not in (None, dataclasses.MISSING):
            v = sw[so.edge or field]
            assert (v * so.scale if so.scale != 1.0 else v) == spec_defaults[field], field
            assert field in (options()[so.edge or field].spec_field,)


@pytest.fixture(scope="module")
def problem():
    from layoutkit.envelope import load_envelope

    env = dataclasses.replace(load_envelope(REPO / "models" / "chen_envelope.toml"), count=40)
    spec = OptimizeSpec(k=10, max_tilt_deg=15.0, tilt_toward="station")
    return DesignProblem.for_spec(MESH, env, spec, spacing=0.016), spec


def test_selection_visibility_is_the_problems_slice_and_equals_a_fresh_raycast(problem):
    """problem.evaluate(sel) (sliced visibility) equals evaluate(sel, R, t) (a new ray-cast of the selected
    sensors through the mesh) and an independent pose_dop recount."""
    from layoutkit.dop import pose_dop
    from layoutkit.visibility import envelope_visibility

    pb, _ = problem
    sel = np.sort(np.random.default_rng(1).choice(pb.N, 10, replace=False))
    a0, p0, c0 = pb.evaluate(sel, rho=0.8717)
    a1, p1, c1 = pb.evaluate(sel, pb.rotations, pb.translations, rho=0.8717)
    np.testing.assert_array_equal(c0, c1)
    np.testing.assert_array_equal(a0, a1)
    c = pb.candidates
    vis = envelope_visibility(pb.mesh, c.positions[sel], c.normals[sel], pb.rotations, pb.translations, pb.stations,
                              sensor_half_angle_deg=60.0)
    np.testing.assert_array_equal(vis, pb.visible[:, :, sel])
    d = pose_dop(c.positions[sel], pb.rotations, pb.translations, rho=0.8717, visible=vis, stations=list(pb.stations))
    np.testing.assert_allclose(a0[c0], np.asarray(d.adop)[c0], rtol=1e-9)
    # one orientation per site: every pair of one site's candidates conflicts, nothing else (no spacing)
    C = pb.conflicts()
    same = (pb.site[:, None] == pb.site[None, :]) & ~np.eye(pb.N, dtype=bool)
    np.testing.assert_array_equal(C, same)


def test_solve_equals_the_array_core_and_refuses_another_tilt(problem):
    pb, spec = problem
    s = spec.replace(method="greedy")
    r = solve(pb, s)
    ref = optimize_stations(pb.jac, pb.visible, 10, method="greedy", rho=s.rho, conflict=pb.conflicts(), rng=0)
    np.testing.assert_array_equal(r.selected, ref.selected)
    assert r.value == ref.value and len(set(pb.site[r.selected])) == 10
    assert np.all(r.info["tilt_deg"] == pb.tilt_deg[r.selected])
    with pytest.raises(ValueError, match="differ from the problem's"):
        solve(pb, s.replace(max_tilt_deg=0.0))
    with pytest.raises(ValueError, match=r"fixed: unknown candidate id\(s\) \['nope'\]"):
        solve(pb, s.replace(fixed=("nope",)))


def test_layout_alone_finds_mesh_envelope_and_settings(tmp_path, small_envelope):
    """optimize writes spec + provenance into the layout; `score LAYOUT` (nothing else) equals `score LAYOUT
    --envelope ENV --mesh MESH --half-angle-deg 55 --rho 0.5` (the settings it was optimised with); a mesh
    that changed since is refused; `render --layout` finds the mesh."""
    out = tmp_path / "lay.json"
    r = CliRunner().invoke(main, ["optimize", MESH, "-k", "10", "--envelope", small_envelope, "--out", str(out),
                                  "--spacing-mm", "14", "--method", "greedy", "--half-angle-deg", "55", "--rho", "0.5",
                                  "--no-render", "--json", "--dense-poses", "0"])
    assert r.exit_code == 0, r.output
    lay = json.loads(out.read_text())
    assert lay["spec"]["half_angle_deg"] == 55.0 and lay["provenance"]["mesh"] == str(Path(MESH).resolve())
    alone = CliRunner().invoke(main, ["score", str(out), "--json"])
    assert alone.exit_code == 0, alone.output
    a = json.loads(alone.stdout)
    full = json.loads(CliRunner().invoke(main, ["score", str(out), "--envelope", small_envelope, "--mesh", MESH,
                                                "--half-angle-deg", "55", "--rho", "0.5", "--json"]).stdout)
    for key in ("worst_adop", "median_adop", "worst_pdop", "coverage_fraction", "poses"):
        assert a[key] == full[key], key
    assert a["sources"]["envelope"] == "layout provenance" and a["sources"]["rho"] == "layout spec"
    assert a["worst_adop"] == pytest.approx(json.loads(r.stdout)["value"], rel=1e-9)  # what optimize reported
    moved = dict(lay, provenance={**lay["provenance"], "mesh_sha256": "0" * 64})
    bad = tmp_path / "moved.json"
    bad.write_text(json.dumps(moved))
    r2 = CliRunner().invoke(main, ["score", str(bad)])
    assert r2.exit_code == 2 and "changed since the layout was made" in r2.output
    plain = tmp_path / "plain.json"
    plain.write_text(json.dumps({"units": "m", "sensors": lay["sensors"]}))
    r3 = CliRunner().invoke(main, ["score", str(plain)])
    assert r3.exit_code == 2 and "no --envelope given and the layout records none" in r3.output
    from layoutkit.workflows.render import RenderOptions, _sources

    mesh_path, _, env, half, _ = _sources(None, out, None, RenderOptions())
    assert mesh_path == str(Path(MESH).resolve()) and half == 55.0 and (env.count, env.seed) == (30, 3)
