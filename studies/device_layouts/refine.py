"""Issue 27: refine a study row's layout by local search over sites and finer mounting angles on a large pose set.

    .venv/bin/python studies/device_layouts/refine.py --device wm0_tangent --start tilt_facets_az4 \\
        [--design-poses 50000] [--levels 3] [--azimuths 8] [--neighbours 6] [--time-limit-s 900] [--tag _r]

The dense loop (``run.py``) chooses among five orientations per site (the surface normal and 25° towards four
azimuths) on working sets of ~1,500 poses. This stage starts from one of its layouts and moves one sensor at a
time: to any of its site's or the ``--neighbours`` nearest sites' orientations on a finer grid (tilt
``max·j/levels``, j = 0 … levels, towards ``--azimuths`` azimuths, :func:`layoutkit.optimize.tilt.tilt_orientations`;
every tilt stays ≤ ``--max-tilt-deg`` about the site's own normal), on ``--design-poses`` poses of the envelope
(seed ``envelope seed + --design-seed``, disjoint from every set the study scores on). A move is kept when it
lowers the objective: first the number of design poses with fewer than ``4 + --spare-lit`` lit sensors (lit at
``--coverage-half-angle-deg``: a margin), then
the L_p norm of ADOP over the design poses (``--p``, a smooth stand-in for the worst case that also pays for
lowering the poses just below the worst), and in a last phase the worst case itself (ties by L_p). The ``swap``
phase instead runs the package's exact 1- and 2-swap local search (:func:`layoutkit.optimize.search.local_search`)
for the worst case on a working set of the hardest design poses, keeping every design pose covered (its ``cover``
poses), and grows the working set by the design poses that refute its result; ``--kicks`` then restarts it from
random 2–3-sensor perturbations of the incumbent (iterated local search). The sites
are the row's own (the housing's sites sampled 8 mm apart, plus the device's mounting facets for a
``run.py --facet-sites`` row); ``--pool-radius-mm R`` keeps only the sites within R of the start's sensors (0: their
own sites), a pool small enough for a finer orientation grid or a swap working set of thousands of poses.

Exact visibility (ray-cast, :func:`layoutkit.optimize.design.layout_visibility`) of every (site, orientation)
candidate at the design poses is computed once; a move costs one :func:`layoutkit.dop_batch.batch_dop` call.
The run's own reported value is the worst ADOP on ``--check-poses`` poses of a further disjoint seed
(``--check-seed``), at the physical 60° acceptance angle — chosen rows are chosen by it, never by the study's sets.

Writes ``results/<device>/refine<tag>.layout.json`` and ``refine<tag>.json`` (spec, per-phase history, design
and check values); ``run.py --stage score`` and ``large_draws.py`` then score it like every other row. Ctrl-C (or
SIGTERM) ends the search after its current step, and the incumbent is checked and written like a finished run's
(its history's last entry names the signal) and the run exits 128 + the signal's number
(:func:`layoutkit.live.stopping.stop_on_signals`); a second Ctrl-C, or Ctrl-C before the search starts, ends the run
at once without writing. An ablation
(``--view-angle-deg``: design for one region of the envelope) writes to ``results/<device>/ablations/`` instead.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from devices import device_of_folder, mesh_path
from run import (
    RHO,
    SCORE_HALF_ANGLE_DEG,
    M,
    _commit,
    _scores,
    append_sites,
    facet_candidates,
)


def _pool(sites, max_tilt_deg, levels, azimuths):
    """(site, orientation) candidates of ``sites`` (Layout): positions, axes (M, 3), site (M,), tilt_deg (M,)."""
    from layoutkit.optimize.tilt import tilt_orientations

    lev = tuple((j + 1) / levels for j in range(levels))
    return tilt_orientations(sites.positions, sites.normals, max_tilt_deg, azimuths, levels=lev)


def _nearest_site(sites, points):
    """(n,) index of the site (Layout) nearest each of ``points`` (n, 3)."""
    return np.argmin(np.linalg.norm(sites.positions[None] - np.asarray(points)[:, None], axis=2), axis=1)


def _tail_mean(values, k):
    """mean of the ``k`` largest of ``values`` (the conditional value at risk of the top ``k``)."""
    k = min(k, values.size)
    return float(np.mean(np.partition(values, values.size - k)[values.size - k:])) if k else math.inf


def _excess(values, target):
    """sum of squared relative excesses of ``values`` over ``target`` (0 when every value is under it)."""
    return float(np.sum(np.maximum(values / target - 1.0, 0.0) ** 2)) if target else math.inf


def _objective(adop, n_lit, need, p, k_tail, target):
    """(uncovered design poses, L_p norm of ADOP over the others, worst ADOP over the others, mean of their
    ``k_tail`` worst, their excess over ``target``)."""
    ok = (n_lit >= need) & np.isfinite(adop)
    a = adop[ok]
    if a.size == 0:
        return (int((~ok).sum()), math.inf, math.inf, math.inf, math.inf)
    w = float(a.max())
    return (int((~ok).sum()), w * float(np.mean((a / w) ** p)) ** (1.0 / p), w, _tail_mean(a, k_tail),
            _excess(a, target))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="wm0_tangent", help="results folder of the device (hmd, wm0_tangent, ...)")
    ap.add_argument("--start", required=True, help="row whose layout to start from (<start>.layout.json; 'shipped': the device's own layout)")
    ap.add_argument("--design-poses", type=int, default=50000)
    ap.add_argument("--design-seed", type=int, default=5000, help="design poses: envelope seed + this")
    ap.add_argument("--view-angle-deg", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                    help="an ablation: keep only the design poses whose view angle (regions.py) is in [LO, HI)")
    ap.add_argument("--check-poses", type=int, default=20000)
    ap.add_argument("--check-seed", type=int, default=6000, help="the run's own held-out check: envelope seed + this")
    ap.add_argument("--spacing-mm", type=float, default=None,
                    help="resample the housing's sites this far apart (site seed --seed; the start's own sites are kept); "
                         "default: the start row's sites")
    ap.add_argument("--max-tilt-deg", type=float, default=25.0)
    ap.add_argument("--levels", type=int, default=3, help="tilt levels max·j/levels, j = 1 … levels (and 0)")
    ap.add_argument("--azimuths", type=int, default=8)
    ap.add_argument("--pool-radius-mm", type=float, default=None,
                    help="keep only the candidates at sites within this distance of the start's sensors (0: their "
                         "own sites): a small pool, so that a finer orientation grid or a large swap working set fits")
    ap.add_argument("--neighbours", type=int, default=0,
                    help="a sensor may move to this many nearest sites (its own included); 0: to any free site")
    ap.add_argument("--screen", type=int, default=2000,
                    help="moves of a sensor are screened on this many worst design poses (and every pose that would be "
                         "uncovered without it)")
    ap.add_argument("--verify", type=int, default=8, help="the best screened moves scored on every design pose")
    ap.add_argument("--tol", type=float, default=1e-3,
                    help="a move is kept when it lowers the phase's objective by more than this fraction")
    ap.add_argument("--phases", nargs="+", default=["lp", "worst"], choices=("lp", "worst", "tail", "excess", "swap"),
                    help="objectives in turn, each to convergence: lp (L_p norm), worst (worst case), tail (mean of "
                         "the --tail-fraction worst design poses: what the worst of a smaller fresh draw estimates), excess (sum "
                         "of squared relative excesses over --target: every region above it pays, so one move may lower "
                         "one region while another still holds the worst), swap (worst case by the package's exact "
                         "1- and 2-swap local search, layoutkit.optimize.search.local_search, on a working set of the "
                         "hardest design poses that grows by the design poses refuting its result, every design pose "
                         "kept covered: a 2-swap moves two sensors at once, where the one-sensor phases stall)")
    ap.add_argument("--working-poses", type=int, default=2000,
                    help="swap phase: the working set starts as this many worst design poses; it grows by at most "
                         "this many refuting poses per round")
    ap.add_argument("--max-working-poses", type=int, default=3000,
                    help="swap phase: the working set's cap (memory ~60 · poses · candidates · 8 bytes); past it the "
                         "poses easiest for the current layout leave")
    ap.add_argument("--kicks", type=int, default=0,
                    help="swap phase: after it converges, this many times replace 2-3 random sensors (random moves that "
                         "keep every design pose covered) and search again from there; kept when the design worst drops")
    ap.add_argument("--pool-size", type=int, default=24,
                    help="swap phase: 2-swaps add two of this many most promising candidates")
    ap.add_argument("--target", type=float, default=None, help="ADOP the excess phase pushes every design pose under")
    ap.add_argument("--tail-fraction", type=float, default=0.01,
                    help="share of the design poses whose mean ADOP the tail phase lowers")
    ap.add_argument("--half-angle-deg", type=float, default=SCORE_HALF_ANGLE_DEG, help="design acceptance half-angle")
    ap.add_argument("--spare-lit", type=int, default=0, help="design poses must light 4 + this many sensors")
    ap.add_argument("--coverage-half-angle-deg", type=float, default=None,
                    help="acceptance half-angle at which the lit count of the coverage constraint is taken (a margin, "
                         "as run.py's --half-angle-deg; default --half-angle-deg); ADOP is always at --half-angle-deg")
    ap.add_argument("--p", type=float, default=32.0, help="exponent of the L_p objective")
    ap.add_argument("--time-limit-s", type=float, default=900.0)
    ap.add_argument("--seed", type=int, default=0, help="order in which sensors are visited")
    ap.add_argument("--tag", default="")
    a = ap.parse_args()
    if "excess" in a.phases and not a.target:
        ap.error("the excess phase needs --target (an ADOP, deg/rad)")

    from layoutkit.dop_batch import batch_dop
    from layoutkit.envelope import envelope_set, load_envelope
    from layoutkit.io.atomic import atomic_write_text
    from layoutkit.io.jsonfile import to_jsonable
    from layoutkit.layout import Layout, load_layout, save_layout
    from layoutkit.live.stopping import stop_on_signals
    from layoutkit.mesh import load_mesh
    from layoutkit.optimize.design import layout_visibility

    t_start = time.perf_counter()
    folder = HERE / "results" / a.device
    # "shipped": the device's own layout, which is the facet sites untilted (run.py --facet-sites, site seed 0)
    start_spec = ({"facet_sites": True, "spec": {"seed": 0}} if a.start == "shipped"
                  else json.loads((folder / f"{a.start}.json").read_text()))
    dev = device_of_folder(a.device)
    env = load_envelope(folder / "env.toml")
    mesh = load_mesh(str(mesh_path(folder)))
    seed0 = start_spec.get("site_seed", start_spec["spec"]["seed"]) or 0  # a refine row: its start row's
    # rows record their site spacing since session 10; every earlier row used run.py's default, 8 mm
    spacing = start_spec.get("spacing_m", 8e-3)
    facets = bool(start_spec.get("facet_sites"))
    sites = facet_candidates(dev, folder, spacing, seed0, facets=facets)
    extra = start_spec.get("extra_sites") or []  # a --spacing-mm row's kept sites
    if extra:
        sites = append_sites(sites, [e["position"] for e in extra], [e["normal"] for e in extra],
                              [e["id"] for e in extra])
    start = load_layout(folder / ("shipped.json" if a.start == "shipped" else f"{a.start}.layout.json"))
    if a.spacing_mm is not None:  # resample the sites, keeping the ones the start's sensors sit on
        on = np.unique(_nearest_site(sites, start.positions)).tolist()
        keep = [i for i in on if not sites.ids[i].startswith("facet") or not facets]
        extra = [{"id": sites.ids[i] if sites.ids[i].startswith("start:") else f"start:{sites.ids[i]}",
                  "position": sites.positions[i].tolist(), "normal": sites.normals[i].tolist()} for i in keep]
        new = facet_candidates(dev, folder, a.spacing_mm * 1e-3, a.seed, facets=facets)
        sites = append_sites(new, sites.positions[keep], sites.normals[keep], [e["id"] for e in extra])
        spacing, seed0 = a.spacing_mm * 1e-3, a.seed
    pos, axes, site, tilt = _pool(sites, a.max_tilt_deg, a.levels, a.azimuths)
    if a.pool_radius_mm is not None:  # the sites near the start's sensors only (every orientation of each)
        d = np.linalg.norm(sites.positions[:, None] - start.positions[None], axis=2).min(axis=1)
        keep = np.flatnonzero(d[site] <= a.pool_radius_mm * 1e-3 + 1e-9)
        pos, axes, site, tilt = pos[keep], axes[keep], site[keep], tilt[keep]
    # the start layout's own sensors are candidates too (their 25° azimuths need not be on this grid)
    start_site = _nearest_site(sites, start.positions)
    start_tilt = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", start.normals, sites.normals[start_site]), -1, 1)))
    if np.max(np.linalg.norm(sites.positions[start_site] - start.positions, axis=1)) > 1e-9:
        raise SystemExit(f"{a.start}: its sensors are not at the row's candidate sites")
    if np.max(start_tilt) > a.max_tilt_deg + 1e-6:
        raise SystemExit(f"{a.start}: a sensor is tilted {np.max(start_tilt):.1f}° from its site's normal, over "
                         f"--max-tilt-deg {a.max_tilt_deg:g}")
    pos, axes = np.vstack([pos, start.positions]), np.vstack([axes, start.normals])
    site, tilt = np.concatenate([site, start_site]), np.concatenate([tilt, start_tilt])
    n_pool = len(pos)
    sel = np.arange(n_pool - start.n, n_pool)

    _, R, t = envelope_set(env, count=a.design_poses, seed=env.seed + a.design_seed)
    if a.view_angle_deg is not None:  # an ablation: design for one region of the envelope only
        from regions import view_angle

        va = view_angle(env, dev.front, R, t)
        inside = np.flatnonzero((va >= a.view_angle_deg[0]) & (va < a.view_angle_deg[1]))
        R, t = R[inside], t[inside]
    k_tail = max(1, round(a.tail_fraction * len(R)))  # checked before the ray casting
    if k_tail > a.screen:
        raise SystemExit(f"--tail-fraction {a.tail_fraction:g} is {k_tail} poses, more than --screen {a.screen}")
    print(f"{n_pool} candidates ({np.unique(site).size} sites x {1 + a.levels * a.azimuths} orientations + {start.n} start), "
          f"{len(R)} design poses", flush=True)

    def pool_visibility(half_angle, occluder=mesh, within=None):
        """(P, S, n_pool) visibility of every candidate at the design poses; ``occluder=None``: acceptance cone
        and field of view only, and-ed with ``within`` (P, S, n_pool) chunk by chunk"""
        parts = []
        for i in range(0, n_pool, 200):
            v = layout_visibility(occluder, pos[i:i + 200], axes[i:i + 200], R, t, env.stations, half_angle)
            parts.append(v if within is None else v & within[:, :, i:i + 200])
        return np.concatenate(parts, axis=2)

    vis = pool_visibility(a.half_angle_deg)
    cov_angle = a.half_angle_deg if a.coverage_half_angle_deg is None else a.coverage_half_angle_deg
    if cov_angle == a.half_angle_deg:
        vis_cov = vis
    elif cov_angle < a.half_angle_deg:  # a narrower cone: occlusion does not depend on the angle, no second ray cast
        vis_cov = pool_visibility(cov_angle, occluder=None, within=vis)
    else:
        vis_cov = pool_visibility(cov_angle)
    print(f"visibility: {time.perf_counter() - t_start:.0f} s", flush=True)
    need = M + a.spare_lit
    near = np.argsort(np.linalg.norm(sites.positions[:, None] - sites.positions[None], axis=2), axis=1)[:, :a.neighbours]
    by_site = [np.flatnonzero(site == s) for s in range(sites.n)]

    def evaluate(s, q=None):
        """per-pose ADOP and lit count (coverage angle) of candidate subset ``s`` at the design poses (or at the
        screening poses ``q = (index, vis[index], vis_cov[index])``)"""
        if q is None:
            d = batch_dop(pos[s], R, t, rho=RHO, visible=vis[:, :, s], stations=env.stations)
            return d.adop, vis_cov[:, :, s].sum(axis=(1, 2))
        idx, vq, vcq = q
        d = batch_dop(pos[s], R[idx], t[idx], rho=RHO, visible=vq[:, :, s], stations=env.stations)
        return d.adop, vcq[:, :, s].sum(axis=(1, 2))

    def key(obj, phase):
        return {"lp": (obj[0], obj[1], obj[2]), "worst": (obj[0], obj[2], obj[1]),
                "tail": (obj[0], obj[3], obj[2]), "excess": (obj[0], obj[4], obj[2])}[phase]

    def screening_set(adop, lit, i):
        """the design poses a move of sensor i is screened on: the ``--screen`` worst (by ADOP) and every pose that
        would be uncovered without sensor i (only there can the move uncover a pose; the new sensor only adds)"""
        a_ = np.where(np.isfinite(adop), adop, np.inf)
        top = np.argsort(a_)[-a.screen:]
        risk = lit - vis_cov[:, :, sel[i]].sum(axis=1) < need  # without sensor i's lit pairs
        idx = np.union1d(top, np.flatnonzero(risk))
        return idx, vis[idx], vis_cov[idx]

    def free_moves(s_, i, sites_i):
        """the candidates sensor i of selection ``s_`` may move to: every orientation of ``sites_i`` that no
        other sensor occupies, its own candidate excluded"""
        taken = set(site[s_].tolist()) - {int(site[s_[i]])}
        return [c for x in sites_i if int(x) not in taken for c in by_site[x] if c != s_[i]]

    def step(i, phase, cur, cur_adop, cur_lit):
        """the best verified one-sensor move of sensor i, or None. Every candidate is first scored on the
        screening poses: in the worst phase a move whose screened worst (a lower bound of its worst) is not below
        the current worst, or that uncovers a screened pose, is rejected exactly; in the L_p phase the other poses
        keep their current terms. The ``--verify`` best screened moves are then scored on every design pose."""
        cands = free_moves(sel, i, near[site[sel[i]]] if a.neighbours else range(sites.n))
        q = screening_set(cur_adop, cur_lit, i)
        ok_cur = (cur_lit >= need) & np.isfinite(cur_adop)
        w = cur[2]
        rest = ok_cur.copy()  # the covered poses off the screening set keep their current L_p terms
        rest[q[0]] = False
        rest_sum = float(np.sum((cur_adop[rest] / w) ** a.p))
        scored = []
        for c in cands:
            trial = sel.copy()
            trial[i] = c
            ad, lit = evaluate(trial, q)
            ok = (lit >= need) & np.isfinite(ad)
            unc = int((~ok).sum())
            if phase == "worst":
                wq = float(ad[ok].max()) if ok.any() else math.inf
                if unc or wq >= w:
                    continue
                scored.append(((0, wq), c))
            elif phase == "excess":  # poses off the screening set are under the target unless the move lifts them
                scored.append(((unc, _excess(ad[ok], a.target) + _excess(cur_adop[rest], a.target)), c))
            elif phase == "tail":  # the screening set holds the current tail; the other poses keep their values
                scored.append(((unc, _tail_mean(np.concatenate([ad[ok], cur_adop[rest]]), k_tail)), c))
            else:
                lp = w * ((rest_sum + float(np.sum((ad[ok] / w) ** a.p))) / len(cur_adop)) ** (1.0 / a.p)
                scored.append(((unc, lp), c))
        scored.sort(key=lambda x: x[0])
        for _, c in scored[:a.verify]:
            trial = sel.copy()
            trial[i] = c
            ad, lit = evaluate(trial)
            obj = _objective(ad, lit, need, a.p, k_tail, a.target)
            k_new, k_cur = key(obj, phase), key(cur, phase)
            if k_new[0] < k_cur[0] or (k_new[0] == k_cur[0] and k_new[1] < k_cur[1] * (1 - a.tol)):
                return c, obj, ad, lit
        return None

    def kick(s_, cover, rng):
        """``s_`` with 2-3 random sensors moved, one at a time, to random candidates keeping every design pose
        covered (and one sensor per site)"""
        from layoutkit.optimize.search import cover_one_swaps

        s_ = np.array(s_)
        for _ in range(int(rng.integers(2, 4))):
            r = int(rng.integers(len(s_)))
            adds = np.sort(free_moves(s_, r, range(sites.n)))  # in index order, as the seeded draw expects
            ok = cover_one_swaps(cover, need, s_, adds)[r]
            if ok.any():
                s_[r] = rng.choice(adds[ok])
        return s_

    def swap_rounds(s_, cur, cur_adop, cur_lit, cover, conflict, W=None):
        """The swap phase (``--phases`` help): rounds of exact 1-/2-swap local search (worst ADOP) on a working
        set W of design poses (default: the ``--working-poses`` worst), every design pose kept covered
        (``cover``: (P, N) lit counts; ``conflict``: (N, N) bool, one sensor per site); each result is scored on every design pose and kept when it lowers the
        worst over them (by more than rounding) without uncovering one; the design poses above its working-set worst join W.
        Returns the kept selection and state, the per-round history and the last W."""
        from layoutkit.optimize.core import candidate_jacobians
        from layoutkit.optimize.objectives import parse_objective
        from layoutkit.optimize.problem import build_problem
        from layoutkit.optimize.search import local_search

        obj_w = parse_objective("worst-adop")
        order = np.argsort(np.where(np.isfinite(cur_adop), cur_adop, np.inf))
        W = np.union1d(order[-min(a.working_poses, a.max_working_poses):], [] if W is None else W).astype(int)
        if W.size > a.max_working_poses:
            W = np.sort(W[np.argsort(-cur_adop[W])][:a.max_working_poses])
        rounds, seen = [], {W.tobytes()}
        while running():
            jac = candidate_jacobians(pos, R[W], t[W], env.stations)
            prob = build_problem(jac, vis[W], RHO, len(s_), need, obj_w, conflict=conflict,
                                 lit=vis_cov[W].sum(axis=1))
            del jac
            new, w_val, moves = local_search(prob, np.sort(s_), two_swap=True, pool_size=a.pool_size,
                                             deadline=deadline, cover=cover)
            del prob
            ad, lit = evaluate(new)
            obj = _objective(ad, lit, need, a.p, k_tail, a.target)
            kept = obj[0] <= cur[0] and obj[2] < cur[2] * (1 - 1e-6)
            bad = np.flatnonzero(~((lit >= need) & np.isfinite(ad)) | (ad > w_val * (1 + 1e-9)))
            rounds.append({"working_poses": int(W.size), "moves": int(moves), "working_worst": float(w_val),
                           "design_worst": obj[2], "uncovered": obj[0], "kept": bool(kept),
                           "refuting_poses": int(bad.size), "time_s": time.perf_counter() - t_start})
            print(f"swap round: W {W.size}, {moves} moves, W worst {w_val:.0f}, design worst {obj[2]:.0f} "
                  f"(uncovered {obj[0]}), {bad.size} refuting, {'kept' if kept else 'not kept'} "
                  f"({time.perf_counter() - t_start:.0f} s)", flush=True)
            if kept:
                s_, cur, cur_adop, cur_lit = np.asarray(new), obj, ad, lit
            if bad.size == 0 or (moves == 0 and not kept):
                break
            add = bad[np.argsort(-np.where(np.isfinite(ad[bad]), ad[bad], np.inf))][:a.working_poses]
            old = np.setdiff1d(W, add)
            room = a.max_working_poses - add.size
            if old.size > room:  # full: the old poses easiest for both the incumbent and this result leave
                old = old[np.argsort(-np.maximum(cur_adop[old], ad[old]))][:max(room, 0)]
            W = np.union1d(old, add)
            if W.tobytes() in seen:  # the capped working set cycles: no result will hold on the design poses
                break
            seen.add(W.tobytes())
        return s_, cur, cur_adop, cur_lit, rounds, W

    rng = np.random.default_rng(a.seed)
    cur_adop, cur_lit = evaluate(sel)
    cur = _objective(cur_adop, cur_lit, need, a.p, k_tail, a.target)
    history = [{"phase": "start", "time_s": time.perf_counter() - t_start, "uncovered": cur[0], "lp": cur[1],
                "worst": cur[2], "tail_mean": cur[3], "excess": cur[4]}]
    print(f"start: uncovered {cur[0]}, L{a.p:g} {cur[1]:.0f}, worst {cur[2]:.0f}, tail {cur[3]:.0f}, excess {cur[4]:.3g}", flush=True)
    deadline = t_start + a.time_limit_s

    def running():
        return not stop.requested and time.perf_counter() < deadline

    def heard(name):
        print(f"{name}: ending the search after the current step; the incumbent is checked and written "
              "(Ctrl-C again: stop at once)", flush=True)

    # Ctrl-C / SIGTERM end the search between steps; the incumbent is still checked and written
    with stop_on_signals(interrupt=True, on_request=heard) as stop:
        for phase in a.phases:
            if phase == "swap":
                if cur[0]:  # the swap search keeps every design pose covered: it needs a start that covers them
                    print(f"swap phase skipped: {cur[0]} design poses have fewer than {need} lit", flush=True)
                    history.append({"phase": phase, "skipped": f"{cur[0]} design poses uncovered at the start"})
                    continue
                # (P, N) lit counts: every move keeps every design pose covered (one station: a view, no copy)
                cover = vis_cov[:, 0] if vis_cov.shape[1] == 1 else vis_cov.sum(axis=1, dtype=np.uint8)
                conflict = site[:, None] == site[None, :]  # one sensor per site (a site's orientations conflict)
                np.fill_diagonal(conflict, False)
                sel, cur, cur_adop, cur_lit, rounds, W = swap_rounds(sel, cur, cur_adop, cur_lit, cover, conflict)
                kicks = []
                for _ in range(a.kicks):
                    if not running():
                        break
                    ks = kick(sel, cover, rng)
                    k_adop, k_lit = evaluate(ks)
                    k_obj = _objective(k_adop, k_lit, need, a.p, k_tail, a.target)
                    s2, o2, ad2, lit2, r2, W2 = swap_rounds(ks, k_obj, k_adop, k_lit, cover, conflict, W)
                    better = o2[0] <= cur[0] and o2[2] < cur[2] * (1 - 1e-6)  # a lower worst, not rounding
                    kicks.append({"kicked_worst": k_obj[2], "searched_worst": o2[2], "kept": bool(better),
                                  "rounds": len(r2), "time_s": time.perf_counter() - t_start})
                    print(f"kick {len(kicks)}: {k_obj[2]:.0f} -> {o2[2]:.0f} ({'kept' if better else 'not kept'}; "
                          f"incumbent {min(cur[2], o2[2]):.0f})", flush=True)
                    if better:
                        sel, cur, cur_adop, cur_lit, W = s2, o2, ad2, lit2, W2
                history.append({"phase": phase, "time_s": time.perf_counter() - t_start, "uncovered": cur[0],
                                "lp": cur[1], "worst": cur[2], "tail_mean": cur[3], "excess": cur[4],
                                "moves": sum(r["moves"] for r in rounds if r["kept"]), "rounds": rounds,
                                "kicks": kicks})
                continue
            improved = True
            while improved and running():
                improved, moves = False, 0
                for i in rng.permutation(len(sel)):
                    if not running():
                        break
                    found = step(i, phase, cur, cur_adop, cur_lit)
                    if found is not None:
                        sel[i], cur, cur_adop, cur_lit = found
                        improved, moves = True, moves + 1
                history.append({"phase": phase, "time_s": time.perf_counter() - t_start, "uncovered": cur[0],
                                "lp": cur[1], "worst": cur[2], "tail_mean": cur[3], "excess": cur[4], "moves": moves})
                print(f"{phase} sweep: {moves} moves, uncovered {cur[0]}, L{a.p:g} {cur[1]:.0f}, worst {cur[2]:.0f}, "
                      f"tail {cur[3]:.0f}, excess {cur[4]:.3g} "
                      f"({time.perf_counter() - t_start:.0f} s)", flush=True)

        lay = Layout(pos[sel], axes[sel], tuple(f"S{i + 1:02d}" for i in range(len(sel))),
                     {"x-refined-from": a.start},
                     tuple({"x-site": sites.ids[int(site[c])], "x-tilt-deg": float(tilt[c])} for c in sel))
        # an ablation covers part of the envelope only: its rows live apart, out of run.py's score stage
        dest = folder / "ablations" if a.view_angle_deg is not None else folder
        dest.mkdir(exist_ok=True)
        out = dest / f"refine{a.tag}.layout.json"
        save_layout(lay, out)
        # the run's own held-out check: fresh poses, scored as the study scores every row (run._scores: 60°,
        # self-occlusion)
        sc = _scores(out, str(mesh_path(folder)), env, sets=[("check", a.check_poses, a.check_seed)])["check"]
        check = {"poses": a.check_poses, "seed_offset": a.check_seed, "covered_fraction": sc["covered_fraction"],
                 "worst_adop": sc["worst_adop_over_covered"]}
        status = "ok" if cur[0] == 0 and sc["covered_fraction"] == 1.0 else "incomplete"
        if stop.requested:  # the layout is still a valid row (its check is real); the history says where it was cut
            history.append({"phase": "stopped", "signal": stop.name, "time_s": time.perf_counter() - t_start})
        region = ""
        if a.view_angle_deg is not None:  # an ablation is checked on its own region of the check poses
            _, Rc, tc = envelope_set(env, count=a.check_poses, seed=env.seed + a.check_seed)
            va = view_angle(env, dev.front, Rc, tc)
            x = sc["_adop"][(va >= a.view_angle_deg[0]) & (va < a.view_angle_deg[1])]
            check.update(poses=int(x.size), covered_fraction=float(np.isfinite(x).mean()),
                         worst_adop=float(np.max(x[np.isfinite(x)])))
            status, region = "ablation", f" with view angle in [{a.view_angle_deg[0]:g}, {a.view_angle_deg[1]:g})°"
        res = {"spec": vars(a), "start": a.start, "facet_sites": bool(start_spec.get("facet_sites")), "site_seed": seed0, "spacing_m": spacing,
               "extra_sites": extra,
               "candidates": n_pool, "status": status,
               "value": check["worst_adop"], "value_refers_to": f"worst ADOP over the {check['poses']} fresh poses{region} "
               f"(envelope seed + {a.check_seed}), 60° acceptance, self-occlusion", "check": check,
               "design": {"uncovered": cur[0], "lp": cur[1], "worst_adop": cur[2], "tail_mean_adop": cur[3], "excess": cur[4]}, "history": history,
               "tilt_deg": [float(tilt[c]) for c in sel], "sites": [sites.ids[int(site[c])] for c in sel],
               "wall_s": time.perf_counter() - t_start, "loadavg_end": os.getloadavg(), "layout": str(out),
               "code_commit": _commit()}
        atomic_write_text(dest / f"refine{a.tag}.json", json.dumps(to_jsonable(res), indent=1) + "\n")
        cut = f" (search cut by {stop.name})" if stop.requested else ""
        print(f"{status}{cut}: check worst {check['worst_adop']:.0f} (covered {check['covered_fraction']:.4f}) -> {out}")
    if stop.requested:  # the shell's convention for a run ended by a signal (its row is written)
        sys.exit(128 + stop.signum)


if __name__ == "__main__":
    try:
        main()
    except KeyboardInterrupt:  # before the search (sites, ray casting) or a second Ctrl-C: nothing is written
        sys.exit("interrupted: nothing written")
