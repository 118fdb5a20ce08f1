"""Sensor tilt as a design variable: against exhaustive search over (site, orientation) choices.

Proof kind: exhaustive search — every k-subset of the oriented candidates with at most one
orientation per site (the optimiser's `exhaustive` method, itself checked against a plain loop over
pose_dop in test_optimize.py), plus an explicit brute-force over orientation assignments.
"""
import itertools

import numpy as np
import pytest

from layoutkit.dop import pose_dop
from layoutkit.optimize.core import candidate_jacobians, optimize_stations
from layoutkit.optimize.instances import cone_visibility
from layoutkit.optimize.tilt import site_conflicts, tilt_orientations
from layoutkit.optimize.tilt_instance import leaning_instance


def _solve(tilt, method, k=4, toward=None):
    pos, nor, R, t = leaning_instance()
    p2, a2, site, tl = tilt_orientations(pos, nor, tilt, 2, toward=toward)
    vis = cone_visibility(p2, a2, R, t, half_angle_deg=60)
    jac = candidate_jacobians(p2, R, t)
    r = optimize_stations(jac, vis[:, None], k, rho=0.8717, method=method, conflict=site_conflicts(site),
                          min_visible=4, rng=0, time_limit=20)
    return r, site, tl, (p2, a2, R, t)


def test_tilt_lowers_worst_adop_and_pipeline_finds_exhaustive_optimum():
    r0, *_ = _solve(0.0, "exhaustive")
    ex, site, tl, _ = _solve(30.0, "exhaustive")
    pl, site_p, _, _ = _solve(30.0, "pipeline")
    assert ex.success and pl.success
    assert ex.value < 0.5 * r0.value  # normals lean away: tilting pays
    assert pl.value == pytest.approx(ex.value, rel=1e-9)
    assert len(set(site[ex.selected])) == len(ex.selected)  # one orientation per site
    assert len(set(site_p[pl.selected])) == len(pl.selected)
    assert (tl[ex.selected] > 0).any()


def test_exhaustive_with_tilt_equals_brute_force_over_orientations():
    """Independent brute force: every 4 sites x every orientation of each, pose_dop directly."""
    ex, site, tl, (p2, a2, R, t) = _solve(30.0, "exhaustive")
    n_sites = site.max() + 1
    orient = [np.flatnonzero(site == s) for s in range(n_sites)]
    best = np.inf
    for sites in itertools.combinations(range(n_sites), 4):
        for choice in itertools.product(*[orient[s] for s in sites]):
            c = np.array(choice)
            vis = cone_visibility(p2[c], a2[c], R, t, half_angle_deg=60)
            if (vis.sum(1) < 4).any():
                continue
            d = pose_dop(p2[c], R, t, rho=0.8717, visible=vis)
            best = min(best, float(d.adop.max()))
    assert ex.value == pytest.approx(best, rel=1e-9)


def test_tilt_orientations_geometry():
    pos, nor, _, _ = leaning_instance()
    p2, a2, site, tl = tilt_orientations(pos, nor, 30.0, 4)
    ang = np.degrees(np.arccos(np.clip(np.sum(a2 * nor[site], axis=1), -1, 1)))
    np.testing.assert_allclose(ang, tl, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(a2, axis=1), 1.0)
    with pytest.raises(ValueError, match="max_tilt_deg"):
        tilt_orientations(pos, nor, 95.0)


def test_optimize_layout_max_tilt_keyword_matches_stations_path():
    """optimize_layout(max_tilt_deg=...) (the array API a sweep drives) = the explicit expansion."""
    from layoutkit.optimize import optimize_layout

    pos, nor, R, t = leaning_instance()
    vis = cone_visibility(pos, nor, R, t, half_angle_deg=60)
    r = optimize_layout(pos, nor, vis, R, t, 4, rho=0.8717, method="exhaustive", max_tilt_deg=30.0,
                        tilt_directions=2)
    ex, site, tl, _ = _solve(30.0, "exhaustive")
    assert r.value == pytest.approx(ex.value, rel=1e-12)
    assert sorted(r.info["site"].tolist()) == sorted(site[ex.selected].tolist())


def test_meridional_tilts_lie_in_the_plane_of_normal_and_axis():
    """Closed-form geometry of ``toward``: each tilted axis is a unit vector at the tilt angle from its
    normal, coplanar with the normal and the axis, the first block closer to the axis and the second
    farther; a site whose normal is the axis has no tilted orientation."""
    rng = np.random.default_rng(3)
    nor = rng.normal(size=(40, 3))
    nor /= np.linalg.norm(nor, axis=1, keepdims=True)
    w = np.array([0.2, -0.1, 1.0])
    nor[7] = w / np.linalg.norm(w)
    pos = rng.normal(size=(40, 3))
    p2, a2, site, tl = tilt_orientations(pos, nor, 20.0, toward=w, levels=(0.5, 1.0))
    assert len(p2) == 40 + 4 * 39 and 7 not in site[40:]
    np.testing.assert_array_equal(site[:40], np.arange(40))
    np.testing.assert_allclose(p2, pos[site])
    n = nor[site]
    np.testing.assert_allclose(np.linalg.norm(a2, axis=1), 1.0)
    np.testing.assert_allclose(np.degrees(np.arccos(np.clip(np.sum(a2 * n, axis=1), -1, 1))), tl, atol=1e-6)
    np.testing.assert_allclose(np.linalg.det(np.stack([n, a2, np.broadcast_to(w, n.shape)], axis=1)), 0.0,
                               atol=1e-12)
    ang = lambda a: np.degrees(np.arccos(np.clip(a @ (w / np.linalg.norm(w)), -1, 1)))  # angle to the axis
    th = ang(n)
    # in the plane, towards the axis: |theta - tilt|; away: theta + tilt (folded past 180)
    towards = np.tile(np.repeat([True, False], 39), 2)
    want = np.where(towards, np.abs(th[40:] - tl[40:]), 180 - np.abs(180 - th[40:] - tl[40:]))
    np.testing.assert_allclose(ang(a2[40:]), want, atol=1e-6)
    with pytest.raises(ValueError, match="toward"):
        tilt_orientations(pos, nor, 20.0, toward=[0, 0, 0])


@pytest.mark.slow
def test_meridional_tilt_toward_the_station_finds_the_exhaustive_optimum():
    """Exhaustive search with the 2 meridional orientations towards/away from the mean station direction
    (body frame, from the instance's poses): the pipeline equals it, and it beats the untilted optimum."""
    from layoutkit.lighthouse import Station
    from layoutkit.optimize.design import mean_station_direction

    _, _, R, t = leaning_instance()
    w = mean_station_direction(R, t, [Station()])
    d = np.array([Ri.T @ (np.zeros(3) - ti) / np.linalg.norm(ti) for Ri, ti in zip(R, t)])  # station at 0
    np.testing.assert_allclose(w, d.mean(0) / np.linalg.norm(d.mean(0)), atol=1e-12)
    assert np.degrees(np.arccos(d @ w)).max() < 30  # the instance's 25° cone (+ parallax) about it
    r0, *_ = _solve(0.0, "exhaustive")
    ex, site, tl, _ = _solve(30.0, "exhaustive", toward=w)
    pl, site_p, _, _ = _solve(30.0, "pipeline", toward=w)
    assert ex.success and pl.success and ex.value < 0.5 * r0.value
    assert pl.value == pytest.approx(ex.value, rel=1e-9)
    assert len(set(site_p[pl.selected])) == len(pl.selected)


def test_one_orientation_per_site_cut_tightens_the_bound_and_stays_below_the_optimum():
    """The relaxation with one row sum_site z <= 1 per site (5 orientations each: 4 azimuths at 30° and the
    normal) against the pairwise z_i + z_j <= 1 rows it replaces: its bound is at least as high (tighter) and
    never above the exhaustive optimum over one-orientation-per-site selections; branch-and-bound with it
    proves that optimum (proof kind: exhaustive search). Measured here: pairwise bound 4637, one-of-N 4748
    (exhaustive optimum 4856)."""
    from layoutkit.optimize.bnb import branch_and_bound
    from layoutkit.optimize.objectives import parse_objective
    from layoutkit.optimize.problem import build_problem
    from layoutkit.optimize.relaxation import relax

    pos, nor, R, t = leaning_instance(n=7, P=20)
    p2, a2, site, _ = tilt_orientations(pos, nor, 30.0, 4)
    vis = cone_visibility(p2, a2, R, t, half_angle_deg=60)
    jac = candidate_jacobians(p2, R, t)
    C = site_conflicts(site)
    cliques = [np.flatnonzero(site == s) for s in range(len(pos))]
    ex = optimize_stations(jac, vis[:, None], 4, rho=0.8717, method="exhaustive", conflict=C, min_visible=4)
    obj = parse_objective("worst-adop")
    pairs = relax(build_problem(jac, vis[:, None], 0.8717, 4, 4, obj, conflict=C))
    pb = build_problem(jac, vis[:, None], 0.8717, 4, 4, obj, conflict=C, cliques=cliques)
    clq = relax(pb)
    assert ex.success and pairs.certified_by == clq.certified_by == "relaxation"
    assert pairs.bound <= clq.bound * (1 + 1e-6) and clq.bound <= ex.value * (1 + 1e-9)
    for c in cliques:  # the relaxed z respects one orientation per site
        assert clq.z[c].sum() <= 1 + 1e-6
    bb = branch_and_bound(pb, groups=[])
    assert bb.value == pytest.approx(ex.value, rel=1e-9) and bb.bound <= ex.value * (1 + 1e-9)
    assert bb.status in ("complete", "gap reached") and bb.bound == pytest.approx(ex.value, rel=1e-6)  # proven
