"""Mesh loading: every format round-trips the geometry (independent reference: the builder's own
arrays), units scale exactly, bad files fail with the exact message, suspicious ones warn."""
import json
import warnings

import numpy as np
import pytest
import trimesh

from layoutkit.mesh import MeshWarning, describe_mesh, load_mesh, mesh_hash, save_mesh
from layoutkit.shapes import cubesat_3u, zhai_target


@pytest.mark.parametrize("fmt", ["stl", "obj", "ply", "off", "glb", "gltf"])
def test_every_format_round_trips_bounds_area_and_volume(tmp_path, fmt):
    """Reference: the in-memory builder mesh (area, volume, bounds are format independent)."""
    mesh = cubesat_3u()
    p = tmp_path / f"c.{fmt}"
    save_mesh(mesh, p)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a clean closed model must load without any warning
        back = load_mesh(p)
    np.testing.assert_allclose(back.bounds, mesh.bounds, atol=1e-7)
    assert back.area == pytest.approx(mesh.area, rel=1e-6)
    assert back.volume == pytest.approx(mesh.volume, rel=1e-6)
    assert back.is_watertight


def test_glb_keeps_part_names_and_their_faces(tmp_path):
    """Each named part comes back with the same area as the builder's part (face groups survive)."""
    mesh = zhai_target()
    save_mesh(mesh, tmp_path / "z.glb")
    back = load_mesh(tmp_path / "z.glb")
    assert set(back.metadata["parts"]) == {"bus", "wing+y", "wing-y"}
    for name, idx in mesh.metadata["parts"].items():
        assert back.area_faces[back.metadata["parts"][name]].sum() == pytest.approx(mesh.area_faces[idx].sum())


@pytest.mark.parametrize("units,scale", [("mm", 1e-3), ("cm", 1e-2), ("m", 1.0), ("in", 0.0254)])
def test_units_scale_vertices_exactly(tmp_path, units, scale):
    box = trimesh.creation.box((100.0, 50.0, 20.0))  # a 'spacecraft' of 100 x 50 x 20 file units
    box.export(tmp_path / "b.stl")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", MeshWarning)
        m = load_mesh(tmp_path / "b.stl", units=units)
    np.testing.assert_allclose(m.extents, np.array([100.0, 50.0, 20.0]) * scale, rtol=1e-6)


def test_millimetre_model_read_as_metres_warns_exactly(tmp_path):
    box = trimesh.creation.box((340.0, 100.0, 100.0))  # a 3U CubeSat drawn in mm
    p = tmp_path / "cubesat_mm.stl"
    box.export(p)
    with pytest.warns(MeshWarning) as rec:
        load_mesh(p)
    assert str(rec[0].message) == (f"{p}: largest extent is 340 m with units='m'; "
                                   "if the file is in millimetres pass units='mm'")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_mesh(p, units="mm").extents.max() == pytest.approx(0.34)


def test_metre_model_read_as_millimetres_warns(tmp_path):
    box = trimesh.creation.box((0.34, 0.1, 0.1))
    p = tmp_path / "c.stl"
    box.export(p)
    with pytest.warns(MeshWarning, match=r"largest extent is 0\.34 mm with units='mm'; if the file is in metres pass units='m'"):
        load_mesh(p, units="mm")


def test_empty_file_message(tmp_path):
    p = tmp_path / "empty.stl"
    p.write_bytes(b"")
    with pytest.raises(ValueError) as e:
        load_mesh(p)
    assert str(e.value) == f"{p}: empty file"


@pytest.mark.parametrize("fmt,count", [("stl", 12), ("obj", 3), ("ply", 3)])
def test_nan_vertices_message(tmp_path, fmt, count):
    """One NaN vertex: STL repeats it in each of its 4 faces (x 3 coords), indexed formats once."""
    box = trimesh.creation.box()
    box.vertices[0] = np.nan
    p = tmp_path / f"nan.{fmt}"
    box.export(p)
    with pytest.raises(ValueError) as e:
        load_mesh(p)
    assert str(e.value) == f"{p}: {count} non-finite vertex coordinate(s) (NaN or inf)"


def test_unknown_format_message(tmp_path):
    p = tmp_path / "model.step"
    p.write_text("ISO-10303-21;")
    with pytest.raises(ValueError) as e:
        load_mesh(p)
    assert str(e.value) == (f"{p}: unknown mesh format '.step'; supported: .stl, .obj, .ply, .off, .glb, .gltf")


def test_missing_file_and_bad_units_messages(tmp_path):
    with pytest.raises(ValueError) as e:
        load_mesh(tmp_path / "nope.stl")
    assert str(e.value) == f"{tmp_path / 'nope.stl'}: no such mesh file"
    with pytest.raises(ValueError) as e:
        load_mesh(tmp_path / "nope.stl", units="ft")
    assert str(e.value) == "units: expected one of ['cm', 'in', 'm', 'mm'], got 'ft'"


def test_point_cloud_and_zero_area_messages(tmp_path):
    p = tmp_path / "pts.ply"
    trimesh.PointCloud(np.random.default_rng(0).normal(size=(10, 3))).export(p)
    with pytest.raises(ValueError) as e:
        load_mesh(p)
    assert str(e.value) == f"{p}: no faces (empty mesh or point cloud)"
    flat = tmp_path / "flat.obj"
    flat.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")  # collinear: zero area
    with pytest.raises(ValueError) as e:
        load_mesh(flat)
    assert str(e.value) == f"{flat}: degenerate mesh (total surface area is zero)"


def test_garbage_content_names_the_format(tmp_path):
    p = tmp_path / "bad.glb"
    p.write_bytes(b"this is not a glb file at all")
    with pytest.raises(ValueError, match=rf"^{p}: could not read as GLB \("):
        load_mesh(p)


def test_open_mesh_warns_but_loads(tmp_path):
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    box.update_faces(np.arange(len(box.faces)) != 0)  # remove one triangle -> 3 open edges
    p = tmp_path / "open.stl"
    box.export(p)
    with pytest.warns(MeshWarning) as rec:
        m = load_mesh(p)
    assert str(rec[0].message) == (f"{p}: mesh is not watertight (3 open edge(s), 0 edge(s) shared by more than "
                                   "two faces); outward normals and occlusion treat it as a bare surface")
    assert len(m.faces) == 11


def test_degenerate_faces_are_dropped_with_warning(tmp_path):
    p = tmp_path / "d.obj"
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    lines = [f"v {x} {y} {z}" for x, y, z in box.vertices] + [f"f {a+1} {b+1} {c+1}" for a, b, c in box.faces]
    lines.append("f 1 1 2")  # a sliver with zero area
    p.write_text("\n".join(lines) + "\n")
    with pytest.warns(MeshWarning, match="dropped 1 zero-area face"):
        m = load_mesh(p)
    assert len(m.faces) == 12 and m.is_watertight


def test_mesh_hash_identifies_geometry(tmp_path):
    a, b = zhai_target(), zhai_target()
    assert mesh_hash(a) == mesh_hash(b)
    b.vertices[0, 0] += 1e-9
    assert mesh_hash(a) != mesh_hash(b)
    d = describe_mesh(a)
    json.dumps(d)  # JSON-able for mesh-info --json
    assert d["faces"] == 36 and d["watertight"] and d["parts"] == {"bus": 12, "wing+y": 12, "wing-y": 12}


def test_cli_mesh_info(tmp_path):
    """mesh-info reports the size the file really has, and bad files exit 2 with the loader's message."""
    from click.testing import CliRunner

    from layoutkit.cli import main

    box = trimesh.creation.box((340.0, 100.0, 100.0))
    p = tmp_path / "cubesat_mm.stl"
    box.export(p)
    r = CliRunner().invoke(main, ["mesh-info", str(p), "--units", "mm", "--json"])
    assert r.exit_code == 0, r.output
    info = json.loads(r.stdout)
    np.testing.assert_allclose(sorted(info["extents_m"]), [0.1, 0.1, 0.34])
    assert info["faces"] == 12 and info["watertight"] and info["warnings"] == []
    r = CliRunner().invoke(main, ["mesh-info", str(p)])
    assert r.exit_code == 0 and "largest extent is 340 m with units='m'" in r.output
    empty = tmp_path / "e.stl"
    empty.write_bytes(b"")
    r = CliRunner().invoke(main, ["mesh-info", str(empty)])
    assert r.exit_code == 2 and r.output.strip() == f"error: {empty}: empty file"
