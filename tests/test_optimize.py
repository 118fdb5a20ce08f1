"""Layout optimiser: exact metric, low-rank updates, certified bounds, exhaustive optimality,
infeasibility analysis, constraints and input errors."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from layoutkit.dop import pose_dop
from layoutkit.optimize import METHODS, minimum_k, optimize_layout, parse_objective
from layoutkit.optimize.core import candidate_jacobians
from layoutkit.optimize.instances import synthetic_instance
from layoutkit.optimize.problem import build_problem, subset_pose_values
from layoutkit.optimize.relaxation import pose_trace_bounds, relaxed_pose_values
from layoutkit.optimize import search

RHO = 0.8717


def small(seed, n=14, p=10):
    return synthetic_instance(n, p, rng=seed, cone_deg=45, half_angle_deg=70)


def problem_of(inst, k, rho, objective="worst-adop", m=4):
    jac = candidate_jacobians(inst["positions"], inst["rotations"], inst["translations"])
    return build_problem(jac, inst["visible"][:, None], rho, k, m, parse_objective(objective))


@pytest.fixture(scope="module")
def refs():
    """Exhaustive optima of two small instances at rho = 0 and rho = 0.8717 (brute force)."""
    out = {}
    for seed in (0, 4):
        inst = small(seed)
        for rho in (0.0, RHO):
            out[seed, rho] = (inst, optimize_layout(**inst, k=6, rho=rho, method="exhaustive"))
    return out


def test_exact_metric_matches_core_pose_dop(refs):
    """Independent reference: layoutkit.dop.pose_dop on the chosen sensors (per-pose ADOP/PDOP)."""
    inst, res = refs[0, RHO]
    sel = res.selected
    d = pose_dop(inst["positions"][sel], inst["rotations"], inst["translations"], rho=RHO,
                 visible=inst["visible"][:, sel])
    np.testing.assert_allclose(res.adop, d.adop, rtol=1e-10)
    np.testing.assert_allclose(res.pdop, d.pdop, rtol=1e-10)
    assert res.value == pytest.approx(d.adop.max(), rel=1e-12)


def test_exhaustive_is_brute_force_optimum():
    """Proof by enumeration in a plain Python loop over every subset with pose_dop."""
    inst = small(4, n=10, p=6)
    res = optimize_layout(**inst, k=5, rho=RHO, method="exhaustive")
    best = np.inf
    for s in itertools.combinations(range(10), 5):
        s = list(s)
        if (inst["visible"][:, s].sum(1) < 4).any():
            continue
        d = pose_dop(inst["positions"][s], inst["rotations"], inst["translations"], rho=RHO,
                     visible=inst["visible"][:, s])
        best = min(best, d.adop.max())
    assert np.isfinite(best)
    assert res.value == pytest.approx(best, rel=1e-10)
    assert res.status == "optimal" and res.gap == 0


@pytest.mark.parametrize("method", sorted(METHODS))
@pytest.mark.parametrize("rho", [0.0, RHO])
def test_methods_feasible_and_bound_valid(refs, method, rho):
    """Every method: k sorted distinct indices, m lit at every pose, value >= exhaustive optimum,
    certified bound <= exhaustive optimum (the bound must never exceed the true optimum)."""
    inst, ref = refs[4, rho]
    res = optimize_layout(**inst, k=6, rho=rho, method=method, rng=1)
    assert res.success, res.message
    sel = res.selected
    assert len(sel) == 6 and len(set(sel.tolist())) == 6 and np.all(np.diff(sel) > 0)
    assert (inst["visible"][:, sel].sum(1) >= 4).all()
    assert res.value >= ref.value * (1 - 1e-9)
    assert res.bound <= ref.value * (1 + 1e-9)
    assert res.gap == pytest.approx(res.value / res.bound - 1)


@pytest.mark.parametrize("seed", [0, 4])
@pytest.mark.parametrize("rho", [0.0, RHO])
def test_pipeline_reaches_exhaustive_optimum(refs, seed, rho):
    """The default pipeline finds the exhaustive optimum within 0.5% (brute-force reference)."""
    inst, ref = refs[seed, rho]
    res = optimize_layout(**inst, k=6, rho=rho, rng=0)
    assert res.value <= ref.value * 1.005
    assert res.bound <= ref.value * (1 + 1e-9)


def test_low_rank_swap_values_match_direct():
    """Woodbury rank-2 updates (with the rho term) against a direct recompute of every swap."""
    inst = synthetic_instance(40, 8, rng=3, cone_deg=45, half_angle_deg=70)
    pr = problem_of(inst, 8, RHO)
    sel = np.arange(0, 40, 5)
    st = search.SearchState(pr, sel)
    adds = np.setdiff1d(np.arange(40), sel)
    v = search.one_swap_values(pr, st, adds, np.arange(8))
    for r in range(8):
        for j in range(len(adds)):
            d, _ = subset_pose_values(pr, np.r_[np.delete(sel, r), adds[j]])
            fin = np.isfinite(d)
            np.testing.assert_allclose(np.sqrt(v[r, j][fin]), d[fin], rtol=1e-7)


@pytest.mark.parametrize("rho", [0.0, 0.5, RHO])
def test_gls_relaxed_value_below_exact_at_integer_points(rho):
    """Gauss–Markov: at 0/1 z the relaxed per-pose value (GLS information) never exceeds the exact
    least-squares ADOP², and the closed-form trace bound never exceeds either."""
    inst = synthetic_instance(30, 12, rng=5, cone_deg=45, half_angle_deg=70)
    pr = problem_of(inst, 8, rho)
    rng = np.random.default_rng(0)
    L = pose_trace_bounds(pr)
    for _ in range(20):
        sel = np.sort(rng.choice(30, 8, replace=False))
        z = np.zeros(30)
        z[sel] = 1
        d, n = subset_pose_values(pr, sel)
        ok = np.isfinite(d)
        relaxed = np.sqrt(relaxed_pose_values(pr, z))
        assert np.all(relaxed[ok] <= d[ok] * (1 + 1e-9))
        assert np.all(L[ok] <= d[ok] * (1 + 1e-9))


def _greedy_trap():
    """Set cover where greedy needs 3 of the 3 candidates and 2 suffice (m = 1): the largest set (2)
    overlaps both halves {0..3} (0) and {4..7} (1)."""
    lit = np.zeros((8, 3), bool)
    lit[[0, 1, 2, 3], 0] = True
    lit[[4, 5, 6, 7], 1] = True
    lit[[0, 1, 4, 5, 6], 2] = True
    return lit


def test_coverage_is_infeasible_only_when_proven():
    """A set-multicover MILP stopped at its time limit proves nothing below its dual bound: the report
    is 'undecided' (feasible, decided False), never 'infeasible' (regression: 50,200 poses, 30 s limit,
    the incumbent of 121 sensors was reported as the smallest k and a 24-sensor layout that covers them
    all was refused). Checked against exhaustive enumeration of the 2³ subsets."""
    from layoutkit.optimize.coverage import analyse_coverage, greedy_cover_size

    lit = _greedy_trap()
    assert greedy_cover_size(lit, 1) == 3  # the fast path cannot decide k = 2
    exact = min(len(s) for r in range(4) for s in itertools.combinations(range(3), r)
                if (lit[:, list(s)].sum(1) >= 1).all())
    kup, sel, klow = minimum_k(lit, 1, return_bound=True)
    assert exact == 2 and kup == klow == 2 and list(sel) == [0, 1]
    for k in (1, 2):
        rep = analyse_coverage(lit, k, 1, time_limit=0.0)  # stops before any cover is proven
        assert rep.feasible and rep.status == "ok" and not rep.decided and "undecided" in rep.message
        rep = analyse_coverage(lit, k, 1)
        assert rep.decided and rep.feasible == (k >= exact)
    # a covering warm start is the proof without the MILP; a non-covering one proves nothing
    rep = analyse_coverage(lit, 2, 1, witness=[0, 1], time_limit=0.0)
    assert rep.feasible and rep.decided and "given 2-sensor selection" in rep.message
    assert not analyse_coverage(lit, 2, 1, witness=[0, 2], time_limit=0.0).decided
    assert not analyse_coverage(lit, 1, 1, witness=[0, 1], time_limit=0.0).decided  # too many sensors


def test_impossible_request_names_poses_and_smallest_k():
    """k too small: status with the poses left short and the smallest k, checked by brute force."""
    inst = synthetic_instance(16, 12, rng=3, cone_deg=60, half_angle_deg=60)
    vis = inst["visible"]
    kmin_bf = next(k for k in range(1, 17) if any(
        (vis[:, list(s)].sum(1) >= 4).all() for s in itertools.combinations(range(16), k)))
    assert minimum_k(vis, 4)[0] == kmin_bf
    res = optimize_layout(**inst, k=kmin_bf - 1, rho=RHO)
    assert not res.success and res.status == "infeasible"
    assert res.min_k == kmin_bf
    assert f"the smallest k that works is {kmin_bf}" in res.message
    assert "Poses left with fewer than 4 lit" in res.message


def test_uncoverable_pose_reported():
    """A pose that sees fewer than m candidates at all is named in the message."""
    inst = small(0)
    vis = inst["visible"].copy()
    vis[3] = False
    vis[3, :2] = True
    res = optimize_layout(**{**inst, "visible": vis}, k=6, rho=0.0)
    assert res.status == "uncoverable"
    assert list(res.uncoverable) == [3]
    assert "poses 3 (2 lit)" in res.message


def test_fixed_and_spacing_constraints(refs):
    """Fixed sensors are kept; no two chosen sites closer than min_spacing (exhaustive reference)."""
    inst, _ = refs[0, 0.0]
    pos = inst["positions"]
    dist = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    sp = float(np.percentile(dist[dist > 0], 5))
    ex = optimize_layout(**inst, k=6, method="exhaustive", fixed=[2], min_spacing=sp)
    res = optimize_layout(**inst, k=6, fixed=[2], min_spacing=sp, rng=0)
    for r in (ex, res):
        assert 2 in r.selected
        d = dist[np.ix_(r.selected, r.selected)]
        assert d[~np.eye(6, dtype=bool)].min() >= sp
    assert res.value <= ex.value * 1.005 and res.bound <= ex.value * (1 + 1e-9)


@pytest.mark.parametrize("objective", ["mean-pdop", "p90-adop", "worst-weighted"])
def test_other_objectives_against_exhaustive(refs, objective):
    """Mean / percentile / weighted objectives: pipeline within 0.5% of exhaustive, bound valid."""
    inst, _ = refs[4, RHO]
    kw = dict(k=6, rho=RHO, objective=objective, weights=(1.0, 1e6))
    ex = optimize_layout(**inst, method="exhaustive", **kw)
    res = optimize_layout(**inst, rng=0, **kw)
    assert res.value <= ex.value * 1.005
    assert res.bound <= ex.value * (1 + 1e-9)


def test_coverage_fraction_allows_uncovered_poses():
    """With coverage_fraction < 1, up to the stated share of poses may have fewer than m lit,
    and the objective is taken over the covered poses (exhaustive reference)."""
    inst = small(0)
    res = optimize_layout(**inst, k=4, coverage_fraction=0.8, method="exhaustive")
    assert res.success
    assert (res.n_lit >= 4).sum() >= 8
    full = optimize_layout(**inst, k=4, method="exhaustive")
    assert not full.success or full.value >= res.value


def test_bad_inputs_have_clear_messages():
    inst = small(0)
    with pytest.raises(ValueError, match=r"objective: expected '<worst\|mean\|pNN>-<adop\|pdop\|weighted>'"):
        optimize_layout(**inst, k=6, objective="best-adop")
    with pytest.raises(ValueError, match=r"visible: expected shape \(10, 14\), got \(10, 13\)"):
        optimize_layout(**{**inst, "visible": inst["visible"][:, :13]}, k=6)
    with pytest.raises(ValueError, match=r"method: expected one of \["):
        optimize_layout(**inst, k=6, method="magic")
    with pytest.raises(ValueError, match=r"k: expected 1 <= k <= 14 \(number of candidates\), got 20"):
        optimize_layout(**inst, k=20)
    with pytest.raises(ValueError, match=r"fixed: 3 fixed sensors exceed k = 2"):
        optimize_layout(**inst, k=2, fixed=[0, 1, 2])


def test_sweep_k_monotone_and_top_level_export():
    """rho = 0: more sensors never hurt (A grows, A^-1 shrinks), so the exhaustive optimum is
    non-increasing in k; the top-level `layoutkit.optimize_layout` is the same function and the
    progress callback sees the stages."""
    import layoutkit
    from layoutkit.optimize import sweep_k

    assert layoutkit.optimize_layout is optimize_layout
    inst = small(0)
    vals = [r.value for r in sweep_k(**inst, ks=[4, 5, 6, 7], rho=0.0, method="exhaustive")]
    assert all(b <= a * (1 + 1e-12) for a, b in zip(vals, vals[1:]))
    stages = []
    optimize_layout(**inst, k=6, rng=0, progress=lambda s, f=None, b=None: stages.append(s))
    assert "relaxation (cvxpy/Clarabel)" in stages and "local search" in stages


def test_two_stations_against_exhaustive_and_core():
    """Two stations: pipeline = exhaustive optimum, bound below it, per-pose ADOP equal to
    `pose_dop(..., stations=...)` of the core (independent multi-station reference)."""
    from layoutkit.geometry import look_at_rotation
    from layoutkit.lighthouse import Station
    from layoutkit.optimize import optimize_stations
    from layoutkit.optimize.instances import cone_visibility

    inst = small(0)
    R, t = inst["rotations"], inst["translations"]
    pos_b = np.array([1.0, 0.0, 0.0])
    look = look_at_rotation(np.array([-0.4, 0.0, 2.0]) - pos_b).T  # station B looks at the envelope
    stations = [Station("A"), Station("B", look, pos_b)]
    vis = np.stack([cone_visibility(inst["positions"], inst["normals"], *st.world_to_station(R, t))
                    for st in stations], axis=1)
    jac = candidate_jacobians(inst["positions"], R, t, stations)
    ex = optimize_stations(jac, vis, 6, rho=RHO, method="exhaustive")
    pl = optimize_stations(jac, vis, 6, rho=RHO, rng=0)
    assert ex.success and pl.value <= ex.value * 1.005 and pl.bound <= ex.value * (1 + 1e-9)
    d = pose_dop(inst["positions"][pl.selected], R, t, rho=RHO, visible=vis[:, :, pl.selected],
                 stations=stations)
    np.testing.assert_allclose(pl.adop, d.adop, rtol=1e-10)


@pytest.mark.parametrize("rho", [0.0, RHO])
def test_per_pose_relaxation_bounds_below_per_pose_minimum(rho):
    """Each per-pose relaxation bound lies between the closed-form trace bound and the smallest
    d_p over every feasible 6-subset (exhaustive per-pose minimum)."""
    from layoutkit.optimize.problem import pose_values_from_info, subset_info
    from layoutkit.optimize.relaxation import pose_relaxation_bounds

    inst = small(4)
    pr = problem_of(inst, 6, rho, objective="mean-adop")
    Z = np.array(list(itertools.combinations(range(14), 6)))
    A, b, n = subset_info(pr, Z)
    d = np.sqrt(pose_values_from_info(A, b, rho, pr.objective.w))
    feas = (n >= 4).all(axis=1)
    dmin = d[feas].min(axis=0)
    L = pose_relaxation_bounds(pr)
    T = pose_trace_bounds(pr)
    assert np.all(L >= T * (1 - 1e-12))
    assert np.all(L <= dmin * (1 + 1e-9))
    assert np.mean(L) > 1.5 * np.mean(T)  # the relaxation is the useful one


def test_exhaustive_refuses_huge_enumeration_with_reason():
    """Too many subsets: a status and a message that says why (no hour-long run)."""
    inst = synthetic_instance(60, 10, rng=1, cone_deg=45, half_angle_deg=70)
    res = optimize_layout(**inst, k=12, method="exhaustive")
    assert res.status == "no_feasible_found"
    assert "exhaustive: 1399358844975 subsets is too many (limit 5,000,000)" in res.message
