"""Dense envelopes by adaptive pose generation (issue 13, item 1): :func:`dense_solve`.

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

from .poses import far_range_poses, farthest_point_poses, pose_descriptors, range_sweep_poses

__all__ = ["dense_solve", "default_dense", "working_capacity", "WORKING_BYTES", "DEFAULT_DENSE_TIME_S"]

#: the dense loop's budget (s) when the caller gives no time limit
DEFAULT_DENSE_TIME_S = 300.0


def _dense_value(obj, adop, pdop, cov, cov_all, need_all, uncoverable):
    """``(short, value)``: dense and coverage-only poses left uncovered (``cov_all``) that are not known
    to be uncoverable (with full coverage required; else 0), and the objective over the covered dense
    poses (``adop, pdop, cov``). Rounds compare lexicographically; the reported dense value is inf
    while ``short > 0``."""
    short = int(np.sum(~cov_all & ~uncoverable)) if need_all else 0
    val = float(obj.aggregate_values(obj.from_dop(adop, pdop), cov)) if cov.any() else math.inf
    return short, val


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


def _covered_only(problem, sel, R, t, min_visible, coverage, chunk=8192):
    """(P,) bool: the rule's coverage of candidate subset ``sel`` at poses ``R, t`` (visibility only,
    in chunks of ``chunk`` poses: bounded memory for any P)."""
    from ..coverage_rule import covered, layout_counts

    out = np.ones(len(R), bool)
    for s0 in range(0, len(R), chunk):
        vis = problem.visibility_at(sel, R[s0:s0 + chunk], t[s0:s0 + chunk])
        out[s0:s0 + chunk] = covered(layout_counts(vis, coverage), min_visible)
    return out


def default_dense(envelope, time_limit_s=None):
    """The dense loop a plain ``layoutkit optimize`` runs: ``(DenseSpec or None, budget s, note)``.

    Its budget is the time limit (default :data:`DEFAULT_DENSE_TIME_S`); its size grows with the budget —
    10 dense poses per second of budget, between 2,000 and 10,000 (the round-0 relaxation and search over
    the working set must fit the budget; the working set is capped by memory anyway,
    :func:`working_capacity`) — with 4 × as many coverage-only poses. The envelope's own poses are the seed of
    the working set (``seed_poses=0``: round 0 is the pipeline on them, its relaxation finishes and certifies
    a bound; the rounds after it add the violators of the dense set). A trajectory envelope is a fixed
    pose list (no fresh poses to draw): no dense loop, and the note says so.
    """
    from .spec import DenseSpec

    T = DEFAULT_DENSE_TIME_S if time_limit_s is None else float(time_limit_s)
    if envelope is None or envelope.attitude == "trajectory":
        return None, time_limit_s, "a trajectory envelope is a fixed pose list: optimised over its poses only"
    n = int(min(10000, max(2000, round(10.0 * T))))
    return DenseSpec(poses=n, seed_poses=0), T, f"dense loop by default: {n} dense poses, {T:g} s budget"


def dense_solve(problem, spec, kw, *, echo=None):
    """Adaptive pose generation around :func:`layoutkit.optimize.core.optimize_stations` (module docstring).

    problem : :class:`layoutkit.optimize.design.DesignProblem` with an envelope (its poses = the design
    set); spec : :class:`layoutkit.optimize.spec.OptimizeSpec` whose ``dense`` (:class:`DenseSpec`) holds
    the loop's settings — ``poses`` extra poses drawn from the envelope (seed ``envelope.seed + 1``) form,
    with the design poses, the dense set; ``coverage_count`` more (seed + 3) are checked for coverage only
    every round (uncovered ones join the working set like violators); ``seed_poses`` dense poses seed the
    working set before round 0 (farthest-point sampling of :func:`pose_descriptors`; "all": every dense pose
    that fits ``max_working``, keeping a tenth for violators); ``add`` violators join per round, no two
    closer than ``min_sep`` (descriptor distance ~ rad); a round whose dense worst is within ``tol`` of its
    working-set value adds none (the next round is a full polish); ``patience`` rounds without a better
    dense value stop the loop; ``coverage_dop``: the coverage poses are dense poses (DOP too);
    ``join_above``: poses above ``join_above`` × the working-set value join (None: 1 + tol);
    ``far_range``: far-range copies of design and dense poses seed the working set
    (:func:`far_range_poses`); ``range_sweep``: every round, the worst case along every dense pose's ray
    (:func:`range_sweep_poses`) joins the dense set; ``max_working``: cap on the working set (None:
    :func:`working_capacity`); ``later_method`` ("polish"), ``later_patience``, ``later_two_swap``: the rounds
    after round 0; ``first_share``: round 0's share of ``spec.time_limit_s`` (the budget of all rounds;
    None: 0.6 with ``seed_poses="all"``, else 0.3), every later round half of what is left.
    kw : :func:`optimize_stations` keywords of the rounds (objective, weights, rho, min_visible,
    coverage_fraction, method, fixed, conflict, progress, ctx_options); rounds run with
    ``branch_and_bound="off"`` (a B&B certificate of one working set would take the loop's budget).
    echo : callable for one line per round, or None.

    Returns ``(result, info)``: the OptimizeResult of the best round (its per-pose arrays are for the working
    set of that round; its bound the largest round bound: every working set is a subset of the dense set) and
    a dict with per-round values (``rounds[i]``: the round's ``selected`` layout and the dense-set indices
    ``added`` after it; dense index = design poses first, then the dense poses), the dense-set per-pose DOP
    (``dense_adop``, ``dense_pdop``, ``dense_covered``), ``dense_value`` and ``dense_gap``, the best layout's
    working set (``working_rotations``, ``working_translations``: the poses it was tuned on) and its value
    there (``working_value``), ``seed_indices`` (the space-filling seed) and ``converged`` (some round's dense
    worst came within ``tol`` of its working-set value).
    """
    loop = _DenseLoop(problem, spec, kw, echo)
    return loop.run()


class _DenseLoop:
    """State of one run of :func:`dense_solve`: the pose sets (seed), the working set (grow), the rounds
    (evaluate), the best round and the stop rules. Rows ``[0, nD)`` of ``RD, tD`` are the dense set
    (design set first), rows ``[nD, nD + nC)`` the coverage-only poses, later rows swept poses that
    joined the dense set (``range_sweep``)."""

    def __init__(self, problem, spec, kw, echo):
        from ..envelope import envelope_set
        from .objectives import parse_objective

        d = spec.dense
        self.t0 = time.perf_counter()
        self.problem, self.spec, self.d, self.kw, self.echo = problem, spec, d, kw, echo
        env = self.env = problem.envelope
        if env is None:
            raise ValueError("dense: the problem has no envelope to draw dense poses from")
        for flag, on in (("far_range", d.far_range), ("range_sweep", d.range_sweep)):
            if on and env.attitude == "trajectory":
                raise ValueError(f"{flag}: a trajectory envelope gives every pose its own range; nothing to move")
        _, Rd, td = envelope_set(env, count=int(d.poses), seed=env.seed + 1)
        Rw, tw = problem.rotations, problem.translations
        self.n_design = len(Rw)
        self.n_far = 0  # rows [nD - n_far, nD): far-range copies of the design and dense poses
        if d.far_range:
            Rf, tf = far_range_poses(env, np.concatenate([Rw, Rd]), np.concatenate([tw, td]))
            Rd, td, self.n_far = np.concatenate([Rd, Rf]), np.concatenate([td, tf]), len(Rf)
        self.nD = len(Rw) + len(Rd)
        ncov = d.coverage_count
        Rc, tc = (envelope_set(env, count=int(ncov), seed=env.seed + 3)[1:] if ncov
                  else (np.zeros((0, 3, 3)), np.zeros((0, 3))))
        self.nC = len(Rc)
        self.RD, self.tD = np.concatenate([Rw, Rd, Rc]), np.concatenate([tw, td, tc])
        self.in_work = np.zeros(len(self.RD), bool)
        self.in_work[: len(Rw)] = True
        self.jac, self.vis = problem.jac, problem.visible
        self.obj = parse_objective(kw.get("objective", "worst-adop"), kw.get("weights"))
        self.rho, self.m = kw.get("rho", 0.0), kw.get("min_visible", 4)
        self.need_all = kw.get("coverage_fraction", 1.0) >= 1.0
        self.coverage = spec.coverage
        self.span = tuple(float(x) for x in env.range_m)
        self.s_ref = np.asarray(env.stations[env.reference_station].translation, float)
        self.desc = pose_descriptors(self.RD, self.tD, problem.stations, range_span=self.span)
        self.uncoverable = np.zeros(len(self.RD), bool)  # dense poses with fewer than m lit candidates (by the rule)
        self.n_rays = self.nD + (self.nC if d.coverage_dop else 0)  # range_sweep: the poses whose rays are swept
        self.swept = set()  # (ray, range) of the swept poses that joined the dense set
        self.order = list(range(len(Rw)))  # dense-set index of every working-set row
        self.max_working = (working_capacity(problem.N, problem.S) if d.max_working is None else d.max_working)
        self.seed_idx = np.zeros(0, int)
        self.best = None
        self.hist = []
        self.active = self.z_relax = self.last_fail = None
        self.warm = (kw.get("ctx_options") or {}).get("warm_start")  # round 0 may start from a given layout
        self.stall = 0
        self.grew = False  # the working set grew after the last round
        self.note = ""
        self.interrupted = None
        self.converged = False  # some round's dense worst was within tol of its working-set value
        self.polish = False  # the next round is a full polish (the last round converged)

    # -- rows of the dense set and of the working set ---------------------------------------------------
    def lit_full(self, R, t):
        """Full-candidate visibility at poses ``R, t`` and whether the rule can cover them."""
        from ..coverage_rule import covered, layout_counts

        vc = self.problem.visibility_at(None, R, t)
        return vc, covered(layout_counts(vc, self.coverage), self.m)

    def lit_all(self, idx):
        """Full-candidate visibility of dense poses ``idx`` and whether the rule can cover them."""
        vc, ok = self.lit_full(self.RD[idx], self.tD[idx])
        self.uncoverable[idx[~ok]] = True
        return vc, ok

    def join_dense(self, Rn, tn):
        """Append poses to the dense set; returns their dense indices."""
        i0 = len(self.RD)
        self.RD, self.tD = np.concatenate([self.RD, Rn]), np.concatenate([self.tD, tn])
        self.desc = np.concatenate([self.desc, pose_descriptors(Rn, tn, self.problem.stations, range_span=self.span)])
        self.in_work = np.concatenate([self.in_work, np.zeros(len(Rn), bool)])
        self.uncoverable = np.concatenate([self.uncoverable, np.zeros(len(Rn), bool)])
        return np.arange(i0, len(self.RD))

    def grow(self, idx, vc):
        """Dense poses ``idx`` (visibility ``vc``) join the working set: their rows of the search arrays."""
        self.jac = np.concatenate([self.jac, self.problem.jacobians_at(self.RD[idx], self.tD[idx])])
        self.vis = np.concatenate([self.vis, vc])
        self.in_work[idx] = True
        self.order.extend(int(i) for i in idx)

    # -- seed ---------------------------------------------------------------------------------------
    def seed(self):
        """Dense poses into the working set before round 0 (module docstring, step 1)."""
        d, nD, nW = self.d, self.nD, self.n_design
        if d.seed_poses == "all":  # room for the dense set, leaving a tenth of the capacity for violators
            n_seed = max(0, min(nD - nW, int(0.9 * int(self.max_working)) - nW))
        else:
            n_seed = max(0, min(int(d.seed_poses), int(self.max_working) - nW))
        self.n_seed = n_seed
        whole = n_seed >= nD - nW  # the working set starts as the whole dense set
        self.first_share = d.first_share
        if self.first_share is None:  # a large working set: its relaxation alone takes minutes
            self.first_share = 0.6 if d.seed_poses == "all" else 0.3
        if not n_seed:
            return
        if whole:
            idx = np.arange(nW, nD)
        elif d.far_range:  # the far-range copies first, then originals
            far = np.arange(nD - self.n_far, nD)
            idx = far[:n_seed] if n_seed <= len(far) else np.r_[far, farthest_point_poses(
                self.desc[:nD - self.n_far], n_seed - len(far), start=np.arange(nW))]
        else:
            idx = farthest_point_poses(self.desc[:nD], n_seed, start=np.arange(nW))
        vc, ok = self.lit_all(idx)
        self.seed_idx = idx[ok]
        self.grow(self.seed_idx, vc[ok])

    def drop_seed(self, rnd, res):
        """Round 0 failed on the seeded working set: back to the design poses, violators from there."""
        self.note = f"round {rnd} on the seeded working set: {res.status}; seed dropped"
        self.jac, self.vis = self.problem.jac, self.problem.visible
        self.in_work[self.n_design:] = False
        del self.order[self.n_design:]
        self.seed_idx = np.zeros(0, int)

    # -- one round --------------------------------------------------------------------------------
    def round_kw(self, rnd):
        """optimize_stations keywords of round ``rnd``, or None when the budget is spent."""
        d, kw = self.d, self.kw
        kwr = dict(kw)
        # branch-and-bound would spend the loop's budget certifying one working set: off here
        kwr["branch_and_bound"] = "off"
        T = self.spec.time_limit_s
        if T is not None:
            left = self.t0 + float(T) - time.perf_counter()
            if left <= 0.05 * float(T):
                return None
            share = self.first_share if rnd == 0 else 0.5
            kwr["time_limit"] = left if rnd == d.rounds - 1 else share * left
        opts = {"warm_start": self.warm, "active_poses": self.active}
        if rnd > 0 and d.later_method:
            kwr["method"] = d.later_method
            if d.later_method == "polish" and self.z_relax is not None:
                opts["z_hint"] = self.z_relax  # kicks and 2-swap pool ranked by the last relaxation
            # after a converged round: a full polish (2-swaps, the default kick patience) of the
            # working set that holds the dense worst; else short 1-swap rounds
            opts["patience"] = (kw.get("ctx_options") or {}).get("patience", 6) if self.polish else d.later_patience
            opts["two_swap"] = True if self.polish else d.later_two_swap
        kwr["ctx_options"] = {**(kw.get("ctx_options") or {}), **opts}
        return kwr

    def evaluate(self, res):
        """The round's layout on the dense set (DOP and coverage), the coverage poses and the swept rays."""
        p, sel, nD, m, cov_rule = self.problem, res.selected, self.nD, self.m, self.coverage
        RD, tD = self.RD, self.tD
        ev = {"n_rows": len(RD)}
        ev["a"], ev["p"], ev["cov"] = p.evaluate(sel, RD[:nD], tD[:nD], rho=self.rho, min_visible=m, coverage=cov_rule)
        if self.d.coverage_dop:  # the coverage poses are dense poses too (DOP and coverage)
            ae, pe, ce = p.evaluate(sel, RD[nD:], tD[nD:], rho=self.rho, min_visible=m, coverage=cov_rule)
            ev["cov_all"] = np.concatenate([ev["cov"], ce])
        else:
            ev["cov_all"] = np.concatenate([ev["cov"], _covered_only(p, sel, RD[nD:], tD[nD:], m, cov_rule)])
            ext = np.flatnonzero(self.in_work[nD:]) + nD  # coverage poses in the working set count as dense poses
            ae, pe, ce = p.evaluate(sel, RD[ext], tD[ext], rho=self.rho, min_visible=m, coverage=cov_rule)
        ev["ext"] = (ae, pe, ce)
        if self.d.range_sweep:  # the worst case along every ray (range segment) of the dense poses
            c = p.candidates
            Rs, ts, src = range_sweep_poses(self.env, RD[:self.n_rays], tD[:self.n_rays], c.positions[sel],
                                            c.normals[sel], p.half_angle_deg)
            as_, ps_, cs_ = p.evaluate(sel, Rs, ts, rho=self.rho, min_visible=m, coverage=cov_rule)
            sunc = np.zeros(len(Rs), bool)  # swept poses no layout can cover
            if self.need_all and not cs_.all():
                sunc[~cs_] = ~self.lit_full(Rs[~cs_], ts[~cs_])[1]
        else:
            Rs, ts, src = np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0, int)
            as_, ps_, cs_, sunc = np.zeros(0), np.zeros(0), np.zeros(0, bool), np.zeros(0, bool)
        ev["swept"] = (Rs, ts, src)
        ev["sw"] = (as_, ps_, cs_, sunc)
        ev["dval"] = _dense_value(self.obj, np.r_[ev["a"], ae, as_], np.r_[ev["p"], pe, ps_],
                                  np.r_[ev["cov"], ce, cs_], np.r_[ev["cov_all"], cs_], self.need_all,
                                  np.r_[self.uncoverable, sunc])
        return ev

    def record(self, rnd, res, ev):
        """History line, echo, and the best round so far (fewest uncovered poses, then the dense value)."""
        dval = ev["dval"]
        n_work = int(self.in_work.sum())
        self.hist.append({"round": rnd, "working_poses": n_work, "working_value": res.value,
                          "dense_value_covered": dval[1], "dense_uncovered": dval[0], "bound": res.bound,
                          "status": res.status, "time_s": time.perf_counter() - self.t0,
                          "swept_poses": int(len(ev["swept"][0])), "selected": [int(x) for x in res.selected],
                          "added": []})
        if self.echo is not None:
            self.echo(f"dense round {rnd}: working set {n_work} poses, value {res.value:.5g}, "
                      f"dense-set value {dval[1]:.5g} over covered poses, {dval[0]} coverable poses uncovered "
                      f"({time.perf_counter() - self.t0:.0f} s)")
        b = self.best
        if b is None or dval[0] < b["dval"][0] or (dval[0] == b["dval"][0] and dval[1] < b["dval"][1] * (1 - 1e-3)):
            self.best = {"res": res, "work_rows": np.array(self.order, int), **ev}
            self.stall = 0
        elif not self.grew:  # a round on a grown working set is progress of the pose generation
            self.stall += 1
        self.grew = False
        self.warm = self.best["res"].selected
        self.active = None
        if isinstance(res.info, dict) and res.info.get("active_poses") is not None:
            self.active = res.info["active_poses"]
        if isinstance(res.info, dict) and res.info.get("relaxation_z") is not None:
            self.z_relax = res.info["relaxation_z"]

    def add_violators(self, res, ev):
        """Grow the working set by the round's violators (module docstring, step 3)."""
        d, obj, nD = self.d, self.obj, self.nD
        a, p, cov, cov_all = ev["a"], ev["p"], ev["cov"], ev["cov_all"]
        ae, pe, ce = ev["ext"]
        Rs, ts, src = ev["swept"]
        as_, ps_, cs_, sunc = ev["sw"]
        n_rows = ev["n_rows"]
        score = np.concatenate([np.where(cov, obj.from_dop(a, p), np.inf),
                                np.where(ce, obj.from_dop(ae, pe), np.inf) if d.coverage_dop else
                                np.where(cov_all[nD:], -np.inf, np.inf),  # coverage-only rows: coverage
                                np.where(cs_, obj.from_dop(as_, ps_), np.inf)])  # [n_rows, ...): swept poses
        open_ = np.r_[~self.in_work & ~self.uncoverable, ~sunc]
        viol = np.flatnonzero(open_ & (score > res.value * (1 + d.tol)))
        room = int(self.max_working) - int(self.in_work.sum())
        self.polish = len(viol) == 0
        if d.join_above is not None:
            viol = np.flatnonzero(open_ & (score > res.value * float(d.join_above)))
        if self.polish:
            self.converged = True
        if len(viol) == 0 or room <= 0:
            if room <= 0 and len(viol):
                self.note = f"working set reached max_working = {self.max_working} poses"
            return  # polish round: same working set, fresh kicks, warm start from the best layout
        srt = viol[np.argsort(-score[viol], kind="stable")]
        want = min(int(d.add), room)
        if len(Rs):  # the worst swept poses join the dense set (at most 8 × add a round), the rest are dropped
            sw = srt[srt >= n_rows][: 8 * int(d.add)] - n_rows
            rng_s = np.linalg.norm(ts[sw] - self.s_ref, axis=1)
            key = [(int(src[j]), round(float(x), 9)) for j, x in zip(sw, rng_s)]
            fresh = np.array([kk not in self.swept for kk in key], bool)
            self.swept.update(kk for kk, f in zip(key, fresh) if f)
            sw = sw[fresh]
            rows = srt[srt < n_rows]
            ids = self.join_dense(Rs[sw], ts[sw]) if len(sw) else np.zeros(0, int)
            # rows and the swept poses that joined, worst first
            srt = np.r_[rows, ids][np.argsort(-np.r_[score[rows], score[n_rows + sw]], kind="stable")]
        new, v_new = [], []
        for s0 in range(0, len(srt), 4 * want):  # skip poses no layout can cover (too few lit candidates)
            chunk = srt[s0:s0 + 4 * want]
            vc, ok = self.lit_all(chunk)
            new += list(chunk[ok])
            v_new += list(vc[ok])
            if len(new) >= want:
                break
        if not new:
            return
        new = np.asarray(new)
        pick = _spread_pick(np.arange(len(new)), self.desc[new], want, d.min_sep)
        self.grow(new[pick], np.asarray(v_new)[pick])
        self.grew = True
        self.hist[-1]["added"] = [int(x) for x in new[pick]]

    # -- the loop and its stop rules ----------------------------------------------------------------
    def run(self):
        """Seed, then rounds until a stop rule; ``(result, info)`` of :func:`dense_solve`."""
        from .core import optimize_stations
        from .runcontrol import Interrupted

        self.seed()
        seed = self.spec.seed
        try:  # Ctrl-C / SIGTERM between or inside rounds: the best layout so far is the result
            for rnd in range(int(self.d.rounds)):
                kwr = self.round_kw(rnd)
                if kwr is None:
                    break
                res = optimize_stations(self.jac, self.vis, self.spec.k, rng=None if seed is None else seed + rnd,
                                        coverage=self.coverage, **kwr)
                if not res.success:
                    self.last_fail = res
                if not res.success and self.best is None and len(self.order) > self.n_design:
                    # the seeded working set was too hard for round 0 (k at its minimum, a short budget):
                    # retry on the design poses alone, adding violators from there
                    self.drop_seed(rnd, res)
                    continue
                if not res.success:
                    if self.best is None:
                        return res, {"rounds": self.hist, "dense_set_poses": int(self.nD), "note": self.note}
                    self.note = f"round {rnd}: {res.status}: {res.message}"
                    break
                ev = self.evaluate(res)
                self.record(rnd, res, ev)
                if res.status == "interrupted":
                    self.interrupted = res.info.get("interrupted", "SIGINT")
                    break
                if self.stall >= self.d.patience:
                    break
                self.add_violators(res, ev)
        except (Interrupted, KeyboardInterrupt) as exc:
            self.interrupted = getattr(exc, "signame", "SIGINT")
            if self.best is None:
                raise
            self.note = f"interrupted by {self.interrupted}: best layout of the finished rounds"
        if self.best is None:  # no round produced a layout (round 0 failed and the budget ended before a retry)
            return self.last_fail, {"rounds": self.hist, "dense_set_poses": int(self.nD),
                                    "note": self.note or "no round produced a layout"}
        return self.result()

    def result(self):
        """The best round's result with the loop's certificate, and the info dict."""
        import dataclasses

        b = self.best
        res, ev = b["res"], b
        ae, pe, ce = ev["ext"]
        as_, ps_, cs_, sunc = ev["sw"]
        n_rows = ev["n_rows"]
        # poses found uncoverable after the best round: its value over the coverable ones
        short, dval = _dense_value(self.obj, np.r_[ev["a"], ae, as_], np.r_[ev["p"], pe, ps_],
                                   np.r_[ev["cov"], ce, cs_], np.r_[ev["cov_all"], cs_], self.need_all,
                                   np.r_[self.uncoverable[:n_rows], sunc])
        if short:
            dval = math.inf
        # every round's working set is a subset of the dense set: the largest round bound holds for it
        fin = [h for h in self.hist if h["bound"] is not None and np.isfinite(h["bound"])]
        bounds = [h["bound"] for h in fin]
        if bounds and not (np.isfinite(res.bound) and res.bound >= max(bounds)):
            src = int(np.argmax(bounds))
            res = dataclasses.replace(res, bound=float(max(bounds)),
                                      certified_by=f"relaxation (dense round {fin[src]['round']})",
                                      gap=res.value / max(bounds) - 1)
        if short and res.status in ("ok", "optimal"):  # an honest status: the loop ended short of coverage
            res = dataclasses.replace(res, status="incomplete", message=res.message + (
                f" [incomplete: the dense loop ended ({self.note or 'its rounds, budget or patience spent'}) "
                f"with {short} of its poses below {self.m} lit sensors]"))
        if self.interrupted:
            res = dataclasses.replace(res, status="interrupted", info={**res.info, "interrupted": self.interrupted},
                                      message=res.message + " [interrupted: best dense round so far]")
        gap = dval / res.bound - 1 if np.isfinite(res.bound) and res.bound > 0 else float("nan")
        RD, tD, nD, work_rows = self.RD, self.tD, self.nD, b["work_rows"]
        info = {"rounds": self.hist, "dense_set_poses": int(len(RD) if self.d.coverage_dop else nD),
                "coverage_poses": int(self.nC), "coverage_dop": bool(self.d.coverage_dop),
                "range_sweep": bool(self.d.range_sweep), "swept_poses": int(len(sunc)),
                "joined_swept_poses": int(len(RD) - nD - self.nC),
                "working_set_poses": int(len(work_rows)),
                "final_working_set_poses": int(self.in_work.sum()), "seed_poses": self.n_seed,
                "seed_indices": self.seed_idx, "converged": self.converged,
                "dense_value": dval, "dense_gap": gap, "dense_adop": ev["a"], "dense_pdop": ev["p"],
                "dense_covered": ev["cov"], "working_value": float(res.value),
                "working_rotations": RD[work_rows], "working_translations": tD[work_rows],
                "time_s": time.perf_counter() - self.t0, "uncoverable_dense_poses": int(self.uncoverable.sum()),
                "uncovered_dense_poses": int(short), "note": self.note,
                "relaxation_z": self.z_relax}  # the last relaxation's fractional z (the certificate's round)
        return res, info
