"""The compiled PnP kernel (layoutkit.pnp_numba, registry name ``lm``) against the numpy reference
(``lm-numpy``, layoutkit.pnp_lh1.solve_pnp_lm) on the same frames.

Proof kind: an independent implementation of the same algorithm (frames-last numpy arrays vs a
scalar per-frame kernel) must give the same status in every frame and the same pose to rounding,
over every path of the solver: POSIT starts at n = 12, the IPPE pair and the ambiguity test on
4 coplanar sensors, 5-6 facing sensors, tracking starts (good, wrong, not a rotation), per-angle
visibility, per-frame bodies with non-finite points, collinear / too few / invalid / behind
frames, the iteration cap, sigma None / 0, and the threaded path (>= PARALLEL_MIN_FRAMES frames).
"""
import numpy as np
import pytest

from layoutkit.geometry import random_rotations, rotvec_to_matrix, transform_points
from layoutkit.lighthouse import in_field_of_view, sweep_angles
from layoutkit.noise import sample_angle_noise
from layoutkit.pnp import PNP_SOLVERS, solve_pnp
from layoutkit.pnp_lh1 import PARALLEL_MIN_FRAMES
from layoutkit.shapes import chen_target
from layoutkit.units import RHO_PAPER, SIGMA_THETA_PAPER

LAY = chen_target()[1]
P12 = LAY.positions
TOP = [0, 1, 2, 3]


def _poses(F, rng, P=P12):
    R = random_rotations(F, rng)
    t = np.empty((F, 3))
    todo = np.arange(F)
    while todo.size:
        d = rng.uniform(1.0, 3.0, todo.size)
        v = rng.standard_normal((todo.size, 3))
        v[:, 2] = np.abs(v[:, 2]) + 1.0
        cand = v / np.linalg.norm(v, axis=1, keepdims=True) * d[:, None]
        ok = np.all(in_field_of_view(transform_points(R[todo], cand, P)), axis=1)
        t[todo[ok]] = cand[ok]
        todo = todo[~ok]
    return R, t


def _angles(R, t, rng, P=P12, rho=RHO_PAPER):
    a = sweep_angles(transform_points(R, t, P))
    return a + sample_angle_noise(a.shape[:-1], SIGMA_THETA_PAPER, rho, rng)


def _same(a, b, tol=1e-9):
    """Same statuses; same poses (rad, m) and residuals where posed; same runner-ups. Frames that hit
    the iteration cap (not_converged) compare by status only: after 20 steps of a non-converging
    LM the sums' different rounding order (pairwise numpy sums vs sequential) has grown."""
    np.testing.assert_array_equal(a.status, b.status)
    np.testing.assert_array_equal(a.success, b.success)
    fin = np.isfinite(a.translation[:, 0])
    np.testing.assert_array_equal(fin, np.isfinite(b.translation[:, 0]))
    fin &= a.status != 3
    np.testing.assert_allclose(a.rotation[fin], b.rotation[fin], rtol=0, atol=tol)
    np.testing.assert_allclose(a.translation[fin], b.translation[fin], rtol=0, atol=tol)
    np.testing.assert_allclose(a.residual_rms[fin], b.residual_rms[fin], rtol=1e-6, atol=1e-15)
    alt = np.isfinite(a.alt_translation[:, 0])
    np.testing.assert_array_equal(alt, np.isfinite(b.alt_translation[:, 0]))
    np.testing.assert_allclose(a.alt_translation[alt], b.alt_translation[alt], rtol=0, atol=tol)
    assert np.mean(a.iterations == b.iterations) > 0.99


def _both(*args, **kw):
    return (solve_pnp(*args, method="lm", **kw), solve_pnp(*args, method="lm-numpy", **kw))


def test_registry_names():
    assert set(PNP_SOLVERS) == {"lm", "lm-numpy"}


@pytest.mark.parametrize("rho", [0.0, RHO_PAPER])
def test_twelve_sensors_threaded(rng, rho):
    """n = 12, random poses, paper noise, enough frames for the threaded path."""
    F = max(600, PARALLEL_MIN_FRAMES + 1)
    R, t = _poses(F, rng)
    a, b = _both(P12, _angles(R, t, rng, rho=rho), rho=rho)
    assert a.success.mean() > 0.99
    _same(a, b)


def test_coplanar_four_ippe_and_ambiguity(rng):
    """4 coplanar top sensors (IPPE pair, the ambiguity test with runner-ups), one thread (few frames)."""
    R, t = _poses(200, rng)
    R = np.einsum("fij,jk->fik", R, np.eye(3))
    ang = _angles(R, t, rng)
    vis = np.zeros((200, 12), bool)
    vis[:, TOP] = True
    a, b = _both(P12, ang, vis)
    assert (a.status == 5).sum() > 0 and (a.status == 0).sum() > 0   # both outcomes present
    _same(a, b)
    a, b = _both(P12, ang, vis, sigma=None)                         # no test: lower residual wins
    _same(a, b)
    a, b = _both(P12, ang, vis, sigma=0.0)
    _same(a, b)


def test_small_facing_sets_per_angle_and_starts(rng):
    """5-6 sensors with single-axis gaps, tracking starts (near, wrong, not a rotation), the iteration cap."""
    F = 400
    R, t = _poses(F, rng)
    ang = _angles(R, t, rng)
    vis = np.zeros((F, 12, 2), bool)
    for f in range(F):
        vis[f, rng.choice(12, 6, replace=False)] = True
    vis[::3, 0, 1] = False                                          # one axis missing
    vis[1::7] = False
    vis[1::7, :3] = True                                            # 3 sensors: no cold start
    a, b = _both(P12, ang, vis)
    _same(a, b)
    near = (np.matmul(rotvec_to_matrix(rng.normal(0, 0.01, (F, 3))), R), t + rng.normal(0, 0.005, (F, 3)))
    a, b = _both(P12, ang, vis, initial=near)
    assert (a.status == 11).sum() > 0                               # 3-sensor frames from the start
    _same(a, b)
    wrong = (random_rotations(F, rng), t[::-1].copy())
    wrong[0][::5] *= 1.01                                           # not rotations: projected first
    wrong[0][2::9] = np.nan                                         # no start for some frames
    a, b = _both(P12, ang, vis, initial=wrong)
    _same(a, b)
    a, b = _both(P12, ang, vis, max_iterations=1)
    assert (a.status == 3).sum() > 0                                # not converged
    _same(a, b)


def test_bad_frames_and_per_frame_bodies(rng):
    """Too few, collinear, invalid, behind and per-frame bodies with non-finite unseen points."""
    F = 60
    R, t = _poses(F, rng)
    ang = _angles(R, t, rng)
    ang[0] = np.nan                                                 # nothing seen
    ang[1, 2:] = np.nan                                             # two sensors: too few
    ang[2, 5, 0] = np.inf                                           # invalid angle
    ang[3, 6, 1] = 4.0                                              # outside (0, pi)
    Pf = np.broadcast_to(P12, (F, 12, 3)).copy()
    Pf[4:8, :, 1] = 0.0
    Pf[4:8, :, 2] = 0.0                                             # collinear bodies
    ang[8:12] = np.pi - ang[8:12]                                   # mirrored: behind / wrong side
    Pf[12:20, 11] = np.nan                                          # a non-finite point (unseen)
    a, b = _both(Pf, ang)
    assert {1, 2, 6}.issubset(set(a.status.tolist()))
    _same(a, b)


@pytest.mark.parametrize("n", [24, 48])
def test_many_sensors(rng, n):
    """Bodies of 24 and 48 sensors on a 12.5 x 12.5 x 6.25 cm box (the benchmark's larger bodies)."""
    P = rng.uniform(-0.0625, 0.0625, (n, 3)) * [1.0, 1.0, 0.5]
    R, t = _poses(300, rng, P)
    a, b = _both(P, _angles(R, t, rng, P))
    assert a.success.mean() > 0.99
    _same(a, b)


@pytest.mark.parametrize("F", [120, PARALLEL_MIN_FRAMES + 40])
def test_runs_of_one_lit_pattern(rng, F):
    """The kernel computes a body's geometry (scatter, planarity, collinearity, POSIT's centred points)
    once per run of consecutive frames with the same lit pattern: runs of 1-7 frames whose pattern
    changes between all lit, per-angle gaps (a sensor with one angle), the coplanar top face,
    a collinear edge and too few sensors; on one numba thread and on two (threaded blocks cut runs)."""
    import numba

    R, t = _poses(F, rng)
    a = _angles(R, t, rng)
    pats = [np.ones((12, 2), bool)]
    gap = np.ones((12, 2), bool)
    gap[[2, 7], 0] = False
    pats.append(gap)
    top = np.zeros((12, 2), bool)
    top[TOP] = True
    pats.append(top)
    edge = np.zeros((12, 2), bool)
    edge[[0, 1]] = True                       # two sensors: too few
    pats.append(edge)
    five = np.zeros((12, 2), bool)
    five[[0, 1, 2, 3, 8]] = True
    pats.append(five)
    vis = np.empty((F, 12, 2), bool)
    f = 0
    while f < F:
        k = int(rng.integers(1, 8))
        vis[f:f + k] = pats[int(rng.integers(len(pats)))]
        f += k
    threads = numba.get_num_threads()
    try:
        for nt in sorted({1, min(2, numba.config.NUMBA_NUM_THREADS)}):
            numba.set_num_threads(nt)
            x = solve_pnp(P12, a, vis, method="lm")
            y = solve_pnp(P12, a, vis, method="lm-numpy")
            assert len(np.unique(x.status)) >= 3
            _same(x, y)
    finally:
        numba.set_num_threads(threads)


def test_chunks_write_into_the_whole_batch(rng):
    """Over several chunks the compiled solver writes each chunk into its slice of the batch's outputs
    (no concatenation); the result is the one-chunk result in every field, every frame: all-lit chunks,
    chunks with invalid angles (STATUS_INVALID_ANGLE set after the solve), a frame without a start, the
    4-sensor top face (an ambiguous frame with its runner-up)."""
    R, t = _poses(60, rng)
    ang = _angles(R, t, rng)
    ang[13, 4, 0] = 3.5             # out of (0, pi): invalid, in the second chunk of 7
    ang[40, 2, 1] = -np.inf         # invalid, sixth chunk
    ang[22, :9] = np.nan            # 3 sensors seen: no start
    ang[50:57, 4:] = np.nan         # the top face only (a whole chunk of 7): coplanar, IPPE, ambiguity
    one = solve_pnp(P12, ang, chunk_size=60)
    assert set(one.status.tolist()) == {0, 5, 6, 7} and np.isnan(one.rotation[13]).all()
    for chunk in (7, 16, 59):
        many = solve_pnp(P12, ang, chunk_size=chunk)
        for field in ("rotation", "translation", "success", "status", "residual_rms", "iterations",
                      "alt_rotation", "alt_translation", "alt_residual_rms"):
            np.testing.assert_array_equal(getattr(many, field), getattr(one, field), err_msg=field)
    # all lit, no invalid angle: the fast path of every chunk
    ok = np.delete(np.arange(60), [13, 22, 40] + list(range(50, 57)))
    np.testing.assert_array_equal(solve_pnp(P12, ang[ok], chunk_size=8).rotation, solve_pnp(P12, ang[ok]).rotation)


def test_unrolled_ldl_factor_and_solve_match_numpy(rng):
    """lm_numba.factor / apply (the 6 x 6 LDL^T of A + lam diag(A), unrolled in scalars) against
    numpy's solve of the same damped system (closed form, independent): 200 random SPD normal matrices
    over six decades of conditioning, and a rank-deficient one refused (ok False)."""
    from layoutkit.lm_numba import apply, factor

    L, inv, y, x = np.empty((6, 6)), np.empty(6), np.empty(6), np.empty(6)
    for k in range(200):
        J = rng.normal(size=(12, 6)) * np.logspace(0, -3 * (k % 3), 6)
        A, g, lam = J.T @ J, rng.normal(size=6), [0.0, 1e-3, 0.5][k % 3]
        assert factor(A, lam, L, inv)
        apply(L, inv, g, y, x)
        ref = np.linalg.solve(A + lam * np.diag(np.diag(A)), g)
        assert np.allclose(x, ref, rtol=1e-8 * np.linalg.cond(A), atol=0), (k, x, ref)
    J = rng.normal(size=(12, 5)) @ rng.normal(size=(5, 6))  # rank 5
    assert not factor(J.T @ J, 0.0, L, inv)
