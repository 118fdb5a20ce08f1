"""Off-screen render time per picture for every shipped model at 1600 × 1200 (issue 3, renders).

Budget from the issue: ≤ 2 s per render after start-up. Anchor in the same run: a bare pyvista
screenshot of the same mesh (Plotter + add_mesh + screenshot, nothing else) — the floor set by
VTK's software rasteriser here; ``ratio_to_bare`` says what our scene (edges, glyphs, labels,
colour bar) costs on top. Each render is a complete call of the public function (scene build,
render, PNG write). Rounds interleaved over models, median of ≥ 5; peak memory beside time
(process max RSS — VTK allocates outside Python — and tracemalloc for the Python side).

Also writes the README pictures to ``docs/images/`` (the renders of the last round).

    .venv/bin/python benchmarks/bench_render.py [--quick]
"""
import argparse
import shutil
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _util import interleaved, max_rss_bytes, peak_python_memory, write_result  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "models"
IMAGES = ROOT / "docs" / "images"
SIZE = (1600, 1200)
BUDGET_S = 2.0


def _inputs():
    """Mesh, sensors (layout or candidate sites) and per-sensor lit fraction for each shipped model."""
    from layoutkit.candidates import sample_candidates
    from layoutkit.envelope import Envelope, load_envelope
    from layoutkit.layout import load_layout
    from layoutkit.mesh import load_mesh
    from layoutkit.visibility import envelope_visibility
    from layoutkit.workflows.render import lit_fraction

    specs = {
        "chen_target": ("chen_target.stl", "chen_target.layout.json", "chen_envelope.toml"),
        "zhai_target": ("zhai_target.stl", None, None),
        "cubesat_3u": ("cubesat_3u.ply", None, None),
        "docking_target": ("docking_target.stl", None, "docking_two_stations.toml"),
    }
    out = {}
    for name, (mesh_file, layout_file, env_file) in specs.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mesh = load_mesh(MODELS / mesh_file)
        diag = float(np.linalg.norm(mesh.extents))
        if layout_file:
            lay, what = load_layout(MODELS / layout_file), "sensors"
        else:
            lay = sample_candidates(mesh, spacing=diag / 40, rng=np.random.default_rng(0))
            what = "candidate sites"
        if env_file:
            env = load_envelope(MODELS / env_file)
        else:  # any attitude, 3-6 body diagonals away
            env = Envelope(range_m=(3 * diag, 6 * diag), count=300, seed=1, name="uniform attitude")
        R, t = env.poses()
        frac = lit_fraction(envelope_visibility(mesh, lay.positions, lay.normals, R, t, env.stations))
        out[name] = dict(mesh=mesh, layout=lay, lit=frac, what=what, envelope=env, faces=len(mesh.faces),
                         spacing=lay.metadata.get("spacing_m"))
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer rounds (5 → 5 still; smaller quality grid)")
    ap.add_argument("--no-images", action="store_true", help="do not refresh docs/images")
    args = ap.parse_args()
    rounds = 5

    t0 = time.perf_counter()
    from layoutkit import render
    from layoutkit.geometry import rotvec_to_matrix
    from layoutkit.units import RHO_PAPER, SIGMA_THETA_PAPER
    from layoutkit.quality import tracking_quality_map
    from layoutkit.visibility import visible_sensors

    backend = render.offscreen_backend()
    import pyvista as pv  # noqa: F401  (start-up cost measured separately)
    import matplotlib.figure  # noqa: F401
    startup_s = time.perf_counter() - t0
    rss_start = max_rss_bytes()

    models = _inputs()
    chen = models["chen_target"]
    qmap_grid = (30, 60) if args.quick else (45, 90)
    q = tracking_quality_map(chen["mesh"], chen["layout"].positions, chen["layout"].normals, distance=2.0,
                             rho=RHO_PAPER, grid=qmap_grid, roll_samples=6)
    R_sv = rotvec_to_matrix([np.pi + 0.35, 0.25, 0.4])
    t_sv = np.array([0.25, -0.15, 1.8])
    lit_sv = visible_sensors(chen["mesh"], chen["layout"].positions, chen["layout"].normals, R_sv, t_sv)
    # docking target seen from station 0 of its envelope: the pose (of the first 100) where the mesh
    # shadows the most candidate sites that face the station inside its field of view
    dock = models["docking_target"]
    st = dock["envelope"].stations[0]
    R_w, t_w = dock["envelope"].poses()
    R_d, t_d = st.world_to_station(R_w[:100], t_w[:100])
    dl = dock["layout"]
    v_occ = visible_sensors(dock["mesh"], dl.positions, dl.normals, R_d, t_d, fov_deg=st.fov_deg)
    v_free = visible_sensors(dock["mesh"], dl.positions, dl.normals, R_d, t_d, fov_deg=st.fov_deg, occlusion=False)
    k_d = int(np.argmax(v_free.sum(1) - v_occ.sum(1)))
    R_d, t_d, lit_d, shadow_d = R_d[k_d], t_d[k_d], v_occ[k_d], v_free[k_d] & ~v_occ[k_d]

    tmp = Path(tempfile.mkdtemp(prefix="bench_render_"))
    funcs = {}
    for name, m in models.items():
        lay = m["layout"]
        is_layout = m["what"] == "sensors"
        radius = None if is_layout else 0.3 * m["spacing"]

        def f(name=name, m=m, lay=lay, is_layout=is_layout, radius=radius):
            title = (f"{name}: layout, coloured by envelope coverage" if is_layout else
                     f"{name}: candidate-site coverage, envelope '{m['envelope'].name}'")
            render.render_layout_views(m["mesh"], lay.positions, lay.normals, m["lit"], views=("iso",), size=SIZE,
                                       out_dir=tmp, prefix=f"{name}_{'layout' if is_layout else 'coverage'}",
                                       ids=lay.ids if is_layout else None, arrows=is_layout, labels=is_layout,
                                       sensor_radius=radius, what=m["what"], title=title)
        funcs[f"layout_view:{name}"] = f

    def four_views():
        render.render_layout_views(chen["mesh"], chen["layout"].positions, chen["layout"].normals, chen["lit"],
                                   views=("iso", "front", "top", "side"), size=SIZE, out_dir=tmp, prefix="chen_views",
                                   ids=chen["layout"].ids, title="chen_target: layout, coloured by envelope coverage")
    funcs["four_views:chen_target"] = four_views

    def station_view():
        render.render_station_view(chen["mesh"], chen["layout"].positions, chen["layout"].normals, R_sv, t_sv, lit_sv,
                                   fov_deg=None, size=SIZE, out=tmp / "chen_station_view.png", ids=chen["layout"].ids,
                                   title="chen_target: view from the lighthouse")
    funcs["station_view:chen_target"] = station_view

    def station_view_docking():
        render.render_station_view(dock["mesh"], dl.positions, dl.normals, R_d, t_d, lit_d, fov_deg=None, size=SIZE,
                                   out=tmp / "docking_station_view.png", shadowed=shadow_d,
                                   sensor_radius=0.3 * dock["spacing"], what="candidate sites",
                                   title=f"docking_target seen from station {st.id} of '{dock['envelope'].name}'")
    funcs["station_view:docking_target"] = station_view_docking

    def quality_map():
        render.render_tracking_map(q, out=tmp / "chen_quality_map.png", size=SIZE, sigma_theta=SIGMA_THETA_PAPER,
                                   title="Chen target: tracking quality over all viewing directions (2 m)")
    funcs["quality_map:chen_target"] = quality_map

    def quality_sphere():
        render.render_tracking_map(q, out=tmp / "chen_quality_sphere.png", kind="sphere", size=SIZE)
    funcs["quality_sphere:chen_target"] = quality_sphere

    def bare(m):
        def f():
            pl = pv.Plotter(off_screen=True, window_size=SIZE)
            pl.add_mesh(render._polydata(m["mesh"]))
            pl.screenshot(str(tmp / "bare.png"))
            pl.close()
        return f
    for name, m in models.items():
        funcs[f"bare_pyvista:{name}"] = bare(m)

    for f in funcs.values():  # warm-up (first-use shader compilation etc.)
        f()
    times = interleaved(funcs, rounds=rounds)
    rss_end = max_rss_bytes()
    py_peak = {k: peak_python_memory(funcs[k]) for k in ("layout_view:docking_target", "quality_map:chen_target")}

    results = {}
    for k, ts in times.items():
        results[k] = {"median_s": statistics.median(ts), "min_s": min(ts), "max_s": max(ts), "rounds": len(ts)}
    for name, m in models.items():
        r = results[f"layout_view:{name}"]
        r["faces"] = m["faces"]
        r["points"] = int(m["layout"].n)
        r["ratio_to_bare"] = r["median_s"] / results[f"bare_pyvista:{name}"]["median_s"]
    results["four_views:chen_target"]["per_view_s"] = results["four_views:chen_target"]["median_s"] / 4
    renders = [k for k in results if not k.startswith("bare_")]
    worst = max(results[k]["median_s"] if not k.startswith("four") else results[k]["per_view_s"] for k in renders)
    out = {
        "size_px": list(SIZE),
        "backend": backend,
        "startup_s": startup_s,
        "budget_s": BUDGET_S,
        "worst_median_per_render_s": worst,
        "all_within_budget": bool(worst <= BUDGET_S),
        "renders": results,
        "memory": {"max_rss_after_startup_mb": rss_start / 2**20, "max_rss_end_mb": rss_end / 2**20,
                   "python_peak_mb": {k: v / 2**20 for k, v in py_peak.items()}},
        "quality_map": q.summary(),
        "note": "Median of interleaved rounds of complete public-function calls (scene build + render + PNG) at "
                "1600x1200 on a shared 2-core machine with VTK's software renderer (Mesa llvmpipe via EGL).",
    }
    p = write_result("render", out)
    print(f"backend {backend}, start-up {startup_s:.2f} s")
    for k, r in results.items():
        extra = f"  ×{r['ratio_to_bare']:.1f} bare" if "ratio_to_bare" in r else ""
        print(f"{k:34s} {r['median_s']:.3f} s{extra}")
    print(f"worst per render {worst:.3f} s (budget {BUDGET_S} s) → {p}")

    if not args.no_images:
        IMAGES.mkdir(parents=True, exist_ok=True)
        copies = {"chen_target_layout_iso.png": "chen_layout_iso.png",
                  "zhai_target_coverage_iso.png": "zhai_target_coverage.png",
                  "cubesat_3u_coverage_iso.png": "cubesat_3u_coverage.png",
                  "docking_target_coverage_iso.png": "docking_target_coverage.png",
                  "chen_station_view.png": "chen_station_view.png",
                  "docking_station_view.png": "docking_station_view.png",
                  "chen_quality_map.png": "chen_quality_map.png",
                  "chen_quality_sphere.png": "chen_quality_sphere.png",
                  "chen_views_top.png": "chen_layout_top.png"}
        for src, dst in copies.items():
            shutil.copy(tmp / src, IMAGES / dst)
        print(f"README pictures → {IMAGES}")
    shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
