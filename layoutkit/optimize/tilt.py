"""Sensor tilt as a design variable (issue 13, item 3).

A site may carry several orientations: its surface normal and the normal tilted by
``max_tilt_deg`` (and half of it) towards ``n_directions`` azimuths about the normal, or — with
``toward`` — in the plane of the normal and a body axis only, towards it and away from it (the
meridional tilts: on a dome whose envelope looks along that axis, rim sensors tilted up are lit from
the front as well as from the side). Each
orientation is a candidate of its own — the angle Jacobian (Chen eqs. 10–14) depends on the
position only, visibility (acceptance cone, occlusion origin) on the orientation — and candidates of
the same site conflict pairwise, so at most one orientation per site is chosen (the spacing
machinery of the optimiser enforces it in every move, the relaxation as ``z_i + z_j <= 1``).
Mounting cost is the user's call: ``max_tilt_deg = 0`` gives the plain surface normals.
"""
from __future__ import annotations

import numpy as np

__all__ = ["tilt_orientations", "site_conflicts"]


def _basis(n):
    """Two unit vectors orthogonal to each row of ``n (N, 3)``."""
    a = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    u = np.cross(n, a)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u, np.cross(n, u)


def tilt_orientations(positions, normals, max_tilt_deg, n_directions=4, levels=(1.0,), toward=None):
    """Expand sites into (site, orientation) candidates.

    positions, normals : (N, 3) sites (m) and unit surface normals, body frame.
    max_tilt_deg : largest angle between a sensor's axis and the surface normal (deg); 0 = normals only.
    n_directions : azimuths of the tilt about the normal; levels : tilt fractions of max_tilt_deg.
    toward : (3,) body axis or None; if given, the tilts are meridional instead (towards ``toward``
    and away from it, ``n_directions`` unused) and a site whose normal is parallel to it (within
    1e-6) keeps its normal only.
    Returns ``(positions (M, 3), axes (M, 3), site (M,) int, tilt_deg (M,))`` with the untilted
    orientation of every site first (indices 0..N-1 are the plain sites in order).
    """
    p = np.asarray(positions, float)
    n = np.asarray(normals, float)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    N = len(p)
    if not np.isfinite(max_tilt_deg) or max_tilt_deg < 0 or max_tilt_deg >= 90:
        raise ValueError(f"max_tilt_deg: expected 0 <= tilt < 90, got {max_tilt_deg}")
    if max_tilt_deg == 0:
        return p, n, np.arange(N), np.zeros(N)
    if toward is None:
        u, v = _basis(n)
        dirs = []
        for lev in levels:
            for j in range(int(n_directions)):
                phi = 2 * np.pi * j / n_directions + (np.pi / n_directions if lev != levels[-1] else 0.0)
                dirs.append((lev, np.cos(phi) * u + np.sin(phi) * v, np.ones(N, bool)))
    else:
        w = np.asarray(toward, float).reshape(3)
        if not np.all(np.isfinite(w)) or np.linalg.norm(w) == 0:
            raise ValueError(f"toward: expected a finite non-zero 3-vector, got {toward!r}")
        w = w / np.linalg.norm(w)
        m = w - (n @ w)[:, None] * n  # meridian direction (the axis's part orthogonal to the normal)
        mn = np.linalg.norm(m, axis=1)
        ok = mn > 1e-6
        m = m / np.where(ok, mn, 1.0)[:, None]
        dirs = [(lev, sgn * m, ok) for lev in levels for sgn in (1.0, -1.0)]
    P, A, S, T = [p], [n], [np.arange(N)], [np.zeros(N)]
    for lev, d, ok in dirs:
        th = np.deg2rad(lev * max_tilt_deg)
        P.append(p[ok])
        A.append((np.cos(th) * n + np.sin(th) * d)[ok])
        S.append(np.arange(N)[ok])
        T.append(np.full(int(ok.sum()), np.rad2deg(th)))
    return np.concatenate(P), np.concatenate(A), np.concatenate(S), np.concatenate(T)


def site_conflicts(site, conflict=None):
    """(M, M) bool: candidates of the same site conflict, OR-ed with a spacing conflict matrix
    given per candidate (``conflict`` (M, M) or None)."""
    site = np.asarray(site)
    C = site[:, None] == site[None, :]
    np.fill_diagonal(C, False)
    if conflict is not None:
        C |= np.asarray(conflict, bool)
    return C
