"""Fused search kernels (issue 13, item 7: the dense loop evaluates layouts at 10^4 poses many times).

Proof kind: independent re-computation. ``pose_values`` is compared with the batched-numpy reference
``pose_values_numpy`` (LU inverse, eigenvalue test for singular matrices) and with the covariance of
Chen eq. 18 formed explicitly (``(1 - rho) A^-1 + rho sum_c u_c u_c^T``); ``move_values`` with the
information of each move gathered and summed in plain numpy. Singular and rank-deficient inputs
must come out as inf in both.
"""
from __future__ import annotations

import numpy as np
import pytest

from layoutkit.optimize.kernels import move_values, pose_values
from layoutkit.optimize.problem import pose_values_numpy


def _info(rng, M, C=2, rows=8):
    X = rng.normal(size=(M, rows, 6)) * rng.uniform(0.01, 100, size=(M, 1, 6))
    return np.einsum("mri,mrj->mij", X, X), rng.normal(size=(M, C, 6))


@pytest.mark.parametrize("rho", [0.0, 0.8717])
@pytest.mark.parametrize("w", [[1, 1, 1, 0, 0, 0], [0, 0, 0, 1, 1, 1], [2.0, 2, 2, 0.5, 0.5, 0.5]])
def test_pose_values_match_numpy_and_the_explicit_covariance(rho, w):
    """Regular, badly scaled, singular (zero row/column, rank 5, all zero) matrices; C = 2 and 4."""
    rng = np.random.default_rng(1)
    w = np.asarray(w, float)
    for C in (2, 4):
        A, b = _info(rng, 400, C)
        A[:5] = 0.0
        A[5:10, 2, :] = 0.0
        A[5:10, :, 2] = 0.0
        X = rng.normal(size=(5, 5, 6))
        A[10:15] = np.einsum("mri,mrj->mij", X, X)  # rank 5
        got = pose_values(A, b, rho, w)
        ref = pose_values_numpy(A, b, rho, w)
        assert np.array_equal(np.isfinite(got), np.isfinite(ref))
        assert not np.isfinite(got[:15]).any() and np.isfinite(got[15:]).all()
        np.testing.assert_allclose(got[15:], ref[15:], rtol=1e-9)
        Ai = np.linalg.inv(A[15:])
        u = np.einsum("mij,mcj->mci", Ai, b[15:])
        H = (1 - rho) * Ai + rho * np.einsum("mci,mcj->mij", u, u)
        np.testing.assert_allclose(got[15:], np.einsum("mii,i->m", H, w), rtol=1e-8)
    # leading batch dims are kept, b broadcasts
    A, b = _info(rng, 12)
    assert pose_values(A.reshape(3, 4, 6, 6), b.reshape(3, 4, 2, 6), rho, w).shape == (3, 4)


@pytest.mark.parametrize("rho", [0.0, 0.8717])
def test_move_values_match_gathered_information(rho):
    """1-swaps, 2-swaps and pure additions (greedy) at a subset of poses, against numpy gathers."""
    rng = np.random.default_rng(2)
    P, N, C = 30, 20, 2
    U = rng.normal(size=(P, N, C, 6)) * (rng.random((P, N, 1, 1)) < 0.7)
    G = np.einsum("pnci,pncj->pnij", U, U)
    sel = np.array([0, 3, 5, 7, 9, 11, 13, 15])
    Ab, bb = G[:, sel].sum(axis=1), U[:, sel].sum(axis=1)
    poses = np.array([0, 4, 7, 29, 4])
    w = np.array([1.0, 1, 1, 0, 0, 0])
    for outs, ins in ((sel[[0, 2, 7]][:, None], np.array([[1], [2], [19]])),
                      (np.array([[0, 3], [5, 15]]), np.array([[1, 2], [18, 19]])),
                      (np.zeros((3, 0), int), np.array([[1], [2], [4]]))):
        got = move_values(Ab, bb, G, U, poses, outs, ins, rho, w)
        for l in range(len(outs)):
            A = Ab[poses] - G[poses][:, outs[l]].sum(axis=1) + G[poses][:, ins[l]].sum(axis=1)
            b = bb[poses] - U[poses][:, outs[l]].sum(axis=1) + U[poses][:, ins[l]].sum(axis=1)
            ref = pose_values_numpy(A, b, rho, w)
            assert np.array_equal(np.isfinite(got[l]), np.isfinite(ref))
            np.testing.assert_allclose(got[l][np.isfinite(ref)], ref[np.isfinite(ref)], rtol=1e-9)
    with pytest.raises(ValueError, match="same number of moves"):
        move_values(Ab, bb, G, U, poses, np.zeros((2, 1), int), np.zeros((3, 1), int), rho, w)


def test_polish_z_hint_is_validated_and_used_for_kicks():
    """The polish method's site ranking: a wrong-length hint is a clear error; the kick rule the hint feeds
    (``_kick``) given a z that puts all weight
    on four sites outside the selection makes kicks draw them far more often than uniform kicks do (the
    pipeline's rule: half ∝ z, half uniform), counted over 400 kicks each."""
    from layoutkit.optimize import candidate_jacobians, optimize_stations
    from layoutkit.optimize.instances import synthetic_instance
    from layoutkit.optimize.methods import _kick
    from layoutkit.optimize.objectives import parse_objective
    from layoutkit.optimize.problem import build_problem

    inst = synthetic_instance(40, 12, rng=3, cone_deg=30, half_angle_deg=70)
    jac = candidate_jacobians(inst["positions"], inst["rotations"], inst["translations"])
    vis = inst["visible"][:, None]
    with pytest.raises(ValueError, match="z_hint: expected 40 finite values"):
        optimize_stations(jac, vis, 8, method="polish", ctx_options={"z_hint": np.ones(3)})
    pr = build_problem(jac, vis, 0.0, 8, 4, parse_objective("worst-adop"))
    ok = optimize_stations(jac, vis, 8, method="polish", rng=0)
    assert ok.success
    sel = np.asarray(ok.selected)
    hot = np.setdiff1d(np.arange(pr.N), sel)[:4]
    z = np.zeros(pr.N)
    z[hot] = 1.0
    rng = np.random.default_rng(0)
    hits_z = hits_u = 0
    for _ in range(400):
        a = _kick(pr, sel, rng, z)
        b = _kick(pr, sel, rng, np.full(pr.N, 8 / pr.N))
        hits_z += 0 if a is None else int(np.isin(a, hot).sum())
        hits_u += 0 if b is None else int(np.isin(b, hot).sum())
    assert hits_z > 3 * max(hits_u, 1)
