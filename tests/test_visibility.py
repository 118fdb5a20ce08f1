"""Visibility: the cheap tests against their definitions (per-pair arccos / sweep angles of the core),
occlusion against closed-form geometry and against a brute-force float64 segment-triangle test
(no ray engine) on the self-occluding docking target, embree against trimesh's default engine."""
import numpy as np
import pytest
import trimesh

from layoutkit.geometry import random_rotations, rotvec_to_matrix
from layoutkit.lighthouse import Station, in_field_of_view
from layoutkit.shapes import docking_target
from layoutkit.visibility import (
    RAY_ENGINES,
    envelope_visibility,
    segment_occlusion_reference,
    visible_sensors,
)


def _poses_in_front(rng, count, rmin, rmax, cone_deg=40.0):
    d = rng.normal(size=(count, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    c = np.cos(np.deg2rad(cone_deg))
    d[:, 2] = np.abs(d[:, 2]) + c  # mostly in front of the station
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return random_rotations(count, rng), d * rng.uniform(rmin, rmax, count)[:, None]


def test_cheap_tests_match_their_definitions(rng):
    """Reference: per pair in the station frame — in_field_of_view of the core, the arccos of the
    angle between R m and the direction to the station, the range. Pairs within 1e-9 of a boundary skipped."""
    mesh = trimesh.creation.box((0.1, 0.1, 0.1))
    n = 40
    P = rng.uniform(-0.5, 0.5, (n, 3))
    N = rng.normal(size=(n, 3))
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    R, t = _poses_in_front(rng, 300, 0.5, 3.0, cone_deg=70.0)
    for half, fov, rmax in ((60.0, 120.0, None), (30.0, 90.0, 2.0), (100.0, 150.0, 2.5)):
        got = visible_sensors(mesh, P, N, R, t, sensor_half_angle_deg=half, fov_deg=fov, max_range=rmax,
                              occlusion=False)
        p_lh = np.einsum("pij,nj->pni", R, P) + t[:, None]
        m_lh = np.einsum("pij,nj->pni", R, N)
        to_st = -p_lh / np.linalg.norm(p_lh, axis=-1, keepdims=True)
        ang = np.degrees(np.arccos(np.clip(np.sum(m_lh * to_st, -1), -1, 1)))
        want = in_field_of_view(p_lh, fov) & (ang <= half)
        th = np.degrees(np.abs(np.arctan2(p_lh[..., 2:3], p_lh[..., :2]) - np.pi / 2)).max(-1)
        margin = np.minimum(np.abs(ang - half), np.abs(th - fov / 2))
        if rmax is not None:
            rng_ = np.linalg.norm(p_lh, axis=-1)
            want &= rng_ <= rmax
            margin = np.minimum(margin, np.abs(rng_ - rmax))
        sure = margin > 1e-9
        assert sure.mean() > 0.99 and want[sure].sum() > 100 and (~want[sure]).sum() > 100
        np.testing.assert_array_equal(got[sure], want[sure])


def test_plate_in_front_of_sensor_occludes_in_closed_form():
    """A 1 m plate at z = 0.5 above a sensor at the origin (normal +z). Body = station frame shifted:
    the segment to a station at (x, 0, 3) crosses the plate iff |x * 0.5/3| < 0.5 (similar triangles)."""
    plate = trimesh.creation.box((1.0, 1.0, 0.01), transform=trimesh.transformations.translation_matrix((0, 0, 0.5)))
    P, N = np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]])
    # station at s in the body frame: pose R = rot 180 deg about x (body +z faces the station), t = -R s
    R = rotvec_to_matrix(np.array([np.pi, 0.0, 0.0]))
    xs = np.array([0.0, 1.0, 2.5, 2.9, 3.1, 3.5, 5.0])
    s = np.column_stack([xs, np.zeros_like(xs), np.full_like(xs, 3.0)])
    t = -s @ R.T
    Rs = np.repeat(R[None], len(xs), 0)
    got = visible_sensors(plate, P, N, Rs, t, sensor_half_angle_deg=89.0, fov_deg=170.0)[:, 0]
    crossing = np.abs(xs * 0.5 / 3.0) < 0.5 - 0.005 * xs / 3  # plate half-width at its lower face
    np.testing.assert_array_equal(got, ~crossing)
    # a station BETWEEN sensor and plate: the open segment ends before the plate -> visible
    s_near = np.array([[0.0, 0.0, 0.3]])
    assert visible_sensors(plate, P, N, R, (-s_near @ R.T)[0], sensor_half_angle_deg=89.0, fov_deg=170.0)[0]


@pytest.fixture(scope="module")
def small_docking():
    return docking_target(sections=24, dish_rings=8)


def test_occlusion_equals_brute_force_on_docking_target(small_docking):
    """Reduced version of benchmarks/bench_visibility.py: every pair passing the cheap tests,
    embree vs all-triangle float64 test; zero mismatches outside the 10 um grazing band."""
    mesh = small_docking
    rng = np.random.default_rng(3)
    pts, fi = trimesh.sample.sample_surface_even(mesh, 150, radius=0.15, seed=rng)
    N = mesh.face_normals[fi]
    R, t = _poses_in_front(rng, 40, 4.0, 9.0)
    cheap = visible_sensors(mesh, pts, N, R, t, occlusion=False)
    vis = visible_sensors(mesh, pts, N, R, t)
    ip, isn = np.nonzero(cheap)
    o = pts[isn] + 1e-5 * mesh.scale * N[isn]
    s = -np.einsum("pji,pj->pi", R, t)[ip]
    occ, amb = segment_occlusion_reference(mesh.triangles, o, s, tol=1e-5)
    assert len(ip) > 1000 and occ.sum() > 50  # real occlusion, enough pairs
    assert amb.sum() <= 0.01 * len(ip)
    np.testing.assert_array_equal(~vis[ip, isn][~amb], occ[~amb])
    assert not np.any(vis & ~cheap)  # occlusion only removes


def test_chunking_does_not_change_the_answer(small_docking):
    rng = np.random.default_rng(9)
    pts, fi = trimesh.sample.sample_surface_even(small_docking, 40, radius=0.3, seed=rng)
    R, t = _poses_in_front(rng, 30, 4.0, 8.0)
    a = visible_sensors(small_docking, pts, small_docking.face_normals[fi], R, t)
    b = visible_sensors(small_docking, pts, small_docking.face_normals[fi], R, t, chunk=7)
    np.testing.assert_array_equal(a, b)
    assert a.any() and not a.all()


def test_narrower_cone_is_the_wider_visibility_and_its_cone(small_docking):
    """Occlusion does not depend on the acceptance angle: visibility at 55° equals visibility at 60° and-ed
    with the cone-only test at 55° (what studies/device_layouts/refine.py uses instead of a second ray cast)."""
    rng = np.random.default_rng(11)
    pts, fi = trimesh.sample.sample_surface_even(small_docking, 80, radius=0.2, seed=rng)
    N = small_docking.face_normals[fi]
    R, t = _poses_in_front(rng, 60, 4.0, 9.0)
    wide = visible_sensors(small_docking, pts, N, R, t, sensor_half_angle_deg=60.0)
    narrow = visible_sensors(small_docking, pts, N, R, t, sensor_half_angle_deg=55.0)
    cone = visible_sensors(small_docking, pts, N, R, t, sensor_half_angle_deg=55.0, occlusion=False)
    np.testing.assert_array_equal(narrow, wide & cone)
    assert (wide & ~narrow).any() and (cone & ~wide).any()  # both the cone and the occlusion cut pairs here


def test_reference_classifies_hand_made_segments():
    """Single triangle z = 0 with vertices (0,0), (1,0), (0,1): through the inside, through a
    vertex (grazing), beside it, stopping short, starting on it."""
    tri = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]], float)
    o = np.array([[0.2, 0.2, -1], [0, 0, -1], [1, 1, -1], [0.2, 0.2, -1], [0.2, 0.2, 1e-7]])
    s = np.array([[0.2, 0.2, 1], [0, 0, 1], [1, 1, 1], [0.2, 0.2, -0.1], [0.2, 0.2, 1]])
    occ, amb = segment_occlusion_reference(tri, o, s, tol=1e-5)
    np.testing.assert_array_equal(occ, [True, False, False, False, False])
    np.testing.assert_array_equal(amb, [False, True, False, False, True])


def test_triangle_engine_agrees_with_embree(small_docking):
    assert set(RAY_ENGINES) == {"embree", "triangle"}
    rng = np.random.default_rng(5)
    pts, fi = trimesh.sample.sample_surface_even(small_docking, 60, radius=0.3, seed=rng)
    R, t = _poses_in_front(rng, 3, 4.0, 8.0)
    a = visible_sensors(small_docking, pts, small_docking.face_normals[fi], R, t, engine="embree")
    b = visible_sensors(small_docking, pts, small_docking.face_normals[fi], R, t, engine="triangle")
    np.testing.assert_array_equal(a, b)


def test_envelope_visibility_uses_each_station_frame(small_docking, rng):
    """Reference: poses moved into each station's frame by hand (R_s = Rst^T R, t_s = Rst^T (t - tst)).
    Physical check: a station on the far side sees the sensors the near one cannot (opposite faces)."""
    mesh = trimesh.creation.box((0.2, 0.2, 0.2))
    P = np.array([[0, 0, 0.1], [0, 0, -0.1]])
    N = np.array([[0, 0, 1.0], [0, 0, -1.0]])
    A = Station("A")
    B = Station("B", rotation=rotvec_to_matrix(np.array([0.0, np.pi, 0.0])), translation=np.array([0.0, 0.0, 4.0]))
    Rw = np.repeat(rotvec_to_matrix(np.array([np.pi, 0.0, 0.0]))[None], 2, 0)  # body +z towards A
    tw = np.array([[0.0, 0.0, 2.0], [0.3, -0.2, 2.2]])
    v = envelope_visibility(mesh, P, N, Rw, tw, [A, B])
    assert v.shape == (2, 2, 2)
    np.testing.assert_array_equal(v[:, 0], [[True, False], [True, False]])
    np.testing.assert_array_equal(v[:, 1], [[False, True], [False, True]])
    Rr, tr = random_rotations(20, rng), rng.uniform(-0.5, 0.5, (20, 3)) + [0, 0, 2]
    v = envelope_visibility(mesh, P, N, Rr, tr, [A, B])
    Rb = np.einsum("ji,pjk->pik", B.rotation, Rr)
    tb = (tr - B.translation) @ B.rotation
    np.testing.assert_array_equal(v[:, 1], visible_sensors(mesh, P, N, Rb, tb))


def test_single_pose_and_bad_shapes():
    mesh = trimesh.creation.box((0.2, 0.2, 0.2))
    P, N = np.array([[0, 0, 0.1]]), np.array([[0, 0, 1.0]])
    R = rotvec_to_matrix(np.array([np.pi, 0.0, 0.0]))
    assert visible_sensors(mesh, P, N, R, np.array([0, 0, 2.0])).shape == (1,)
    with pytest.raises(ValueError) as e:
        visible_sensors(mesh, P, np.zeros((2, 3)), R, np.array([0, 0, 2.0]))
    assert str(e.value) == "normals: expected shape (1, 3), got (2, 3)"
    with pytest.raises(ValueError) as e:
        visible_sensors(mesh, P, N, np.stack([R, R]), np.zeros((3, 3)))
    assert str(e.value) == "rotation and translation: expected the same number of poses, got 2 and 3"
    with pytest.raises(ValueError) as e:
        visible_sensors(mesh, P, N, R, np.array([0, 0, 2.0]), engine="optix")
    assert str(e.value) == "ray engine: expected one of ['embree', 'triangle'], got 'optix'"


def test_cli_visibility_report_matches_direct_computation(tmp_path):
    """The command's per-sensor fractions and lit counts equal envelope_visibility on the same inputs."""
    import json
    from pathlib import Path

    from click.testing import CliRunner

    from layoutkit.cli import main
    from layoutkit.envelope import load_envelope
    from layoutkit.layout import load_layout
    from layoutkit.mesh import load_mesh

    models = Path(__file__).resolve().parent.parent / "models"
    args = [str(models / "chen_target.stl"), "--layout", str(models / "chen_target.layout.json"),
            "--envelope", str(models / "chen_envelope.toml")]
    out = tmp_path / "v.json"
    r = CliRunner().invoke(main, ["visibility", *args, "--json-out", str(out)])
    assert r.exit_code == 0, r.output
    rep = json.loads(out.read_text())
    env, lay = load_envelope(models / "chen_envelope.toml"), load_layout(models / "chen_target.layout.json")
    R, t = env.poses()
    v = envelope_visibility(load_mesh(models / "chen_target.stl"), lay.positions, lay.normals, R, t, env.stations)
    np.testing.assert_allclose([s["A"] for s in rep["sensor_lit_fraction"]], v[:, 0].mean(0))
    assert rep["lit_count_min"] == v[:, 0].sum(-1).min()
    assert rep["poses_below_min_lit"] == int((v[:, 0].sum(-1) < 4).sum())
    assert "poses with < 4 lit" in r.output
    r = CliRunner().invoke(main, ["visibility", *args[:3], "--envelope", str(tmp_path / "none.toml")])
    assert r.exit_code == 2 and f"error: {tmp_path / 'none.toml'}: no such envelope file" in r.output
