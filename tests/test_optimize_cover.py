"""local_search's ``cover``: coverage-only poses outside the problem's DOP working set.

Kind of proof: brute force. Every 1- and 2-swap's lit counts are recomputed directly, and the
search's result is checked for coverage and exact 1-swap local optimality by enumerating every
swap of the constrained problem.
"""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from layoutkit.optimize import parse_objective, search
from layoutkit.optimize.core import candidate_jacobians
from layoutkit.optimize.instances import synthetic_instance
from layoutkit.optimize.problem import build_problem, subset_pose_values

RHO = 0.8717


def test_cover_one_swaps_match_direct_counts():
    """Each 1-swap's feasibility against the lit counts of the swapped selection, recomputed."""
    rng = np.random.default_rng(0)
    cover = rng.choice(np.arange(3, dtype=np.uint8), size=(20, 12), p=[0.15, 0.45, 0.4])  # counts may exceed 1
    sel = np.array([0, 3, 5, 8, 11])
    adds = np.setdiff1d(np.arange(12), sel)
    m = 3
    got = search.cover_one_swaps(cover, m, sel, adds)
    for r in range(len(sel)):
        for j, c in enumerate(adds):
            s2 = np.r_[np.delete(sel, r), c]
            assert got[r, j] == bool((cover[:, s2].sum(axis=1) >= m).all())
    assert got.any() and not got.all()  # both outcomes occur: the comparison can fail


def test_cover_two_swaps_match_direct_counts():
    rng = np.random.default_rng(1)
    cover = (rng.random((15, 10)) < 0.7).astype(np.uint8)
    sel = np.array([0, 2, 4, 6, 8])
    m = 2
    while not (cover[:, sel].sum(axis=1) >= m).all():  # a covering start, as local_search requires
        cover[np.flatnonzero(cover[:, sel].sum(axis=1) < m)[0], sel[:m]] = 1
    moves = [(o, i) for o in itertools.combinations(sel, 2) for i in itertools.combinations(np.setdiff1d(np.arange(10), sel), 2)]
    o1, o2 = np.array([m_[0][0] for m_ in moves]), np.array([m_[0][1] for m_ in moves])
    i1, i2 = np.array([m_[1][0] for m_ in moves]), np.array([m_[1][1] for m_ in moves])
    got = search._cover_two_swaps(cover, m, sel, o1, o2, i1, i2, chunk=7)  # several chunks
    for n, (out, inn) in enumerate(moves):
        s2 = np.r_[np.setdiff1d(sel, out), inn]
        assert got[n] == bool((cover[:, s2].sum(axis=1) >= m).all())
    assert got.any() and not got.all()


def _split_instance(seed):
    """16 candidates, 24 poses: DOP scored on the first 3 (the problem), the other 21 coverage-only."""
    inst = synthetic_instance(16, 24, rng=seed, cone_deg=45, half_angle_deg=70)
    jac = candidate_jacobians(inst["positions"], inst["rotations"], inst["translations"])
    vis = inst["visible"][:, None]
    problem = build_problem(jac[:3], vis[:3], RHO, 5, 4, parse_objective("worst-adop"))
    lit = vis.any(axis=1)
    feasible = [np.array(s) for s in itertools.combinations(range(16), 5) if (lit[:, s].sum(axis=1) >= 4).all()]
    return problem, lit[3:], feasible


@pytest.mark.parametrize("seed", [21, 24])
def test_search_keeps_cover_poses_and_is_an_exact_local_optimum(seed):
    """Seeds where the constraint binds: without ``cover`` the search ends uncovering a coverage-only pose;
    with it, the result covers every pose, and no 1-swap that keeps all 24 poses covered lowers its
    worst over the 3 scored poses (every swap enumerated)."""
    problem, cover, feasible = _split_instance(seed)
    s0 = feasible[len(feasible) // 2]
    free, _, _ = search.local_search(problem, s0, two_swap=True)
    assert not (cover[:, free].sum(axis=1) >= 4).all()  # the constraint matters here
    sel, value, _ = search.local_search(problem, s0, two_swap=True, cover=cover)
    assert (cover[:, sel].sum(axis=1) >= 4).all()
    d, n = subset_pose_values(problem, sel)
    assert value == pytest.approx(d.max(), rel=1e-9) and (n >= 4).all()
    for r in range(len(sel)):
        for c in np.setdiff1d(np.arange(problem.N), sel):
            s2 = np.r_[np.delete(sel, r), c]
            d2, n2 = subset_pose_values(problem, s2)
            if (n2 >= 4).all() and (cover[:, s2].sum(axis=1) >= 4).all():
                assert d2.max() >= value * (1 - 1e-9)
    # and never better than the exhaustive optimum of the constrained problem
    best = min(subset_pose_values(problem, s)[0].max() for s in feasible)
    assert value >= best * (1 - 1e-12)


def test_bad_cover_is_refused_with_a_reason():
    problem, cover, feasible = _split_instance(21)
    with pytest.raises(ValueError, match="cover: expected"):
        search.local_search(problem, feasible[0], cover=cover[:, :5])
    uncovering = next(np.array(s) for s in itertools.combinations(range(16), 5)
                      if not (cover[:, s].sum(axis=1) >= 4).all())
    with pytest.raises(ValueError, match="fewer than 4 lit"):
        search.local_search(problem, uncovering, cover=cover)
