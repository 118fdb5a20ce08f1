"""Tracking-quality map: ADOP, PDOP and lit-sensor count over all viewing directions.

The picture a designer looks at first (design §1: Valve's HMD Designer shows the same kind of
map). For every viewing direction ``d`` (unit vector in the body frame pointing from the target
origin to the station) the station sits at ``distance * d`` and looks at the target origin; the
body then appears on the station boresight. The station may stand at any roll about that line of
sight; the sweep-angle geometry is not roll-invariant (two orthogonal sweeps, a square field of
view), so each direction is evaluated at ``roll_samples`` roll angles and the map reports the
worst and the median over roll.

Pose of the body in the station frame (``p_lh = R p_body + t``, design §2): with ``M`` the
rotation whose rows are the station axes in the body frame (z = ``-d``, the boresight towards the
target), ``R = Rz(psi) M`` and ``t = (0, 0, distance)`` for roll ``psi``.

Pure numpy; visibility comes from :func:`layoutkit.visibility.visible_sensors` (occlusion
included) and the DOP from :func:`layoutkit.dop.pose_dop`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._validate import as_array, check_finite
from .geometry import look_at_rotation

__all__ = ["QualityMap", "tracking_quality_map", "viewing_poses", "latlon_grid", "fibonacci_directions"]

MIN_LIT = 4  # fewer lit sensors than this: the pose is not tracked (DOP reported as inf)


@dataclass(frozen=True)
class QualityMap:
    """ADOP/PDOP/lit count over viewing directions and roll about the line of sight.

    directions : (*G, 3) float, unit vectors in the body frame from the target origin to the
        station; ``G = (n_lat, n_lon)`` for a latitude/longitude grid, ``(n_directions,)`` otherwise.
    lat, lon : (*G,) float, rad — ``lat = asin(d_z)``, ``lon = atan2(d_y, d_x)`` (body frame).
    lat_edges, lon_edges : (n_lat + 1,), (n_lon + 1,) float, rad, cell edges of a grid; ``None``
        for scattered directions.
    roll : (K,) float, rad, roll samples of the station about the line of sight.
    adop : (*G, K) float, deg of attitude per rad of angle noise (Chen eq. 22); inf where fewer
        than ``min_lit`` sensors are lit or the geometry is singular.
    pdop : (*G, K) float, m of position per rad of angle noise; inf likewise.
    n_lit : (*G, K) int, lit sensors (field of view, acceptance cone, range, occlusion).
    status : (*G, K) int — 0 ok, 1 fewer than ``min_lit`` lit, 2 singular geometry.
    distance : float, m; rho : float, same-rotor correlation used (Chen eq. 19); min_lit : int.
    """

    directions: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    lat_edges: "np.ndarray | None"
    lon_edges: "np.ndarray | None"
    roll: np.ndarray
    adop: np.ndarray
    pdop: np.ndarray
    n_lit: np.ndarray
    status: np.ndarray
    distance: float
    rho: float
    min_lit: int = MIN_LIT

    @property
    def is_grid(self) -> bool:
        return self.lat_edges is not None

    @property
    def success(self) -> np.ndarray:
        """(*G, K) bool, tracked with non-singular geometry."""
        return self.status == 0

    @property
    def adop_worst(self) -> np.ndarray:
        """(*G,) worst (largest) ADOP over roll, deg/rad."""
        return self.adop.max(axis=-1)

    @property
    def adop_median(self) -> np.ndarray:
        """(*G,) median ADOP over roll, deg/rad (inf if more than half the rolls are untracked)."""
        return np.median(self.adop, axis=-1)

    @property
    def pdop_worst(self) -> np.ndarray:
        """(*G,) worst PDOP over roll, m/rad."""
        return self.pdop.max(axis=-1)

    @property
    def pdop_median(self) -> np.ndarray:
        """(*G,) median PDOP over roll, m/rad."""
        return np.median(self.pdop, axis=-1)

    @property
    def n_lit_min(self) -> np.ndarray:
        """(*G,) fewest lit sensors over roll."""
        return self.n_lit.min(axis=-1)

    @property
    def n_lit_median(self) -> np.ndarray:
        """(*G,) median lit-sensor count over roll."""
        return np.median(self.n_lit, axis=-1)

    @property
    def tracked_fraction(self) -> float:
        """Fraction of (direction, roll) samples that are tracked (unweighted by solid angle)."""
        return float(np.mean(self.success))

    @property
    def message(self) -> str:
        s = self.status
        return (f"{int(np.sum(s == 0))}/{s.size} direction×roll samples tracked; "
                f"{int(np.sum(s == 1))} with fewer than {self.min_lit} lit, {int(np.sum(s == 2))} singular")

    def summary(self) -> dict:
        """Plain numbers for reports: solid-angle-weighted statistics over directions."""
        w = np.cos(self.lat) if self.is_grid else np.ones_like(self.lat)
        w = w / w.sum()
        ok = np.all(self.success, axis=-1)
        aw = self.adop_worst
        pw = self.pdop_worst
        fin = np.isfinite(aw)
        return {
            "distance_m": self.distance,
            "rho": self.rho,
            "directions": int(self.lat.size),
            "roll_samples": int(self.roll.size),
            "tracked_solid_angle_fraction": float(np.sum(w * ok)),
            "adop_worst_deg_per_rad_max_tracked": float(aw[fin].max()) if fin.any() else float("inf"),
            "adop_worst_deg_per_rad_median_tracked": float(np.median(aw[fin])) if fin.any() else float("inf"),
            "pdop_worst_m_per_rad_max_tracked": float(pw[fin].max()) if fin.any() else float("inf"),
            "n_lit_min": int(self.n_lit.min()),
            "n_lit_max": int(self.n_lit.max()),
        }


def latlon_grid(n_lat: int, n_lon: int):
    """Cell-centred latitude/longitude grid on the unit sphere.

    Returns ``(directions (n_lat, n_lon, 3), lat (n_lat, n_lon), lon (n_lat, n_lon),
    lat_edges (n_lat + 1,), lon_edges (n_lon + 1,))``, angles in rad, body frame
    (``lat = asin(z)``, ``lon = atan2(y, x)``).
    """
    if n_lat < 1 or n_lon < 1:
        raise ValueError(f"grid: expected at least 1 × 1 cells, got {n_lat} × {n_lon}")
    lat_e = np.linspace(-np.pi / 2, np.pi / 2, n_lat + 1)
    lon_e = np.linspace(-np.pi, np.pi, n_lon + 1)
    lat_c = 0.5 * (lat_e[1:] + lat_e[:-1])
    lon_c = 0.5 * (lon_e[1:] + lon_e[:-1])
    lat, lon = np.meshgrid(lat_c, lon_c, indexing="ij")
    d = np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], -1)
    return d, lat, lon, lat_e, lon_e


def fibonacci_directions(n: int) -> np.ndarray:
    """(n, 3) nearly uniform unit vectors (golden-angle spiral), deterministic."""
    if n < 1:
        raise ValueError(f"n_directions: expected >= 1, got {n}")
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)


def viewing_poses(directions, distance: float, roll):
    """Body poses that put a station at ``distance * d`` looking at the body origin.

    directions : (..., 3) unit vectors, body frame, from the target to the station.
    distance : m. roll : (K,) rad, station roll about the line of sight.
    Returns ``rotation (..., K, 3, 3)``, ``translation (..., K, 3)``: the body pose in the
    station frame (``p_lh = R p_body + t``); the body origin lands at ``(0, 0, distance)``.
    """
    d = as_array(directions, "directions", (..., 3))
    roll = np.atleast_1d(np.asarray(roll, float))
    M = look_at_rotation(-d)  # rows: station axes in the body frame; z points at the target
    c, s = np.cos(roll), np.sin(roll)
    z, o = np.zeros_like(roll), np.ones_like(roll)
    Rz = np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)
    R = Rz @ M[..., None, :, :]  # (..., K, 3, 3)
    t = np.broadcast_to(np.array([0.0, 0.0, float(distance)]), R.shape[:-1]).copy()
    return R, t


def tracking_quality_map(mesh, positions, normals, *, distance: float, rho: float = 0.0,
                         grid: "tuple[int, int] | None" = (45, 90), n_directions: "int | None" = None,
                         roll_samples: int = 6, sensor_half_angle_deg: float = 60.0,
                         fov_deg: float = 120.0, max_range: "float | None" = None,
                         min_lit: int = MIN_LIT, chunk: int = 20000) -> QualityMap:
    """ADOP, PDOP and lit-sensor count over all viewing directions around a target.

    mesh : ``trimesh.Trimesh`` (m, body frame), used for self-occlusion.
    positions, normals : (n, 3) sensor positions (m) and outward normals, body frame.
    distance : m, station–target-origin range. rho : same-rotor angle correlation (Chen eq. 19).
    grid : ``(n_lat, n_lon)`` cell-centred latitude/longitude grid (default 4° cells), or
    n_directions : number of nearly uniform (Fibonacci) directions; it overrides ``grid``.
    roll_samples : K rolls of the station about the line of sight, evenly in [0, π/2) — the
        sweep geometry has the symmetry of a square: a roll by π/2 maps (x, y) → (-y, x), i.e.
        ``theta_x' = π - theta_y``, ``theta_y' = theta_x``, which leaves the field of view, the
        same-axis correlation structure and hence the DOP unchanged.
    sensor_half_angle_deg, fov_deg, max_range : visibility model (see ``visible_sensors``).
    min_lit : poses with fewer lit sensors are untracked (status 1, DOP inf).
    chunk : poses per visibility/DOP batch (bounds memory).
    Returns a :class:`QualityMap`; ADOP in deg/rad, PDOP in m/rad (multiply by sigma_theta in rad
    for the predicted 1-sigma attitude in deg and position in m, Chen eq. 24).
    """
    from .dop import pose_dop
    from .visibility import visible_sensors

    P = as_array(positions, "positions", (None, 3))
    N = as_array(normals, "normals", (P.shape[0], 3))
    check_finite(P, "positions")
    check_finite(N, "normals")
    if not np.isfinite(distance) or distance <= 0:
        raise ValueError(f"distance: expected a positive number of metres, got {distance}")
    if roll_samples < 1:
        raise ValueError(f"roll_samples: expected >= 1, got {roll_samples}")
    if n_directions is not None:
        d = fibonacci_directions(int(n_directions))
        lat = np.arcsin(np.clip(d[:, 2], -1, 1))
        lon = np.arctan2(d[:, 1], d[:, 0])
        lat_e = lon_e = None
    elif grid is not None:
        d, lat, lon, lat_e, lon_e = latlon_grid(int(grid[0]), int(grid[1]))
    else:
        raise ValueError("give grid=(n_lat, n_lon) or n_directions")
    roll = np.arange(roll_samples) * (0.5 * np.pi / roll_samples)
    R, t = viewing_poses(d, distance, roll)
    G = d.shape[:-1]
    K = roll.size
    Rf = R.reshape(-1, 3, 3)
    tf = t.reshape(-1, 3)
    n_pose = Rf.shape[0]
    adop = np.empty(n_pose)
    pdop = np.empty(n_pose)
    n_lit = np.empty(n_pose, int)
    status = np.empty(n_pose, int)
    for a in range(0, n_pose, chunk):
        b = min(a + chunk, n_pose)
        vis = visible_sensors(mesh, P, N, Rf[a:b], tf[a:b], sensor_half_angle_deg=sensor_half_angle_deg,
                              fov_deg=fov_deg, max_range=max_range)
        res = pose_dop(P, Rf[a:b], tf[a:b], rho=rho, visible=vis)  # Chen eqs. (18), (22)
        nl = vis.sum(-1)
        few = nl < min_lit
        adop[a:b] = np.where(few, np.inf, res.adop)
        pdop[a:b] = np.where(few, np.inf, res.pdop)
        n_lit[a:b] = nl
        status[a:b] = np.where(few, 1, res.status)
    shape = G + (K,)
    return QualityMap(directions=d, lat=lat, lon=lon, lat_edges=lat_e, lon_edges=lon_e, roll=roll,
                      adop=adop.reshape(shape), pdop=pdop.reshape(shape), n_lit=n_lit.reshape(shape),
                      status=status.reshape(shape), distance=float(distance), rho=float(rho),
                      min_lit=int(min_lit))
