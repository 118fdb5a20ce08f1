"""Pose from sweep angles through any forward model: calibrated, LH1 or LH2, one or several stations.

The fast solver in :mod:`layoutkit.pnp` is specialised to one ideal LH1 station. This module is the
general one: a batched Levenberg–Marquardt over frames that minimises the angle residuals
``angles - measure(p_s, calib_s)`` (:func:`layoutkit.lighthouse.measure`; residuals are never
pre-corrected) of all stations at once, the body pose in the stations' common world frame.

Model (per frame): ``p_world = R p_body + t``; station s sees ``p_s = R_s^T (p_world - T_s)``.
Perturbation as everywhere (design §2): ``R <- exp([dphi]x) R``, ``t <- t + dt``; the Jacobian row of
one angle is ``[l x a, a]`` with ``a = R_s (d angle / d p_s)`` and ``l = R p_body`` (as in
:func:`layoutkit.dop.angle_jacobian`, with the calibrated ``d angle / d p_s`` of
:func:`layoutkit.lighthouse.measure_jacobian`).

Optional motion compensation: station s's angles of a window were taken ``dt_s`` seconds from the
window time; with a body angular velocity ``omega`` (rad/s, world frame) and velocity ``v`` (m/s)
the pose station s saw is ``R_s' = exp([omega dt_s]x) R``, ``t_s' = t + v dt_s`` (constant
velocity across the window); the rotation Jacobian becomes ``l x (E^T a)`` with ``E = exp([omega dt_s]x)``.

Start: every station alone through the ideal-LH1 solver :func:`layoutkit.pnp_lh1.solve_pnp_lh1`
(its angles first undistorted by :func:`layoutkit.lighthouse.undistort` and, for LH2, turned into
LH1-equivalent angles — for the start only), taken to the world frame; per frame the start with the lowest joint cost wins.
"""
from __future__ import annotations

import numpy as np

from ._validate import as_array
from .geometry import rotvec_to_matrix
from .lighthouse import Station, lh2_to_lh1_angles, measure_jacobian, undistort
from .pnp_lh1 import solve_pnp_lh1
from .pnp_result import PnPResult, concat_results
from .status import AMBIGUOUS as STATUS_AMBIGUOUS, BEHIND as STATUS_BEHIND, DEGENERATE as STATUS_DEGENERATE
from .status import LOW_REDUNDANCY as STATUS_LOW_REDUNDANCY, MIN_ANGLES, MIN_REDUNDANCY
from .status import NOT_CONVERGED as STATUS_NOT_CONVERGED, OK as STATUS_OK, TOO_FEW_LIT as STATUS_TOO_FEW

__all__ = ["solve_joint", "JOINT_METHODS", "model_angles_jacobian", "group_windows", "window_angles", "ray_midpoints",
           "firmware_corrected_angles", "crossing_beam_positions", "MIN_ANGLES", "DEFAULT_CHUNK",
           "WINDOW_S"]

# MIN_ANGLES (6, the unknowns): fewest angles for a pose, fewer gives ``STATUS_TOO_FEW``; a pose
# from fewer than MIN_ANGLES + MIN_REDUNDANCY angles over all stations is ``STATUS_LOW_REDUNDANCY``
# (the redundancy rule of :mod:`layoutkit.status`).
DEFAULT_CHUNK = 2048
_RTOL = 1e-8      # converged when the LM step's predicted decrease is below this fraction of the cost
_ATOL = 1e-26     # ... plus this (rad², per two angles): the noise-free floor


def _wrap(a):
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def model_angles_jacobian(points_body, rotation, translation, stations, *, dt=None, velocity=None,
                          jacobian: bool = True):
    """Predicted angles of all stations and their Jacobian with respect to the world pose.

    points_body : (n, 3) m; rotation : (F, 3, 3), translation : (F, 3) m (world frame).
    stations : S :class:`Station` (pose, kind, calibration).
    dt : (F, S) s, optional time of each station's sweeps from the window time, or (F, S, 2) one
        time per station and axis; velocity :
        ``(omega (F, 3) rad/s, v (F, 3) m/s)`` (world frame), used with ``dt``.
    Returns ``angles (F, S, n, 2)``, ``J (F, S, n, 2, 6)`` (None without ``jacobian``) and the
    station-frame points ``p_s (F, S, n, 3)``.
    """
    P = np.asarray(points_body, float)
    R = np.asarray(rotation, float)
    t = np.asarray(translation, float)
    F = R.shape[0]
    lever = np.einsum("fij,nj->fni", R, P)                       # l = R p_body (F, n, 3)
    if dt is not None and velocity is not None and np.ndim(dt) == 3:
        # one time per station and axis (e.g. the two LH2 light planes ~P/3 apart): each axis'
        # angles and Jacobian rows from the pose at its own time
        parts = [model_angles_jacobian(P, R, t, stations, dt=np.asarray(dt, float)[..., k], velocity=velocity,
                                       jacobian=jacobian) for k in (0, 1)]
        A = np.stack([parts[0][0][..., 0], parts[1][0][..., 1]], -1)
        J = None if not jacobian else np.stack([parts[0][1][..., 0, :], parts[1][1][..., 1, :]], -2)
        return A, J, 0.5 * (parts[0][2] + parts[1][2])
    angs, jacs, pts = [], [], []
    for s, st in enumerate(stations):
        E = None
        if dt is not None and velocity is not None:
            d = np.asarray(dt, float)[:, s]
            E = rotvec_to_matrix(np.asarray(velocity[0], float) * d[:, None])
            lw = np.einsum("fij,fnj->fni", E, lever)
            tw = t + np.asarray(velocity[1], float) * d[:, None]
        else:
            lw, tw = lever, t
        pw = lw + tw[:, None, :]
        ps = (pw - st.translation) @ st.rotation                 # R_s^T (p_w - T_s)
        a, dp, _ = measure_jacobian(ps, st.calibration, st.kind, jacobian=jacobian)
        angs.append(a)
        pts.append(ps)
        if jacobian:
            aw = dp @ st.rotation.T                              # d angle / d p_world (F, n, 2, 3)
            if E is not None:
                aw_rot = np.einsum("fji,fnkj->fnki", E, aw)      # E^T a
            else:
                aw_rot = aw
            l = lever[:, :, None, :]
            J = np.empty(a.shape + (6,))
            J[..., :3] = np.cross(l, aw_rot)
            J[..., 3:] = aw
            jacs.append(J)
    A = np.stack(angs, 1) if angs else np.zeros((F, 0, P.shape[0], 2))
    return A, (np.stack(jacs, 1) if jacobian else None), np.stack(pts, 1)


def _start(P, ang, mask, stations):
    """Per-station starts in the world frame: list of (R (F,3,3), t (F,3), ok (F,)), the planar
    runner-ups (``PnPResult.alt_rotation``) included."""
    out = []
    for s, st in enumerate(stations):
        a = np.where(mask[:, s], ang[:, s], np.nan)
        if st.calibration is not None:
            a = undistort(a, st.calibration, max_iterations=20, tol=1e-9)
        if st.kind == "lh2":
            a = lh2_to_lh1_angles(a)
        lit = np.all(np.isfinite(a), -1)
        r = solve_pnp_lh1(P, a, lit)
        # an ambiguous or low-redundancy single-station pose is still a start: the joint fit decides
        ok = r.success | np.isin(r.status, (STATUS_NOT_CONVERGED, STATUS_AMBIGUOUS, STATUS_LOW_REDUNDANCY))
        Rw = np.einsum("ij,fjk->fik", st.rotation, np.where(ok[:, None, None], r.rotation, np.eye(3)))
        tw = np.where(ok[:, None], r.translation, 0.0) @ st.rotation.T + st.translation
        out.append((Rw, tw, ok))
        if r.alt_rotation is not None:                       # the planar runner-up is a start too
            alt = ok & np.all(np.isfinite(r.alt_rotation), (1, 2)) & np.all(np.isfinite(r.alt_translation), 1)
            if alt.any():
                Ra = np.einsum("ij,fjk->fik", st.rotation, np.where(alt[:, None, None], r.alt_rotation, np.eye(3)))
                ta = np.where(alt[:, None], r.alt_translation, 0.0) @ st.rotation.T + st.translation
                out.append((Ra, ta, alt))
    return out


def _cost(P, R, t, stations, meas, mask, dt, vel, jacobian):
    A, J, ps = model_angles_jacobian(P, R, t, stations, dt=dt, velocity=vel, jacobian=jacobian)
    r = np.where(mask, _wrap(meas - A), 0.0)
    return np.sum(r * r, axis=(1, 2, 3)), r, J, ps


def _factor(A, lam):
    """Cholesky factor of ``M = A + lam diag(A)`` per frame (A (f, 6, 6), numpy): L (f, 6, 6) and ok (f,),
    False where a pivot L[c, c]^2 is not above 1e-14 max diag(A) (the compiled core's test)."""
    M = A + lam[:, None, None] * (np.eye(6) * np.diagonal(A, axis1=1, axis2=2)[:, None, :])
    scale = np.maximum(np.max(np.diagonal(A, axis1=1, axis2=2), 1), 1e-300)
    L = np.full(A.shape, np.nan)
    ok = np.zeros(len(A), bool)
    good = np.flatnonzero(np.all(np.isfinite(M), (1, 2)))
    try:
        L[good] = np.linalg.cholesky(M[good])
        ok[good] = True
    except np.linalg.LinAlgError:                # one frame is not positive definite: frame by frame
        for i in good:
            try:
                L[i] = np.linalg.cholesky(M[i])
                ok[i] = True
            except np.linalg.LinAlgError:
                pass
    ok &= np.all(np.diagonal(L, axis1=1, axis2=2) ** 2 > 1e-14 * scale[:, None], 1)
    return L, ok


def _apply(L, g):
    """(L L^T)^-1 g per frame (L (f, 6, 6) from :func:`_factor`, g (f, 6)) → (f, 6)."""
    y = np.linalg.solve(L, g[..., None])
    return np.linalg.solve(np.swapaxes(L, 1, 2), y)[..., 0]


def _lm(P, R, t, stations, meas, mask, dt, vel, max_iterations):
    """Batched Levenberg–Marquardt over the frames from (R, t): the numpy reference of the compiled
    solve, with the rule of the shared LM core (:func:`layoutkit.lm_numba.make_refine`, as
    :func:`layoutkit.pnp_lh1._refine`): a step is first tried with the previous iteration's factor of
    ``A + lam diag(A)``; converged when the step's predicted decrease ``step . g`` is at most
    ``_RTOL cost + _ATOL m / 2`` (that step taken without an evaluation); damping ×0.1 on an accepted
    step (``cost_new <= cost``, floor 1e-12), ×10 on a rejected one, given up above 1e10 or when the
    factor fails. Returns R, t, the cost, converged, iterations, and the station-frame points and the
    Jacobian of the last accepted evaluated pose (the converged step after it is below the tolerance)."""
    F = R.shape[0]
    R, t = R.copy(), t.copy()
    cost, r, J, ps = _cost(P, R, t, stations, meas, mask, dt, vel, True)
    m = mask.sum(axis=(1, 2, 3))
    lam = np.full(F, 1e-6)
    its = np.zeros(F, int)
    conv = np.zeros(F, bool)
    Lf, have = np.zeros((F, 6, 6)), np.zeros(F, bool)
    act = np.arange(F)

    def sub(idx):
        return (None if dt is None else dt[idx], None if vel is None else (vel[0][idx], vel[1][idx]))

    for _ in range(max_iterations):
        if act.size == 0:
            break
        ca, la = cost[act], lam[act]
        tol = _RTOL * ca + _ATOL * 0.5 * m[act]
        Jm = (J[act] * mask[act][..., None]).reshape(act.size, -1, 6)
        g = np.einsum("fki,fk->fi", Jm, r[act].reshape(act.size, -1))
        step, dl = np.zeros((act.size, 6)), np.zeros(act.size)
        small, okc = np.zeros(act.size, bool), np.ones(act.size, bool)
        h = have[act]
        if h.any():                                   # the previous factor first
            step[h] = _apply(Lf[act[h]], g[h])
            dl[h] = np.sum(step[h] * g[h], 1)
            small[h] = dl[h] <= tol[h]
        need = ~small
        if need.any():                                # else a new factor at the current pose
            A = np.swapaxes(Jm[need], 1, 2) @ Jm[need]
            L, okf = _factor(A, la[need])
            step[need] = np.where(okf[:, None], _apply(np.where(okf[:, None, None], L, np.eye(6)), g[need]), np.nan)
            dl[need] = np.sum(step[need] * g[need], 1)
            small[need] = okf & (dl[need] <= tol[need])
            okc[need] = okf
            Lf[act[need]], have[act[need]] = L, True
        Rn = rotvec_to_matrix(np.nan_to_num(step[:, :3])) @ R[act]
        tn = t[act] + step[:, 3:]
        todo = okc & ~small
        acc = np.zeros(act.size, bool)
        if todo.any():
            ti = act[todo]
            d, v = sub(ti)
            cn, rn, Jn, psn = _cost(P, Rn[todo], tn[todo], stations, meas[ti], mask[ti], d, v, True)
            better = cn <= cost[ti]
            acc[todo] = better
            j = ti[better]
            cost[j], r[j], J[j], ps[j] = cn[better], rn[better], Jn[better], psn[better]
        cost[act[small]] = np.maximum(ca[small] - dl[small], 0.0)
        take = acc | small
        R[act[take]], t[act[take]] = Rn[take], tn[take]
        lnew = np.where(acc, np.maximum(la * 0.1, 1e-12), np.where(todo, la * 10.0, la))
        lam[act] = lnew
        its[act] += 1
        conv[act[small]] = True
        act = act[~(small | ~okc | (lnew > 1e10))]
    return R, t, cost, conv, its, ps, J


def solve_joint(points_body, angles, visible=None, *, stations, initial=None, dt=None, velocity=None,
                max_iterations: int = 30, chunk_size: int = DEFAULT_CHUNK, method: str = "lm") -> PnPResult:
    """Body poses in the stations' world frame from the angles of all stations at once.

    points_body : (n, 3) m, sensors in the body frame.
    angles : (F, S, n, 2) rad, each station's measured angles in its own kind's convention (LH1
        ``theta``, LH2 light-plane angles, as :func:`layoutkit.lighthouse.measure` predicts them);
        NaN = not seen. (F, n, 2) is accepted for S = 1.
    visible : optional (F, S, n) or (F, S, n, 2) bool (per sensor or per angle).
    stations : S :class:`Station` with poses in one world frame (and calibrations).
    initial : optional ``(R (F, 3, 3), t (F, 3))`` world start; default the per-station solves.
    dt, velocity : optional motion compensation (see :func:`model_angles_jacobian`; dt (F, S) or
        (F, S, 2) per axis).
    method : ``"lm"`` (default) the compiled kernel :mod:`layoutkit.joint_numba` (start selection and
        Levenberg–Marquardt per frame, on numba's threads), ``"lm-numpy"`` the numpy reference
        :func:`_lm` (the same steps; the tests hold the kernel to it). Keys of :data:`JOINT_METHODS`.
    Returns a :class:`layoutkit.pnp_result.PnPResult` (world frame; ``residual_rms`` over the used angles).
    Frames with fewer than ``MIN_ANGLES`` (6) usable angles (or no station start) get
    ``STATUS_TOO_FEW``; singular normal equations ``STATUS_DEGENERATE``; a used point behind its
    station ``STATUS_BEHIND``; a converged pose from fewer than ``MIN_ANGLES + MIN_REDUNDANCY`` (8)
    angles over all stations ``STATUS_LOW_REDUNDANCY`` (pose returned, not ok). Never raises on
    bad angle values.
    """
    stations = list(stations)
    S = len(stations)
    if S == 0:
        raise ValueError("stations: at least one station is required")
    if method not in JOINT_METHODS:
        raise ValueError(f"method: expected one of {list(JOINT_METHODS)}, got {method!r}")
    P = as_array(points_body, "points_body", (None, 3))
    n = P.shape[0]
    ang = np.asarray(angles, float)
    if ang.ndim == 3 and S == 1:
        ang = ang[:, None]
    if ang.ndim != 4 or ang.shape[1:] != (S, n, 2):
        raise ValueError(f"angles: expected shape (F, {S}, {n}, 2), got {ang.shape}")
    F = ang.shape[0]
    mask = np.isfinite(ang)
    if visible is not None:
        v = np.asarray(visible, bool)
        if v.ndim == 3:
            v = v[..., None]
        try:
            mask &= np.broadcast_to(v, mask.shape)
        except ValueError:
            raise ValueError(f"visible: expected shape (F, {S}, {n}) or (F, {S}, {n}, 2), got {v.shape}") from None
    if dt is not None:
        dt = np.asarray(dt, float)
        dt = np.broadcast_to(dt, (F, S, 2) if dt.ndim == 3 else (F, S))
    if velocity is not None:
        velocity = (np.broadcast_to(np.asarray(velocity[0], float), (F, 3)),
                    np.broadcast_to(np.asarray(velocity[1], float), (F, 3)))
    parts = []
    chunk = max(int(chunk_size), 1)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for s0 in range(0, F, chunk):
            e = min(F, s0 + chunk)
            ini = None if initial is None else (np.asarray(initial[0], float)[s0:e], np.asarray(initial[1], float)[s0:e])
            parts.append(_solve_chunk(P, ang[s0:e], mask[s0:e], stations, ini,
                                      None if dt is None else dt[s0:e],
                                      None if velocity is None else (velocity[0][s0:e], velocity[1][s0:e]),
                                      max_iterations, method))
    return concat_results(parts)


def _kernel_array(a, dtype) -> np.ndarray:
    """``a`` as a C-contiguous, writeable array of ``dtype``: numba compiles a kernel once per
    argument type, and a read-only view (``np.broadcast_to``, a buffer) is another type — each such
    variant cost ~15 s of compilation in a fresh checkout."""
    return np.require(a, dtype, ["C", "W"])


class _Compiled:
    """The chunk's arrays for :mod:`layoutkit.joint_numba` (station poses, kinds, calibrations;
    motion as (F, S, 2) times and (F, 3) velocities, zeros without)."""

    def __init__(self, P, meas, mask, stations, dt, vel):
        F, S = meas.shape[:2]
        self.P = _kernel_array(P, float)
        self.SR = _kernel_array(np.stack([st.rotation for st in stations]), float)
        self.ST = _kernel_array(np.stack([st.translation for st in stations]), float)
        self.kinds = np.array([0 if st.kind == "lh1" else 1 for st in stations], np.int64)
        self.cals = _kernel_array(np.stack([np.zeros((2, 7)) if st.calibration is None else
                                            st.calibration.params for st in stations]), float)
        self.corrected = np.array([st.calibration is not None and st.calibration.gib_argument == "corrected"
                                   for st in stations])
        self.meas = _kernel_array(meas, float)
        self.mask = _kernel_array(mask, bool)
        self.motion = dt is not None and vel is not None
        if self.motion:
            d = np.asarray(dt, float)
            self.dt = _kernel_array(np.broadcast_to(d if d.ndim == 3 else d[..., None], (F, S, 2)), float)
            self.omega = _kernel_array(vel[0], float)
            self.vel = _kernel_array(vel[1], float)
        else:
            self.dt, self.omega, self.vel = np.zeros((F, S, 2)), np.zeros((F, 3)), np.zeros((F, 3))

    def args(self):
        return (self.P, self.SR, self.ST, self.kinds, self.cals, self.corrected, self.meas, self.mask, self.dt,
                self.omega, self.vel, self.motion)


def _start_costs(P, meas, mask, stations, dt, vel, starts, kernel):
    """(K, F) joint cost of each start (inf where not a start)."""
    F = meas.shape[0]
    if kernel is not None:
        from . import joint_numba

        Rs = _kernel_array(np.stack([s[0] for s in starts]), float)
        ts = _kernel_array(np.stack([s[1] for s in starts]), float)
        ok = _kernel_array(np.stack([s[2] for s in starts]), bool)
        out = np.empty(ok.shape)
        joint_numba.start_costs(*kernel.args(), Rs, ts, ok, out)
        return out
    out = np.full((len(starts), F), np.inf)
    for k, (Rw, tw, ok) in enumerate(starts):
        if not ok.any():
            continue
        sub = (None if dt is None else dt[ok], None if vel is None else (vel[0][ok], vel[1][ok]))
        c = _cost(P, Rw[ok], tw[ok], stations, meas[ok], mask[ok], sub[0], sub[1], False)[0]
        out[k, ok] = np.where(np.isfinite(c), c, np.inf)
    return out


def _lm_compiled(kernel, R0, t0, go, max_iterations):
    """:func:`_lm` for the frames ``go`` through :func:`layoutkit.joint_numba.solve_frames`: the poses,
    cost, done, iterations, and per frame the final Gram matrix and the depth sums."""
    from . import joint_numba

    F = R0.shape[0]
    S, n = kernel.mask.shape[1:3]
    R, t = np.full((F, 3, 3), np.nan), np.full((F, 3), np.nan)
    cost, done, its = np.full(F, np.inf), np.zeros(F, bool), np.zeros(F, np.int64)
    A, zsum = np.zeros((F, 6, 6)), np.zeros((F, S, n))
    joint_numba.solve_frames(*kernel.args(), _kernel_array(R0, float), _kernel_array(t0, float),
                             _kernel_array(go, bool), int(max_iterations), _RTOL, _ATOL, R, t, cost, done, its, A, zsum)
    return R, t, cost, done, its, A, zsum


#: Joint solvers (:func:`solve_joint` ``method``): the compiled kernel and the numpy reference.
JOINT_METHODS = ("lm", "lm-numpy")


def _solve_chunk(P, ang, mask, stations, initial, dt, vel, max_iterations, method="lm") -> PnPResult:
    F = ang.shape[0]
    meas = np.where(mask, ang, 0.0)
    m = mask.sum(axis=(1, 2, 3))
    kernel = _Compiled(P, meas, mask, stations, dt, vel) if method == "lm" else None
    if initial is not None:
        R0, t0 = initial[0].copy(), initial[1].copy()
        have = np.all(np.isfinite(R0), (1, 2)) & np.all(np.isfinite(t0), 1)
    else:
        starts = _start(P, ang, mask, stations)
        best = np.full(F, np.inf)
        R0, t0 = np.tile(np.eye(3), (F, 1, 1)), np.zeros((F, 3))
        costs = _start_costs(P, meas, mask, stations, dt, vel, starts, kernel)
        for (Rw, tw, ok), c in zip(starts, costs):   # in order: the first of equal costs wins
            take = c < best
            R0[take], t0[take], best[take] = Rw[take], tw[take], c[take]
        have = np.isfinite(best)
    status = np.full(F, STATUS_TOO_FEW)
    R = np.full((F, 3, 3), np.nan)
    t = np.full((F, 3), np.nan)
    res = np.full(F, np.nan)
    its = np.zeros(F, int)
    go = have & (m >= MIN_ANGLES)
    if go.any():
        mk = mask[go]
        if kernel is not None:
            Rg, tg, cost, done, it, A, zsum = (v[go] for v in _lm_compiled(kernel, R0, t0, go, max_iterations))
            z = zsum / 2.0                                       # mean over the two axes' times
        else:
            sub = (None if dt is None else dt[go], None if vel is None else (vel[0][go], vel[1][go]))
            Rg, tg, cost, done, it, ps, J = _lm(P, R0[go].copy(), t0[go].copy(), stations, meas[go], mask[go],
                                              sub[0], sub[1], max_iterations)
            Jm = (J * mk[..., None]).reshape(Rg.shape[0], -1, 6)
            A = np.swapaxes(Jm, 1, 2) @ Jm
            z = ps[..., 2]
        w = np.linalg.eigvalsh(A / np.maximum(np.trace(A, axis1=1, axis2=2), 1e-300)[:, None, None])
        singular = w[:, 0] <= 1e-12 * w[:, -1]
        used = np.any(mk, -1)                                    # (f, S, n)
        behind = np.any(used & (z <= 0), axis=(1, 2))
        low = m[go] < MIN_ANGLES + MIN_REDUNDANCY                # cannot check itself
        st = np.where(singular, STATUS_DEGENERATE,
                      np.where(behind, STATUS_BEHIND, np.where(~done, STATUS_NOT_CONVERGED,
                                                               np.where(low, STATUS_LOW_REDUNDANCY, STATUS_OK))))
        status[go] = st
        R[go], t[go] = Rg, tg
        res[go] = np.sqrt(cost / m[go])
        its[go] = it
        bad = go.copy()
        bad[go] = st == STATUS_DEGENERATE
        R[bad], t[bad] = np.nan, np.nan
    return PnPResult(R, t, status == STATUS_OK, status, res, its)


#: Window rule: rows (one station's frame each) whose times lie within this many seconds of the
#: window's first row form one joint sample, at most one row per station (cflib's sample matcher
#: groups LH2 sweeps the same way).
WINDOW_S = 0.020


def group_windows(t, station, n_stations: int, window_s: float = WINDOW_S):
    """Group frame-table rows into joint time windows.

    t : (R,) s; station : (R,) int station index in ``[0, n_stations)`` (-1 = unknown: skipped).
    Rule, in time order: a window opens at the first row not yet taken and takes the following
    rows while ``t - t_open <= window_s`` and their station has no row in it yet; a second row of a
    station already in the window closes it (that row opens the next window).
    Returns ``rows (W, S)`` int (row index, -1 = station not in the window) and ``t_window (W,)``
    (mean time of the window's rows, s).
    """
    t = np.asarray(t, float)
    st = np.asarray(station, int)
    order = np.argsort(t, kind="stable")
    rows, times = [], []
    cur = np.full(n_stations, -1)
    t_open = None
    for r in order:
        s = st[r]
        if s < 0 or s >= n_stations or not np.isfinite(t[r]):
            continue
        if t_open is None or t[r] - t_open > window_s or cur[s] >= 0:
            if t_open is not None:
                rows.append(cur)
                times.append(float(np.mean(t[cur[cur >= 0]])))
            cur = np.full(n_stations, -1)
            t_open = t[r]
        cur[s] = r
    if t_open is not None:
        rows.append(cur)
        times.append(float(np.mean(t[cur[cur >= 0]])))
    if not rows:
        return np.zeros((0, n_stations), int), np.zeros(0)
    return np.stack(rows), np.asarray(times)


def window_angles(angles_rows, rows):
    """Per-row angles ``(R, n, 2)`` → per-window ``(W, S, n, 2)`` (NaN where a station is absent)."""
    a = np.asarray(angles_rows, float)
    out = np.full(rows.shape + a.shape[1:], np.nan)
    have = rows >= 0
    out[have] = a[rows[have]]
    return out


# ------------------------------------------------------------------ crossing-beam reference
# The Crazyflie firmware's own two-station position (crazyflie-firmware
# src/modules/src/lighthouse/lighthouse_position_est.c estimatePositionCrossingBeams with
# src/utils/src/lighthouse/lighthouse_geometry.c lighthouseGeometryGetPositionFromRayIntersection):
# per sensor seen by both stations, the ray of each station from its corrected (ideal) sweep
# angles, the midpoint of the two rays' closest points; the position is the mean over those sensors.
# Re-derived here from the geometry (no orientation; a reference to compare the joint solve with).


def ray_midpoints(origins, directions):
    """Closest points of two lines and their midpoint (Schneider & Eberly §10.8.2, the firmware's
    ``intersect_lines``).

    origins : (..., 2, 3) m, a point of each line; directions : (..., 2, 3) (any length).
    Returns ``(midpoint (..., 3) m, gap (..., ) m = distance between the closest points)``; NaN
    where the lines are (nearly) parallel (``a c - b² < 1e-12 a c``).
    """
    o = np.asarray(origins, float)
    u, v = np.asarray(directions, float)[..., 0, :], np.asarray(directions, float)[..., 1, :]
    w0 = o[..., 0, :] - o[..., 1, :]
    a, b, c = np.sum(u * u, -1), np.sum(u * v, -1), np.sum(v * v, -1)
    d, e = np.sum(u * w0, -1), np.sum(v * w0, -1)
    den = a * c - b * b
    bad = ~(np.abs(den) > 1e-12 * a * c)
    den = np.where(bad, 1.0, den)
    s = (b * e - c * d) / den                   # on line 0: o0 + s u
    q = (a * e - b * d) / den                   # on line 1: o1 + q v
    p0 = o[..., 0, :] + s[..., None] * u
    p1 = o[..., 1, :] + q[..., None] * v
    mid = np.where(bad[..., None], np.nan, 0.5 * (p0 + p1))
    return mid, np.where(bad, np.nan, np.linalg.norm(p0 - p1, axis=-1))


def firmware_corrected_angles(measured, station: Station, *, max_iterations: int = 5, tol: float = 5e-4):
    """Measured angles ``(..., n, 2)`` of ``station`` (its own convention) → LH1-equivalent ideal
    angles, as the firmware corrects them before the crossing-beam method: the calibration's
    fixed-point inverse (5 steps or 5e-4 rad, :func:`layoutkit.lighthouse.undistort`), then for LH2
    the light planes → sweep angles (:func:`layoutkit.lighthouse.lh2_to_lh1_angles`)."""
    a = np.asarray(measured, float)
    if station.calibration is not None:
        a = undistort(a, station.calibration, max_iterations=max_iterations, tol=tol)
    return lh2_to_lh1_angles(a) if station.kind == "lh2" else a


def crossing_beam_positions(theta, stations):
    """Two-station crossing-beam positions (the firmware's method; see the section comment).

    theta : (..., 2, n, 2) rad, LH1-equivalent ideal sweep angles of the two stations (NaN = not seen).
    stations : the two :class:`Station` (world poses).
    Returns ``(position (..., 3) m, world frame: the mean of the per-sensor midpoints over the
    sensors seen on both axes by both stations; NaN with none), n_used (...,) int, gap (..., )
    m, the mean distance between the two rays' closest points)``. The position is that of the mean
    of the used sensors' body positions (the deck's centre when all four are used).
    """
    from .lighthouse import angles_to_ray

    th = np.asarray(theta, float)
    if th.shape[-3] != 2 or len(stations) != 2:
        raise ValueError(f"theta: expected (..., 2, n, 2) for two stations, got {th.shape} and {len(stations)} stations")
    rays = angles_to_ray(th)                                          # (..., 2, n, 3) station frames
    dirs = np.stack([rays[..., s, :, :] @ st.rotation.T for s, st in enumerate(stations)], -2)  # (..., n, 2, 3)
    orig = np.broadcast_to(np.stack([st.translation for st in stations]), dirs.shape)
    mid, gap = ray_midpoints(orig, dirs)
    use = np.all(np.isfinite(th), axis=(-3, -1)) & np.all(np.isfinite(mid), -1)
    k = use.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        pos = np.where(use[..., None], mid, 0.0).sum(-2) / k[..., None]
        g = np.where(use, gap, 0.0).sum(-1) / k
    return np.where((k > 0)[..., None], pos, np.nan), k, np.where(k > 0, g, np.nan)
