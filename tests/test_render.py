"""Off-screen renders (layoutkit.render, layoutkit render CLI): sizes, content, pinhole geometry, errors."""
import json
from pathlib import Path

import numpy as np
import pytest

from layoutkit import render
from layoutkit.shapes import chen_target

MODELS = Path(__file__).resolve().parents[1] / "models"


def _png(path):
    from PIL import Image

    return np.asarray(Image.open(path).convert("RGB"))


def _not_blank(img, min_fraction=0.02):
    """A picture with content: enough non-background pixels and more than a couple of colours."""
    non_white = np.any(img < 245, axis=-1).mean()
    return non_white > min_fraction and len(np.unique(img.reshape(-1, 3)[::97], axis=0)) > 20


def test_layout_views_write_pngs_of_the_requested_size_with_content(tmp_path):
    """Each standard view is a W×H PNG that is not blank, and views differ from each other."""
    mesh, lay = chen_target()
    lit = np.linspace(0.0, 1.0, lay.n)
    cand = mesh.sample(50, return_index=False)
    paths = render.render_layout_views(mesh, lay.positions, lay.normals, lit, candidates=cand,
                                       views=("iso", "top"), size=(320, 240), out_dir=tmp_path, ids=lay.ids)
    assert [p.name for p in paths] == ["layout_iso.png", "layout_top.png"]
    imgs = [_png(p) for p in paths]
    for im in imgs:
        assert im.shape == (240, 320, 3)
        assert _not_blank(im)
    assert np.mean(np.any(imgs[0] != imgs[1], axis=-1)) > 0.05


def test_lit_fraction_colours_follow_the_colour_map(tmp_path):
    """The sensor spheres take viridis colours: a fully lit sensor is yellow-ish, a never-lit one dark
    purple (reference: matplotlib's viridis at 0 and 1)."""
    from matplotlib import colormaps

    mesh, lay = chen_target()
    top = slice(0, 4)  # the four top-face sensors, seen from above
    lit = np.zeros(lay.n)
    lit[0] = 1.0
    p = render.render_layout_views(mesh, lay.positions[top], lay.normals[top], lit[top], views=("top",),
                                   size=(400, 300), out_dir=tmp_path, arrows=False)[0]
    img = _png(p).astype(float)
    yellow = np.asarray(colormaps["viridis"](1.0)[:3]) * 255
    purple = np.asarray(colormaps["viridis"](0.0)[:3]) * 255
    d_y = np.linalg.norm(img - yellow, axis=-1)
    d_p = np.linalg.norm(img - purple, axis=-1)
    assert np.sum(d_y < 60) > 20 and np.sum(d_p < 60) > 20


@pytest.mark.parametrize("crop", [False, True])
def test_station_view_matches_the_pinhole_model(tmp_path, crop):
    """Pinhole match (design §8): a lit sensor floating in front of the target is drawn where
    ``u = cx + f x/z, v = cy + f y/z`` predicts (f from the vertical view angle; principal point the
    window centre, or shifted for the framing crop); centroid error < 0.3 px (measured < 0.1 px)."""
    from layoutkit.geometry import rotvec_to_matrix

    mesh, lay = chen_target()
    R = rotvec_to_matrix([np.pi + 0.3, 0.2, 0.1])        # top face towards the station
    t = np.array([0.15, -0.08, 1.6])
    s_body = -R.T @ t                                     # station in the body frame
    P = np.array([[0.02, 0.01, 0.06], [-0.03, -0.02, 0.055]])  # above the top face, nothing in front
    to = s_body - P
    N = to / np.linalg.norm(to, axis=1, keepdims=True)
    size = (640, 480)
    fov = None if crop else 30.0
    out = render.render_station_view(mesh, P, N, R, t, np.array([True, False]), fov_deg=fov, size=size,
                                     out=tmp_path / "sv.png", anti_aliasing=False)
    img = _png(out).astype(int)
    assert img.shape == (480, 640, 3)
    view_deg, pp = render.station_view_camera(mesh, R, t, size, fov)
    uv, z = render.station_view_pixels(P, R, t, fov_deg=view_deg, size=size, principal_point=pp)
    assert np.all(z > 0)
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    for k, mask in enumerate([(g > r + 40) & (g > b + 40), (r > g + 60) & (r > b + 60)]):
        rows, cols = np.nonzero(mask)
        assert rows.size > 10
        # pixel (col i, row j) has its centre at (i + 0.5, j + 0.5)
        centroid = np.array([cols.mean() + 0.5, rows.mean() + 0.5])
        assert np.linalg.norm(centroid - uv[k]) < 0.3, (k, centroid, uv[k])


def test_station_view_three_colours(tmp_path):
    """Lit sensors are drawn green, shadowed ones orange, other unlit ones red (colour classes counted
    in the image; the top-face sensors all face the station at this pose)."""
    from layoutkit.geometry import rotvec_to_matrix

    mesh, lay = chen_target()
    R = rotvec_to_matrix([np.pi, 0.0, 0.0])
    t = np.array([0.0, 0.0, 1.5])
    top = slice(0, 4)
    lit = np.array([True, True, False, False])
    shadowed = np.array([False, False, True, False])
    out = render.render_station_view(mesh, lay.positions[top], lay.normals[top], R, t, lit, fov_deg=None,
                                     size=(400, 300), out=tmp_path / "sv.png", shadowed=shadowed)
    img = _png(out).astype(int)
    colours = {"green": render.LIT_COLOR, "orange": render.SHADOW_COLOR, "red": render.UNLIT_COLOR}
    counts = {}
    for name, hexc in colours.items():
        ref = np.array([int(hexc[i:i + 2], 16) for i in (1, 3, 5)])
        counts[name] = int(np.sum(np.linalg.norm(img - ref, axis=-1) < 50))
    # two green spheres, one orange, one red (areas roughly proportional)
    assert counts["orange"] > 20 and counts["red"] > 20
    assert 1.3 < counts["green"] / counts["orange"] < 3.0
    with pytest.raises(ValueError, match=r"shadowed: expected shape \(4,\), got \(3,\)"):
        render.render_station_view(mesh, lay.positions[top], lay.normals[top], R, t, lit, out=tmp_path / "x.png",
                                   shadowed=np.zeros(3, bool))


def test_tracking_map_pictures(tmp_path):
    """The Mollweide and sphere maps are W×H PNGs with content."""
    from layoutkit.quality import tracking_quality_map

    mesh, lay = chen_target()
    q = tracking_quality_map(mesh, lay.positions, lay.normals, distance=2.0, grid=(12, 24), roll_samples=2)
    a = render.render_tracking_map(q, out=tmp_path / "m.png", size=(800, 600), sigma_theta=4.014e-5)
    b = render.render_tracking_map(q, out=tmp_path / "s.png", kind="sphere", size=(600, 300))
    assert _png(a).shape == (600, 800, 3) and _not_blank(_png(a), 0.2)
    assert _png(b).shape == (300, 600, 3) and _not_blank(_png(b))
    with pytest.raises(ValueError, match="kind: expected 'mollweide' or 'sphere', got 'globe'"):
        render.render_tracking_map(q, out=tmp_path / "x.png", kind="globe")


def test_render_bad_input_messages(tmp_path):
    mesh, lay = chen_target()
    with pytest.raises(ValueError) as e:
        render.render_layout_views(mesh, lay.positions, lay.normals, views=("iso", "diagonal"), out_dir=tmp_path)
    assert str(e.value) == ("views: unknown ['diagonal']; choose from "
                            "['back', 'bottom', 'front', 'iso', 'iso_back', 'side', 'top']")
    with pytest.raises(ValueError) as e:
        render.render_layout_views(mesh, lay.positions, lay.normals, np.full(lay.n, 1.5), out_dir=tmp_path)
    assert str(e.value) == "lit_fraction: expected values in [0, 1]"
    with pytest.raises(ValueError) as e:
        render.render_layout_views(mesh, lay.positions, lay.normals, size=(0, 10), out_dir=tmp_path)
    assert str(e.value) == "size: expected 16..8192 pixels per side, got 0 x 10"
    with pytest.raises(ValueError) as e:
        render.render_station_view(mesh, lay.positions, lay.normals, np.eye(3), [0, 0, 1], np.ones(3, bool),
                                   out=tmp_path / "x.png")
    assert str(e.value) == "lit: expected shape (12,), got (3,)"


def test_backend_choice_and_clear_error_without_opengl(monkeypatch):
    """Back-end probe: a user setting wins; without display the EGL probe picks EGL, then OSMesa; with
    neither, RenderingUnavailable names the packages (instead of VTK's segfault)."""
    probe = render.offscreen_backend.__wrapped__
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.setenv("VTK_DEFAULT_OPENGL_WINDOW", "vtkOSOpenGLRenderWindow")
    assert probe() == "vtkOSOpenGLRenderWindow"
    monkeypatch.delenv("VTK_DEFAULT_OPENGL_WINDOW")
    monkeypatch.setattr(render, "_egl_device_ok", lambda: False)
    monkeypatch.setattr(render.ctypes.util, "find_library", lambda name: "libOSMesa.so.8" if name == "OSMesa" else None)
    assert probe() == "vtkOSOpenGLRenderWindow"
    monkeypatch.delenv("VTK_DEFAULT_OPENGL_WINDOW")
    monkeypatch.setattr(render.ctypes.util, "find_library", lambda name: None)
    with pytest.raises(render.RenderingUnavailable) as e:
        probe()
    assert "apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri" in str(e.value)
    assert "libosmesa6" in str(e.value)


def test_lit_fraction_is_the_any_station_mean_over_poses():
    """Reference by explicit loops over poses and stations."""
    from layoutkit.workflows.render import lit_fraction

    rng = np.random.default_rng(3)
    v = rng.random((50, 2, 7)) < 0.3
    ref = [np.mean([v[p, 0, i] or v[p, 1, i] for p in range(50)]) for i in range(7)]
    np.testing.assert_allclose(lit_fraction(v), ref)


def test_cli_render_writes_every_picture(tmp_path):
    """``layoutkit render`` with layout, envelope, quality map and station view writes the PNGs it lists."""
    from click.testing import CliRunner

    from layoutkit.cli import main

    res = CliRunner().invoke(main, [
        "render", str(MODELS / "chen_target.stl"), "--layout", str(MODELS / "chen_target.layout.json"),
        "--envelope", str(MODELS / "chen_envelope.toml"), "--out-dir", str(tmp_path), "--size", "400x300",
        "--views", "iso", "--quality-map", "--grid-deg", "20", "--roll-samples", "2", "--rho", "0.8717",
        "--station-view-pose", "envelope:3", "--json"])
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)
    names = [Path(p).name for p in out["paths"]]
    assert names == ["chen_target_iso.png", "chen_target_quality_map.png", "chen_target_station_view.png"]
    for p in out["paths"]:
        assert _png(p).shape == (300, 400, 3)
    assert set(out["lit_fraction"]) == set(chen_target()[1].ids)
    assert 0 < out["quality_map"]["tracked_solid_angle_fraction"] < 1


@pytest.mark.parametrize("args, msg", [
    (["--size", "big"], "error: expected WIDTHxHEIGHT in pixels, e.g. 1600x1200, got 'big'"),
    (["--views", "iso,diagonal"],
     "error: unknown view(s) ['diagonal']; choose from iso, iso_back, front, back, side, top, bottom"),
    (["--station-view-pose", "1,2"],
     "error: station view pose: expected 'rx,ry,rz,tx,ty,tz' (rotation vector deg, translation m) "
     "or 'envelope:K', got '1,2'"),
    (["--quality-map"], "error: --quality-map needs a layout (--layout)"),
])
def test_cli_render_bad_input(tmp_path, args, msg):
    from click.testing import CliRunner

    from layoutkit.cli import main

    res = CliRunner().invoke(main, ["render", str(MODELS / "chen_target.stl"), "--out-dir", str(tmp_path),
                                    "--views", "iso", "--size", "64x48"] + args)
    assert res.exit_code == 2
    assert res.output.strip().splitlines()[-1] == msg


def test_scale_bar_is_as_long_as_its_label_says(tmp_path):
    """Every 3-D picture carries a scale bar of a round length. Reference: the pinhole model of
    design §8 (:func:`render.station_view_pixels`, itself checked against the picture above) maps the
    bar's end points to pixels; the blue bar found in the rendered image spans that many columns
    (within 1.5 px; an open tube has no caps), and its length is the 1-2-5 value its label prints."""
    from layoutkit.geometry import rotvec_to_matrix

    assert [render.nice_length(x) for x in (0.035, 0.05, 0.0999, 7.0, 1.0)] == [0.02, 0.05, 0.05, 5.0, 1.0]
    assert render.length_text(0.02) == "20 mm" and render.length_text(2.0) == "2 m"
    mesh, lay = chen_target()
    R = rotvec_to_matrix([np.pi, 0.0, 0.0])  # the station looks at the top face, bar along the image rows
    t = np.array([0.0, 0.0, 0.6])
    size = (640, 480)
    out = render.render_station_view(mesh, lay.positions[:0], lay.normals[:0], R, t, np.zeros(0, bool), fov_deg=40.0,
                                     size=size, out=tmp_path / "sv.png", anti_aliasing=False)
    img = _png(out).astype(int)
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    mask = (b > r + 60) & (b > g + 40)
    assert mask.sum() > 50
    center = 0.5 * (np.asarray(mesh.bounds[0]) + np.asarray(mesh.bounds[1]))
    a, e, length = render.scale_bar_geometry(mesh.vertices, center, R[2], -R[1], render._scale(mesh), gap=0.035)
    assert length == render.nice_length(0.25 * render._scale(mesh))
    uv, _ = render.station_view_pixels(np.array([a, e]), R, t, fov_deg=40.0, size=size)
    row = mask[int(uv[:, 1].mean())]  # the image row through the bar's axis (the label sits beside it)
    mid = int(uv[:, 0].mean())
    assert row[mid]
    lo = mid - np.argmin(row[mid::-1]) + 1  # the contiguous blue run through the bar's middle
    hi = mid + np.argmin(row[mid:]) - 1
    assert abs((hi - lo + 1) - abs(uv[1, 0] - uv[0, 0])) < 1.5, (lo, hi, uv)  # measured 22 px vs 21.98
