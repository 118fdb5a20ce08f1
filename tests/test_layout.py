"""Layout JSON: round trip, units, extra keys kept, clear messages for bad files."""
import json

import numpy as np
import pytest

from layoutkit.layout import load_layout, save_layout
from layoutkit.shapes import chen_target


def test_round_trip_keeps_extra_keys(tmp_path):
    _, lay = chen_target()
    d = lay.to_dict()
    d["objective"] = {"name": "worst-adop", "value": 1.5}
    d["sensors"][0]["part"] = "top"
    p = tmp_path / "l.json"
    p.write_text(json.dumps(d))
    back = load_layout(p)
    np.testing.assert_allclose(back.positions, lay.positions)
    assert back.metadata["objective"]["value"] == 1.5
    assert back.extra[0] == {"part": "top"}
    save_layout(back, tmp_path / "m.json")
    assert json.loads((tmp_path / "m.json").read_text())["sensors"][0]["part"] == "top"


def test_units_are_converted_to_metres(tmp_path):
    p = tmp_path / "mm.json"
    p.write_text(json.dumps({"units": "mm", "sensors": [{"id": "a", "position": [10, 20, 30], "normal": [0, 0, 2]}]}))
    lay = load_layout(p)
    np.testing.assert_allclose(lay.positions, [[0.01, 0.02, 0.03]])
    np.testing.assert_allclose(lay.normals, [[0, 0, 1]])


@pytest.mark.parametrize("content, message", [
    ("{", "not valid JSON"),
    ('{"units": "furlong", "sensors": []}', "layout units: expected one of \\['cm', 'in', 'm', 'mm'\\], got 'furlong'"),
    ('{"units": "m", "sensors": []}', "'sensors' must be a non-empty list"),
    ('{"sensors": [{"id": "a", "position": [0, 0], "normal": [0, 0, 1]}]}',
     r"layout sensor 0 \(id 'a'\): 'position': expected 3 numbers \[x, y, z\], got 2: \[0, 0\]"),
    ('{"sensors": [{"id": "a", "position": [0, 0, "x"], "normal": [0, 0, 1]}]}',
     r"layout sensor 0 \(id 'a'\): 'position': expected 3 numbers"),
    ('{"sensors": [{"id": "a", "position": [0, 0, NaN], "normal": [0, 0, 1]}]}', "'position': NaN or infinite"),
    ('{"sensors": [{"id": "a", "normal": [0, 0, 1]}]}', "layout sensor 0 \\(id 'a'\\): needs numeric 'position'"),
    ('{"sensors": [{"id": "a", "position": [0, 0, 0], "normal": [0, 0, 1]}, {"id": "a", "position": [1, 0, 0], "normal": [0, 0, 1]}]}', "ids must be unique"),
])
def test_bad_files_give_clear_messages(tmp_path, content, message):
    p = tmp_path / "bad.json"
    p.write_text(content)
    with pytest.raises(ValueError, match=message):
        load_layout(p)


def test_chen_target_reconstruction_properties():
    """12 sensors on the surface of a 12.5 × 12.5 × 6.25 cm convex polyhedron, normals = facet normals."""
    import trimesh

    mesh, lay = chen_target()
    np.testing.assert_allclose(mesh.extents, [0.125, 0.125, 0.0625])
    assert mesh.is_convex and mesh.is_watertight and lay.n == 12
    _, dist, tri = trimesh.proximity.closest_point(mesh, lay.positions)
    assert np.abs(dist).max() < 1e-12
    np.testing.assert_allclose(np.einsum("ij,ij->i", mesh.face_normals[tri], lay.normals), 1.0, atol=1e-12)


def test_binary_file_as_layout_names_the_file(tmp_path):
    p = tmp_path / "mesh.stl"
    p.write_bytes(b"\x80\x81\x00binary")
    with pytest.raises(ValueError, match=r"mesh.stl: not valid JSON \(a binary file, not text\)"):
        load_layout(p)
