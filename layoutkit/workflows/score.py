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

import json
from pathlib import Path

import numpy as np

from ..units import RHO_PAPER

__all__ = ["FROM_LAYOUT", "score_arrays", "score_layout", "write_score_report", "comparison_table"]

#: Above this many poses ``score_layout`` streams (chunks of :data:`CHUNK_POSES`).
STREAM_POSES = 200_000
CHUNK_POSES = 50_000
#: Percentile sketch of a streamed score: relative resolution 10^(1/200) - 1 = 1.2 %.
_SKETCH = dict(lo=1e-6, hi=1e12, bins_per_decade=200)

#: ``score_layout(mesh=FROM_LAYOUT)``: the mesh named in the layout's provenance (none if it names none)
FROM_LAYOUT = "from-layout"


def score_arrays(positions, vis, R, t, stations, *, rho, min_visible=4, coverage="any-station", ids=None):
    """Score from arrays: positions (n, 3) m; vis (P, S, n) bool; R, t world poses; stations.

    Returns a JSON-able dict (see :func:`score_layout`) plus ``_adop``, ``_pdop``, ``_covered`` arrays.
    The statistics are :func:`layoutkit.optimize.stats.pose_stats` over the covered poses.
    """
    from ..coverage_rule import covered, layout_counts
    from ..dop_batch import batch_dop
    from ..optimize.stats import pose_stats

    d = batch_dop(positions, R, t, rho=rho, visible=vis, stations=stations)
    counts = layout_counts(vis, coverage)  # (P, R)
    cov = covered(counts, min_visible)
    st = pose_stats(d.adop, d.pdop, cov)
    n_sing = int(np.sum(cov & (d.status != 0)))
    P, S, n = vis.shape
    ids = list(ids) if ids is not None else [f"S{i + 1:02d}" for i in range(n)]
    st_ids = [s.id for s in stations]
    usage = [{"id": ids[i], "lit_fraction": float(vis[:, :, i].any(axis=1).mean()),
              "lit_fraction_per_station": {st_ids[s]: float(vis[:, s, i].mean()) for s in range(S)},
              "lit_fraction_covered_poses": float(vis[cov][:, :, i].any(axis=1).mean()) if cov.any() else 0.0}
             for i in range(n)]
    ok = bool(cov.any())
    nan = float("nan")
    out = {
        "poses": int(P), "covered_poses": int(cov.sum()), "coverage_fraction": float(cov.mean()),
        "coverage_rule": coverage, "min_visible": int(min_visible), "rho": float(rho), "sensors": int(n),
        "stations": st_ids,
        **{k: (st[k] if ok else nan) for k in ("worst_adop", "median_adop", "p95_adop", "p99_adop", "mean_adop",
                                               "worst_pdop", "median_pdop", "p95_pdop")},
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


def _resolve(lay, where, envelope, mesh, units, settings):
    """Envelope, mesh (+ units) and settings: explicit arguments first, then the layout's own record
    (:func:`layoutkit.optimize.design.layout_sources`), then the defaults. Returns
    ``(envelope, mesh, units, settings, sources, recorded mesh SHA-256)``; ``ValueError`` naming the layout
    when it is needed and says nothing, or when its mesh is missing."""
    from ..optimize.design import layout_sources

    src = layout_sources(lay, where)
    spec = src["spec"] or {}
    sources = {"envelope": "argument" if envelope is not None else "layout provenance"}
    if envelope is None:
        if src["envelope"] is None:
            raise ValueError(f"{where}: no --envelope given and the layout records none (only layouts written by "
                             "`layoutkit optimize` do); give --envelope")
        envelope = src["envelope"]
    if mesh == FROM_LAYOUT:
        mesh, units = src["mesh"], src["units"] if units is None else units
        sources["mesh"] = "layout provenance" if mesh is not None else "none"
        if mesh is not None and not Path(mesh).is_file():
            raise ValueError(f"{where}: its mesh {mesh} (provenance) is not there; give --mesh (or move it back)")
    else:
        sources["mesh"] = "argument" if mesh is not None else "none"
    defaults = {"rho": RHO_PAPER, "half_angle_deg": 60.0, "min_visible": 4, "coverage": "any-station"}
    out = {}
    for k, v in settings.items():
        rec = src["half_angle_deg"] if k == "half_angle_deg" and src["half_angle_deg"] is not None else spec.get(k)
        out[k] = v if v is not None else (rec if rec is not None else defaults[k])
        sources[k] = "argument" if v is not None else ("layout spec" if rec is not None else "default")
    return envelope, mesh, units or "m", out, sources, src["mesh_sha256"]


def score_layout(layout, envelope=None, *, mesh=None, units=None, rho=None, half_angle_deg=None, min_visible=None,
                 coverage=None, poses=None, seed=None, compare=None, report=None, draws=0, progress=None):
    """Score ``layout`` (path or Layout) over ``envelope`` (path or Envelope).

    A layout written by ``layoutkit optimize`` records its envelope, mesh and settings: ``envelope=None``
    takes the recorded envelope, ``mesh=FROM_LAYOUT`` the recorded mesh (checked against its SHA-256), and
    ``rho``, ``half_angle_deg``, ``min_visible``, ``coverage`` left at None the recorded values (else
    0.8717, 60°, 4, any-station). ``result["sources"]`` says where each came from.
    mesh : optional mesh path / Trimesh for occlusion (``units`` of the file; None: acceptance cone and
    field of view only); poses, seed : override the envelope's pose count / seed (e.g. a dense or held-out
    set). draws : > 0 scores on that many fresh draws of the envelope instead (``poses`` each, default
    2,000; seeds ``envelope.seed + 2 + 1000 i``, the held-out draws of ``layoutkit optimize``): the statistics
    are over all of them and ``result["draws"]`` has each draw's worst ADOP and coverage. compare : a second
    layout scored over the same poses (``result["compare"]``, and ``result["comparison"]``: one row per
    quantity with both values and their ratio compare / layout). report : folder for plots + JSON. Returns a
    JSON-able dict with at least worst_adop, median_adop, p95_adop (deg/rad), worst_pdop (m/rad),
    coverage_fraction and poses. More than :data:`STREAM_POSES` poses (without ``draws``) are drawn and
    scored in chunks (:func:`_score_streamed`: memory flat, quantiles from a log histogram, the report's
    plots from the first chunk); ``progress(n)`` is told every chunk's pose count.
    """
    from ..coverage_rule import check_rule
    from ..envelope import envelope_set
    from ..layout import Layout, load_layout
    from ..mesh import load_mesh, mesh_hash
    from ..optimize import DesignProblem
    from ..optimize.heldout import HELDOUT_POSES_PER_DRAW

    lay = layout if isinstance(layout, Layout) else load_layout(layout)
    where = str(layout) if isinstance(layout, (str, Path)) else "layout"
    envelope, mesh, units, st, sources, want_hash = _resolve(
        lay, where, envelope, mesh, units,
        {"rho": rho, "half_angle_deg": half_angle_deg, "min_visible": min_visible, "coverage": coverage})
    check_rule(st["coverage"])
    mesh_name = str(mesh) if isinstance(mesh, (str, Path)) else (None if mesh is None else "(in memory)")
    if isinstance(mesh, (str, Path)):
        mesh = load_mesh(mesh, units)
        if sources["mesh"] == "layout provenance" and want_hash and mesh_hash(mesh) != want_hash:
            raise ValueError(f"{where}: its mesh {mesh_name} changed since the layout was made (SHA-256 differs); "
                             "give --mesh explicitly to score on it anyway")
    if poses is not None and int(poses) > STREAM_POSES and not draws:  # memory flat for any pose count
        env = envelope_set(envelope, 1, seed)[0]
        res, other, first = _score_streamed(lay, env, int(poses), mesh, st, compare, progress)
        R, t = first
    else:
        per = int(poses or HELDOUT_POSES_PER_DRAW)
        if draws and int(draws) * per > STREAM_POSES:
            raise ValueError(f"score: --draws {draws} x --poses {per} is more than {STREAM_POSES} poses "
                             "held at once; give fewer draws, or one large --poses set (streamed)")
        env, R, t, sizes = _pose_sets(envelope, poses, seed, draws)
        res = other = None

    def one(L):
        pb = DesignProblem.load(mesh, None, candidates=L, half_angle_deg=st["half_angle_deg"], stations=env.stations)
        vis = pb.visibility_at(None, R, t)
        out = score_arrays(L.positions, vis, R, t, pb.stations, rho=st["rho"], min_visible=st["min_visible"],
                           coverage=st["coverage"], ids=L.ids)
        if draws:
            out["draws"] = _per_draw(out, sizes, env)
        return out

    if res is None:
        res = one(lay)
    res.update({"layout": str(layout) if isinstance(layout, (str, Path)) else "(in memory)",
                "envelope": str(envelope) if isinstance(envelope, (str, Path)) else env.name,
                "envelope_seed": env.seed, "half_angle_deg": float(st["half_angle_deg"]),
                "occlusion": "mesh" if mesh is not None else "none (no mesh: acceptance cone and field of view only)",
                "mesh": mesh_name, "sources": sources})
    if compare is not None:
        if other is None:
            oth = compare if isinstance(compare, Layout) else load_layout(compare)
            other = one(oth)
        other["layout"] = str(compare) if isinstance(compare, (str, Path)) else "(in memory)"
    if report is not None:
        res["report"] = write_score_report(report, res, other, R, t, env)
    if other is not None:
        res["compare"] = {k: v for k, v in other.items() if not k.startswith("_")}
        res["comparison"] = comparison_table(res, other)
    return res


#: the quantities of the comparison table: (label, key)
COMPARISON_ROWS = (("poses", "poses"), ("covered poses", "covered_poses"), ("coverage fraction", "coverage_fraction"),
                   ("ADOP worst (deg/rad)", "worst_adop"), ("ADOP p99", "p99_adop"), ("ADOP p95", "p95_adop"),
                   ("ADOP median", "median_adop"), ("PDOP worst (m/rad)", "worst_pdop"), ("PDOP p95", "p95_pdop"),
                   ("PDOP median", "median_pdop"))


def comparison_table(res, other) -> list:
    """One row per quantity (and per draw's worst ADOP): ``{"quantity", "layout", "compare", "ratio"}`` with
    ratio = compare / layout (None where undefined)."""
    rows = [(lab, res.get(k), other.get(k)) for lab, k in COMPARISON_ROWS]
    for i, (a, b) in enumerate(zip(res.get("draws", []), other.get("draws", []))):
        rows.append((f"draw {i} (seed {a['seed']}) ADOP worst", a["worst_adop"], b["worst_adop"]))
    out = []
    for lab, a, b in rows:
        ok = isinstance(a, (int, float)) and isinstance(b, (int, float)) and a not in (0, 0.0) and np.isfinite(a)
        out.append({"quantity": lab, "layout": a, "compare": b, "ratio": float(b / a) if ok else None})
    return out


def _pose_sets(envelope, poses, seed, draws):
    """``(Envelope, R, t, sizes)``: the envelope's pose set (``poses``/``seed`` overrides), or ``draws`` fresh
    draws of ``poses`` (default 2,000) each, concatenated (``sizes``: poses per draw)."""
    from ..envelope import envelope_set
    from ..optimize.heldout import HELDOUT_POSES_PER_DRAW, heldout_seed

    if not draws:
        env, R, t = envelope_set(envelope, poses, seed)
        return env, R, t, [len(R)]
    if seed is not None:
        raise ValueError("score: give either --seed (one pose set) or --draws (fresh draws with their own seeds)")
    env = envelope_set(envelope, 1)[0]
    if env.attitude == "trajectory":
        raise ValueError("score --draws: a trajectory envelope is a fixed pose list; there are no fresh draws")
    sets = [envelope_set(env, poses or HELDOUT_POSES_PER_DRAW, heldout_seed(env, i))[1:] for i in range(int(draws))]
    env = envelope_set(env, poses or HELDOUT_POSES_PER_DRAW, heldout_seed(env, 0))[0]
    return env, np.concatenate([r for r, _ in sets]), np.concatenate([t for _, t in sets]), [len(r) for r, _ in sets]


def _per_draw(out, sizes, env):
    """Worst ADOP and coverage of each draw (slices of the pooled arrays)."""
    from ..optimize.heldout import heldout_seed

    rows, s0 = [], 0
    for i, n in enumerate(sizes):
        a, cov = out["_adop"][s0:s0 + n], out["_covered"][s0:s0 + n]
        rows.append({"seed": heldout_seed(env, i), "poses": int(n), "covered_fraction": float(cov.mean()),
                     "worst_adop": float(a[cov].max()) if cov.any() else float("nan")})
        s0 += n
    return rows


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


class _Stream:
    """Running score of one layout over pose chunks (exact counts, max, mean; sketched quantiles)."""

    def __init__(self, n_sensors, stations):
        from ..parallel.sketch import LogHistogram, Moments

        self.hist = {q: LogHistogram(**_SKETCH) for q in ("adop", "pdop")}
        self.mom = {q: Moments() for q in ("adop", "pdop")}
        self.P = self.covered = self.singular = 0
        self.lit_min = None
        self.lit_any = np.zeros(n_sensors)
        self.lit_cov = np.zeros(n_sensors)
        self.lit_st = np.zeros((len(stations), n_sensors))
        self.uncovered = []

    def add(self, r, vis):
        cov = r["_covered"]
        for q in ("adop", "pdop"):
            x = r[f"_{q}"][cov]
            self.hist[q].add(x)
            self.mom[q].add(x)
        if self.uncovered is not None and len(self.uncovered) < 200:
            self.uncovered += (self.P + np.flatnonzero(~cov)).tolist()[:200 - len(self.uncovered)]
        self.P += len(cov)
        self.covered += int(cov.sum())
        self.singular += int(r["singular_covered_poses"])
        self.lit_min = r["lit_count_min"] if self.lit_min is None else min(self.lit_min, r["lit_count_min"])
        self.lit_any += vis.any(axis=1).sum(0)
        self.lit_cov += vis[cov].any(axis=1).sum(0)
        self.lit_st += vis.sum(0)

    def result(self, first: dict, stations) -> dict:
        out = dict(first)
        ok = self.covered > 0
        nan = float("nan")
        for q in ("adop", "pdop"):
            h, m = self.hist[q], self.mom[q]
            out.update({f"worst_{q}": m.max if ok else nan, f"mean_{q}": m.mean if ok else nan,
                        f"median_{q}": h.quantile(0.5) if ok else nan, f"p95_{q}": h.quantile(0.95) if ok else nan})
            if q == "adop":
                out["p99_adop"] = h.quantile(0.99) if ok else nan
            if m.nonfinite:  # inf DOP (singular) among the covered poses: the worst is inf
                out[f"worst_{q}"] = float("inf")
        ids = [u["id"] for u in first["per_sensor"]]
        out["per_sensor"] = [{"id": ids[i], "lit_fraction": float(self.lit_any[i] / self.P),
                              "lit_fraction_per_station": {s.id: float(self.lit_st[k, i] / self.P)
                                                           for k, s in enumerate(stations)},
                              "lit_fraction_covered_poses": float(self.lit_cov[i] / self.covered) if ok else 0.0}
                             for i in range(len(ids))]
        out.update({"poses": self.P, "covered_poses": self.covered, "coverage_fraction": self.covered / self.P,
                    "singular_covered_poses": self.singular, "uncovered_pose_indices": self.uncovered,
                    "lit_count_min": int(self.lit_min), "success": ok, "status": "ok" if ok else "no_coverage",
                    "message": (f"{self.covered}/{self.P} poses covered ({out['coverage_rule']}, >= "
                                f"{out['min_visible']} lit)" if ok else
                                f"no pose of {self.P} has {out['min_visible']} lit sensors by the "
                                f"{out['coverage_rule']} rule")})
        return out


def _score_streamed(lay, env, poses: int, mesh, st: dict, compare, progress):
    """Score ``poses`` envelope poses in chunks of :data:`CHUNK_POSES` (memory flat for any count).

    Chunk k draws its poses with the seed ``SeedSequence([env.seed, k])`` (a streamed set is the same
    for any machine, not the one-shot draw of the same count). Counts, worst and mean are exact; the
    median / p95 / p99 come from a log histogram (``result["streamed"]`` gives its resolution). The
    ``_adop``/``_pdop``/``_covered`` arrays (report plots) are the first chunk's. Returns
    ``(result, compare result or None, (R, t) of the first chunk)``."""
    import dataclasses

    from ..layout import Layout, load_layout
    from ..optimize import DesignProblem

    lays = [lay] + ([compare if isinstance(compare, Layout) else load_layout(compare)] if compare is not None else [])
    streams, firsts, first_pose = None, None, None
    done = k = 0
    while done < poses:
        n = min(CHUNK_POSES, poses - done)
        seed = int(np.random.SeedSequence([int(env.seed), k]).generate_state(1)[0])
        ck = dataclasses.replace(env, count=n, seed=seed)
        res = []
        for L in lays:
            pb = DesignProblem.load(mesh, ck, candidates=L, half_angle_deg=st["half_angle_deg"])
            r = score_arrays(L.positions, pb.visible, pb.rotations, pb.translations, pb.stations, rho=st["rho"],
                             min_visible=st["min_visible"], coverage=st["coverage"], ids=L.ids)
            res.append((r, pb.visible))
        if streams is None:
            streams = [_Stream(len(L.ids), pb.stations) for L in lays]
            firsts = [r for r, _ in res]
            first_pose = (pb.rotations, pb.translations)
        for sm, (r, vis) in zip(streams, res):
            sm.add(r, vis)
        done += n
        k += 1
        if progress is not None:
            progress(n)
    sketch = {"chunks": k, "chunk_poses": CHUNK_POSES, "quantiles": "log histogram",
              "relative_resolution": 10 ** (1 / _SKETCH["bins_per_decade"]) - 1,
              "plots": f"the first {len(firsts[0]['_covered'])} poses"}
    out = [sm.result(f, pb.stations) | {"streamed": sketch} for sm, f in zip(streams, firsts)]
    return out[0], (out[1] if len(out) > 1 else None), first_pose
