"""Shipped shapes: sizes and volumes against closed forms, closed manifold parts, the committed
model files are what the builders produce, and the docking target really self-occludes."""
from pathlib import Path

import numpy as np
import pytest

from layoutkit.geometry import rotvec_to_matrix
from layoutkit.layout import load_layout
from layoutkit.mesh import load_mesh, mesh_hash
from layoutkit.shapes import chen_target, cubesat_3u, docking_target, zhai_target
from layoutkit.visibility import visible_sensors

MODELS = Path(__file__).resolve().parent.parent / "models"


def _part(mesh, name):
    return mesh.submesh([mesh.metadata["parts"][name]], append=True)


def test_zhai_target_dimensions():
    """Zhai 2014: 3 m cube, two 10 m x 3 m wings on +-y; volume 27 + 2 x 10 x 3 x 0.05."""
    m = zhai_target()
    np.testing.assert_allclose(m.bounds, [[-1.5, -11.5, -1.5], [1.5, 11.5, 1.5]])
    assert m.volume == pytest.approx(27.0 + 2 * 10 * 3 * 0.05)
    for w in ("wing+y", "wing-y"):
        np.testing.assert_allclose(_part(m, w).extents, [0.05, 10.0, 3.0])
    np.testing.assert_allclose(_part(m, "bus").bounds, [[-1.5] * 3, [1.5] * 3])  # body frame at the cube centre


def test_cubesat_dimensions():
    m = cubesat_3u()
    np.testing.assert_allclose(_part(m, "bus").extents, [0.1, 0.1, 0.34])
    assert m.volume == pytest.approx(0.1 * 0.1 * 0.34 + 4 * 0.3 * 0.1 * 0.002)
    assert m.is_watertight and all(_part(m, k).is_watertight for k in m.metadata["parts"])


def test_docking_target_size_and_parts():
    m = docking_target()
    assert len(m.faces) >= 10_000 and m.is_watertight and m.is_winding_consistent
    parts = {k: _part(m, k) for k in m.metadata["parts"]}
    assert set(parts) == {"bus", "docking_port", "dish", "wing+y", "wing-y", "boom"}
    assert all(p.is_watertight and p.volume > 0 for p in parts.values())
    assert parts["bus"].volume == pytest.approx(1.2 * 1.2 * 1.6)
    # a paraboloid shell of constant vertical thickness th has volume pi R^2 th (+ the mast cylinder);
    # the 96-gon revolution is short by the polygon factor sin(2 pi/96) / (2 pi/96)
    poly = np.sin(2 * np.pi / 96) / (2 * np.pi / 96)
    mast = np.pi * 0.03 ** 2 * 0.3 * np.sin(2 * np.pi / 32) / (2 * np.pi / 32)
    assert parts["dish"].volume == pytest.approx(np.pi * 0.5 ** 2 * 0.02 * poly + mast, rel=2e-3)


def test_docking_dish_shadows_the_bus_face():
    """A station 10 m out on +x sees a sensor at the +x face centre only if the dish (radius 0.5 m,
    centred on the x axis) is not in the way: centre occluded, a corner-ish point outside the dish rim visible."""
    m = docking_target()
    P = np.array([[0.6, 0.0, 0.0], [0.6, 0.5, 0.7], [0.6, 0.0, -0.3]])
    N = np.tile([1.0, 0.0, 0.0], (3, 1))
    R = rotvec_to_matrix(np.array([0.0, np.pi / 2, 0.0]))  # body +x -> station -z (towards the station)
    np.testing.assert_allclose(R @ [1.0, 0, 0], [0, 0, -1], atol=1e-12)
    t = np.array([0.0, 0.0, 10.0])
    vis = visible_sensors(m, P, N, R, t)
    np.testing.assert_array_equal(vis, [False, True, False])
    np.testing.assert_array_equal(visible_sensors(m, P, N, R, t, occlusion=False), [True, True, True])


@pytest.mark.parametrize("fname,builder", [("zhai_target.glb", zhai_target), ("cubesat_3u.glb", cubesat_3u),
                                           ("docking_target.stl", docking_target)])
def test_committed_models_match_builders(fname, builder):
    """models/ is built by models/build_models.py; a stale file would fail here."""
    f = load_mesh(MODELS / fname)
    b = builder()
    np.testing.assert_allclose(f.bounds, b.bounds, atol=1e-6)
    assert len(f.faces) == len(b.faces) and f.area == pytest.approx(b.area, rel=1e-6)


def test_committed_chen_layout_matches_mesh_file():
    mesh, lay = chen_target()
    f = load_layout(MODELS / "chen_target.layout.json")
    np.testing.assert_allclose(f.positions, lay.positions)
    assert f.metadata["mesh_sha256"] == mesh_hash(load_mesh(MODELS / "chen_target.stl"))


@pytest.mark.slow
def test_committed_camera_frames_match_their_builder(tmp_path):
    """models/camera_frames/ (the README tour's `camera-attitude` input) is what build_models.py's
    builder renders: the first frame pixel for pixel (0.0 DN mean difference here) and its truth row.
    Regression: the builder referenced helpers renamed in the house rework and build_models.py imported
    it from a module that no longer held it — both failures were swallowed by the builder's
    no-off-screen-rendering guard, so models/ could not be rebuilt."""
    import importlib
    import re

    import cv2

    src = (MODELS / "build_models.py").read_text()  # the builder the script imports must exist there
    mod = re.search(r"from (\S+) import write_example_frames", src).group(1)
    write_example_frames = getattr(importlib.import_module(mod), "write_example_frames")

    paths = write_example_frames(tmp_path, times_s=(0.0,))
    new = cv2.imread(str(paths[0]), cv2.IMREAD_UNCHANGED).astype(float)
    old = cv2.imread(str(MODELS / "camera_frames" / "frame_000.png"), cv2.IMREAD_UNCHANGED).astype(float)
    assert new.shape == old.shape and np.abs(new - old).mean() < 0.5
    assert (tmp_path / "truth.csv").read_text().splitlines()[1] == \
        (MODELS / "camera_frames" / "truth.csv").read_text().splitlines()[1]
