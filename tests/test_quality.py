"""Tracking-quality map (layoutkit.quality): pose construction, batch == per-item DOP, brute-force n_lit."""
import numpy as np
import pytest

from layoutkit.dop import pose_dop
from layoutkit.quality import (QualityMap, fibonacci_directions, latlon_grid, tracking_quality_map,
                               viewing_poses)
from layoutkit.shapes import chen_target, cubesat_3u


def _brute_visible(mesh, P, N, R, t, half_deg=60.0, fov_deg=120.0, eps=1e-7):
    """Independent float64 reference: explicit sweep angles, acceptance cone, and a Möller–Trumbore
    segment test of the sensor→station segment against every triangle (no ray engine)."""
    q = P @ R.T + t                                    # station frame
    th = np.stack([np.arctan2(q[:, 2], q[:, 0]), np.arctan2(q[:, 2], q[:, 1])], -1)
    in_fov = np.all(np.abs(th - np.pi / 2) <= np.deg2rad(fov_deg) / 2 + 1e-12, -1) & (q[:, 2] > 0)
    s = -R.T @ t                                       # station in the body frame
    to = s - P
    dist = np.linalg.norm(to, axis=1)
    cone = np.sum(N * to, 1) / dist >= np.cos(np.deg2rad(half_deg))
    tri = mesh.triangles                               # (F, 3, 3)
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    occl = np.zeros(len(P), bool)
    for i in range(len(P)):
        o = P[i] + N[i] * 1e-6
        d = s - o
        h = np.cross(d, e2)
        a = np.einsum("fj,fj->f", e1, h)
        ok = np.abs(a) > 1e-15
        f = np.where(ok, 1.0 / np.where(ok, a, 1.0), 0.0)
        sv = o - v0
        u = f * np.einsum("fj,fj->f", sv, h)
        qv = np.cross(sv, e1)
        v = f * (qv @ d)
        tt = f * np.einsum("fj,fj->f", e2, qv)
        hit = ok & (u >= -eps) & (v >= -eps) & (u + v <= 1 + eps) & (tt > eps) & (tt < 1 - eps)
        occl[i] = hit.any()
    return in_fov & cone & ~occl


def test_viewing_poses_put_station_on_direction_and_target_on_boresight():
    """Closed-form property check: R is a rotation, the station (origin of the station frame) sits at
    distance·d in the body frame, the body origin is on the boresight (+z) at that distance, and the
    roll samples differ by a rotation about the boresight only."""
    d = fibonacci_directions(7)
    roll = np.array([0.0, 0.3, 1.2])
    R, t = viewing_poses(d, 2.5, roll)
    assert R.shape == (7, 3, 3, 3) and t.shape == (7, 3, 3)
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    station_body = -np.einsum("...ji,...j->...i", R, t)  # -R^T t
    np.testing.assert_allclose(station_body, 2.5 * np.broadcast_to(d[:, None, :], station_body.shape), atol=1e-12)
    np.testing.assert_allclose(t, np.broadcast_to([0, 0, 2.5], t.shape), atol=1e-12)
    rel = R[:, 1] @ np.swapaxes(R[:, 0], -1, -2)  # rotation between roll 0 and roll 0.3
    np.testing.assert_allclose(rel[:, 2], np.broadcast_to([0, 0, 1], (7, 3)), atol=1e-12)
    np.testing.assert_allclose(np.arctan2(rel[:, 1, 0], rel[:, 0, 0]), 0.3, atol=1e-12)


def test_latlon_grid_cells_are_unit_vectors_at_their_angles():
    """Closed form: each grid direction has latitude asin(z) and longitude atan2(y, x) of its cell centre."""
    d, lat, lon, lat_e, lon_e = latlon_grid(6, 12)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.arcsin(d[..., 2]), lat, atol=1e-12)
    np.testing.assert_allclose(np.arctan2(d[..., 1], d[..., 0]), lon, atol=1e-12)
    np.testing.assert_allclose(lat[:, 0], 0.5 * (lat_e[1:] + lat_e[:-1]))
    assert lat_e[0] == -np.pi / 2 and lon_e[-1] == np.pi


def test_quality_map_batch_equals_per_direction_pose_dop():
    """Batch == per-item: map entries equal a direct single-pose ``pose_dop`` call (with the visibility
    of that one pose) for several directions and rolls; untracked entries are inf with status 1."""
    from layoutkit.visibility import visible_sensors

    mesh, lay = chen_target()
    q = tracking_quality_map(mesh, lay.positions, lay.normals, distance=2.0, rho=0.8717, grid=(9, 18),
                             roll_samples=3)
    assert isinstance(q, QualityMap) and q.adop.shape == (9, 18, 3)
    checked_finite = 0
    for (i, j, k) in [(8, 0, 0), (7, 5, 1), (6, 11, 2), (5, 3, 0), (4, 9, 1), (1, 2, 2), (0, 17, 0)]:
        R, t = viewing_poses(q.directions[i, j], 2.0, q.roll[k:k + 1])
        vis = visible_sensors(mesh, lay.positions, lay.normals, R, t)[0]
        ref = pose_dop(lay.positions, R[0], t[0], rho=0.8717, visible=vis)
        assert q.n_lit[i, j, k] == vis.sum()
        if vis.sum() >= 4:
            checked_finite += 1
            assert q.status[i, j, k] == ref.status
            np.testing.assert_allclose(q.adop[i, j, k], ref.adop, rtol=1e-10)
            np.testing.assert_allclose(q.pdop[i, j, k], ref.pdop, rtol=1e-10)
        else:
            assert np.isinf(q.adop[i, j, k]) and np.isinf(q.pdop[i, j, k]) and q.status[i, j, k] == 1
    assert checked_finite >= 3  # the test must exercise tracked directions
    # worst/median over roll are the max/median of the per-roll values
    np.testing.assert_array_equal(q.adop_worst, q.adop.max(-1))
    np.testing.assert_array_equal(q.n_lit_min, q.n_lit.min(-1))


def test_quality_map_n_lit_matches_brute_force_visibility_with_occlusion():
    """Brute force: n_lit at every direction × roll equals an independent float64 segment–triangle test
    on the 3U CubeSat, whose deployed panels shadow sensors on the bus (real occlusions occur)."""
    mesh = cubesat_3u()
    rng = np.random.default_rng(7)
    faces = rng.choice(len(mesh.faces), 14, replace=False)
    P = mesh.triangles_center[faces]
    N = mesh.face_normals[faces]
    q = tracking_quality_map(mesh, P, N, distance=1.5, grid=(6, 10), roll_samples=2)
    R, t = viewing_poses(q.directions, 1.5, q.roll)
    n_occluded = 0
    for idx in np.ndindex(q.n_lit.shape):
        ref = _brute_visible(mesh, P, N, R[idx], t[idx])
        no_occl = _brute_visible(trimesh_empty(), P, N, R[idx], t[idx])
        n_occluded += int(no_occl.sum() - ref.sum())
        assert q.n_lit[idx] == ref.sum(), idx
    assert n_occluded > 0  # occlusion really happened


def trimesh_empty():
    import trimesh

    return trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), int), process=False)


def test_quarter_roll_symmetry_of_the_dop():
    """Documented symmetry: a π/2 roll of the station about the line of sight swaps the sweeps and
    leaves ADOP/PDOP (with correlation) unchanged — why rolls are sampled in [0, π/2)."""
    mesh, lay = chen_target()
    d = fibonacci_directions(40)
    R, t = viewing_poses(d, 2.0, [0.2, 0.2 + np.pi / 2, 0.2 + np.pi])
    a = pose_dop(lay.positions, R, t, rho=0.8717)
    np.testing.assert_allclose(a.adop[:, 1], a.adop[:, 0], rtol=1e-9)
    np.testing.assert_allclose(a.pdop[:, 2], a.pdop[:, 0], rtol=1e-9)


def test_fibonacci_directions_and_summary():
    """Scattered directions: unit vectors, near-uniform (mean ≈ 0); summary fractions within [0, 1]."""
    d = fibonacci_directions(500)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    assert np.linalg.norm(d.mean(0)) < 0.01
    mesh, lay = chen_target()
    q = tracking_quality_map(mesh, lay.positions, lay.normals, distance=2.0, n_directions=60, roll_samples=2)
    assert q.adop.shape == (60, 2) and not q.is_grid
    s = q.summary()
    assert 0.0 < s["tracked_solid_angle_fraction"] < 1.0  # the Chen target has no sensors underneath
    assert s["n_lit_max"] <= lay.n


@pytest.mark.parametrize("kw, msg", [
    (dict(distance=0.0), "distance: expected a positive number of metres, got 0.0"),
    (dict(distance=2.0, roll_samples=0), "roll_samples: expected >= 1, got 0"),
    (dict(distance=2.0, grid=None), "give grid=(n_lat, n_lon) or n_directions"),
])
def test_quality_map_bad_input(kw, msg):
    mesh, lay = chen_target()
    with pytest.raises(ValueError) as e:
        tracking_quality_map(mesh, lay.positions, lay.normals, **kw)
    assert str(e.value) == msg


def test_quality_map_bad_positions_shape():
    mesh, lay = chen_target()
    with pytest.raises(ValueError, match=r"positions: expected shape \(\*, 3\), got \(12, 2\)"):
        tracking_quality_map(mesh, lay.positions[:, :2], lay.normals, distance=2.0)
