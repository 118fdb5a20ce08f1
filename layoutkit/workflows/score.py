"""Score a fixed layout over an operating envelope (``layoutkit score``; issue 13, item 4).

DOP distribution (worst, median, percentiles) of the exact metric (Chen eq. 18 with rho, lit
sensors only, every station: :func:`layoutkit.dop_batch.batch_dop`), coverage by the chosen rule
(:mod:`layoutkit.coverage_rule`), per-sensor usage, and a report folder with the CDF and the
envelope map (each pose placed by the direction of the reference station in the body frame,
coloured by ADOP, poses not covered by the rule marked). ``compare`` scores a second layout over
the same poses for a side-by-side table and one CDF plot.

DOP statistics are taken over the **covered** poses (a pose the rule does not cover has no fix to
be precise about); ``coverage_fraction`` says how many those are. A covered pose with singular
geometry has DOP inf and makes the worst case inf.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from ..units import RHO_PAPER

__all__ = ["envelope_set", "layout_visibility", "score_arrays", "score_layout", "write_score_report"]


def envelope_set(envelope, count=None, seed=None):
    """``(Envelope, R (P,3,3), t (P,3))`` of ``envelope`` (path or Envelope), optionally with another
    pose ``count`` or ``seed`` (a held-out set of the same envelope)."""
    from ..envelope import Envelope, load_envelope

    env = envelope if isinstance(envelope, Envelope) else load_envelope(envelope)
    ch = {}
    if count is not None:
        ch["count"] = int(count)
    if seed is not None:
        ch["seed"] = int(seed)
    if ch:
        env = dataclasses.replace(env, **ch)
    R, t = env.poses()
    return env, R, t


def layout_visibility(mesh, positions, normals, R, t, stations, half_angle_deg=60.0):
    """``(P, S, n)`` bool visibility; without a mesh: acceptance cone and field of view only
    (exact for a convex body, no occlusion)."""
    from ..visibility import envelope_visibility

    if mesh is None:
        return envelope_visibility(None, positions, normals, R, t, stations, sensor_half_angle_deg=half_angle_deg,
                                   occlusion=False, surface_offset=0.0)
    return envelope_visibility(mesh, positions, normals, R, t, stations, sensor_half_angle_deg=half_angle_deg)


def _pct(x, q):
    return float(np.percentile(x, q)) if len(x) else float("nan")


def score_arrays(positions, vis, R, t, stations, *, rho, min_visible=4, coverage="any-station", ids=None):
    """Score from arrays: positions (n, 3) m; vis (P, S, n) bool; R, t world poses; stations.

    Returns a JSON-able dict (see :func:`score_layout`) plus ``_adop``, ``_pdop``, ``_covered`` arrays.
    """
    from ..coverage_rule import covered, layout_counts
    from ..dop_batch import batch_dop

    d = batch_dop(positions, R, t, rho=rho, visible=vis, stations=stations)
    counts = layout_counts(vis, coverage)  # (P, R)
    cov = covered(counts, min_visible)
    a, p = d.adop[cov], d.pdop[cov]
    n_sing = int(np.sum(cov & (d.status != 0)))
    P, S, n = vis.shape
    ids = list(ids) if ids is not None else [f"S{i + 1:02d}" for i in range(n)]
    st_ids = [s.id for s in stations]
    usage = [{"id": ids[i], "lit_fraction": float(vis[:, :, i].any(axis=1).mean()),
              "lit_fraction_per_station": {st_ids[s]: float(vis[:, s, i].mean()) for s in range(S)},
              "lit_fraction_covered_poses": float(vis[cov][:, :, i].any(axis=1).mean()) if cov.any() else 0.0}
             for i in range(n)]
    ok = bool(cov.any())
    out = {
        "poses": int(P), "covered_poses": int(cov.sum()), "coverage_fraction": float(cov.mean()),
        "coverage_rule": coverage, "min_visible": int(min_visible), "rho": float(rho), "sensors": int(n),
        "stations": st_ids,
        "worst_adop": float(np.max(a)) if ok else float("nan"),
        "median_adop": _pct(a, 50), "p95_adop": _pct(a, 95), "p99_adop": _pct(a, 99),
        "mean_adop": float(np.mean(a)) if ok and np.all(np.isfinite(a)) else (float("inf") if ok else float("nan")),
        "worst_pdop": float(np.max(p)) if ok else float("nan"),
        "median_pdop": _pct(p, 50), "p95_pdop": _pct(p, 95),
        "singular_covered_poses": n_sing,
        "uncovered_pose_indices": np.flatnonzero(~cov)[:200].tolist(),
        "lit_count_min": int(counts.min()) if P else 0,
        "per_sensor": usage,
        "units": {"adop": "deg/rad", "pdop": "m/rad"},
        "success": ok,
        "status": "ok" if ok else "no_coverage",
        "message": (f"{int(cov.sum())}/{P} poses covered ({coverage}, >= {min_visible} lit)"
                    + (f"; {n_sing} covered pose(s) with singular geometry (DOP inf)" if n_sing else "")
                    if ok else f"no pose of {P} has {min_visible} lit sensors by the {coverage} rule"),
        "_adop": d.adop, "_pdop": d.pdop, "_covered": cov,
    }
    return out


def score_layout(layout, envelope, *, mesh=None, units="m", rho=RHO_PAPER, half_angle_deg=60.0,
                 min_visible=4, coverage="any-station", poses=None, seed=None, compare=None,
                 report=None):
    """Score ``layout`` (path or Layout) over ``envelope`` (path or Envelope).

    mesh : optional mesh path / Trimesh for occlusion (``units`` of the file); poses, seed :
    override the envelope's pose count / seed (e.g. a dense or held-out set). compare : a second
    layout scored over the same poses (``result["compare"]``). report : folder for plots + JSON.
    Returns a JSON-able dict with at least worst_adop, median_adop, p95_adop (deg/rad), worst_pdop
    (m/rad), coverage_fraction and poses.
    """
    from ..coverage_rule import check_rule
    from ..layout import Layout, load_layout
    from ..mesh import load_mesh

    check_rule(coverage)
    lay = layout if isinstance(layout, Layout) else load_layout(layout)
    if mesh is not None and isinstance(mesh, (str, Path)):
        mesh_name = str(mesh)
        mesh = load_mesh(mesh, units)
    else:
        mesh_name = None if mesh is None else "(in memory)"
    env, R, t = envelope_set(envelope, poses, seed)

    def one(L):
        vis = layout_visibility(mesh, L.positions, L.normals, R, t, env.stations, half_angle_deg)
        return score_arrays(L.positions, vis, R, t, env.stations, rho=rho, min_visible=min_visible,
                            coverage=coverage, ids=L.ids)

    res = one(lay)
    res.update({"layout": str(layout) if isinstance(layout, (str, Path)) else "(in memory)",
                "envelope": str(envelope) if isinstance(envelope, (str, Path)) else env.name,
                "envelope_seed": env.seed, "half_angle_deg": float(half_angle_deg),
                "occlusion": "mesh" if mesh is not None else "none (no mesh: acceptance cone and field of view only)",
                "mesh": mesh_name})
    other = None
    if compare is not None:
        oth = compare if isinstance(compare, Layout) else load_layout(compare)
        other = one(oth)
        other["layout"] = str(compare) if isinstance(compare, (str, Path)) else "(in memory)"
    if report is not None:
        res["report"] = write_score_report(report, res, other, R, t, env)
    if other is not None:
        res["compare"] = {k: v for k, v in other.items() if not k.startswith("_")}
    return res


def write_score_report(report_dir, res, other, R, t, env):
    """dop_cdf.png (both layouts with a comparison), envelope_map.png, score.json into a folder."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io.jsonfile import to_jsonable
    from ..io.atomic import atomic_write_text

    d = Path(report_dir)
    d.mkdir(parents=True, exist_ok=True)
    files = []
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for r, lab in ((res, "layout"), (other, "compare")):
        if r is None:
            continue
        for a, key, xl in ((ax[0], "_adop", "ADOP (deg/rad)"), (ax[1], "_pdop", "PDOP (m/rad)")):
            y = np.sort(r[key][r["_covered"]])
            y = y[np.isfinite(y)]
            if len(y):
                a.plot(y, np.arange(1, len(y) + 1) / r["poses"], label=f"{lab}: {Path(str(r.get('layout'))).name}")
            a.set_xlabel(xl)
            a.set_ylabel("fraction of envelope poses (covered, DOP <= x)")
            a.set_xscale("log")
            a.grid(alpha=0.3)
    ax[0].legend(fontsize=8)
    fig.suptitle(f"DOP over {res['poses']} envelope poses ({res['coverage_rule']}, >= {res['min_visible']} lit)")
    p = d / "dop_cdf.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    files.append(p.name)
    # envelope map: direction of the reference station in the body frame
    ref = env.stations[env.reference_station]
    v = np.einsum("pji,pj->pi", R, ref.translation[None] - t)  # R^T (s - t)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    lat = np.degrees(np.arcsin(np.clip(v[:, 2], -1, 1)))
    lon = np.degrees(np.arctan2(v[:, 1], v[:, 0]))
    fig, ax = plt.subplots(figsize=(9, 4.5))
    cov = res["_covered"]
    a = res["_adop"]
    good = cov & np.isfinite(a)
    sc = ax.scatter(lon[good], lat[good], c=a[good], s=8, cmap="viridis_r",
                    norm=matplotlib.colors.LogNorm() if good.any() else None)
    if good.any():
        fig.colorbar(sc, ax=ax, label="ADOP (deg/rad)")
    bad = ~good
    ax.scatter(lon[bad], lat[bad], marker="x", c="red", s=14, label=f"not covered / singular ({int(bad.sum())})")
    ax.set_xlabel("station azimuth in the body frame (deg)")
    ax.set_ylabel("station elevation (deg)")
    ax.set_title(f"envelope map ({res['coverage_rule']} rule): worst ADOP {res['worst_adop']:.4g}")
    ax.legend(fontsize=8, loc="lower right")
    ax.grid(alpha=0.3)
    p = d / "envelope_map.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    files.append(p.name)
    out = {k: v for k, v in res.items() if not k.startswith("_")}
    if other is not None:
        out["compare"] = {k: v for k, v in other.items() if not k.startswith("_")}
    atomic_write_text(d / "score.json", json.dumps(to_jsonable(out), indent=2) + "\n")
    files.append("score.json")
    return {"dir": str(d), "files": files}
