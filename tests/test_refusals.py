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

import numpy as np
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
    assert r.stderr.split("\n")[-2].startswith(f"error: {p}: range_m [1000.0, 3000.0]: 3000 m is farther than any lighthouse "
                               "reaches (<= 30 m): the numbers are probably millimetres (3 m?)"), r.output
    ok = _run(["score", LAYOUT, "--envelope", p, "--json", "--allow-odd-size"])
    assert ok.exit_code == 0 and "warning:" in ok.output  # let through on request, still said


def test_import_reference_names_the_dropped_rows_and_refuses_millimetres(tmp_path):
    """A NaN row was dropped without saying which, and a mocap file in mm was taken as metres."""
    p = tmp_path / "ref.csv"
    p.write_text("t,x,y,z,qx,qy,qz,qw\n0.0,1.0,2.0,1.5,0,0,0,1\n0.1,1.0,nan,1.5,0,0,0,1\n0.2,1.0,2.0,1.5,0,0,0,1\n")
    r = _run(["import", "reference", p, "--out", tmp_path / "o.csv"])
    assert r.exit_code == 0 and f"note: 1 row(s) of {p} left out: a time or value is NaN or empty (line 3)" in r.output
    mm = tmp_path / "mm.csv"
    mm.write_text(p.read_text().replace("1.0,2.0,1.5", "1000.0,2000.0,1500.0").replace("1.0,nan,1.5", "1000,2001,1500"))
    r = _run(["import", "reference", mm, "--out", tmp_path / "o2.csv"])
    assert r.exit_code == 2 and r.output.startswith(f"error: {mm}: positions: 2693 m is farther than any lighthouse "
                                                    "reaches"), r.output
    assert "millimetres" in r.output and not (tmp_path / "o2.csv").exists()
    ok = _run(["import", "reference", mm, "--out", tmp_path / "o3.csv", "--units", "mm", "--json"])
    assert ok.exit_code == 0 and json.loads(ok.stdout)["rows"] == 3


def test_frame_table_in_degrees_is_refused_naming_column_and_line(tmp_path):
    """Every frame came back 'invalid angle' with no column named; now the file is refused once."""
    import csv
    import math

    f = tmp_path / "f.csv"
    assert _run(["simulate", "--layout", LAYOUT, "--frames", 5, "--out", f]).exit_code == 0
    rows = list(csv.reader(f.open()))
    deg = tmp_path / "deg.csv"
    with deg.open("w", newline="") as fh:
        csv.writer(fh).writerows([rows[0]] + [[str(math.degrees(float(v))) if c.startswith("th_") and v else v
                                               for c, v in zip(rows[0], r)] for r in rows[1:]])
    r = _run(["solve", deg, "--layout", LAYOUT])
    assert r.exit_code == 2 and r.output.startswith(f"error: {deg}: line 2, column th_"), r.output
    assert "frame tables hold radians; these look like degrees" in r.output
    assert _run(["solve", f, "--layout", LAYOUT]).exit_code == 0


def test_replay_with_another_layouts_capture_says_so(tmp_path):
    """A 12-sensor capture replayed with the 4-sensor deck layout said only 'another --protocol?'."""
    cap = tmp_path / "c.lkcap"
    assert _run(["fake-fpga", "--layout", LAYOUT, "--out", cap, "--duration", 0.3]).exit_code == 0
    (tmp_path / "c.lkcap.json").unlink()  # no sidecar: the layout given is the one used
    r = _run(["replay", cap, "--layout", REPO / "models" / "crazyflie_lighthouse_deck.layout.json"])
    assert r.exit_code == 2 and "frames of 12 sensors, the layout has 4 (another layout's capture?)" in r.output


def test_sweep_plot_names_the_objective_unit_and_shows_cells_without_a_layout(tmp_path, small_envelope):
    """The sweep plot's y axis said only 'objective' and infeasible cells were not drawn at all."""
    import matplotlib.figure

    from layoutkit.workflows.sweep import _plots
    from layoutkit.workflows.sweep_config import parse_sweep

    cfg = parse_sweep({"base": {"mesh": str(REPO / "models" / "chen_target.stl"), "envelope": small_envelope,
                                "objective": "worst-pdop"}, "axes": {"k": [4, 8, 10]}}, tmp_path / "s.toml")
    rows = [{"k": 4, "status": "infeasible", "value": None, "worst_adop_deg_per_rad": None},
            {"k": 8, "status": "ok", "value": 40.0, "worst_adop_deg_per_rad": 3000.0},
            {"k": 10, "status": "ok", "value": 30.0, "worst_adop_deg_per_rad": 2000.0}]
    seen = []
    orig = matplotlib.figure.Figure.savefig

    def spy(self, *a, **k):
        seen.append(self)
        return orig(self, *a, **k)

    matplotlib.figure.Figure.savefig = spy
    try:
        files = _plots(tmp_path, cfg, rows, rows[1:], print)
    finally:
        matplotlib.figure.Figure.savefig = orig
    assert files == ["objective_vs_axes.png", "pareto_worst_adop_vs_k.png"]
    ax = seen[0].axes[0]
    assert ax.get_ylabel() == "worst-pdop (m/rad)"
    crosses = [c for c in ax.collections if c.get_label().startswith("infeasible")]
    assert len(crosses) == 1 and crosses[0].get_offsets()[:, 0].tolist() == [4.0]


@pytest.mark.parametrize("extra, message", [
    (["--candidates", "{c}", "--spacing-mm", "8"], "--candidates and --spacing-mm cannot be used together"),
    (["--weights", "1,1"], "--weights is for the *-weighted objectives; --objective worst-adop would ignore it"),
    (["--spacing-mm", "10", "--keepout-box", "10,10,10,0,0,0"],
     "the first corner must be the lower one (x0 <= x1, y0 <= y1, z0 <= z1), got x 0.01 > 0"),
])
def test_optimize_refuses_contradicting_flags(tmp_path, small_envelope, extra, message):
    """Accepted silently before (--candidates won over --spacing-mm, --weights was ignored); an
    inverted keep-out box said 'the format is wrong'."""
    c = tmp_path / "c.json"
    assert _run(["candidates", REPO / "models" / "chen_target.stl", "--spacing-mm", "20", "--out", c]).exit_code == 0
    r = _run(["optimize", REPO / "models" / "chen_target.stl", "--sensors", 8, "--envelope", small_envelope,
              "--out", tmp_path / "l.json", *[x.format(c=c) for x in extra]])
    assert r.exit_code == 2 and "error:" in r.output and message in r.output, r.output
    assert not (tmp_path / "l.json").exists()


def test_score_streams_many_poses_and_agrees_with_the_exact_statistics(monkeypatch, small_envelope):
    """``score --poses 100000000`` grew to 5.8 GB with no output: above STREAM_POSES the poses are
    drawn and scored chunk by chunk. Checked against the exact statistics of the same poses (the
    chunks redrawn with their documented seeds, scored in one piece): counts and worst exact, the
    sketched median / p95 / p99 within the histogram's resolution."""
    import dataclasses

    import layoutkit.workflows.score as sc
    from layoutkit.envelope import load_envelope
    from layoutkit.layout import load_layout
    from layoutkit.optimize import DesignProblem

    monkeypatch.setattr(sc, "STREAM_POSES", 500)
    monkeypatch.setattr(sc, "CHUNK_POSES", 300)
    seen = []
    res = sc.score_layout(LAYOUT, small_envelope, poses=1000, rho=0.8717, progress=seen.append)
    assert seen == [300, 300, 300, 100] and res["streamed"]["chunks"] == 4 and res["poses"] == 1000
    env = load_envelope(small_envelope)
    R, t = [], []
    for k, n in enumerate(seen):
        seed = int(np.random.SeedSequence([env.seed, k]).generate_state(1)[0])
        r, tt = dataclasses.replace(env, count=n, seed=seed).poses()
        R.append(r)
        t.append(tt)
    lay = load_layout(LAYOUT)
    whole = dataclasses.replace(env, count=1000)
    pb = DesignProblem.load(None, whole, candidates=lay, half_angle_deg=60.0)
    # the same poses: replace the problem's poses by the concatenated chunks
    from layoutkit.visibility import facing_mask

    R, t = np.concatenate(R), np.concatenate(t)
    st = pb.stations[0]
    vis = facing_mask(lay.positions, lay.normals, *st.world_to_station(R, t), half_angle_deg=60.0,
                      fov_deg=st.fov_deg)[:, None, :]
    exact = sc.score_arrays(lay.positions, vis, R, t, pb.stations, rho=0.8717)
    assert res["covered_poses"] == exact["covered_poses"] and res["lit_count_min"] == exact["lit_count_min"]
    assert res["worst_adop"] == pytest.approx(exact["worst_adop"], rel=1e-12)
    assert res["worst_pdop"] == pytest.approx(exact["worst_pdop"], rel=1e-12)
    tol = res["streamed"]["relative_resolution"]
    for k in ("median_adop", "p95_adop", "p99_adop", "median_pdop", "p95_pdop"):
        assert abs(res[k] / exact[k] - 1) <= tol, (k, res[k], exact[k])
    assert [u["lit_fraction"] for u in res["per_sensor"]] == pytest.approx([u["lit_fraction"] for u in exact["per_sensor"]])


def test_demo_comparison_says_what_the_shipped_layout_leaves_uncovered(tmp_path, small_envelope):
    """The demo reported a worst ADOP 3.4x the shipped layout's without saying that the shipped one
    leaves poses uncovered: versus_layout puts coverage beside the DOP. Closed-form reference: the
    four top sensors with their normals reversed face away from the station in every pose where the
    shipped top face is lit (the envelope keeps the top face towards the station), so that layout
    covers no pose at all, and the comparison says so in its message."""
    from layoutkit.workflows.optimize import versus_layout

    d = json.loads(LAYOUT.read_text())
    d["sensors"] = [s | {"normal": [-c for c in s["normal"]]} for s in d["sensors"] if s["id"].startswith("T")]
    away = tmp_path / "away.json"
    away.write_text(json.dumps(d))
    v = versus_layout(LAYOUT, away, small_envelope, REPO / "models" / "chen_target.stl", 0.8717)
    a, b = v["optimised"], v["other"]
    assert a["poses"] == b["poses"] == 30 and a["covered_poses"] == 30 and b["covered_poses"] == 0
    assert "30 poses it cannot track at all" in v["message"] and "covers none of the 30 poses" in v["message"]
    same = versus_layout(LAYOUT, LAYOUT, small_envelope, REPO / "models" / "chen_target.stl", 0.8717)
    assert {k: v for k, v in same["optimised"].items() if k != "layout"} == \
           {k: v for k, v in same["other"].items() if k != "layout"}
    assert "cannot track" not in same["message"]


def test_envelope_without_a_station_says_which_station_it_assumed(tmp_path, small_envelope):
    """An envelope without ``[[station]]`` silently got a default station. Now a warning names the
    file and the assumed station; the reference for "assumed" is the same envelope with that station
    written out: identical scores, and no warning."""
    r = _run(["score", LAYOUT, "--envelope", small_envelope, "--json"])
    assert r.exit_code == 0
    warned = [ln for ln in r.stderr.splitlines() if ln.startswith("warning:")]
    assert len(warned) == 1 and f"{small_envelope}: station: no [[station]] table" in warned[0], r.stderr
    explicit = tmp_path / "explicit.toml"
    explicit.write_text(Path(small_envelope).read_text() + '\n[[station]]\nid = "A"\nposition_m = [0.0, 0.0, 0.0]\n'
                        'rotvec_deg = [0.0, 0.0, 0.0]\nkind = "lh1"\nfov_deg = 120.0\n')
    r2 = _run(["score", LAYOUT, "--envelope", explicit, "--json"])
    assert r2.exit_code == 0 and "warning:" not in r2.stderr, r2.stderr
    a, b = json.loads(r.stdout), json.loads(r2.stdout)
    assert (a["covered_poses"], a["worst_adop"], a["median_pdop"]) == (b["covered_poses"], b["worst_adop"],
                                                                        b["median_pdop"])


def test_simulate_and_import_refuse_to_overwrite_another_runs_files(tmp_path):
    """``simulate --out`` replaced an existing frame table (frames and the truth of an earlier run)
    without a word. Now: exit 2 naming the file, the file byte-identical; ``--overwrite`` replaces it."""
    out = tmp_path / "frames.csv"
    first = _run(["simulate", "--layout", LAYOUT, "--frames", 5, "--out", out, "--seed", 1])
    assert first.exit_code == 0
    before = out.read_bytes()
    again = _run(["simulate", "--layout", LAYOUT, "--frames", 5, "--out", out, "--seed", 2])
    assert again.exit_code == 2 and f"error: {out}: already exists" in again.stderr and out.read_bytes() == before
    forced = _run(["simulate", "--layout", LAYOUT, "--frames", 5, "--out", out, "--seed", 2, "--overwrite"])
    assert forced.exit_code == 0 and out.read_bytes() != before
    # the same rule for an imported reference
    mocap, ref = tmp_path / "mocap.csv", tmp_path / "ref.csv"
    mocap.write_text("t,x,y,z\n0.0,0.1,0.2,1.5\n0.1,0.1,0.2,1.6\n0.2,0.1,0.2,1.7\n")
    assert _run(["import", "reference", mocap, "--out", ref]).exit_code == 0
    kept = ref.read_bytes()
    again = _run(["import", "reference", mocap, "--out", ref])
    assert again.exit_code == 2 and f"error: {ref}: already exists" in again.stderr and ref.read_bytes() == kept
