"""Dense envelopes by adaptive pose generation (issue 13, item 1).

Worst-case optimisation over a small pose sample fits the sample: the worst case of a continuous
envelope sits at its rim (grazing attitudes, far range), which 200 random poses sample sparsely.
Here the optimiser works on a *working set* of poses, the incumbent is evaluated on a *dense set*
of the same envelope (design poses + ``dense_poses`` more from seed ``envelope.seed + 1``, by the
fused kernel :func:`layoutkit.dop_batch.batch_dop`), and the loop is

1. working set = design poses + dense poses: by default (``seed_poses="all"``) as many as fit the memory
   budget :data:`WORKING_BYTES` — the whole dense set when it fits, since the search generates poses
   itself (the relaxation's active poses, the local search's critical poses with every move confirmed on
   all working poses by the fused kernels of :mod:`layoutkit.optimize.kernels`); a subset is chosen by
   farthest-point sampling of the pose descriptors (:func:`pose_descriptors`: direction of every station
   in the body frame and the range) — a space-filling design of the envelope that reaches its rim;
2. round 0: the caller's method (the pipeline: relaxation, roundings, local search) on the working
   set with ``first_share`` of the budget; later rounds: method ``polish`` (local search and
   random kicks from the best layout so far, no relaxation — seconds per round, so many rounds fit);
3. evaluate the round's layout on the dense set (DOP) and on ``coverage_poses`` more poses (coverage
   only), add up to ``add`` poses: uncovered coverable ones first, then dense poses above the
   working-set value, worst first and spread over the envelope (no two new poses closer than
   ``min_sep`` in descriptor space while enough others are left); poses no layout can cover are
   skipped and counted; repeat.

A round in which no dense pose exceeds the working-set value by more than ``tol`` adds nothing
and the next round is a full *polish* of that working set (1- and 2-swaps, the full kick patience).
The loop stops when the dense-set worst case has not improved for ``patience`` rounds (rounds on a
working set that grew before them do not count), the working
set reaches ``max_working`` poses (bounded memory: the optimiser holds O(working set × candidates)),
k cannot cover the working set, or the budget (``time_limit``) ends; Ctrl-C / SIGTERM keeps the best
finished round. The layout with the best dense-set value (fewest uncovered poses first) is kept;
``info["working_*"]`` is the working set it was tuned on — its "design set".

Certificate: the working set is a subset of the dense set (design + dense poses + the coverage
poses that joined the working set; the dense value is taken over all of them), so the relaxation
bound of any round (a lower bound for the working set) is also a lower bound for the dense set; the
gap reported is ``dense value / bound - 1``.
"""
from __future__ import annotations

import math
import time

import numpy as np

__all__ = ["dense_optimize", "evaluate_selection", "pose_descriptors", "farthest_point_poses",
           "far_range_poses", "range_sweep_poses", "working_capacity", "WORKING_BYTES"]


def evaluate_selection(prep, sel, R, t, rho, min_visible, coverage):
    """Per-pose ADOP, PDOP and coverage of candidate subset ``sel`` at world poses ``R, t``."""
    from ..coverage_rule import covered, layout_counts
    from ..dop_batch import batch_dop
    from .score import layout_visibility

    cand = prep["candidates"]
    pos, nor = cand.positions[sel], cand.normals[sel]
    vis = layout_visibility(prep["mesh"], pos, nor, R, t, prep["stations"], prep["sensor_half_angle_deg"])
    d = batch_dop(pos, R, t, rho=rho, visible=vis, stations=prep["stations"])
    cov = covered(layout_counts(vis, coverage), min_visible)
    return d.adop, d.pdop, cov


def pose_descriptors(R, t, stations, range_weight=0.5, range_span=None):
    """Pose descriptors ``(P, 3 S + 1)`` for space-filling pose designs.

    R (P, 3, 3), t (P, 3): body poses in the world frame (``p_world = R p + t``, m); stations: list
    of :class:`layoutkit.lighthouse.Station`. Per station the unit direction from the body origin to
    the station in the BODY frame (what decides which sites are lit and how they are foreshortened),
    then the range to the first station scaled to [0, ``range_weight``] over the set (ADOP grows
    with range). Euclidean distance between descriptors ~ angle (rad) between attitudes. range_span :
    ``(r_min, r_max)`` of the scaling (None: the set's own; give it to add poses to an existing set).
    """
    R = np.asarray(R, float)
    t = np.asarray(t, float)
    cols = []
    for st in stations:
        d = np.asarray(st.translation, float)[None] - t
        db = np.einsum("pji,pj->pi", R, d)  # R^T d
        cols.append(db / np.maximum(np.linalg.norm(db, axis=1, keepdims=True), 1e-300))
    r = np.linalg.norm(np.asarray(stations[0].translation, float)[None] - t, axis=1)
    lo, hi = (r.min(), r.max()) if range_span is None and len(r) else (range_span or (0.0, 0.0))
    span = hi - lo
    cols.append((range_weight * (r - lo) / span if span > 0 else np.zeros_like(r))[:, None])
    return np.concatenate(cols, axis=1)


def farthest_point_poses(desc, count, start=()):
    """Indices of ``count`` rows of ``desc (P, D)`` by farthest-point sampling (greedy maximin).

    start : indices already chosen (e.g. the design poses); the new ones are each as far as possible
    from everything chosen before. Deterministic. Returns (count,) int (fewer if P is smaller).
    """
    desc = np.asarray(desc, float)
    P = len(desc)
    start = np.asarray(start, int)
    if len(start):
        dmin = np.full(P, np.inf)
        for s0 in range(0, len(start), 256):  # bounded memory: (P, 256) distances at a time
            blk = desc[start[s0:s0 + 256]]
            dmin = np.minimum(dmin, np.sqrt(((desc[:, None, :] - blk[None]) ** 2).sum(-1)).min(axis=1))
    else:
        dmin = np.linalg.norm(desc - desc.mean(axis=0), axis=1) + 1e-12  # first pick: the most extreme
    out = []
    for _ in range(min(int(count), P - len(start))):
        j = int(np.argmax(dmin))
        if not dmin[j] > 0:
            break
        out.append(j)
        dmin = np.minimum(dmin, np.linalg.norm(desc - desc[j], axis=1))
    return np.asarray(out, int)


def far_range_poses(env, R, t):
    """Copies of poses ``R (P, 3, 3), t (P, 3)`` moved along their bearing from the envelope's reference
    station to its maximum range (``env.range_m[1]``): same attitude, same bearing, so the
    same body-frame direction of that station.

    Range dominance: the sweep-angle Jacobian of a sensor scales as 1/range, so with the same lit sensors
    the DOP of a pose grows (about linearly) with its range; the copy is then at least as bad for every
    layout (measured: with the same lit set, copy DOP ≥ DOP on every pose, and ≥ 0.96 × the range ratio ×
    DOP). What breaks it is parallax — a sensor near its half-angle lit at one range and not the other
    (~1.5 % of poses per layout) — so the originals stay in the dense set. A working set of far-range copies
    samples the binding part of the envelope (for each attitude, its far end) instead of one range per
    attitude: a layout tuned on random ranges leaves attitude pockets whose samples all happen to be near,
    and fresh poses there at far range exceed the tuned value (issue 13). Measured on the study device it
    did not lower the held-out worst case (parallax pockets at nearer ranges took over; docs/optimize.md).
    """
    ref = env.stations[env.reference_station]
    s = np.asarray(ref.translation, float)
    d = np.asarray(t, float) - s
    r = np.linalg.norm(d, axis=1, keepdims=True)
    return np.asarray(R, float).copy(), s + d * (float(env.range_m[1]) / np.maximum(r, 1e-300))


def range_sweep_poses(env, R, t, positions, normals, half_angle_deg=60.0, delta=1e-4):
    """The poses along each pose's range segment where the lit set of a layout can change.

    R (P, 3, 3), t (P, 3): world poses of ``env`` (the ray of a pose: same attitude, bearing from the
    envelope's reference station, range over ``env.range_m``); positions, normals (n, 3): the layout's
    sensors in the body frame (m, unit). Along a ray the body-frame direction ``b`` of the station is
    fixed and the sensor-to-station vector is ``-(p + r b)``, so sensor ``p, n`` faces the station
    (angle to its normal ≤ ``half_angle_deg``, :func:`layoutkit.visibility.facing_mask`) iff
    ``a + β r ≥ c |p + r b|`` with ``a = -n·p``, ``β = -n·b``, ``c = cos(half-angle)``: squared, a quadratic
    in r whose roots (on the cone's front sheet) are the crossing ranges. Between crossings the lit set
    is fixed and the DOP grows with range (the Jacobian of a sweep angle scales as 1/r:
    :func:`far_range_poses`), so the worst case of the segment is at its ends; the poses returned are, for
    every ray, both ends of the range interval and ``r_c (1 ∓ delta)`` on both sides of each crossing
    ``r_c`` inside it. All are poses of the envelope, so the values there are values of the
    envelope. Occlusion and other stations are not swept (their visibility is evaluated at these points;
    exact facing geometry of the reference station only). Returns ``(R_s, t_s, src)`` with ``src`` (M,)
    the index of the source pose of every returned pose.
    """
    ref = env.stations[env.reference_station]
    s = np.asarray(ref.translation, float)
    R = np.asarray(R, float)
    d = np.asarray(t, float) - s
    r = np.linalg.norm(d, axis=1, keepdims=True)
    u = d / np.maximum(r, 1e-300)  # world bearing station -> body
    b = np.einsum("pji,pj->pi", R, u)  # body frame; the station is at -r b from the body origin
    pos, nor = np.asarray(positions, float), np.asarray(normals, float)
    c2 = math.cos(math.radians(float(half_angle_deg))) ** 2
    al = -np.sum(nor * pos, axis=1)[None]  # (1, n)
    be = -(b @ nor.T)  # (P, n)
    qa = be * be - c2  # (a + β r)^2 - c^2 (|p|^2 + 2 r p·b + r^2) = qa r^2 + qb r + qc
    qb = 2.0 * (al * be - c2 * (b @ pos.T))
    qc = al * al - c2 * np.sum(pos * pos, axis=1)[None]
    disc = qb * qb - 4.0 * qa * qc
    lin = np.abs(qa) < 1e-12
    sq = np.sqrt(np.maximum(disc, 0.0))
    r0, r1 = (float(x) for x in env.range_m)
    cols = [np.full((len(R), 1), r1), np.full((len(R), 1), r0)]
    with np.errstate(divide="ignore", invalid="ignore"):
        quad = ~lin & (disc >= 0)
        for root in (np.where(quad, (-qb - sq) / (2 * qa), np.nan), np.where(quad, (-qb + sq) / (2 * qa), np.nan),
                     np.where(lin, -qc / qb, np.nan)):
            ok = np.isfinite(root) & (root > r0) & (root < r1) & (al + be * root >= 0)
            for f in (1.0 - delta, 1.0 + delta):
                cols.append(np.where(ok, np.clip(root * f, r0, r1), np.nan))
    rr = np.concatenate(cols, axis=1)  # (P, 2 + 6 n)
    src, col = np.nonzero(np.isfinite(rr))
    return R[src].copy(), s + u[src] * rr[src, col][:, None], src


def _dense_value(obj, adop, pdop, cov, cov_all, need_all, uncoverable):
    """``(short, value)``: dense and coverage-only poses left uncovered (``cov_all``) that are not known
    to be uncoverable (with full coverage required; else 0), and the objective over the covered dense
    poses (``adop, pdop, cov``). Rounds compare lexicographically; the reported dense value is inf
    while ``short > 0``."""
    short = int(np.sum(~cov_all & ~uncoverable)) if need_all else 0
    val = float(obj.aggregate_values(obj.from_dop(adop, pdop), cov)) if cov.any() else math.inf
    return short, val


def _covered_only(prep, sel, R, t, min_visible, coverage, chunk=8192):
    """(P,) bool: the rule's coverage of candidate subset ``sel`` at poses ``R, t`` (visibility only,
    in chunks of ``chunk`` poses: bounded memory for any P)."""
    from ..coverage_rule import covered, layout_counts
    from .score import layout_visibility

    cand = prep["candidates"]
    out = np.ones(len(R), bool)
    for s0 in range(0, len(R), chunk):
        vis = layout_visibility(prep["mesh"], cand.positions[sel], cand.normals[sel], R[s0:s0 + chunk],
                                t[s0:s0 + chunk], prep["stations"], prep["sensor_half_angle_deg"])
        out[s0:s0 + chunk] = covered(layout_counts(vis, coverage), min_visible)
    return out


def _spread_pick(order, desc, add, min_sep):
    """Up to ``add`` of ``order`` (worst first), skipping poses within ``min_sep`` of one already
    picked; the skipped ones fill up if too few are far enough apart."""
    picked, skipped = [], []
    for i in order:
        if len(picked) >= add:
            break
        if picked and min_sep > 0 and np.min(np.linalg.norm(desc[picked] - desc[i], axis=1)) < min_sep:
            skipped.append(i)
            continue
        picked.append(i)
    return np.asarray(picked + skipped[: max(0, add - len(picked))], int)


#: bytes of search arrays (Jacobians, U, G: 60 doubles per pose, station and candidate) the working set may hold
WORKING_BYTES = 2.0e9


def working_capacity(n_candidates, n_stations, budget_bytes=WORKING_BYTES):
    """Largest working set (poses) whose search arrays fit ``budget_bytes``: the selection problem holds
    ``jac`` and ``U`` (12 doubles) and ``G`` (36 doubles) per pose, station and candidate
    (:class:`layoutkit.optimize.problem.Problem`), about 480 B × S × N per pose."""
    return max(1, int(budget_bytes // (480 * max(1, int(n_stations)) * max(1, int(n_candidates)))))


def dense_optimize(prep, k, kw, *, dense_poses, seed=0, coverage="any-station", rounds=40, add=192,
                   seed_poses="all", coverage_poses=0, min_sep=0.05, tol=0.02, patience=8, max_working=None,
                   first_share=None, later_method="polish", later_patience=2, later_two_swap=False,
                   join_above=None, coverage_dop=False, far_range=False, range_sweep=False, time_limit=None,
                   echo=None):
    """Adaptive pose generation around :func:`layoutkit.optimize.optimize_stations` (module docstring).

    prep : :func:`layoutkit.workflows.optimize.prepare_problem` output (its poses = design set);
    kw : optimize_stations keywords (objective, rho, min_visible, coverage_fraction, ...; rounds run
    with ``branch_and_bound="off"``: a B&B certificate of one working set would take the loop's budget);
    dense_poses : extra poses drawn from the envelope (seed ``envelope.seed + 1``) that, with the
    design poses, form the dense set. coverage_poses : more poses (seed ``envelope.seed + 3``) on which
    only the coverage rule is checked every round (cheap: visibility of k sensors); uncovered ones join
    the working set like violators, so coverage holds on a set much denser than the DOP set (a fresh
    pose between dense poses can otherwise lose its m-th lit sensor). seed_poses : dense poses added to the working
    set before round 0 by farthest-point sampling of :func:`pose_descriptors` (0: design poses only; "all"
    (default): every dense pose that fits ``max_working`` with room left for violators — the whole dense set
    when it fits, since the search itself generates poses: the relaxation's active poses and the local
    search's critical poses, every move confirmed on all working poses). add : violators
    added per round; min_sep : their minimum descriptor distance (~rad). tol : a round whose dense
    worst is within ``tol`` of its working-set value adds no poses (polish round). patience : rounds
    without a better dense value before stopping. coverage_dop : evaluate the coverage poses for the
    DOP as well (cheap: the fused kernel), so they are dense poses — the dense value is taken over all of
    them and their DOP violators join the working set; a round whose working set grew before it (new poses:
    progress of the pose generation) does not count. join_above : poses whose value exceeds ``join_above`` ×
    the working-set value join the working set (None: ``1 + tol``; below 1: near-violators too, poses a small
    change of the layout makes critical). far_range : add to the dense set a copy of every design and dense
    pose at the envelope's maximum range (:func:`far_range_poses`: same attitude and bearing) and seed the
    working set with these copies first (the originals join as violators); the dense set then holds
    ``2 ×`` (design + dense) poses, all in the envelope, so the bound argument below is unchanged.
    Not for trajectory envelopes (their poses carry their own ranges). range_sweep : every round, evaluate
    the round's layout along the whole range segment of every dense pose (its *ray*: same attitude and
    bearing, :func:`range_sweep_poses` — both ends and both sides of every range where one of its sensors
    crosses its half-angle, so the worst case of each ray), and let the worst swept poses join the dense set
    and the working set like violators (up to ``8 × add`` new dense poses a round); the dense value is taken
    over the swept poses too. Each swept pose is a pose of the envelope, so the bound argument is unchanged.
    Not for trajectory envelopes. max_working : cap on the working set (memory; None:
    :func:`working_capacity` of :data:`WORKING_BYTES`).
    later_method : method of the rounds after round 0 (default "polish": local search and kicks from
    the incumbent, no relaxation — a round then costs seconds, not minutes; its kicks and 2-swap pool use
    round 0's relaxed z like the pipeline's; None: ``kw["method"]``),
    with ``later_patience`` random kicks in a row without improvement ending a round and 2-swaps only
    if ``later_two_swap`` (1-swaps keep the rounds short, so more violators are seen in the budget).
    time_limit : total budget of all rounds (s); round 0 gets ``first_share`` of it (None: 0.6 with
    ``seed_poses="all"`` — the pipeline's relaxation and roundings on thousands of poses are the strongest
    search available and need minutes; else 0.3), every later round
    half of what is left (the last round the rest); None: each round uses the optimiser's default.
    Returns ``(result, info)``: the OptimizeResult of the best round (its per-pose arrays are for the
    working set of that round) and a dict with per-round values, the dense-set per-pose DOP, the
    best layout's working set (``working_rotations``, ``working_translations``: the poses it was
    tuned on) and its value there (``working_value``); ``rounds[i]`` has the round's ``selected``
    layout and the dense-set indices ``added`` after it (dense index = design poses first, then the
    ``dense_poses``); ``seed_indices`` the space-filling seed; ``converged`` whether some round's dense
    worst came within ``tol`` of its working-set value.
    """
    import dataclasses

    from ..coverage_rule import covered, layout_counts
    from ..optimize import candidate_jacobians, optimize_stations, parse_objective
    from ..optimize.methods import Interrupted
    from ..visibility import envelope_visibility
    from .score import envelope_set

    t0 = time.perf_counter()
    env = prep["envelope"]
    for flag, on in (("far_range", far_range), ("range_sweep", range_sweep)):
        if on and env.attitude == "trajectory":
            raise ValueError(f"{flag}: a trajectory envelope gives every pose its own range; nothing to move")
    _, Rd, td = envelope_set(env, count=int(dense_poses), seed=env.seed + 1)
    Rw, tw = prep["rotations"], prep["translations"]
    n_far = 0  # rows [nD - n_far, nD): far-range copies of the design and dense poses
    if far_range:
        Rf, tf = far_range_poses(env, np.concatenate([Rw, Rd]), np.concatenate([tw, td]))
        Rd, td, n_far = np.concatenate([Rd, Rf]), np.concatenate([td, tf]), len(Rf)
    nD = len(Rw) + len(Rd)  # rows [0, nD): dense set ⊇ design set; rows [nD, ...): coverage-only poses
    Rc, tc = (envelope_set(env, count=int(coverage_poses), seed=env.seed + 3)[1:] if coverage_poses
              else (np.zeros((0, 3, 3)), np.zeros((0, 3))))
    RD, tD = np.concatenate([Rw, Rd, Rc]), np.concatenate([tw, td, tc])
    in_work = np.zeros(len(RD), bool)
    in_work[: len(Rw)] = True
    jac, vis = prep["jac"], prep["visible"]
    obj = parse_objective(kw.get("objective", "worst-adop"), kw.get("weights"))
    rho, m = kw.get("rho", 0.0), kw.get("min_visible", 4)
    need_all = kw.get("coverage_fraction", 1.0) >= 1.0
    cand = prep["candidates"]
    span = tuple(float(x) for x in env.range_m)
    s_ref = np.asarray(env.stations[env.reference_station].translation, float)
    desc = pose_descriptors(RD, tD, prep["stations"], range_span=span)
    uncoverable = np.zeros(len(RD), bool)  # dense poses with fewer than m lit candidates (by the rule)
    n_rays = nD + (len(Rc) if coverage_dop else 0)  # range_sweep: the poses whose rays are swept
    swept = set()  # (ray, range) of the swept poses that joined the dense set

    def lit_full(R, t):
        """Full-candidate visibility at poses ``R, t`` and whether the rule can cover them."""
        vc = envelope_visibility(prep["mesh"], cand.positions, cand.normals, R, t,
                                 prep["stations"], sensor_half_angle_deg=prep["sensor_half_angle_deg"])
        return vc, covered(layout_counts(vc, coverage), m)

    def lit_all(idx):
        """Full-candidate visibility of dense poses ``idx`` and whether the rule can cover them."""
        vc, ok = lit_full(RD[idx], tD[idx])
        uncoverable[idx[~ok]] = True
        return vc, ok

    def join_dense(Rn, tn):
        """Append poses to the dense set; returns their dense indices."""
        nonlocal RD, tD, desc, in_work, uncoverable
        i0 = len(RD)
        RD, tD = np.concatenate([RD, Rn]), np.concatenate([tD, tn])
        desc = np.concatenate([desc, pose_descriptors(Rn, tn, prep["stations"], range_span=span)])
        in_work = np.concatenate([in_work, np.zeros(len(Rn), bool)])
        uncoverable = np.concatenate([uncoverable, np.zeros(len(Rn), bool)])
        return np.arange(i0, len(RD))

    def grow(idx, vc):
        nonlocal jac, vis
        jac = np.concatenate([jac, candidate_jacobians(cand.positions, RD[idx], tD[idx], prep["stations"])])
        vis = np.concatenate([vis, vc])
        in_work[idx] = True
        order.extend(int(i) for i in idx)

    order = list(range(len(Rw)))  # dense-set index of every working-set row
    if max_working is None:
        max_working = working_capacity(cand.n, len(prep["stations"]))
    if seed_poses == "all":  # room for the dense set, leaving a tenth of the capacity for violators
        n_seed = max(0, min(nD - len(Rw), int(0.9 * int(max_working)) - len(Rw)))
    else:
        n_seed = max(0, min(int(seed_poses), int(max_working) - len(Rw)))
    whole = n_seed >= nD - len(Rw)  # the working set starts as the whole dense set
    if first_share is None:  # a large working set: its relaxation alone takes minutes
        first_share = 0.6 if seed_poses == "all" else 0.3
    seed_idx = np.zeros(0, int)
    if n_seed:
        if whole:
            idx = np.arange(len(Rw), nD)
        elif far_range:  # the far-range copies first, then originals
            far = np.arange(nD - n_far, nD)
            idx = far[:n_seed] if n_seed <= len(far) else np.r_[far, farthest_point_poses(
                desc[:nD - n_far], n_seed - len(far), start=np.arange(len(Rw)))]
        else:
            idx = farthest_point_poses(desc[:nD], n_seed, start=np.arange(len(Rw)))
        vc, ok = lit_all(idx)
        seed_idx = idx[ok]
        grow(seed_idx, vc[ok])
    best = None
    hist = []
    warm, active = None, None
    z_relax = None  # the fractional z of the last round that solved the relaxation
    last_fail = None  # the last failed round's result
    stall = 0
    grew = False  # the working set grew after the last round
    note = ""
    interrupted = None
    converged = False  # some round's dense worst was within tol of its working-set value
    polish = False  # the next round is a full polish (the last round converged)
    try:  # Ctrl-C / SIGTERM between or inside rounds: the best layout so far is the result
        for rnd in range(int(rounds)):
            kwr = dict(kw)
            # branch-and-bound would spend the loop's budget certifying one working set: off here
            kwr["branch_and_bound"] = "off"
            if time_limit is not None:
                left = t0 + float(time_limit) - time.perf_counter()
                if left <= 0.05 * float(time_limit):
                    break
                share = first_share if rnd == 0 else 0.5
                kwr["time_limit"] = left if rnd == rounds - 1 else share * left
            opts = {"warm_start": warm, "active_poses": active}
            if rnd > 0 and later_method:
                kwr["method"] = later_method
                if later_method == "polish" and z_relax is not None:
                    opts["z_hint"] = z_relax  # kicks and 2-swap pool ranked by the last relaxation
                # after a converged round: a full polish (2-swaps, the default kick patience) of the
                # working set that holds the dense worst; else short 1-swap rounds
                opts["patience"] = (kw.get("ctx_options") or {}).get("patience", 6) if polish else later_patience
                opts["two_swap"] = True if polish else later_two_swap
            kwr["ctx_options"] = {**(kw.get("ctx_options") or {}), **opts}
            res = optimize_stations(jac, vis, k, rng=seed + rnd, coverage=coverage, **kwr)
            if not res.success:
                last_fail = res
            if not res.success and best is None and len(order) > len(Rw):
                # the seeded working set was too hard for round 0 (k at its minimum, a short budget):
                # retry on the design poses alone, adding violators from there
                note = f"round {rnd} on the seeded working set: {res.status}; seed dropped"
                jac, vis = prep["jac"], prep["visible"]
                in_work[len(Rw):] = False
                del order[len(Rw):]
                seed_idx = np.zeros(0, int)
                continue
            if not res.success:
                if best is None:
                    return res, {"rounds": hist, "dense_set_poses": int(nD), "note": note}
                note = f"round {rnd}: {res.status}: {res.message}"
                break
            a, p, cov = evaluate_selection(prep, res.selected, RD[:nD], tD[:nD], rho, m, coverage)
            if coverage_dop:  # the coverage poses are dense poses too (DOP and coverage)
                ae, pe, ce = evaluate_selection(prep, res.selected, RD[nD:], tD[nD:], rho, m, coverage)
                cov_all = np.concatenate([cov, ce])
            else:
                cov_all = np.concatenate([cov, _covered_only(prep, res.selected, RD[nD:], tD[nD:], m, coverage)])
                ext = np.flatnonzero(in_work[nD:]) + nD  # coverage poses in the working set count as dense poses
                ae, pe, ce = evaluate_selection(prep, res.selected, RD[ext], tD[ext], rho, m, coverage)
            n_rows = len(RD)
            if range_sweep:  # the worst case along every ray (range segment) of the dense poses
                Rs, ts, src = range_sweep_poses(env, RD[:n_rays], tD[:n_rays], cand.positions[res.selected],
                                                cand.normals[res.selected], prep["sensor_half_angle_deg"])
                as_, ps_, cs_ = evaluate_selection(prep, res.selected, Rs, ts, rho, m, coverage)
                sunc = np.zeros(len(Rs), bool)  # swept poses no layout can cover
                if need_all and not cs_.all():
                    sunc[~cs_] = ~lit_full(Rs[~cs_], ts[~cs_])[1]
            else:
                Rs, ts, src = np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0, int)
                as_, ps_, cs_, sunc = np.zeros(0), np.zeros(0), np.zeros(0, bool), np.zeros(0, bool)
            dval = _dense_value(obj, np.r_[a, ae, as_], np.r_[p, pe, ps_], np.r_[cov, ce, cs_], np.r_[cov_all, cs_],
                                need_all, np.r_[uncoverable, sunc])
            n_work = int(in_work.sum())
            hist.append({"round": rnd, "working_poses": n_work, "working_value": res.value,
                         "dense_value_covered": dval[1], "dense_uncovered": dval[0], "bound": res.bound,
                         "status": res.status, "time_s": time.perf_counter() - t0, "swept_poses": int(len(Rs)),
                         "selected": [int(x) for x in res.selected], "added": []})
            if echo is not None:
                echo(f"dense round {rnd}: working set {n_work} poses, value {res.value:.5g}, "
                     f"dense-set value {dval[1]:.5g} over covered poses, {dval[0]} coverable poses uncovered "
                     f"({time.perf_counter() - t0:.0f} s)")
            if best is None or dval[0] < best[1][0] or (dval[0] == best[1][0] and dval[1] < best[1][1] * (1 - 1e-3)):
                best = (res, dval, a, p, cov, cov_all, np.array(order, int), (ae, pe, ce), (n_rows, as_, ps_, cs_, sunc))
                stall = 0
            elif not grew:  # a round on a grown working set is progress of the pose generation
                stall += 1
            grew = False
            warm = best[0].selected
            active = None
            if isinstance(res.info, dict) and res.info.get("active_poses") is not None:
                active = res.info["active_poses"]
            if isinstance(res.info, dict) and res.info.get("relaxation_z") is not None:
                z_relax = res.info["relaxation_z"]
            if res.status == "interrupted":
                interrupted = res.info.get("interrupted", "SIGINT")
                break
            if stall >= patience:
                break
            score = np.concatenate([np.where(cov, obj.from_dop(a, p), np.inf),
                                    np.where(ce, obj.from_dop(ae, pe), np.inf) if coverage_dop else
                                    np.where(cov_all[nD:], -np.inf, np.inf),  # coverage-only rows: coverage
                                    np.where(cs_, obj.from_dop(as_, ps_), np.inf)])  # [n_rows, ...): swept poses
            open_ = np.r_[~in_work & ~uncoverable, ~sunc]
            viol = np.flatnonzero(open_ & (score > res.value * (1 + tol)))
            room = int(max_working) - n_work
            polish = len(viol) == 0
            if join_above is not None:
                viol = np.flatnonzero(open_ & (score > res.value * float(join_above)))
            if polish:
                converged = True
            if len(viol) == 0 or room <= 0:
                if room <= 0 and len(viol):
                    note = f"working set reached max_working = {max_working} poses"
                continue  # polish round: same working set, fresh kicks, warm start from the best layout
            srt = viol[np.argsort(-score[viol], kind="stable")]
            want = min(int(add), room)
            if len(Rs):  # the worst swept poses join the dense set (at most 8 × add a round), the rest are dropped
                sw = srt[srt >= n_rows][: 8 * int(add)] - n_rows
                rng_s = np.linalg.norm(ts[sw] - s_ref, axis=1)
                key = [(int(src[j]), round(float(x), 9)) for j, x in zip(sw, rng_s)]
                fresh = np.array([kk not in swept for kk in key], bool)
                swept.update(kk for kk, f in zip(key, fresh) if f)
                sw = sw[fresh]
                rows = srt[srt < n_rows]
                ids = join_dense(Rs[sw], ts[sw]) if len(sw) else np.zeros(0, int)
                # rows and the swept poses that joined, worst first
                srt = np.r_[rows, ids][np.argsort(-np.r_[score[rows], score[n_rows + sw]], kind="stable")]
            new, v_new = [], []
            for s0 in range(0, len(srt), 4 * want):  # skip poses no layout can cover (too few lit candidates)
                chunk = srt[s0:s0 + 4 * want]
                vc, ok = lit_all(chunk)
                new += list(chunk[ok])
                v_new += list(vc[ok])
                if len(new) >= want:
                    break
            if not new:
                continue
            new = np.asarray(new)
            pick = _spread_pick(np.arange(len(new)), desc[new], want, min_sep)
            grow(new[pick], np.asarray(v_new)[pick])
            grew = True
            hist[-1]["added"] = [int(x) for x in new[pick]]
    except (Interrupted, KeyboardInterrupt) as exc:
        interrupted = getattr(exc, "signame", "SIGINT")
        if best is None:
            raise
        note = f"interrupted by {interrupted}: best layout of the finished rounds"
    if best is None:  # no round produced a layout (round 0 failed and the budget ended before a retry)
        return last_fail, {"rounds": hist, "dense_set_poses": int(nD), "note": note or "no round produced a layout"}
    res, dval, a, p, cov, cov_all, work_rows, (ae, pe, ce), (n_rows, as_, ps_, cs_, sunc) = best
    # poses found uncoverable after the best round: its value over the coverable ones
    short, dval = _dense_value(obj, np.r_[a, ae, as_], np.r_[p, pe, ps_], np.r_[cov, ce, cs_], np.r_[cov_all, cs_],
                               need_all, np.r_[uncoverable[:n_rows], sunc])
    if short:
        dval = math.inf
    # every round's working set is a subset of the dense set: the largest round bound holds for it
    bounds = [h["bound"] for h in hist if h["bound"] is not None and np.isfinite(h["bound"])]
    if bounds and not (np.isfinite(res.bound) and res.bound >= max(bounds)):
        src = int(np.argmax(bounds))
        res = dataclasses.replace(res, bound=float(max(bounds)), certified_by="relaxation (dense round "
                                  f"{[h['round'] for h in hist if h['bound'] is not None and np.isfinite(h['bound'])][src]})",
                                  gap=res.value / max(bounds) - 1)
    if interrupted:
        res = dataclasses.replace(res, status="interrupted", info={**res.info, "interrupted": interrupted},
                                  message=res.message + " [interrupted: best dense round so far]")
    gap = dval / res.bound - 1 if np.isfinite(res.bound) and res.bound > 0 else float("nan")
    info = {"rounds": hist, "dense_set_poses": int(len(RD) if coverage_dop else nD),
            "coverage_poses": int(len(Rc)), "coverage_dop": bool(coverage_dop),
            "range_sweep": bool(range_sweep), "swept_poses": int(len(sunc)),
            "joined_swept_poses": int(len(RD) - nD - len(Rc)),
            "working_set_poses": int(len(work_rows)),
            "final_working_set_poses": int(in_work.sum()), "seed_poses": n_seed,
            "seed_indices": seed_idx, "converged": converged,
            "dense_value": dval, "dense_gap": gap, "dense_adop": a, "dense_pdop": p, "dense_covered": cov,
            "working_value": float(res.value), "working_rotations": RD[work_rows],
            "working_translations": tD[work_rows],
            "time_s": time.perf_counter() - t0, "uncoverable_dense_poses": int(uncoverable.sum()),
            "uncovered_dense_poses": int(short), "note": note}
    return res, info
