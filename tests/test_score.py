"""``layoutkit score``: values against an independent recomputation, coverage rules by explicit count.

Proof kind: independent reference — the DOP is recomputed with ``pose_dop`` (batched matrices, not
the fused kernel) from ``envelope_visibility``; coverage rules are recounted by a plain Python loop
over poses and stations.
"""
import json

import numpy as np
from click.testing import CliRunner

from layoutkit.cli import main
from layoutkit.cli.options import COVERAGE_CHOICES
from layoutkit.coverage_rule import COVERAGE_RULES
from layoutkit.dop import pose_dop
from layoutkit.envelope import load_envelope
from layoutkit.layout import load_layout
from layoutkit.visibility import envelope_visibility
from layoutkit.workflows.score import score_layout

LAY = "models/chen_target.layout.json"
ENV = "models/chen_envelope.toml"
MESH = "models/chen_target.stl"


def test_cli_choices_match_registry():
    assert tuple(COVERAGE_RULES) == COVERAGE_CHOICES


def test_score_json_matches_pose_dop(tmp_path):
    r = CliRunner().invoke(main, ["score", LAY, "--envelope", ENV, "--mesh", MESH, "--rho", "0.8717",
                                  "--half-angle-deg", "60", "--units", "m", "--json"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    lay = load_layout(LAY)
    env = load_envelope(ENV)
    R, t = env.poses()
    import trimesh

    vis = envelope_visibility(trimesh.load(MESH, force="mesh"), lay.positions, lay.normals, R, t, env.stations,
                              sensor_half_angle_deg=60.0)
    d = pose_dop(lay.positions, R, t, rho=0.8717, visible=vis, stations=list(env.stations))
    cov = vis.any(axis=1).sum(axis=1) >= 4
    a, p = d.adop[cov], d.pdop[cov]
    assert out["poses"] == 200
    assert out["coverage_fraction"] == cov.mean()
    np.testing.assert_allclose(out["worst_adop"], a.max(), rtol=1e-9)
    np.testing.assert_allclose(out["median_adop"], np.median(a), rtol=1e-9)
    np.testing.assert_allclose(out["p95_adop"], np.percentile(a, 95), rtol=1e-9)
    np.testing.assert_allclose(out["worst_pdop"], p.max(), rtol=1e-9)
    # per-sensor usage: share of poses at which the sensor is lit
    np.testing.assert_allclose([u["lit_fraction"] for u in out["per_sensor"]], vis.any(axis=1).mean(axis=0))


def test_coverage_rules_two_stations_by_explicit_count():
    import dataclasses

    from layoutkit.optimize.design import layout_visibility

    env = dataclasses.replace(load_envelope("models/docking_two_stations.toml"), count=300)
    lay = load_layout(LAY)
    R, t = env.poses()
    res = {rule: score_layout(LAY, "models/docking_two_stations.toml", coverage=rule, min_visible=4, poses=300)
           for rule in COVERAGE_CHOICES}
    vis = layout_visibility(None, lay.positions, lay.normals, R, t, env.stations)
    cnt = {"any-station": 0, "each-station": 0, "joint": 0}
    for p in range(len(R)):
        per_station = [int(sum(vis[p, s, i] for i in range(lay.n))) for s in range(2)]
        union = sum(1 for i in range(lay.n) if vis[p, 0, i] or vis[p, 1, i])
        cnt["any-station"] += union >= 4
        cnt["each-station"] += min(per_station) >= 4
        cnt["joint"] += sum(per_station) >= 4
    for rule in COVERAGE_CHOICES:
        assert res[rule]["covered_poses"] == cnt[rule], rule
    assert cnt["each-station"] <= cnt["any-station"] <= cnt["joint"]


def test_compare_and_report(tmp_path):
    r = CliRunner().invoke(main, ["score", LAY, "--envelope", ENV, "--compare", LAY, "--poses", "100",
                                  "--report", str(tmp_path / "rep"), "--json"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    assert out["compare"]["worst_adop"] == out["worst_adop"]
    assert {"dop_cdf.png", "envelope_map.png", "score.json"} <= {p.name for p in (tmp_path / "rep").iterdir()}
    r = CliRunner().invoke(main, ["score", LAY, "--envelope", ENV, "--compare", LAY, "--poses", "50"])
    assert r.exit_code == 0 and "ratio" in r.output


def test_errors(tmp_path):
    r = CliRunner().invoke(main, ["score", str(tmp_path / "missing.json"), "--envelope", ENV])
    assert r.exit_code == 2 and "error:" in r.output and "missing.json" in r.output
    # nothing covered: exit 1 with the reason
    r = CliRunner().invoke(main, ["score", LAY, "--envelope", ENV, "--min-visible", "13", "--json"])
    assert r.exit_code == 1
    assert json.loads(r.stdout)["status"] == "no_coverage"
