"""Off-screen pictures of targets, layouts, station views and tracking-quality maps.

Why one module of ~640 lines: every picture (target, layout, station view, quality map) shares
the same scene builders, the camera convention below and the off-screen plumbing; the pictures
are small functions over them.

Everything renders without a display. pyvista/VTK and matplotlib are imported inside the
functions; the first call chooses an off-screen OpenGL back end (:func:`offscreen_backend`) by
setting ``VTK_DEFAULT_OPENGL_WINDOW`` before the first render window exists:

- a user-set ``VTK_DEFAULT_OPENGL_WINDOW`` is respected;
- with an X display (``DISPLAY`` set) VTK's default (X, falling back to EGL) is kept;
- otherwise EGL if an EGL device initialises (Debian: ``libegl1 libegl-mesa0 libgl1-mesa-dri``),
  else OSMesa if ``libOSMesa`` is found (``libosmesa6``), else :class:`RenderingUnavailable` with
  the packages to install. (VTK itself segfaults when the requested back end is missing, which
  is why the probe happens here.)

Frames: meshes, sensors and cameras are in the body frame (m). A station view is an exact
pinhole camera at the station origin looking along the station's +z (design §8): camera
position ``C = -R^T t``, focal point ``C + R[2]``, view-up ``-R[1]`` (image rows grow along +y),
``view_angle`` = the vertical field of view, principal point at the window centre, so a body
point ``p`` with ``q = R p + t`` lands at ``u = W/2 + f q_x/q_z``, ``v = H/2 + f q_y/q_z``
(pixels from the top-left corner) with ``f = (H/2) / tan(view_angle/2)``.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os
from pathlib import Path

import numpy as np

from ._validate import as_array, check_finite

__all__ = [
    "RenderingUnavailable",
    "VIEWS",
    "offscreen_backend",
    "render_layout_views",
    "render_station_view",
    "render_tracking_map",
    "station_view_camera",
    "station_view_pixels",
]

# Standard views: (direction from the scene centre to the camera, view-up), body frame.
VIEWS = {
    "iso": ((1.0, -1.0, 0.8), (0.0, 0.0, 1.0)),
    "iso_back": ((-1.0, 1.0, 0.8), (0.0, 0.0, 1.0)),
    "front": ((0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
    "back": ((0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
    "side": ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "top": ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0)),
    "bottom": ((0.0, 0.0, -1.0), (0.0, 1.0, 0.0)),
}

_ENV = "VTK_DEFAULT_OPENGL_WINDOW"
_EGL = "vtkEGLRenderWindow"
_OSMESA = "vtkOSOpenGLRenderWindow"
_INSTALL_HINT = ("install EGL (Debian/Ubuntu: apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri) "
                 "or OSMesa (apt-get install libosmesa6), or run with an X display")

MESH_COLOR = "#c9ced6"
LIT_COLOR = "#1fa33a"
UNLIT_COLOR = "#d62728"
SHADOW_COLOR = "#ff9f1c"
CANDIDATE_COLOR = "#6b6b6b"


class RenderingUnavailable(RuntimeError):
    """No off-screen OpenGL back end is available on this machine."""


def _egl_device_ok() -> bool:
    """True if libEGL loads and an EGL device display initialises (VTK's EGL path)."""
    from ctypes import CFUNCTYPE, POINTER, byref, c_char_p, c_int, c_uint, c_void_p

    try:
        egl = ctypes.CDLL("libEGL.so.1")
    except OSError:
        return False
    try:
        egl.eglGetProcAddress.restype = c_void_p
        egl.eglGetProcAddress.argtypes = [c_char_p]
        egl.eglInitialize.argtypes = [c_void_p, POINTER(c_int), POINTER(c_int)]
        egl.eglTerminate.argtypes = [c_void_p]
        q_addr = egl.eglGetProcAddress(b"eglQueryDevicesEXT")
        g_addr = egl.eglGetProcAddress(b"eglGetPlatformDisplayEXT")
        if not q_addr or not g_addr:
            return False
        query = CFUNCTYPE(c_uint, c_int, POINTER(c_void_p), POINTER(c_int))(q_addr)
        get_display = CFUNCTYPE(c_void_p, c_uint, c_void_p, POINTER(c_int))(g_addr)
        devices = (c_void_p * 16)()
        n = c_int(0)
        if not query(16, devices, byref(n)):
            return False
        for i in range(n.value):
            disp = get_display(0x313F, devices[i], None)  # EGL_PLATFORM_DEVICE_EXT
            major, minor = c_int(), c_int()
            if disp and egl.eglInitialize(disp, byref(major), byref(minor)):
                egl.eglTerminate(disp)
                return True
    except (AttributeError, OSError):
        return False
    return False


@functools.lru_cache(maxsize=1)
def offscreen_backend() -> str:
    """Choose the VTK off-screen back end for this process (once) and return its class name.

    Sets ``VTK_DEFAULT_OPENGL_WINDOW`` (only if unset and there is no X display) before the first
    render window is made. Raises :class:`RenderingUnavailable` naming the packages to install
    when neither EGL nor OSMesa is usable.
    """
    if os.environ.get(_ENV):
        return os.environ[_ENV]
    if os.environ.get("DISPLAY"):
        return "vtkXOpenGLRenderWindow"
    if _egl_device_ok():
        os.environ[_ENV] = _EGL
        return _EGL
    if ctypes.util.find_library("OSMesa"):
        os.environ[_ENV] = _OSMESA
        return _OSMESA
    raise RenderingUnavailable("off-screen rendering is unavailable: no display, no EGL device and no OSMesa; "
                               + _INSTALL_HINT)


def _plotter(size, *, anti_aliasing: bool = True, shape=(1, 1)):
    """An off-screen ``pyvista.Plotter`` of ``size = (width, height)`` pixels, white background."""
    w, h = _check_size(size)
    offscreen_backend()
    import pyvista as pv

    pl = pv.Plotter(off_screen=True, window_size=(w, h), shape=shape, border=False)
    pl.set_background("white")
    if anti_aliasing:
        pl.enable_anti_aliasing("msaa", multi_samples=8)
    else:
        pl.disable_anti_aliasing()
    # pyvista re-renders after every added actor / camera reset; build the scene silently and
    # render explicitly (``_shoot``) — a 1600 x 1200 software render costs ~0.1–0.4 s
    pl.suppress_rendering = True
    return pl


def _shoot(pl, path) -> Path:
    """Render the current scene and write it to ``path`` (PNG)."""
    import os

    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{path.suffix}")  # complete or not at all (disk full)
    pl.suppress_rendering = False
    pl.render()
    try:
        pl.screenshot(str(tmp))
        os.replace(tmp, path)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            exc.filename = str(path)
        raise
    finally:
        pl.suppress_rendering = True
    return path


def _check_size(size):
    try:
        w, h = (int(v) for v in size)
    except (TypeError, ValueError):
        raise ValueError(f"size: expected (width, height) in pixels, got {size!r}") from None
    if w < 16 or h < 16 or w > 8192 or h > 8192:
        raise ValueError(f"size: expected 16..8192 pixels per side, got {w} x {h}")
    return w, h


def _polydata(mesh):
    """trimesh.Trimesh → pyvista.PolyData (same vertices and triangles)."""
    import pyvista as pv

    return pv.PolyData.from_regular_faces(np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64))


def _scale(mesh) -> float:
    """Bounding-box diagonal of the mesh, m (the scene scale for glyph sizes)."""
    b = np.asarray(mesh.bounds, float)
    return float(np.linalg.norm(b[1] - b[0]))


def _sphere_glyphs(positions, normals, radius, lit_percent=None):
    """Spheres of ``radius`` (m) sitting on the surface at the sensors: centre ``p + 0.8 r n`` (so a
    sensor on one face of a thin panel does not poke through the other face); point array ``"lit"``
    copied from ``lit_percent`` if given. Returns pyvista PolyData."""
    import pyvista as pv

    cloud = pv.PolyData(np.asarray(positions, float))
    cloud["normals"] = np.asarray(normals, float)
    if lit_percent is not None:
        cloud["lit"] = np.asarray(lit_percent, float)  # glyphs copy the point data of their source point
    res = 24 if len(cloud.points) <= 200 else 12
    return cloud.glyph(geom=pv.Sphere(radius=1.0, center=(0.8, 0.0, 0.0), theta_resolution=res, phi_resolution=res),
                       orient="normals", scale=False, factor=radius)


def _sensor_glyphs(positions, normals, radius, arrow_length, lit_percent=None):
    """Sphere glyphs at the sensors (:func:`_sphere_glyphs`) and arrow glyphs along their normals."""
    import pyvista as pv

    cloud = pv.PolyData(np.asarray(positions, float))
    cloud["normals"] = np.asarray(normals, float)
    spheres = _sphere_glyphs(positions, normals, radius, lit_percent)
    arrows = cloud.glyph(geom=pv.Arrow(start=(0, 0, 0), direction=(1, 0, 0), tip_length=0.25,
                                       tip_radius=0.07, shaft_radius=0.025),
                         orient="normals", scale=False, factor=arrow_length)
    return spheres, arrows


#: colour of the axis arrows of tilted sensors
TILT_COLOR = "#d62728"


def tilt_glyphs(positions, axes, tilt_deg, surface_normals, arrow_length):
    """Arrow glyphs that show tilt: ``(plain, axis, normal)`` — along the axes of the untilted sensors, along
    the axes of the tilted ones (``tilt_deg > 0``) and along the surface normals at the tilted ones (None
    without ``surface_normals``). None if no sensor is tilted (``tilt_deg`` None or all 0)."""
    import pyvista as pv

    if tilt_deg is None:
        return None
    tl = np.asarray(tilt_deg, float)
    on = tl > 0
    if not on.any():
        return None
    P, A = np.asarray(positions, float), np.asarray(axes, float)

    def arrows(idx, dirs):
        if not np.any(idx):
            return None
        cloud = pv.PolyData(P[idx])
        cloud["normals"] = dirs[idx]
        return cloud.glyph(geom=pv.Arrow(start=(0, 0, 0), direction=(1, 0, 0), tip_length=0.25, tip_radius=0.07,
                                         shaft_radius=0.025), orient="normals", scale=False, factor=arrow_length)

    normal = None if surface_normals is None else arrows(on, np.asarray(surface_normals, float))
    return arrows(~on, A), arrows(on, A), normal


SCALE_BAR_COLOR = "#1f3a93"


def nice_length(x: float) -> float:
    """The largest 1-2-5 × 10^k length not above ``x`` (> 0), m: a scale bar's round length."""
    e = 10.0 ** np.floor(np.log10(x))
    m = x / e
    return float(e * (5.0 if m >= 5.0 else 2.0 if m >= 2.0 else 1.0))


def length_text(length_m: float) -> str:
    """``0.05`` → ``"50 mm"``, ``2.0`` → ``"2 m"`` (mm below 1 m)."""
    return f"{length_m * 1000:g} mm" if length_m < 1.0 else f"{length_m:g} m"


def scale_bar_geometry(vertices, center, view_direction, up, diag: float, gap: float = 0.08):
    """Where a scale bar goes in a picture looking along ``view_direction`` (body frame, from the
    camera towards the scene) with screen-up ``up``: a round length (:func:`nice_length` of a quarter of
    ``diag``, m) lying along the screen's horizontal in the plane through ``center`` perpendicular to
    the view (so its length in the picture is true at the depth of ``center``), just below the mesh
    ``vertices`` (n, 3) (``gap`` × ``diag`` below them). Returns ``(start (3,), end (3,), length m)``."""
    v = np.asarray(view_direction, float)
    v = v / np.linalg.norm(v)
    right = np.cross(v, np.asarray(up, float))
    right /= np.linalg.norm(right)
    up_s = np.cross(right, v)
    rel = np.asarray(vertices, float) - center
    below = float(np.min(rel @ up_s)) - gap * diag
    left = float(np.min(rel @ right))
    length = nice_length(0.25 * diag)
    start = center + below * up_s + left * right
    return start, start + length * right, length


def _add_scale_bar(pl, mesh, center, view_direction, up, diag: float, h: int, *, tight: bool = False) -> None:
    """Draw (or move: named actors) the scale bar of :func:`scale_bar_geometry` with its length
    written under it, or beside it when ``tight`` (a view framed closely around the mesh)."""
    import pyvista as pv

    a, b, length = scale_bar_geometry(mesh.vertices, center, view_direction, up, diag, gap=0.035 if tight else 0.08)
    pl.add_mesh(pv.Line(a, b).tube(radius=0.006 * diag), color=SCALE_BAR_COLOR, name="scale_bar",
                smooth_shading=True, ambient=0.6)
    right = (b - a) / length  # the screen's horizontal, as scale_bar_geometry laid the bar
    at = b + 0.03 * diag * right if tight else 0.5 * (a + b) - 0.05 * diag * np.cross(right, view_direction)
    pl.add_point_labels([at], [length_text(length)], font_size=max(10, h // 80), text_color=SCALE_BAR_COLOR,
                        shape_opacity=0.0, show_points=False, always_visible=True, name="scale_bar_label")


def _add_mesh(pl, mesh, opacity=1.0, edges=True):
    """The mesh in light grey with its feature edges (dihedral angle > 20°) drawn dark."""
    poly = _polydata(mesh)
    pl.add_mesh(poly, color=MESH_COLOR, opacity=opacity, smooth_shading=False, specular=0.2, ambient=0.25)
    if edges:
        feat = poly.extract_feature_edges(feature_angle=20.0, boundary_edges=True, non_manifold_edges=False,
                                          manifold_edges=False, feature_edges=True)
        if feat.n_points:
            pl.add_mesh(feat, color="#5b616b", line_width=1.5)


def _check_sensors(positions, normals):
    P = as_array(positions, "positions", (None, 3))
    N = as_array(normals, "normals", (P.shape[0], 3))
    check_finite(P, "positions")
    check_finite(N, "normals")
    N = N / np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-300)
    return P, N


def render_layout_views(mesh, positions, normals, lit_fraction=None, *, candidates=None,
                        views=("iso", "front", "top", "side"), size=(1600, 1200), out_dir,
                        prefix: str = "layout", ids=None, title: "str | None" = None,
                        labels: bool = True, arrows: bool = True, sensor_radius: "float | None" = None,
                        what: str = "sensors", anti_aliasing: bool = True, tilt_deg=None,
                        surface_normals=None) -> "list[Path]":
    """Pictures of a mesh with its candidate sites and a sensor layout from standard views.

    mesh : ``trimesh.Trimesh``, m, body frame. positions, normals : (n, 3), m / unit, body frame.
    lit_fraction : (n,) in [0, 1], fraction of the operating envelope in which each sensor is lit
        (by any station); sensors are coloured by it with a colour bar in %. ``None``: one colour.
    candidates : (N, 3) candidate site positions, m, drawn as small grey points (optional).
    views : names from :data:`VIEWS`. size : (width, height) pixels.
    out_dir : folder; files are ``{prefix}_{view}.png``. ids : n sensor labels (optional).
    arrows : draw the normals. sensor_radius : m (default 1.4 % of the mesh diagonal).
    what : noun for the points in the caption (``"sensors"``, ``"candidate sites"``).
    anti_aliasing : 8× MSAA (about +0.7 s per 1600 × 1200 picture with the software renderer).
    tilt_deg : (n,) tilt of each sensor's axis (``normals``) from the surface normal, deg (the optimiser's
    ``x-tilt-deg``): tilted sensors get red axis arrows and, with ``surface_normals`` (n, 3), a grey arrow
    along the surface normal at their site, so the tilt is seen (:func:`tilt_glyphs`).
    Returns the written paths in ``views`` order.
    """
    P, N = _check_sensors(positions, normals)
    bad = [v for v in views if v not in VIEWS]
    if bad or not views:
        raise ValueError(f"views: unknown {bad}; choose from {sorted(VIEWS)}")
    if lit_fraction is not None:
        lit_fraction = as_array(lit_fraction, "lit_fraction", (P.shape[0],))
        if np.any(~np.isfinite(lit_fraction)) or np.any(lit_fraction < 0) or np.any(lit_fraction > 1):
            raise ValueError("lit_fraction: expected values in [0, 1]")
    if candidates is not None:
        candidates = as_array(candidates, "candidates", (None, 3))
    if ids is not None and len(ids) != P.shape[0]:
        raise ValueError(f"ids: expected {P.shape[0]} labels, got {len(ids)}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)

    import pyvista as pv

    pl = _plotter(size, anti_aliasing=anti_aliasing)
    w, h = _check_size(size)
    diag = _scale(mesh)
    _add_mesh(pl, mesh)
    if candidates is not None and len(candidates):
        pl.add_mesh(pv.PolyData(candidates), color=CANDIDATE_COLOR, point_size=max(3, h // 300),
                    render_points_as_spheres=True)
    radius = 0.014 * diag if sensor_radius is None else float(sensor_radius)
    if P.shape[0]:
        spheres, arrow_glyphs = _sensor_glyphs(P, N, radius, 0.09 * diag,
                                               None if lit_fraction is None else 100.0 * lit_fraction)
        tilted = tilt_glyphs(P, N, tilt_deg, surface_normals, 0.09 * diag) if arrows else None
        if arrows and tilted is None:
            pl.add_mesh(arrow_glyphs, color="#303030", smooth_shading=True)
        elif arrows:
            plain, axis, normal = tilted
            for glyphs, color in ((plain, "#303030"), (axis, TILT_COLOR), (normal, "#9a9a9a")):
                if glyphs is not None and glyphs.n_points:
                    pl.add_mesh(glyphs, color=color, smooth_shading=True)
        if lit_fraction is None:
            pl.add_mesh(spheres, color="#ff7f0e", smooth_shading=True)
        else:
            # colour range: 0–100 %, or 0 to the next 10 % above the maximum when all are rarely lit
            top = 100.0 if lit_fraction.max() > 0.6 else max(10.0, 10.0 * np.ceil(10.0 * lit_fraction.max()))
            pl.add_mesh(spheres, scalars="lit", cmap="viridis", clim=(0.0, top), smooth_shading=True,
                        show_scalar_bar=False)
            pl.add_scalar_bar("lit in % of envelope", vertical=True, position_x=0.86, position_y=0.2,
                              width=0.05, height=0.6, n_labels=int(top // 10) + 1 if top <= 50 else 6,
                              fmt="%.0f", color="black", title_font_size=max(12, h // 55),
                              label_font_size=max(11, h // 60))
    pl.add_axes(line_width=3, labels_off=False, color="black")
    head = title or "Photodiode layout"
    parts = ([f"{P.shape[0]} {what}"] if P.shape[0] else []) + (
        [f"{len(candidates)} candidate sites"] if candidates is not None else [])
    if tilt_deg is not None and np.any(np.asarray(tilt_deg, float) > 0) and arrows:
        tl = np.asarray(tilt_deg, float)
        parts.append(f"{int((tl > 0).sum())} tilted up to {tl.max():.0f}° (red: sensor axis, grey: surface normal)")
    n_txt = ", ".join(parts) or "mesh only"
    pl.add_text(f"{head}\n{n_txt}", position="upper_left", font_size=max(10, h // 80), color="black")

    center = 0.5 * (np.asarray(mesh.bounds[0], float) + np.asarray(mesh.bounds[1], float))
    paths = []
    for v in views:
        direction, up = VIEWS[v]
        d = np.asarray(direction, float)
        d = d / np.linalg.norm(d)
        pl.add_text(f"view: {v}, camera along ({d[0]:+.2f}, {d[1]:+.2f}, {d[2]:+.2f}) in the body frame",
                    position="lower_left", font_size=max(9, h // 95), color="#404040", name="view")
        _add_scale_bar(pl, mesh, center, -d, up, diag, h)
        pl.camera.focal_point = center
        pl.camera.position = center + d * 3.0 * diag
        pl.camera.up = up
        pl.reset_camera(render=False)
        pl.camera.zoom(1.15)
        if labels and ids is not None and P.shape[0]:
            # label the sensors whose normal faces this camera (labels are drawn on top of everything)
            face = N @ d > 0.2
            if face.any():
                pl.add_point_labels(P[face] + N[face] * 0.035 * diag, [str(i) for i, f in zip(ids, face) if f],
                                    font_size=max(10, h // 75), text_color="black", shape_color="white",
                                    shape_opacity=0.7, show_points=False, always_visible=True, margin=2,
                                    name="labels")
            else:
                pl.remove_actor("labels")
        paths.append(_shoot(pl, out_dir / f"{prefix}_{v}.png"))
    pl.close()
    return paths


def station_view_pixels(points_body, rotation, translation, *, fov_deg: float, size, principal_point=None):
    """Image coordinates of body points in a station view (the pinhole model of :func:`render_station_view`).

    points_body : (..., 3) m, body frame. rotation (3, 3), translation (3,) m: body pose in the
    station frame. fov_deg : vertical view angle. size : (W, H) px. principal_point : (cx, cy) px,
    default the window centre (W/2, H/2).
    Returns ``uv (..., 2)`` — u to the right, v down, in pixels from the top-left corner of the
    image (pixel column i, row j covers [i, i+1) × [j, j+1)) — and the depth ``z (...,)`` m:
    ``u = cx + f x/z``, ``v = cy + f y/z`` with ``(x, y, z) = R p + t``, ``f = (H/2) / tan(fov/2)``.
    """
    w, h = _check_size(size)
    R = as_array(rotation, "rotation", (3, 3))
    t = as_array(translation, "translation", (3,))
    q = as_array(points_body, "points_body", (..., 3)) @ R.T + t
    f = 0.5 * h / np.tan(np.deg2rad(fov_deg) / 2.0)
    cx, cy = (0.5 * w, 0.5 * h) if principal_point is None else (float(principal_point[0]), float(principal_point[1]))
    uv = np.stack([cx + f * q[..., 0] / q[..., 2], cy + f * q[..., 1] / q[..., 2]], -1)
    return uv, q[..., 2]


def station_view_camera(mesh, rotation, translation, size, fov_deg: "float | None" = None, margin: float = 1.25):
    """Pinhole intrinsics of a station view: ``(fov_deg, (cx, cy) px)``.

    With ``fov_deg`` given the principal point is the window centre. With ``None`` the view is a
    crop of the station image that frames the mesh: the vertical view angle fits the projected
    mesh (times ``margin``) and the principal point moves so that the mesh is centred — the
    camera stays at the station origin looking along +z, so pixels still follow
    :func:`station_view_pixels` exactly.
    """
    w, h = _check_size(size)
    if fov_deg is not None:
        if not 0 < fov_deg < 180:
            raise ValueError(f"fov_deg: expected a view angle in (0, 180) degrees, got {fov_deg}")
        return float(fov_deg), (0.5 * w, 0.5 * h)
    q = np.asarray(mesh.vertices, float) @ np.asarray(rotation, float).T + np.asarray(translation, float)
    q = q[q[:, 2] > 1e-9]
    if q.shape[0] == 0:
        raise ValueError("station view: the mesh is entirely behind the station")
    xn, yn = q[:, 0] / q[:, 2], q[:, 1] / q[:, 2]
    cxn, cyn = 0.5 * (xn.max() + xn.min()), 0.5 * (yn.max() + yn.min())
    half = margin * max(0.5 * (xn.max() - xn.min()) * h / w, 0.5 * (yn.max() - yn.min()), 1e-6)
    fov = float(np.clip(np.rad2deg(2 * np.arctan(half)), 0.05, 170.0))
    f = 0.5 * h / np.tan(np.deg2rad(fov) / 2)
    return fov, (0.5 * w - f * cxn, 0.5 * h - f * cyn)


def render_station_view(mesh, positions, normals, rotation, translation, lit, *, fov_deg: "float | None" = 120.0,
                        size=(1600, 1200), out, ids=None, title: "str | None" = None,
                        anti_aliasing: bool = True, shadowed=None, sensor_radius: "float | None" = None,
                        what: str = "sensors") -> Path:
    """The target seen from a lighthouse: lit sensors green, unlit red (shadowed by the mesh: orange).

    mesh : ``trimesh.Trimesh`` (m, body frame); positions, normals : (n, 3) body frame.
    rotation (3, 3), translation (3,) m : body pose in the station frame (``p_lh = R p + t``).
    lit : (n,) bool, sensors the station sees at this pose (e.g. from ``visible_sensors``).
    fov_deg : vertical view angle of the pinhole camera at the station origin along +z (the
        lighthouse field of view is 120° × 120°), principal point at the window centre; ``None``
        frames the target by a crop of the station image (:func:`station_view_camera`). The
        pixel of a body point is :func:`station_view_pixels` with those intrinsics.
    shadowed : (n,) bool, optional — unlit sensors that would be lit but for the mesh in the way
        (e.g. ``visible_sensors(..., occlusion=False) & ~lit``), drawn orange.
    sensor_radius : m (default: 1 % of the mesh diagonal, at least 5 px). what : caption noun.
    out : PNG path. anti_aliasing : off for exact masks. Returns ``Path(out)``.
    """
    P, N = _check_sensors(positions, normals)
    R = as_array(rotation, "rotation", (3, 3))
    t = as_array(translation, "translation", (3,))
    check_finite(R, "rotation")
    check_finite(t, "translation")
    lit = np.asarray(lit, bool)
    if lit.shape != (P.shape[0],):
        raise ValueError(f"lit: expected shape ({P.shape[0]},), got {lit.shape}")
    shadowed = np.zeros_like(lit) if shadowed is None else np.asarray(shadowed, bool)
    if shadowed.shape != lit.shape:
        raise ValueError(f"shadowed: expected shape ({P.shape[0]},), got {shadowed.shape}")
    shadowed = shadowed & ~lit
    fov_deg, (cx, cy) = station_view_camera(mesh, R, t, size, fov_deg)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)

    w, h = _check_size(size)
    pl = _plotter(size, anti_aliasing=anti_aliasing)
    diag = _scale(mesh)
    _add_mesh(pl, mesh)
    # camera: design §8 pinhole match
    C = -R.T @ t
    pl.camera.position = C
    pl.camera.focal_point = C + R[2]
    pl.camera.up = -R[1]
    pl.camera.view_angle = float(fov_deg)
    # principal point (cx, cy) px: VTK shifts the image by -window_center * (W/2, -H/2) (NDC y up)
    pl.camera.SetWindowCenter(2.0 * (0.5 * w - cx) / w, -2.0 * (0.5 * h - cy) / h)
    if sensor_radius is None:
        # ≥ 1 % of the mesh diagonal and ≥ 5 px at the sensors' median depth
        depth = float(np.median((P @ R.T + t)[:, 2])) if P.shape[0] else float(np.linalg.norm(t))
        radius = max(0.01 * diag, 5 * np.deg2rad(fov_deg) / h * abs(depth))
    else:
        radius = float(sensor_radius)
    for mask, color in ((lit, LIT_COLOR), (shadowed, SHADOW_COLOR), (~lit & ~shadowed, UNLIT_COLOR)):
        if mask.any():
            sph = _sphere_glyphs(P[mask], N[mask], radius)
            pl.add_mesh(sph, color=color, smooth_shading=True, ambient=0.35)
    if ids is not None:
        if len(ids) != P.shape[0]:
            raise ValueError(f"ids: expected {P.shape[0]} labels, got {len(ids)}")
        q = P @ R.T + t
        face = np.sum((N @ R.T) * -q, axis=1) > 0.2 * np.linalg.norm(q, axis=1)  # normal towards the station
        if face.any():
            off = P[face] + N[face] * 2.5 * radius
            pl.add_point_labels(off, [str(i) for i, f in zip(ids, face) if f], font_size=max(10, h // 70),
                                text_color="black", shape_color="white", shape_opacity=0.7, show_points=False,
                                always_visible=True, margin=2)
    dist = float(np.linalg.norm(t))
    head = title or "view from the lighthouse"
    crop = "" if abs(cx - 0.5 * w) < 1e-6 and abs(cy - 0.5 * h) < 1e-6 else " (crop of the station image)"
    pl.add_text(f"{head}\nrange {dist:.2f} m, vertical view angle {fov_deg:.2f} deg{crop}\n"
                f"{what}: {int(lit.sum())}/{lit.size} lit (green)"
                + (f", {int(shadowed.sum())} shadowed by the mesh (orange)" if shadowed.any() else "")
                + f", {int((~lit & ~shadowed).sum())} not lit (red)",
                position="upper_left", font_size=max(10, h // 80), color="black")
    _add_scale_bar(pl, mesh, 0.5 * (np.asarray(mesh.bounds[0], float) + np.asarray(mesh.bounds[1], float)),
                   R[2], -R[1], diag, h, tight=True)
    pl.renderer.ResetCameraClippingRange()
    _shoot(pl, out)
    pl.close()
    return out


def _finite_norm(values, log_ratio=20.0):
    """A matplotlib norm over the finite values: log if they span more than ``log_ratio``."""
    from matplotlib.colors import LogNorm, Normalize

    fin = values[np.isfinite(values)]
    if fin.size == 0:
        return Normalize(0, 1)
    lo, hi = float(fin.min()), float(fin.max())
    if lo > 0 and hi / lo > log_ratio:
        return LogNorm(lo, hi)
    if hi <= lo:
        hi = lo + 1.0
    return Normalize(lo, hi)


def render_tracking_map(quality_map, *, out, kind: str = "mollweide", size=(1600, 1200),
                        title: "str | None" = None, sigma_theta: "float | None" = None) -> Path:
    """Picture of a :class:`layoutkit.quality.QualityMap` over all viewing directions.

    kind : ``"mollweide"`` — four matplotlib Mollweide panels (worst ADOP over roll, worst PDOP
        over roll, fewest lit sensors over roll, median ADOP over roll) against body longitude and
        latitude of the station direction; ``"sphere"`` — three pyvista spheres of directions
        coloured by worst ADOP, worst PDOP and fewest lit sensors.
    sigma_theta : rad, optional; adds the predicted 1-sigma attitude (deg) and position (mm)
        ranges to the colour-bar labels (Chen eq. 24). title : figure title (Mollweide only).
    Untracked directions (fewer than ``min_lit`` lit or singular) are grey. Returns ``Path(out)``.
    """
    if kind not in ("mollweide", "sphere"):
        raise ValueError(f"kind: expected 'mollweide' or 'sphere', got {kind!r}")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if kind == "mollweide":
        return _tracking_map_mollweide(quality_map, out, size, title, sigma_theta)
    return _tracking_map_sphere(quality_map, out, size, title)


def _map_panels(q):
    return [
        ("ADOP, worst over roll", q.adop_worst, "ADOP [deg/rad]", "viridis"),
        ("PDOP, worst over roll", q.pdop_worst, "PDOP [m/rad]", "viridis"),
        ("lit sensors, fewest over roll", q.n_lit_min.astype(float), "lit sensors [count]", "magma"),
        ("ADOP, median over roll", q.adop_median, "ADOP [deg/rad]", "viridis"),
    ]


def _tracking_map_mollweide(q, out, size, title, sigma_theta):
    import matplotlib
    from matplotlib import patheffects
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import BoundaryNorm
    from matplotlib.figure import Figure

    w, h = _check_size(size)
    dpi = 100
    fs = min(w / 1600, h / 1200) * 1.25  # font scale: the text keeps its share of a smaller picture
    fig = Figure(figsize=(w / dpi, h / dpi), dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    fig.suptitle(title or "Tracking quality over all viewing directions", fontsize=16 * fs)
    halo = [patheffects.withStroke(linewidth=2.5, foreground="white")]
    axes_marks = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0),
                  "+z": (0, 0, 1), "-z": (0, 0, -1)}
    for k, (name, val, unit, cmap_name) in enumerate(_map_panels(q)):
        ax = fig.add_subplot(2, 2, k + 1, projection="mollweide")
        cmap = matplotlib.colormaps[cmap_name].with_extremes(bad="#d0d0d0")
        masked = np.ma.masked_invalid(np.where(np.isfinite(val), val, np.nan))
        if "lit" in name:
            top = int(max(np.nanmax(val), 4))
            bounds = np.arange(-0.5, top + 1.5)
            cmap = matplotlib.colormaps[cmap_name].resampled(top + 1).with_extremes(bad="#d0d0d0")
            norm = BoundaryNorm(bounds, cmap.N)
        else:
            norm = _finite_norm(val)
        if q.is_grid:
            lon_e, lat_e = np.meshgrid(q.lon_edges, q.lat_edges)
            art = ax.pcolormesh(lon_e, lat_e, masked, cmap=cmap, norm=norm, shading="flat", rasterized=True)
        else:
            art = ax.scatter(q.lon, q.lat, c=masked, cmap=cmap, norm=norm, s=8, linewidths=0)
        if "lit" in name and q.is_grid and np.nanmin(val) < q.min_lit <= np.nanmax(val):
            ax.contour(q.lon, q.lat, val, levels=[q.min_lit - 0.5], colors="#00b8ff", linewidths=1.5)
        cb = fig.colorbar(art, ax=ax, orientation="horizontal", pad=0.04, fraction=0.05, aspect=40)
        label = unit
        fin = val[np.isfinite(val)]
        if sigma_theta is not None and fin.size and "ADOP" in unit:  # Chen eq. (24)
            label += (f" — 1σ attitude at σθ = {sigma_theta:.3g} rad: "
                      f"{fin.min() * sigma_theta:.3g} to {fin.max() * sigma_theta:.3g} deg")
        if sigma_theta is not None and fin.size and "PDOP" in unit:
            label += (f" — 1σ position at σθ = {sigma_theta:.3g} rad: "
                      f"{1e3 * fin.min() * sigma_theta:.3g} to {1e3 * fin.max() * sigma_theta:.3g} mm")
        cb.set_label(label, fontsize=10 * fs)
        cb.ax.tick_params(labelsize=8 * fs)
        if "lit" in name:
            cb.set_ticks(np.arange(0, top + 1, max(1, (top + 1) // 10)))
        ax.set_title(name, fontsize=12 * fs, pad=14 * fs)
        # graticule as plain lines (matplotlib's tick-based geo grid costs ~0.1 s per panel)
        ax.grid(False)
        ax.set_xticks([])
        ax.set_yticks(np.deg2rad([-60, -30, 0, 30, 60]))
        ax.tick_params(labelsize=8 * fs)
        s = np.linspace(-np.pi / 2, np.pi / 2, 61)
        for lo in np.deg2rad(np.arange(-135, 180, 45)):
            ax.plot(np.full_like(s, lo), s, color="white", alpha=0.6, lw=0.5)
        s = np.linspace(-np.pi, np.pi, 121)
        for la in np.deg2rad([-60, -30, 0, 30, 60]):
            ax.plot(s, np.full_like(s, la), color="white", alpha=0.6, lw=0.5)
        for lbl, v in axes_marks.items():
            lon = np.arctan2(v[1], v[0])
            lat = np.arcsin(v[2])
            ax.plot(lon, lat, marker="+", color="black", ms=8 * fs, mew=1.5, path_effects=halo)
            ax.annotate(lbl, (lon, lat), xytext=(5 * fs, 3 * fs), textcoords="offset points", fontsize=10 * fs, color="black",
                        fontweight="bold", path_effects=halo)
    frac = q.summary()["tracked_solid_angle_fraction"]
    from .io.figures import save_figure

    caption = (f"Station at {q.distance:g} m looking at the target origin; same-sweep correlation rho = {q.rho:g}; "
               f"{q.roll.size} station rolls about the line of sight in [0°, 90°). Station direction in the body "
               f"frame (longitude atan2(y, x), latitude asin(z)); grey: fewer than {q.min_lit} sensors lit or "
               f"singular; blue line: {q.min_lit}-sensor boundary. Tracked at every roll over {100 * frac:.1f} % "
               f"of the sphere.")
    save_figure(fig, out, caption=caption, dpi=dpi, close=False, size_px=(w, h), fontsize=9 * fs)
    return out


def _tracking_map_sphere(q, out, size, title):
    import pyvista as pv

    w, h = _check_size(size)
    pl = _plotter(size, shape=(1, 3))
    if q.is_grid:
        la, lo = np.meshgrid(q.lat_edges, q.lon_edges, indexing="ij")
        X = np.cos(la) * np.cos(lo)
        Y = np.cos(la) * np.sin(lo)
        Z = np.sin(la)
        base = pv.StructuredGrid(X, Y, Z)
        on_cells = True
    else:
        import trimesh

        hull = trimesh.convex.convex_hull(q.directions)
        base = pv.PolyData.from_regular_faces(np.asarray(hull.vertices), np.asarray(hull.faces))
        # hull vertices keep the input order only up to a permutation: map values by nearest direction
        idx = np.argmax(np.asarray(hull.vertices) @ q.directions.T, axis=1)
        on_cells = False
    for k, (name, val, unit, cmap) in enumerate(_map_panels(q)[:3]):
        pl.subplot(0, k)
        grid = base.copy()
        v = np.where(np.isfinite(val), val, np.nan)
        if on_cells:
            v = v.ravel(order="F")  # StructuredGrid cells run with the first index fastest
            grid.cell_data[unit] = v
        else:
            v = v[idx]
            grid.point_data[unit] = v
        fin = v[np.isfinite(v)]
        clim = (float(fin.min()), float(fin.max())) if fin.size else (0.0, 1.0)
        log = "ADOP" in unit or "PDOP" in unit
        log = log and clim[0] > 0 and clim[1] / clim[0] > 20
        extra = {}
        if "lit" in unit:
            # bins of width top/(top+1) over [0, top]: value k falls in bin k, labels at integers
            top = max(clim[1], 4.0)
            clim = (0.0, top)
            extra["n_colors"] = int(top) + 1
        pl.add_mesh(grid, scalars=unit, cmap=cmap, clim=clim, nan_color="#d0d0d0", log_scale=log,
                    show_scalar_bar=False, smooth_shading=False, **extra)
        pl.add_scalar_bar(unit, vertical=False, position_x=0.1, position_y=0.04, width=0.8, height=0.08,
                          color="black", fmt="%.3g" if "PDOP" in unit else "%.0f", title_font_size=max(12, h // 60),
                          label_font_size=max(10, h // 70), n_labels=extra.get("n_colors", 4))
        for lbl, d in (("+x", (1.25, 0, 0)), ("+y", (0, 1.25, 0)), ("+z", (0, 0, 1.25))):
            pl.add_mesh(pv.Arrow(start=np.asarray(d) / 1.25, direction=np.asarray(d) / 1.25, scale=0.35),
                        color="black")
            pl.add_point_labels([np.asarray(d) * 1.15], [lbl], font_size=max(10, h // 70), show_points=False,
                                shape_opacity=0.0, text_color="black")
        pl.add_text(name, position="upper_edge", font_size=max(9, h // 95), color="black")
        pl.camera.focal_point = (0.0, 0.0, 0.0)
        pl.camera.position = (4.0, -4.0, 3.2)
        pl.camera.up = (0.0, 0.0, 1.0)
        pl.reset_camera(render=False)
        pl.camera.zoom(1.6)
    _shoot(pl, out)
    pl.close()
    return out
