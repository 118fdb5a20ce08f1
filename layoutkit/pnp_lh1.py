"""Batched perspective-n-point from the sweep angles of one ideal LH1 station (Chen §2, design §4).

The fast path of :func:`layoutkit.pnp.solve_pnp` (which adds calibrated stations through
:mod:`layoutkit.joint`; the joint solver starts from this module's poses, so this module sits below
both).

Why one module of ~930 lines: the solver is one batched Levenberg–Marquardt over frames-last
component arrays; its starts (POSIT, IPPE pairs), refinement, Jacobians and the private frame
container share that layout and are read together; split, each part would import the others'
private helpers.

Given the body coordinates of n sensors and their LH1 sweep angles in F frames, find per frame
the pose ``p_lh = R p_body + t`` that minimises the sum of squared **angle** residuals
``theta_meas - theta_pred`` over the lit sensors — the maximum-likelihood estimate for the
independent-noise model of Chen §3.3.

Method (vectorised over frames; frames are processed in bounded chunks):

1. Sweep angles are a pinhole camera: normalised image coordinates ``(x/z, y/z) = cot(theta)``
   (Chen eq. 2).
2. Start for non-coplanar lit sets: the bearings are rotated into a virtual camera whose
   boresight is the ray through the mean lit image point, where the target is near the axis
   and scaled orthography is an excellent model; then the scaled-orthographic linear solve with
   perspective correction (POSIT, DeMenthon & Davis 1995), two fixed-point iterations. (Without
   the virtual camera, POSIT starts are off by up to 180° for targets near the field edge.)
3. Start for coplanar or near-coplanar lit sets (``sqrt(lambda_min / lambda_max)`` of the centred
   lit body points below :data:`PLANARITY_THRESHOLD`), and for frames whose first solution is
   poor: the homography of the dominant plane and the two poses of the planar two-fold
   ambiguity from its Jacobian in closed form (IPPE, Collins & Bartoli 2014). Every candidate is
   refined; the lowest residual with all lit sensors in front of the station wins.
4. Refinement: Levenberg–Marquardt on the angle residuals (Chen eqs. 6–12) with the analytic
   Jacobian of :func:`layoutkit.dop.angle_jacobian` written out per component (left
   perturbation ``R <- exp([dphi]x) R``, ``t <- t + dt``), batched 6 × 6 normal equations
   solved by an unrolled Cholesky factorisation. Converged when the step lowers the cost by less
   than ``1e-6`` of itself (typically two iterations from the POSIT start, the second checked
   with the first iteration's factor, so one normal-matrix build per frame).
5. Layout: inside a chunk, per-sensor arrays are frames-last ``(n, F)`` and per-frame 3-vectors
   and rotations are component arrays, so every numpy operation runs over the long frame axis.

Status codes (``PnPResult.status``) are listed in :data:`STATUS_NAMES`.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Protocol

import numpy as np

from . import status as _status
from ._validate import as_array
from .geometry import ensure_rotation
from .pnp_result import PnPResult, concat_results
from .units import RHO_PAPER, SIGMA_THETA_PAPER

__all__ = [
    "PnPSolver",
    "PNP_SOLVERS",
    "STATUS_OK",
    "STATUS_TOO_FEW",
    "STATUS_DEGENERATE",
    "STATUS_NOT_CONVERGED",
    "STATUS_BEHIND",
    "STATUS_AMBIGUOUS",
    "STATUS_INVALID_ANGLE",
    "STATUS_NO_START",
    "STATUS_LOW_REDUNDANCY",
    "STATUS_NAMES",
    "MIN_ANGLES",
    "MIN_REDUNDANCY",
    "MIN_SENSORS",
    "MIN_START_SENSORS",
    "DEFAULT_CHUNK",
    "AMBIGUITY_LR",
    "solve_pnp_lh1",
    "solve_pnp_lm",
]

#: The minimum rule: a pose is attempted when a frame has at least MIN_ANGLES seen angles from at
#: least MIN_SENSORS sensors (6 equations for the 6 pose unknowns; with fewer than 3 sensors the
#: rotation about the line through them is free). A sensor seen on one axis only contributes its
#: one angle. The cold starts (POSIT, IPPE) need 4 sensors seen on both axes; a frame that meets
#: the rule with fewer such sensors is solved from ``initial`` (e.g. a neighbouring frame's pose)
#: or gets STATUS_NO_START. Collinear sensors give STATUS_DEGENERATE. A solved frame with fewer
#: than MIN_ANGLES + MIN_REDUNDANCY seen angles cannot check itself: STATUS_LOW_REDUNDANCY
#: (the redundancy rule of :mod:`layoutkit.status`; pose returned, not ok).
MIN_ANGLES = _status.MIN_ANGLES
MIN_REDUNDANCY = _status.MIN_REDUNDANCY
MIN_SENSORS = 3
MIN_START_SENSORS = 4

STATUS_OK = _status.OK
STATUS_TOO_FEW = _status.TOO_FEW_LIT          # below the minimum rule: < 6 angles or < 3 sensors seen
STATUS_DEGENERATE = _status.DEGENERATE        # lit sensors (nearly) collinear, singular normal equations, or range unobservable
STATUS_NOT_CONVERGED = _status.NOT_CONVERGED  # refinement hit max_iterations without meeting the tolerance
STATUS_BEHIND = _status.BEHIND                # best pose puts a lit sensor at z <= 0 (behind the station)
STATUS_AMBIGUOUS = _status.AMBIGUOUS          # two distinct poses fit the angles equally well at the noise level
STATUS_INVALID_ANGLE = _status.INVALID_ANGLE  # a seen angle is infinite or outside (0, pi) rad: garbage or wrong units
STATUS_NO_START = _status.NO_START            # meets the rule, but < 4 sensors seen on both axes and no initial pose
STATUS_LOW_REDUNDANCY = _status.LOW_REDUNDANCY  # solved from 6 or 7 seen angles: cannot check itself
#: PnP statuses: codes of the one table (:mod:`layoutkit.status`) → description.
STATUS_NAMES = {c: _status.DESCRIPTIONS[c] for c in (STATUS_OK, STATUS_TOO_FEW, STATUS_DEGENERATE, STATUS_NOT_CONVERGED,
                                                      STATUS_BEHIND, STATUS_AMBIGUOUS, STATUS_INVALID_ANGLE,
                                                      STATUS_NO_START, STATUS_LOW_REDUNDANCY)}

DEFAULT_CHUNK = 4096
#: Lit sets with sqrt(lambda_min / lambda_max) of their centred body points below this get the two
#: planar (IPPE) candidates in addition to the POSIT start.
PLANARITY_THRESHOLD = 0.1
#: Below this planarity the lit set counts as exactly coplanar (no POSIT start).
COPLANAR_THRESHOLD = 1e-5
#: Lit sets with sqrt(lambda_mid / lambda_max) below this are collinear (degenerate).
COLLINEAR_THRESHOLD = 1e-5
#: Poses farther than this many RMS radii of the lit set are unobservable (STATUS_DEGENERATE).
MAX_RANGE_RATIO = 1e5
#: A refined solution whose angle-residual RMS exceeds this (rad) is retried from the planar
#: candidates (a wrong basin has residuals far above lighthouse noise, ~4e-5 rad).
RETRY_RESIDUAL = 1e-3
#: Two refined solutions are distinct poses (not one minimum reached twice) when their attitudes
#: differ by more than this (rad).
DISTINCT_ANGLE = 1e-2
#: Likelihood-ratio threshold of the ambiguity test: the runner-up is rejected when
#: ``(cost_2 - cost_1) / sigma^2 = -2 ln(L_2 / L_1)`` reaches this, i.e. it is at least 1000 times
#: less likely than the best pose (2 ln 1000); below, both are reported (STATUS_AMBIGUOUS).
AMBIGUITY_LR = 2.0 * np.log(1000.0)
_RTOL = 1e-6     # converged when the step lowers the cost by less than this fraction of it
_ATOL = 1e-26    # ... or by less than this (rad², per angle) — the noise-free floor


class PnPSolver(Protocol):
    """A batched PnP solver for one chunk of frames (an entry of :data:`PNP_SOLVERS`).

    points_body : (n, 3) or (F, n, 3) m; angles : (F, n, 2) rad; lit : (F, n, 2) bool per angle
    (or (F, n) per sensor), already cleaned (only finite angles in (0, pi) and finite points are
    lit); initial : ``(R (F, 3, 3), t (F, 3))`` or None; max_iterations : int; sigma : rad or None,
    the angle noise of the ambiguity test (STATUS_AMBIGUOUS), rho its same-rotor correlation.
    Returns a :class:`PnPResult`.
    """

    def __call__(self, points_body: np.ndarray, angles: np.ndarray, lit: np.ndarray,
                 initial, max_iterations: int, sigma: float | None = None, rho: float = 0.0) -> PnPResult: ...


# ------------------------------------------------------------------------------ chunk data
#
# Inside a chunk, per-sensor arrays are stored frames-last, (n, F), so that every elementwise
# operation runs over the long frame axis (numpy's inner loop) and sums over sensors are vector
# adds; per-frame scalars are (F,) arrays. This layout is 2-3x faster than (F, n) here.

class _Frames:
    """Per-chunk data: body points Px, Py, Pz ((n, 1) for a shared body, else (n, F)); image
    coordinates ux, uy = cot(theta) (n, F) (Chen eq. 2), zero where that angle is unlit; per-angle
    masks wx, wy (n, F) float; w = wx * wy, the sensors seen on both axes (the starts use only
    those); ``all_lit`` skips the masking; nl (F,) sensors seen on both axes; na (F,) seen angles;
    ns (F,) sensors seen on at least one axis."""

    def __init__(self, P, ang, lit):
        lit = np.asarray(lit, bool)
        if lit.ndim == 2:
            lit = np.repeat(lit[..., None], 2, -1)
        F, n = lit.shape[:2]
        any_lit = lit.any(-1)
        self.shared = P.ndim == 2
        if self.shared:
            self.Px, self.Py, self.Pz = (P[:, k, None].copy() for k in range(3))
        else:
            Pt = np.where(any_lit[..., None], P, 0.0).transpose(2, 1, 0)
            self.Px, self.Py, self.Pz = (np.ascontiguousarray(Pt[k]) for k in range(3))
        self.all_lit = bool(lit.all())
        lx, ly = lit[..., 0].T, lit[..., 1].T
        self.wx = np.ascontiguousarray(lx, dtype=float)
        self.wy = np.ascontiguousarray(ly, dtype=float)
        self.w = self.wx * self.wy
        th = np.ascontiguousarray(ang.transpose(2, 1, 0))  # (2, n, F)
        if self.all_lit:
            self.ux = 1.0 / np.tan(th[0])
            self.uy = 1.0 / np.tan(th[1])
        else:
            self.ux = np.where(lx, 1.0 / np.tan(np.where(lx, th[0], 1.0)), 0.0)
            self.uy = np.where(ly, 1.0 / np.tan(np.where(ly, th[1], 1.0)), 0.0)
        self.nl = self.w.sum(0)
        self.na = (self.wx + self.wy).sum(0)
        self.ns = np.maximum(self.wx, self.wy).sum(0)

    def take(self, idx):
        out = object.__new__(_Frames)
        out.shared = self.shared
        out.all_lit = self.all_lit
        for k in ("Px", "Py", "Pz"):
            v = getattr(self, k)
            setattr(out, k, v if self.shared else v[:, idx])
        for k in ("w", "wx", "wy", "ux", "uy"):
            setattr(out, k, getattr(self, k)[:, idx])
        for k in ("nl", "na", "ns"):
            setattr(out, k, getattr(self, k)[idx])
        if not out.all_lit:
            out.all_lit = bool(out.wx.all() and out.wy.all())
        return out

    def masked(self, a):
        return a if self.all_lit else a * self.w

    def points(self):
        """(F, n, 3) body points, zero where unlit."""
        P = np.stack([np.broadcast_to(v, self.w.shape) for v in (self.Px, self.Py, self.Pz)], -1)
        return P.transpose(1, 0, 2) * self.w.T[..., None]


def _atan_ratio(num, den):
    """atan2(num, den) for den > 0 and small |num / den| by a series, else exactly."""
    q = num / den
    qmax = np.max(np.abs(q), initial=0.0)
    if qmax < 0.05 and np.min(den, initial=1.0) > 0:
        q2 = q * q
        if qmax < 1e-2:  # Taylor series; truncation error below |q|^9 / 9 < 1.2e-19
            return q * (1.0 - q2 * (1.0 / 3.0 - q2 * (0.2 - q2 * (1.0 / 7.0))))
        # truncation error below |q|^15 / 15 < 2.1e-21
        return q * (1.0 - q2 * (1.0 / 3.0 - q2 * (0.2 - q2 * (1.0 / 7.0 - q2 * (1.0 / 9.0 - q2 * (
            1.0 / 11.0 - q2 * (1.0 / 13.0)))))))
    return np.arctan2(num, den)


def _eval(fr, r, t):
    """Lever ``l = R p_body``, station-frame points ``p = l + t`` and angle residuals of (R, t).

    r : (9, F) row-major rotation components, t : (3, F) m. The residual
    ``theta_meas - atan2(z, x)`` is the atan of the tangent of the difference,
    ``(x - u z) / (z + u x)`` with ``u = cot(theta_meas)`` (no cancellation), zero for unlit
    sensors. Returns a dict of (n, F) arrays and ``cost`` (F,) = sum of squared residuals.
    """
    Px, Py, Pz = fr.Px, fr.Py, fr.Pz
    lx = r[0] * Px + r[1] * Py + r[2] * Pz
    ly = r[3] * Px + r[4] * Py + r[5] * Pz
    lz = r[6] * Px + r[7] * Py + r[8] * Pz
    x = lx + t[0]
    y = ly + t[1]
    z = lz + t[2]
    if fr.all_lit:
        rx = _atan_ratio(x - fr.ux * z, z + fr.ux * x)
        ry = _atan_ratio(y - fr.uy * z, z + fr.uy * y)
    else:
        wx, wy = fr.wx, fr.wy
        rx = _atan_ratio((x - fr.ux * z) * wx, (z + fr.ux * x - 1.0) * wx + 1.0)
        ry = _atan_ratio((y - fr.uy * z) * wy, (z + fr.uy * y - 1.0) * wy + 1.0)
    cost = (rx * rx + ry * ry).sum(0)
    return {"lx": lx, "ly": ly, "lz": lz, "x": x, "y": y, "z": z, "rx": rx, "ry": ry, "cost": cost}


def _jacobian(fr, ev):
    """Rows of the angle Jacobian per sensor as (n, F) components (None for structural zeros).

    Per sensor with p = (x, y, z) in the station frame and lever l = R p_body (Chen eqs. 10–14 in
    the left-perturbation form of :func:`layoutkit.dop.angle_jacobian`, whose rows these are):
    ``d theta_x / d p = (-z, 0, x) / (x² + z²)``, ``d theta_y / d p = (0, -z, y) / (y² + z²)``,
    row = ``[l × d theta/d p, d theta/d p]``. Unlit sensors get zero rows.
    Returns ``(jx, jy)``, each a 6-tuple over (dphi, dt).
    """
    x, y, z, lx, ly, lz = ev["x"], ev["y"], ev["z"], ev["lx"], ev["ly"], ev["lz"]
    ix = 1.0 / (x * x + z * z)
    iy = 1.0 / (y * y + z * z)
    if fr.all_lit:
        a0, a2, b1, b2 = -z * ix, x * ix, -z * iy, y * iy
    else:  # per-angle masks: an axis that was not seen contributes no row
        a0 = -z * fr.wx * ix
        a2 = x * fr.wx * ix
        b1 = -z * fr.wy * iy
        b2 = y * fr.wy * iy
    jx = (ly * a2, lz * a0 - lx * a2, -ly * a0, a0, None, a2)
    jy = (ly * b2 - lz * b1, -lx * b2, lx * b1, None, b1, b2)
    return jx, jy


def _gradient(jx, jy, ev):
    """J^T r, a list of 6 (F,) arrays."""
    rx, ry = ev["rx"], ev["ry"]
    g = []
    for p in range(6):
        if jx[p] is None:
            g.append((jy[p] * ry).sum(0))
        elif jy[p] is None:
            g.append((jx[p] * rx).sum(0))
        else:
            g.append((jx[p] * rx + jy[p] * ry).sum(0))
    return g


def _gram(jx, jy):
    """Upper triangle of J^T J: A[p][q] (p <= q), (F,) arrays."""
    F = next(v for v in jx if v is not None).shape[1]
    A = [[None] * 6 for _ in range(6)]
    for p in range(6):
        for q in range(p, 6):
            s = None
            if jx[p] is not None and jx[q] is not None:
                s = jx[p] * jx[q]
            if jy[p] is not None and jy[q] is not None:
                s = jy[p] * jy[q] if s is None else s + jy[p] * jy[q]
            A[p][q] = np.zeros(F) if s is None else s.sum(0)
    return A


def _normal_equations(fr, ev):
    """``(A, g)``: upper triangle of J^T J (A[p][q], p <= q) and J^T r, as (F,) components."""
    jx, jy = _jacobian(fr, ev)
    return _gram(jx, jy), _gradient(jx, jy, ev)


def _cholesky_factor(A, lam):
    """Unrolled Cholesky factor of ``A + lam diag(A)`` per frame (A upper-triangle components).

    Returns ``(L, inv, ok)``: L[i][c] (i > c) and inv[c] = 1 / L[c][c], (F,) arrays, and ok (F,)
    False where a pivot is not positive (singular or rank-deficient normal equations).
    """
    scale = np.maximum(np.maximum.reduce([A[i][i] for i in range(6)]), 1e-300)
    ok = np.ones(scale.shape, bool)
    L = [[None] * 6 for _ in range(6)]
    inv = [None] * 6
    for c in range(6):
        s = A[c][c] * (1.0 + lam)
        for k in range(c):
            s = s - L[c][k] * L[c][k]
        good = s > 1e-14 * scale
        ok &= good
        inv[c] = 1.0 / np.sqrt(np.where(good, s, scale))
        for i in range(c + 1, 6):
            s = A[c][i]
            for k in range(c):
                s = s - L[i][k] * L[c][k]
            L[i][c] = s * inv[c]
    return L, inv, ok


def _cholesky_apply(L, inv, g):
    """Solve with a factor from :func:`_cholesky_factor`; g a list of 6 (F,) → (6, F)."""
    y = [None] * 6
    for i in range(6):
        s = g[i]
        for k in range(i):
            s = s - L[i][k] * y[k]
        y[i] = s * inv[i]
    xs = [None] * 6
    for i in range(5, -1, -1):
        s = y[i]
        for k in range(i + 1, 6):
            s = s - L[k][i] * xs[k]
        xs[i] = s * inv[i]
    return np.stack(xs)


def _subset_factor(fac, idx):
    L, inv = fac
    return ([[None if v is None else v[idx] for v in row] for row in L], [v[idx] for v in inv])


def _rodrigues(phi: np.ndarray) -> np.ndarray:
    """exp([phi]x) for phi (F, 3) rad → (F, 3, 3)."""
    return _exp_components(phi[:, 0], phi[:, 1], phi[:, 2]).T.reshape(-1, 3, 3)


def _exp_components(x, y, z) -> np.ndarray:
    """exp([phi]x) for phi = (x, y, z), each (F,) rad → (9, F) row-major components (Rodrigues,
    series for small angles)."""
    th2 = x * x + y * y + z * z
    small = th2 < 1e-8
    th = np.sqrt(np.where(small, 1.0, th2))
    a = np.where(small, 1.0 - th2 / 6.0 + th2 * th2 / 120.0, np.sin(th) / th)
    b = np.where(small, 0.5 - th2 / 24.0 + th2 * th2 / 720.0, (1.0 - np.cos(th)) / (th * th))
    bxy, bxz, byz = b * x * y, b * x * z, b * y * z
    ax, ay, az = a * x, a * y, a * z
    return np.stack([1.0 - b * (y * y + z * z), bxy - az, bxz + ay,
                     bxy + az, 1.0 - b * (x * x + z * z), byz - ax,
                     bxz - ay, byz + ax, 1.0 - b * (x * x + y * y)])


def _compose(E, r):
    """Row-major components (9, F) of the product E @ R of two (9, F) rotations."""
    out = np.empty_like(r)
    for i in range(3):
        e0, e1, e2 = E[3 * i], E[3 * i + 1], E[3 * i + 2]
        for j in range(3):
            out[3 * i + j] = e0 * r[j] + e1 * r[3 + j] + e2 * r[6 + j]
    return out


def _refine(fr, R, t, max_iterations):
    """Batched Levenberg–Marquardt on the angle residuals from the start (R, t).

    Each iteration evaluates the gradient J^T r at the current pose. If the step it gives with the
    previous iteration's factor of the normal matrix (which moved by ~1e-3 relative since) lowers
    the cost by less than the tolerance, the frame has converged and takes that step; otherwise
    the normal matrix is rebuilt and factored. So a frame that converges in two steps costs one
    full normal-equation build.

    R (F, 3, 3), t (F, 3). Returns R, t, cost (sum of squared residuals), iterations, converged,
    ok (normal equations solvable), depth (smallest and largest z of the lit sensors).
    """
    F = R.shape[0]
    r = np.ascontiguousarray(np.reshape(R, (F, 9)).T, dtype=float)  # (9, F)
    t = np.ascontiguousarray(np.transpose(t), dtype=float)          # (3, F)
    ev = _eval(fr, r, t)
    cost = ev.pop("cost")
    lam = np.full(F, 1e-6)
    iters = np.zeros(F, int)
    conv = np.zeros(F, bool)
    ok = np.ones(F, bool)
    act = np.arange(F)
    fac, fac_act = None, None
    for _ in range(max_iterations):
        if act.size == 0:
            break
        whole = act.size == F
        if whole:
            sub, evs, ra, ta, ca, la = fr, ev, r, t, cost, lam
        else:
            sub, evs = fr.take(act), {k: v[:, act] for k, v in ev.items()}
            ra, ta, ca, la = r[:, act], t[:, act], cost[act], lam[act]
        na = act.size
        tol = _RTOL * ca + _ATOL * 0.5 * sub.na
        jx, jy = _jacobian(sub, evs)
        g = _gradient(jx, jy, evs)
        G = np.stack(g)
        okc = np.ones(na, bool)
        if fac is not None:
            if fac_act.size != na:
                fac = _subset_factor(fac, np.searchsorted(fac_act, act))
            step = _cholesky_apply(*fac, g)
            dl = (step * G).sum(0)  # 2 x predicted decrease of the cost
            small = dl <= tol
        else:
            small = np.zeros(na, bool)
        if not small.any():
            L, inv, okc = _cholesky_factor(_gram(jx, jy), la)
            step = _cholesky_apply(L, inv, g)
            dl = (step * G).sum(0)
            small = okc & (dl <= tol)
            fac, fac_act = (L, inv), act
        elif not small.all():
            fi = np.flatnonzero(~small)
            jxf = tuple(None if v is None else v[:, fi] for v in jx)
            jyf = tuple(None if v is None else v[:, fi] for v in jy)
            L, inv, okf = _cholesky_factor(_gram(jxf, jyf), la[fi])
            stf = _cholesky_apply(L, inv, [v[fi] for v in g])
            step[:, fi] = stf
            dl[fi] = (stf * G[:, fi]).sum(0)
            small[fi] = okf & (dl[fi] <= tol[fi])
            okc[fi] = okf
            fac, fac_act = (L, inv), act[fi]
        rn = _compose(_exp_components(step[0], step[1], step[2]), ra)
        tn = ta + step[3:]
        # frames whose step is negligible take it without a new evaluation
        todo = okc & ~small
        if todo.all():
            evn = _eval(sub, rn, tn)
            better = evn["cost"] <= ca
            acc = better
        else:
            ti = np.flatnonzero(todo)
            evn = _eval(sub.take(ti), rn[:, ti], tn[:, ti])
            better = evn["cost"] <= ca[ti]
            acc = np.zeros(na, bool)
            acc[ti] = better
        take = acc | small
        cnew = np.where(small, np.maximum(ca - dl, 0.0), ca)
        if whole and acc.all():
            cost = evn.pop("cost")
            ev = evn
            r, t = rn, tn
        else:
            cn = evn.pop("cost")
            if todo.all():
                cnew = np.where(acc, cn, cnew)
                dst, srcsel = act[acc], acc
            else:
                cnew[ti[better]] = cn[better]
                dst, srcsel = act[ti[better]], better
            if dst.size:
                for k_, v in ev.items():
                    v[:, dst] = evn[k_][:, srcsel]
            if whole:
                cost = cnew
                r = np.where(take, rn, r)
                t = np.where(take, tn, t)
            else:
                cost[act] = cnew
                r[:, act[take]] = rn[:, take]
                t[:, act[take]] = tn[:, take]
        lnew = np.where(acc, np.maximum(la * 0.1, 1e-12), np.where(~take & okc, la * 10.0, la))
        if whole:
            lam = lnew
            iters += 1
        else:
            lam[act] = lnew
            iters[act] += 1
        conv[act[small]] = True
        ok[act[~okc]] = False
        act = act[~(small | ~okc | (lnew > 1e10))]
    z = ev["z"]
    seen = (fr.wx + fr.wy) > 0
    depth = (np.where(seen, z, np.inf).min(0), np.where(seen, z, -np.inf).max(0))
    return r.T.reshape(F, 3, 3), t.T.copy(), cost, iters, conv, ok, depth


# ------------------------------------------------------------------------------ starts

def _sym3_eigvals(S00, S11, S22, S01, S02, S12):
    """Eigenvalues (ascending) of symmetric 3 × 3 matrices given by (F,) components, closed form."""
    p1 = S01 * S01 + S02 * S02 + S12 * S12
    q = (S00 + S11 + S22) / 3.0
    p2 = (S00 - q) ** 2 + (S11 - q) ** 2 + (S22 - q) ** 2 + 2.0 * p1
    p = np.sqrt(p2 / 6.0)
    ps = np.where(p > 0, p, 1.0)
    B00, B11, B22 = (S00 - q) / ps, (S11 - q) / ps, (S22 - q) / ps
    B01, B02, B12 = S01 / ps, S02 / ps, S12 / ps
    detB = (B00 * (B11 * B22 - B12 * B12) - B01 * (B01 * B22 - B12 * B02)
            + B02 * (B01 * B12 - B11 * B02))
    phi = np.arccos(np.clip(detB / 2.0, -1.0, 1.0)) / 3.0
    e_hi = q + 2.0 * p * np.cos(phi)
    e_lo = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    e_mid = 3.0 * q - e_hi - e_lo
    return e_lo, e_mid, e_hi


def _scatter(fr, w=None):
    """Centroid c (F, 3) and scatter (S00, S11, S22, S01, S02, S12) (F,) of the lit body points
    (weights ``w`` (n, F); default the sensors seen on both axes)."""
    if w is None:
        w, nl = fr.w, np.maximum(fr.nl, 1.0)
    else:
        nl = np.maximum(w.sum(0), 1.0)
    F = nl.shape[0]
    P = (fr.Px, fr.Py, fr.Pz)
    if fr.shared and fr.all_lit:  # the same set in every frame: compute once
        Pm = np.concatenate(P, 1)
        c0 = Pm.mean(0)
        Q = Pm - c0
        S0 = Q.T @ Q
        c = np.broadcast_to(c0, (F, 3)).copy()
        S = tuple(np.full(F, S0[i, j]) for i, j in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)))
        return c, S
    c = np.stack([(w * v).sum(0) for v in P], -1) / nl[:, None]
    M = [(w * P[i] * P[j]).sum(0) for i, j in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))]
    S = tuple(M[k] - nl * c[:, i] * c[:, j]
              for k, (i, j) in enumerate(((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))))
    return c, S


def _normalize(v):
    return v / np.sqrt((v * v).sum(-1))[..., None]


def _orthonormal_pair(a, b):
    """Symmetric orthonormalisation of two 3-vectors per frame (F, 3) → (r1, r2)."""
    a = _normalize(a)
    b = _normalize(b)
    m = _normalize(a + b)
    d = _normalize(a - b)
    return (m + d) * np.sqrt(0.5), (m - d) * np.sqrt(0.5)


def _unit3(v):
    """Normalise a 3-vector given as a (3, F) array (or 3 (F,) arrays) → (3, F), and its norm."""
    v = np.asarray(v)
    nrm = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    return v / nrm, nrm


def _posit(fr, c, S, iterations=2):
    """Scaled-orthographic start with perspective correction (POSIT) in a virtual camera.

    The bearings are rotated so that the ray through the mean lit image point is the virtual
    boresight (where the small target is near the axis and weak perspective is accurate), POSIT
    (DeMenthon & Davis 1995) runs there, and the pose is rotated back. Non-coplanar lit sets only.
    c (F, 3) lit centroid, S the scatter components. Returns R (F, 3, 3), t (F, 3).
    Per-frame 3-vectors are handled as (3, F) component arrays.
    """
    ux, uy = fr.ux, fr.uy
    F = ux.shape[1]
    # virtual boresight: the ray through the mean image point of the lit sensors
    m, _ = _unit3([fr.masked(ux).sum(0), fr.masked(uy).sum(0), fr.nl])
    # Rc: the rotation taking m to e_z, I + [v]x + [v]x² / (1 + c) with v = m × e_z, c = m_z
    vx, vy, cz = m[1], -m[0], m[2]
    k = 1.0 / (1.0 + cz)
    kxy = k * vx * vy
    Rc = np.stack([1.0 - k * vy * vy, kxy, vy, kxy, 1.0 - k * vx * vx, -vx, -vy, vx, cz])  # (9, F)
    ibz = 1.0 / (Rc[6] * ux + Rc[7] * uy + cz)
    vxs = fr.masked((Rc[0] * ux + Rc[1] * uy + vy) * ibz)
    vys = fr.masked((Rc[3] * ux + Rc[4] * uy - vx) * ibz)
    # inverse of the scatter (adjugate / det)
    S00, S11, S22, S01, S02, S12 = S
    C00 = S11 * S22 - S12 * S12
    C01 = S02 * S12 - S01 * S22
    C02 = S01 * S12 - S02 * S11
    C11 = S00 * S22 - S02 * S02
    C12 = S01 * S02 - S00 * S12
    C22 = S00 * S11 - S01 * S01
    idet = 1.0 / (S00 * C00 + S01 * C01 + S02 * C02)
    Si = np.stack([C00, C01, C02, C01, C11, C12, C02, C12, C22]) * idet  # (9, F)
    nl = np.maximum(fr.nl, 1.0)
    ct = np.ascontiguousarray(c.T)
    Qx, Qy, Qz = fr.Px - ct[0], fr.Py - ct[1], fr.Pz - ct[2]
    if not fr.all_lit:
        Qx, Qy, Qz = Qx * fr.w, Qy * fr.w, Qz * fr.w
    ax, ay = vxs, vys
    r3 = iZ = None  # set by the first iteration, read from the second
    for it in range(iterations):
        if it:  # perspective correction 1 + eps_i = z_i / z_c
            e = 1.0 + (r3[0] * iZ) * Qx + (r3[1] * iZ) * Qy + (r3[2] * iZ) * Qz
            ax, ay = vxs * e, vys * e
        # I = S^-1 sum_n Q_n a_n (Q centred, so the image of the centroid drops out)
        qa = ((Qx * ax).sum(0), (Qy * ax).sum(0), (Qz * ax).sum(0))
        qb = ((Qx * ay).sum(0), (Qy * ay).sum(0), (Qz * ay).sum(0))
        I = [Si[3 * i] * qa[0] + Si[3 * i + 1] * qa[1] + Si[3 * i + 2] * qa[2] for i in range(3)]
        J = [Si[3 * i] * qb[0] + Si[3 * i + 1] * qb[1] + Si[3 * i + 2] * qb[2] for i in range(3)]
        I, nI = _unit3(I)
        J, nJ = _unit3(J)
        iZ = 0.5 * (nI + nJ)  # 1 / depth of the centroid
        # symmetric orthonormalisation of the two rows
        mm, _ = _unit3(I + J)
        dd, _ = _unit3(I - J)
        r1 = (mm + dd) * np.sqrt(0.5)
        r2 = (mm - dd) * np.sqrt(0.5)
        r3 = np.stack([r1[1] * r2[2] - r1[2] * r2[1], r1[2] * r2[0] - r1[0] * r2[2],
                       r1[0] * r2[1] - r1[1] * r2[0]])
    Z = 1.0 / iZ
    Rv = np.concatenate([r1, r2, r3])  # (9, F) rows of the virtual-camera rotation
    tv = [ax.sum(0) / nl * Z, ay.sum(0) / nl * Z, Z]
    tv = [tv[i] - (Rv[3 * i] * ct[0] + Rv[3 * i + 1] * ct[1] + Rv[3 * i + 2] * ct[2]) for i in range(3)]
    # back to the station frame: R = Rc^T Rv, t = Rc^T tv
    RcT = Rc[[0, 3, 6, 1, 4, 7, 2, 5, 8]]
    R = _compose(RcT, Rv)
    t = np.stack([RcT[3 * i] * tv[0] + RcT[3 * i + 1] * tv[1] + RcT[3 * i + 2] * tv[2] for i in range(3)], -1)
    return R.T.reshape(F, 3, 3), t


def _ippe_pair(fr, c):
    """The two poses of the planar ambiguity for the dominant plane of the lit set (IPPE).

    Fits the homography from in-plane coordinates (principal axes of the centred lit body points)
    to the normalised image coordinates, takes its Jacobian at the lit centroid ``c`` and
    decomposes it in closed form into the two plane poses (Collins & Bartoli 2014). Exact for
    noise-free coplanar points; a start for near-coplanar ones.
    Returns ``[(R_a, t_a), (R_b, t_b)]``, each (F, 3, 3), (F, 3).
    """
    w = fr.w.T  # (F, n)
    F = w.shape[0]
    Q = (fr.points() - c[:, None, :]) * w[..., None]
    S = np.matmul(Q.transpose(0, 2, 1), Q)
    _, V = np.linalg.eigh(S)  # ascending
    e1, e2 = V[..., 2], V[..., 1]
    e0 = np.cross(e1, e2)  # completes a proper body basis
    E = np.stack([e1, e2, e0], -1)
    nl = np.maximum(fr.nl, 1.0)
    u = np.stack([fr.ux.T, fr.uy.T], -1)
    # Hartley normalisation of both point sets
    sa = np.einsum("fnk,fk->fn", Q, e1)
    sb = np.einsum("fnk,fk->fn", Q, e2)
    m = np.maximum(np.sqrt(((sa * sa + sb * sb) * w).sum(1) / nl), 1e-300)[:, None]
    sa, sb = sa / m, sb / m
    ubar = (u * w[..., None]).sum(1) / nl[:, None]
    du = (u - ubar[:, None, :]) * w[..., None]
    k = np.maximum(np.sqrt((du * du).sum((1, 2)) / nl), 1e-300)[:, None]
    ux, uy = du[..., 0] / k, du[..., 1] / k
    # homography with h33 = 1: [h11 h12 h13 h21 h22 h23 h31 h32], linear least squares
    z = np.zeros_like(sa)
    rx = np.stack([sa, sb, w, z, z, z, -ux * sa, -ux * sb], -1)
    ry = np.stack([z, z, z, sa, sb, w, -uy * sa, -uy * sb], -1)
    Arows = np.concatenate([rx, ry], 1)  # (F, 2n, 8)
    rhs = np.concatenate([ux, uy], 1)
    AtA = np.matmul(Arows.transpose(0, 2, 1), Arows) + 1e-14 * np.eye(8)
    h = np.linalg.solve(AtA, np.matmul(Arows.transpose(0, 2, 1), rhs[..., None]))[..., 0]
    hx, hy = h[:, 2], h[:, 5]
    # Jacobian of the homography at the plane origin, de-normalised
    km = k[:, 0] / m[:, 0]
    j00 = (h[:, 0] - hx * h[:, 6]) * km
    j01 = (h[:, 1] - hx * h[:, 7]) * km
    j10 = (h[:, 3] - hy * h[:, 6]) * km
    j11 = (h[:, 4] - hy * h[:, 7]) * km
    p = ubar[:, 0] + k[:, 0] * hx
    q = ubar[:, 1] + k[:, 0] * hy
    # Rv: rotation taking e_z to the ray (p, q, 1)
    nr = np.sqrt(p * p + q * q + 1.0)
    axis = np.stack([-q, p, np.zeros(F)], -1)
    an = np.linalg.norm(axis, axis=1)
    angle = np.arccos(np.clip(1.0 / nr, -1.0, 1.0))
    Rv = _rodrigues(axis / np.where(an > 0, an, 1.0)[:, None] * angle[:, None])
    b00 = Rv[:, 0, 0] - p * Rv[:, 2, 0]
    b01 = Rv[:, 0, 1] - p * Rv[:, 2, 1]
    b10 = Rv[:, 1, 0] - q * Rv[:, 2, 0]
    b11 = Rv[:, 1, 1] - q * Rv[:, 2, 1]
    det = b00 * b11 - b01 * b10
    det = np.where(np.abs(det) > 1e-300, det, 1e-300)
    i00, i01, i10, i11 = b11 / det, -b01 / det, -b10 / det, b00 / det
    a00, a01 = i00 * j00 + i01 * j10, i00 * j01 + i01 * j11
    a10, a11 = i10 * j00 + i11 * j10, i10 * j01 + i11 * j11
    t00, t01, t11 = a00 * a00 + a10 * a10, a00 * a01 + a10 * a11, a01 * a01 + a11 * a11
    gamma = np.sqrt(np.maximum(0.5 * (t00 + t11 + np.sqrt((t00 - t11) ** 2 + 4 * t01 * t01)), 1e-300))
    r00, r01, r10, r11 = a00 / gamma, a01 / gamma, a10 / gamma, a11 / gamma
    b0 = np.sqrt(np.maximum(1.0 - r00 * r00 - r10 * r10, 0.0))
    b1 = np.sqrt(np.maximum(1.0 - r01 * r01 - r11 * r11, 0.0))
    b1 = np.where(r00 * r01 + r10 * r11 > 0, -b1, b1)  # the two columns orthogonal
    tz = 1.0 / gamma
    out = []
    for sgn in (1.0, -1.0):
        c1, c2 = _orthonormal_pair(np.stack([r00, r10, sgn * b0], -1), np.stack([r01, r11, sgn * b1], -1))
        Rt = np.stack([c1, c2, np.cross(c1, c2)], -1)
        R = np.matmul(np.matmul(Rv, Rt), E.transpose(0, 2, 1))
        t = np.stack([p * tz, q * tz, tz], -1) - np.einsum("fij,fj->fi", R, c)
        out.append((R, t))
    return out


# ------------------------------------------------------------------------------ solver

def _noise_quadratic(fr, ev, sigma: float, rho: float) -> np.ndarray:
    """(F,) ``r^T Sigma^-1 r`` of the angle residuals under Chen eq. 19's noise: variance sigma², the
    same-axis angles of one frame correlated with rho. Per axis, with n lit sensors,
    ``Sigma^-1 = (I - rho / (1 - rho + n rho) 1 1^T) / (sigma² (1 - rho))`` (Sherman–Morrison)."""
    rho = min(max(float(rho), 0.0), 1.0 - 1e-9)
    q = 0.0
    for r, w in ((ev["rx"], fr.wx), (ev["ry"], fr.wy)):  # unseen angles have zero residuals
        c = rho / (1.0 - rho + w.sum(0) * rho)  # n = the angles seen on this axis
        q = q + (r * r).sum(0) - c * r.sum(0) ** 2
    return q / (float(sigma) ** 2 * (1.0 - rho))


def solve_pnp_lm(points_body, angles, lit, initial=None, max_iterations: int = 20, sigma: float | None = None,
                 rho: float = RHO_PAPER) -> PnPResult:
    """Levenberg–Marquardt PnP on one chunk (see the module docstring; shapes as :class:`PnPSolver`).

    sigma : rad, and rho : the angle noise (Chen eq. 19) of the ambiguity test (sigma None: no
    test). The best distinct runner-up among the refined candidates (the other planar solution)
    is kept; when the likelihood-ratio statistic ``-2 ln(L_2 / L_1) = q(r_2) - q(r_1)``
    (:func:`_noise_quadratic` of the two residual vectors) is below :data:`AMBIGUITY_LR` the
    frame is STATUS_AMBIGUOUS and both poses are returned.
    """
    lit = np.asarray(lit, bool)
    F, n = lit.shape[:2]
    fr = _Frames(np.asarray(points_body, float), np.asarray(angles, float), lit)
    c, S = _scatter(fr)  # of the sensors seen on both axes: the starts' input
    e_lo, _, e_hi = _sym3_eigvals(*S)
    planarity = np.sqrt(np.maximum(e_lo, 0.0) / np.maximum(e_hi, 1e-300))
    # collinear: lambda_mid / lambda_max ~ (sum of principal 2x2 minors) / trace² (no eigen-solve,
    # whose double-zero eigenvalue is only accurate to sqrt(eps)), over every sensor seen
    Sa = S if fr.all_lit else _scatter(fr, np.maximum(fr.wx, fr.wy))[1]
    S00, S11, S22, S01, S02, S12 = Sa
    minors = S00 * S11 - S01 * S01 + S00 * S22 - S02 * S02 + S11 * S22 - S12 * S12
    trace = S00 + S11 + S22
    collinear = minors <= COLLINEAR_THRESHOLD ** 2 * trace * trace
    size = np.sqrt(np.maximum(trace, 0.0) / np.maximum(fr.ns, 1.0))  # RMS radius of the lit set

    status = np.full(F, STATUS_TOO_FEW)
    valid = (fr.na >= MIN_ANGLES) & (fr.ns >= MIN_SENSORS)
    status[valid & collinear] = STATUS_DEGENERATE
    todo = valid & ~collinear
    startable = fr.nl >= MIN_START_SENSORS

    best_R = np.full((F, 3, 3), np.nan)
    best_t = np.full((F, 3), np.nan)
    best_cost = np.full(F, np.inf)
    best_it = np.zeros(F, int)
    best_status = np.full(F, STATUS_DEGENERATE)
    alt_R = np.full((F, 3, 3), np.nan)
    alt_t = np.full((F, 3), np.nan)
    alt_cost = np.full(F, np.inf)

    def distinct(Ra, Rb):
        c = (np.einsum("fij,fij->f", Ra, Rb) - 1.0) / 2.0  # cos of the angle between the attitudes
        return ~(np.clip(c, -1.0, 1.0) > np.cos(DISTINCT_ANGLE))

    def keep_alt(j, R, t, cost):
        """Candidates (R, t, cost) for frames j: the cheapest one distinct from the best is the runner-up."""
        take = (cost < alt_cost[j]) & distinct(R, best_R[j])
        k = j[take]
        alt_R[k], alt_t[k], alt_cost[k] = R[take], t[take], cost[take]

    def consider(idx, R0, t0):
        sub = fr if idx.size == F else fr.take(idx)
        R, t, cost, it, conv, ok, (zmin, zmax) = _refine(sub, R0, t0, max_iterations)
        # a pose at a range of more than MAX_RANGE_RATIO body sizes is unobservable (e.g. all
        # lit sensors on one ray: the cost goes to zero as the range goes to infinity)
        ok = ok & np.isfinite(cost) & (zmax <= MAX_RANGE_RATIO * size[idx])
        st = np.where(~ok, STATUS_DEGENERATE, np.where(zmin <= 0, STATUS_BEHIND,
                      np.where(conv, STATUS_OK, STATUS_NOT_CONVERGED)))
        prev_ok = best_status[idx] == STATUS_OK
        better = np.where(st == STATUS_OK, ~prev_ok | (cost < best_cost[idx]),
                          ~prev_ok & ok & (cost < best_cost[idx]))
        j = idx[better]
        jw = idx[better & prev_ok]  # an ok best displaced by a better one may be the runner-up
        old = (best_R[jw].copy(), best_t[jw].copy(), best_cost[jw].copy())
        best_R[j], best_t[j], best_cost[j] = R[better], t[better], cost[better]
        best_it[j], best_status[j] = it[better], st[better]
        if sigma is not None:
            same = np.isfinite(alt_cost[j]) & ~distinct(alt_R[j], best_R[j])
            alt_cost[j[same]] = np.inf  # a runner-up that is the new best's pose is no runner-up
            keep_alt(jw, *old)
            cand = ~better & (st == STATUS_OK)
            keep_alt(idx[cand], R[cand], t[cand], cost[cand])

    def poor(idx, limit=RETRY_RESIDUAL):
        rms = np.sqrt(best_cost[idx] / np.maximum(fr.na[idx], 1))
        return (best_status[idx] != STATUS_OK) | ~(rms <= limit)

    # a cold solution with a residual far above the noise also gets the planar candidates
    retry = RETRY_RESIDUAL if not sigma else min(RETRY_RESIDUAL, 5.0 * float(sigma))

    cold = todo.copy()
    tried_initial = np.zeros(F, bool)
    if initial is not None:
        R0, t0 = initial
        idx = np.flatnonzero(todo & np.all(np.isfinite(R0), (1, 2)) & np.all(np.isfinite(t0), 1))
        if idx.size:
            Ri = ensure_rotation(R0[idx])  # not a rotation: start from the nearest one
            consider(idx, Ri, t0[idx])
            tried_initial[idx] = True
            cold[idx[~poor(idx)]] = False

    no_start = cold & ~startable
    if no_start.any():  # the cold starts need 4 sensors seen on both axes
        best_status[no_start & ~tried_initial] = STATUS_NO_START
        cold &= startable
    idx = np.flatnonzero(cold & (planarity > COPLANAR_THRESHOLD))
    if idx.size:
        sub = fr if idx.size == F else fr.take(idx)
        R0, t0 = _posit(sub, c[idx], tuple(s[idx] for s in S))
        consider(idx, R0, t0)
    tried = np.flatnonzero(cold)
    need = np.zeros(F, bool)
    need[tried] = (planarity[tried] < PLANARITY_THRESHOLD) | poor(tried, retry)
    idx = np.flatnonzero(need)
    if idx.size:
        for R0, t0 in _ippe_pair(fr.take(idx), c[idx]):
            consider(idx, R0, t0)

    status[todo] = best_status[todo]
    res = np.sqrt(best_cost / np.maximum(fr.na, 1))
    res[~todo | ~np.isfinite(best_cost)] = np.nan
    amb = np.zeros(F, bool)
    if sigma is not None and sigma > 0:  # sigma = 0: noise-free data, the lower cost decides
        k = np.flatnonzero(todo & (status == STATUS_OK) & np.isfinite(alt_cost))
        if k.size:
            sub = fr.take(k)
            q1 = _noise_quadratic(sub, _eval(sub, best_R[k].reshape(-1, 9).T, best_t[k].T), sigma, rho)
            q2 = _noise_quadratic(sub, _eval(sub, alt_R[k].reshape(-1, 9).T, alt_t[k].T), sigma, rho)
            amb[k[q2 - q1 < AMBIGUITY_LR]] = True
        status[amb] = STATUS_AMBIGUOUS
    alt_R[~amb] = np.nan
    alt_t[~amb] = np.nan
    alt_res = np.where(amb, np.sqrt(alt_cost / np.maximum(fr.na, 1)), np.nan)
    return PnPResult(rotation=best_R, translation=best_t, success=status == STATUS_OK,
                     status=status, residual_rms=res, iterations=best_it,
                     alt_rotation=alt_R, alt_translation=alt_t, alt_residual_rms=alt_res)


def _with_status(r: PnPResult, where, status: int) -> PnPResult:
    """``r`` with the frames ``where`` (F,) set to ``status`` and no pose."""
    st = np.where(where, status, r.status)
    R = np.where(where[:, None, None], np.nan, r.rotation)
    t = np.where(where[:, None], np.nan, r.translation)
    res = np.where(where, np.nan, r.residual_rms)
    alts = {}
    if r.alt_rotation is not None:
        alts = {"alt_rotation": np.where(where[:, None, None], np.nan, r.alt_rotation),
                "alt_translation": np.where(where[:, None], np.nan, r.alt_translation),
                "alt_residual_rms": np.where(where, np.nan, r.alt_residual_rms)}
    return PnPResult(R, t, st == STATUS_OK, st, res, np.where(where, 0, r.iterations), **alts)


def _with_redundancy(r: PnPResult, n_angles) -> PnPResult:
    """``r`` with its ok frames that have fewer than ``MIN_ANGLES + MIN_REDUNDANCY`` seen angles
    (``n_angles`` (F,)) set to :data:`STATUS_LOW_REDUNDANCY`, pose and residual kept."""
    low = (np.asarray(r.status) == STATUS_OK) & (np.asarray(n_angles) < MIN_ANGLES + MIN_REDUNDANCY)
    if not low.any():
        return r
    st = np.where(low, STATUS_LOW_REDUNDANCY, r.status)
    return replace(r, status=st, success=st == STATUS_OK)


def _compiled_outputs(F: int) -> tuple:
    """The arrays :func:`solve_pnp_compiled` writes: rotation (F, 3, 3), translation (F, 3), status (F,)
    int64, residual_rms (F,), iterations (F,) int64, alt_rotation (F, 3, 3), alt_translation (F, 3),
    alt_residual_rms (F,) (uninitialised; every frame is written)."""
    return (np.empty((F, 3, 3)), np.empty((F, 3)), np.empty(F, np.int64), np.empty(F), np.empty(F, np.int64),
            np.empty((F, 3, 3)), np.empty((F, 3)), np.empty(F))


def _compiled_result(out: tuple) -> PnPResult:
    """The :class:`PnPResult` over the arrays of :func:`_compiled_outputs` (as the kernel wrote them)."""
    R, t, st, res, it, aR, at, ares = out
    return PnPResult(R, t, st == STATUS_OK, st, res, it, aR, at, ares)


_COMPILED_FIELDS = ("rotation", "translation", "status", "residual_rms", "iterations", "alt_rotation",
                    "alt_translation", "alt_residual_rms")

#: Frames from which the compiled solver spreads a chunk over threads (below, one thread: the
#: thread pool's start-up costs more than it saves), and frames per thread task.
PARALLEL_MIN_FRAMES = 256
PARALLEL_BLOCK = 32


def solve_pnp_compiled(points_body, angles, lit, initial=None, max_iterations: int = 20, sigma: float | None = None,
                       rho: float = RHO_PAPER, out=None) -> PnPResult:
    """:func:`solve_pnp_lm` compiled: the same algorithm per frame in one numba kernel
    (:mod:`layoutkit.pnp_numba`; shapes as :class:`PnPSolver`). Same statuses and poses as the numpy
    reference to rounding (``tests/test_pnp_compiled.py``); chunks of at least
    :data:`PARALLEL_MIN_FRAMES` frames run on numba's threads. Compiled on first use, cached on disk.

    out: optional arrays the kernel writes into (:func:`_compiled_outputs`, F frames each, e.g. one
    chunk's slices of the whole batch's outputs); the result holds them. Allocated when None."""
    from . import pnp_numba

    P = np.asarray(points_body, float)
    lit = np.asarray(lit, bool)
    if lit.ndim == 2:
        lit = np.repeat(lit[..., None], 2, -1)
    lit = np.ascontiguousarray(lit)
    ang = np.asarray(angles, dtype=float)
    # cot(theta) here, not per frame in the kernel: numpy's SIMD tan is ~10x the scalar libm call the
    # kernel would make (the values are the reference's, _Frames)
    # (in place: a second (F, n, 2) temporary costs more in page faults than the tangents)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        cot = np.tan(ang) if lit.all() else np.where(lit, np.tan(np.where(lit, ang, 1.0)), 1.0)
        np.divide(1.0, cot, out=cot)
    F = lit.shape[0]
    has = np.zeros(F, bool)
    R0, t0 = np.zeros((1, 3, 3)), np.zeros((1, 3))  # read only where has (no per-frame zeros to fault in)
    if initial is not None:
        Ri = np.array(initial[0], float)
        ti = np.asarray(initial[1], float)
        has = np.all(np.isfinite(Ri), (1, 2)) & np.all(np.isfinite(ti), 1)
        idx = np.flatnonzero(has)
        if idx.size:
            R0, t0 = np.zeros((F, 3, 3)), np.zeros((F, 3))
            Rs = ensure_rotation(Ri[idx])  # not a rotation: start from the nearest one (as solve_pnp_lm)
            R0[idx], t0[idx] = Rs, ti[idx]
    consts = np.array([MIN_ANGLES, MIN_SENSORS, MIN_START_SENSORS, PLANARITY_THRESHOLD, COPLANAR_THRESHOLD,
                       COLLINEAR_THRESHOLD, RETRY_RESIDUAL, np.cos(DISTINCT_ANGLE), AMBIGUITY_LR], float)
    if out is None:
        out = _compiled_outputs(F)
    args = (np.ascontiguousarray(P[None] if P.ndim == 2 else P), P.ndim == 2, cot, lit, R0, t0, has,
            int(max_iterations), np.nan if sigma is None else float(sigma), float(rho), consts)
    if F >= PARALLEL_MIN_FRAMES:
        pnp_numba.solve_batch_parallel(*args, PARALLEL_BLOCK, *out)
    else:
        pnp_numba.solve_batch(*args, *out)
    return _compiled_result(out)  # runner-ups: NaN except ambiguous frames (as solve_pnp_lm)


#: Registry of batched PnP solvers (the names the CLI offers): ``lm`` the compiled kernel,
#: ``lm-numpy`` the numpy reference it is tested against (the same algorithm, frames-last arrays).
PNP_SOLVERS: "dict[str, PnPSolver]" = {"lm": solve_pnp_compiled, "lm-numpy": solve_pnp_lm}


def solve_pnp_lh1(points_body, angles, visible=None, *, initial=None, max_iterations: int = 20,
                  method: str = "lm", chunk_size: int = DEFAULT_CHUNK,
                  sigma: float | None = SIGMA_THETA_PAPER, rho: float = RHO_PAPER) -> PnPResult:
    """Poses from the LH1 sweep angles of one ideal station, batched over frames in chunks.

    The ideal-station path of :func:`layoutkit.pnp.solve_pnp` (arguments, shapes, units and
    statuses as documented there, without ``calibration``): validates the input, turns NaN, infinite
    and out-of-range angles into "not seen" (the latter two with :data:`STATUS_INVALID_ANGLE`), and
    runs the solver ``PNP_SOLVERS[method]`` on chunks of ``chunk_size`` frames.
    """
    if method not in PNP_SOLVERS:
        raise ValueError(f"method: expected one of {sorted(PNP_SOLVERS)}, got {method!r}")
    ang = as_array(angles, "angles", (..., None, 2))
    if ang.ndim == 2:
        ang = ang[None]
    if ang.ndim != 3:
        raise ValueError(f"angles: expected shape (F, n, 2) or (n, 2), got {ang.shape}")
    F, n = ang.shape[:2]
    P = as_array(points_body, "points_body", (..., None, 3))
    if (P.ndim == 2 and P.shape[0] != n) or P.ndim not in (2, 3) or (P.ndim == 3 and P.shape[:2] != (F, n)):
        raise ValueError(f"points_body: expected shape ({n}, 3) or ({F}, {n}, 3), got {P.shape}")
    if visible is None:
        vis = np.ones((F, n, 2), bool)
    else:
        vis = np.asarray(visible, bool)
        if vis.ndim == 1 and F == 1:
            vis = vis[None]
        if vis.shape == (F, n):
            vis = np.repeat(vis[..., None], 2, -1)
        elif vis.shape != (F, n, 2):
            raise ValueError(f"visible: expected shape ({F}, {n}) per sensor or ({F}, {n}, 2) per angle, "
                             f"got {vis.shape}")
    R0 = t0 = None
    if initial is not None:
        R0 = np.asarray(initial[0], float)
        t0 = np.asarray(initial[1], float)
        if R0.shape != (F, 3, 3) or t0.shape != (F, 3):
            raise ValueError(f"initial: expected shapes ({F}, 3, 3) and ({F}, 3), "
                             f"got {R0.shape} and {t0.shape}")
    if P.ndim == 2 and not np.all(np.isfinite(P)):
        P = np.broadcast_to(P, (F, n, 3))
    solver = PNP_SOLVERS[method]
    chunk = max(int(chunk_size), 1)
    parts = []
    # the compiled solver over several chunks writes each chunk into its slice of the whole batch's
    # outputs: no concatenation afterwards (a copy of every output, ~5 % of a compiled solve at n = 12)
    full = _compiled_outputs(F) if solver is solve_pnp_compiled and F > chunk else None
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for s in range(0, F, chunk):
            e = min(F, s + chunk)
            a = ang[s:e]
            p = P if P.ndim == 2 else P[s:e]
            # every angle seen and in (0, pi) (a NaN makes min / max NaN, which compares False): the usual
            # batch, all lit, nothing invalid — two reductions instead of the seven elementwise passes
            # below (~4 % of a compiled solve) or of two comparisons, their and, and all (~2 %)
            if visible is None and P.ndim == 2 and a.size and a.min() > 0 and a.max() < np.pi:
                lit, invalid = np.ones(a.shape, bool), None
            else:
                v = vis[s:e] & ~np.isnan(a)  # NaN = not seen
                good = np.isfinite(a) & (a > 0) & (a < np.pi)
                bad = v & ~good  # a seen angle that is inf or outside (0, pi)
                invalid = bad.any((1, 2)) if bad.any() else None  # (per frame only when there is one)
                lit = v & good
                if P.ndim == 3:
                    lit &= np.all(np.isfinite(p), -1)[..., None]
            ini = None if R0 is None else (R0[s:e], t0[s:e])
            n_angles = np.full(e - s, lit[0].size) if lit.all() else lit.sum((1, 2))
            o = None if full is None else tuple(x[s:e] for x in full)
            r = _with_redundancy(solver(p, a, lit, ini, max_iterations, sigma=sigma, rho=rho,
                                        **({} if o is None else {"out": o})), n_angles)
            if invalid is not None:
                r = _with_status(r, invalid, STATUS_INVALID_ANGLE)
            if o is None:
                parts.append(r)
                continue
            for dst, f in zip(o, _COMPILED_FIELDS):  # fields a status rule replaced: back into the slice
                src = getattr(r, f)
                if src is not dst:
                    dst[...] = src
    return concat_results(parts) if full is None else _compiled_result(full)
