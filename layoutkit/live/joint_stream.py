"""Joint multi-station solving on a stream: paired frames → 20 ms windows → one world pose per window.

Data flow (``LiveConfig.solve == "joint"``; docs/live.md "Joint solving")::

    AngleFrame ─▶ JointWindower ─▶ JointWindow ─▶ (batches) ─▶ solve_windows ─▶ PoseChunk
    (one station)  (reorder buffer +   (<= 1 frame per        layoutkit.joint.solve_joint:
                    the window rule)    station, time t)       residuals through each station's
                                                               calibrated forward model

Window rule (the one of :func:`layoutkit.joint.group_windows`, applied incrementally): frames in
time order; a window opens at the first frame not yet taken and takes the following frames while
``t - t_open <= window_s`` and their station has no frame in it yet; a second frame of a station
already in the window closes it (that frame opens the next window). The window time — the time the
joint pose describes — is the mean of its frames' measurement times (``AngleFrame.t_measured``: LH1
the X and Y sync times, LH2 the two light planes' crossing times; for frames without that, the
frame time). Frames may reach the windower slightly out of time order (a station's frame is
complete only when its second sweep arrives), so frames first wait in a reorder buffer until a frame
``reorder_s`` later has arrived; memory is bounded by the frames of ``reorder_s`` + one window.

Angles: each frame's ``raw`` angles in its station's own convention (LH1 sweep angles, LH2
light-plane angles, as the decoder measured them: distorted when the station has a calibration),
solved through :func:`layoutkit.lighthouse.measure` of each station (never pre-corrected).
Poses are in the stations' common world frame, ``station`` = :data:`JOINT` (``"joint"`` on
``--json-lines`` and in ``poses.csv``).
"""
from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np

from .. import status as _status
from ..io.poses import JOINT
from ..joint import WINDOW_S
from .continuity import continuity_gate, motion_history, recent_velocity
from .posechunk import PoseChunk, empty_pose_arrays

__all__ = ["JOINT", "JointWindow", "JointWindower", "window_arrays", "solve_windows", "crossing_beam_windows",
           "MOTION_MIN_SIGMA", "OUTLIER_P", "auto_sigma_limit", "drop_one_outlier"]

#: a window's motion is modelled (``motion_compensation``) when the known velocity changes its
#: angles by more than this many sigma_theta (RMS over its measurement times): below, the
#: uncompensated bias is negligible and the velocity estimate mostly noise (a deck at rest)
MOTION_MIN_SIGMA = 0.25

#: false-alarm probability of the one-outlier test of a window's angles (:func:`drop_one_outlier`);
#: 0 turns it off
OUTLIER_P = 1e-3


@dataclass(frozen=True)
class JointWindow:
    """One window: ``t`` s (mean of its frames' times), ``frames`` one :class:`AngleFrame` or None per
    station (index = station index)."""

    t: float
    frames: tuple

    @property
    def n_stations(self) -> int:
        return sum(f is not None for f in self.frames)


class JointWindower:
    """Incremental :func:`layoutkit.joint.group_windows` over :class:`AngleFrame` s.

    n_stations : stations known (frames of a station index outside ``[0, n_stations)`` are counted
    in ``unknown_station`` and skipped). window_s : the window rule's span (s). reorder_s : how long a
    frame waits for earlier frames of other stations (s; default one window span, longer than any
    station's pairing delay). ``push`` returns the windows closed by a frame, in time order;
    ``flush`` closes everything (end of stream).
    """

    def __init__(self, n_stations: int, window_s: float = WINDOW_S, reorder_s: float | None = None):
        self.n_stations = int(n_stations)
        self.window_s = float(window_s)
        self.reorder_s = self.window_s if reorder_s is None else float(reorder_s)
        self._heap: list = []   # (t, seq, frame) waiting for order
        self._seq = 0
        self._latest = -np.inf
        self._cur: list | None = None
        self._t_open = None
        self._last_released = -np.inf
        self.unknown_station = 0
        self.late = 0

    def push(self, frame) -> list[JointWindow]:
        s = int(frame.station)
        if not 0 <= s < self.n_stations or not np.isfinite(frame.t):
            self.unknown_station += 1
            return []
        if frame.t < self._last_released:
            # older than a frame already windowed: it cannot be placed in time order any more
            self.late += 1
            return []
        heapq.heappush(self._heap, (float(frame.t), self._seq, frame))
        self._seq += 1
        self._latest = max(self._latest, float(frame.t))
        out: list = []
        while self._heap and self._heap[0][0] <= self._latest - self.reorder_s:
            self._take(heapq.heappop(self._heap)[2], out)
        return out

    def flush(self) -> list[JointWindow]:
        out: list = []
        while self._heap:
            self._take(heapq.heappop(self._heap)[2], out)
        self._close(out)
        return out

    def _take(self, frame, out) -> None:
        s = int(frame.station)
        self._last_released = float(frame.t)
        if self._cur is None or frame.t - self._t_open > self.window_s or self._cur[s] is not None:
            self._close(out)
            self._cur = [None] * self.n_stations
            self._t_open = float(frame.t)
        self._cur[s] = frame

    def _close(self, out) -> None:
        if self._cur is None:
            return
        fr = [f for f in self._cur if f is not None]
        out.append(JointWindow(float(np.mean([f.t_measured for f in fr])), tuple(self._cur)))
        self._cur = None
        self._t_open = None


def window_arrays(windows, n_sensors: int, n_stations: int):
    """Windows → ``t (W,)``, ``angles (W, S, n, 2)`` rad (each station's own convention, NaN = not
    seen or station absent), ``dt (W, S, 2)`` s (each axis' measurement time − window time, 0 where
    absent), ``have (W, S)``."""
    W = len(windows)
    ang = np.full((W, n_stations, n_sensors, 2), np.nan)
    dt = np.zeros((W, n_stations, 2))
    have = np.zeros((W, n_stations), bool)
    t = np.fromiter((w.t for w in windows), float, W)
    for k, w in enumerate(windows):
        for s, f in enumerate(w.frames):
            if f is None:
                continue
            ang[k, s] = f.angles if f.raw is None else f.raw
            dt[k, s] = (np.asarray(f.t_axes, float) if f.t_axes is not None else f.t) - w.t
            have[k, s] = True
    return t, ang, dt, have


def crossing_beam_windows(windows, stations, n_sensors: int):
    """The firmware's crossing-beam position of every window both stations saw (the yardstick of
    ``benchmarks/bench_joint_crazyflie.py`` and the tests): each station's angles corrected as the
    firmware does (:func:`layoutkit.joint.firmware_corrected_angles`), then
    :func:`layoutkit.joint.crossing_beam_positions` over the sensors both stations lit.

    windows : JointWindow list over two stations; stations : the two :class:`Station` (world frame).
    Returns ``t (W',)`` s and ``pos (W', 3)`` m (world frame), for the windows where every one of the
    ``n_sensors`` sensors gave a crossing (the firmware's own rule for a position sample).
    """
    from ..joint import crossing_beam_positions, firmware_corrected_angles

    t, ang, _, have = window_arrays(windows, n_sensors, 2)
    both = have.all(1)
    th = np.stack([firmware_corrected_angles(ang[both, s], st) for s, st in enumerate(stations[:2])], 1)
    pos, k, _ = crossing_beam_positions(th, stations[:2])
    use = k == n_sensors
    return t[both][use], pos[use]


def solve_windows(points_body, windows, config, stations, state: dict | None = None):
    """Joint poses of a batch of windows → :class:`~layoutkit.live.posechunk.PoseChunk` (world frame).

    points_body : (n, 3) m. windows : list of :class:`JointWindow`. config : the run's
    :class:`~layoutkit.live.pipeline.LiveConfig` (``min_lit``, noise, residual limit, continuity
    gate, ``motion_compensation``). stations : the S :class:`~layoutkit.lighthouse.Station` (world
    poses, kinds, calibrations). state : dict kept between batches (the continuity gate's last pose
    and candidate, the motion history), updated in place.

    Statuses: fewer than ``min_lit`` sensors lit on both axes on every station of the window (no
    station can start the solve) → too_few_lit; the joint solve's own failure (degenerate, behind,
    not converged) → solver_failed; RMS residual above ``max_residual_sigma`` sigma → high_residual;
    a predicted 1-sigma position (``PDOP · sigma_theta`` at the pose with the lit sets, Chen eq. 24)
    above ``max_sigma_position`` (default :func:`auto_sigma_limit`) → imprecise; a jump from the
    recent joint track → jump (the per-station continuity gate, on the joint poses). The chunk
    carries ``stations_used`` (stations with a sensor lit on both axes in the window).
    With ``motion_compensation`` each station's angles are modelled at their own time in the window
    (constant body velocity from the recent joint poses, :func:`layoutkit.joint.solve_joint`
    ``dt``/``velocity``) and the window is solved again from the first pose — where the velocity is
    known and moves the angles by more than :data:`MOTION_MIN_SIGMA` sigma across the window. The
    high_residual limit is ``max_residual_sigma * sqrt(sigma² + sm²)`` with ``sm`` the known motion's
    RMS angle change for windows solved as static (0 where it was modelled; :func:`_motion_sigma`).
    """
    from ..dop import pose_dop
    from ..geometry import matrix_to_rotvec
    from ..joint import solve_joint

    state = {} if state is None else state
    P = np.asarray(points_body, float)
    n, S = P.shape[0], len(stations)
    t, ang, dt, have = window_arrays(windows, n, S)
    W = len(windows)
    lit = np.all(np.isfinite(ang), -1)                        # (W, S, n)
    n_lit = lit.sum(axis=(1, 2))
    startable = np.any(lit.sum(-1) >= config.min_lit, axis=1)
    R, tr, res, status, adop, pdop = empty_pose_arrays(W)
    # windows no station can start alone but whose angles from several stations fix a pose from the
    # track's last one (a deck tilted so that each station sees 3 of its 4 sensors)
    cont = ~startable & ((lit.sum(-1) > 0).sum(1) >= 2) & (lit.sum(axis=(1, 2)) >= config.min_lit)
    idx = np.flatnonzero(startable | cont)
    if idx.size:
        a = ang[idx]
        Rs, ts, rr, st0 = _solve_from_starts_or_track(P, a, t[idx], startable[idx], state, config, stations,
                                                      solve_joint)
        ok = st0 == _status.OK
        # body velocity from the recent joint poses (causal; NaN at the start of a stream, after a gap
        # or a jump), kept whether or not it is used
        # (from windows with two or more stations when there are: a one-station window of a small
        # deck is ~100x less precise, and its pose would make the velocity noise)
        zero = np.zeros(idx.size)
        vok = ok & (have[idx].sum(1) >= min(2, S))
        w, v = recent_velocity(t[idx], Rs, ts, vok, zero, zero, state.get("motion"), config)
        state["motion"] = motion_history(state.get("motion"), t[idx], Rs, ts, vok, zero, zero, config.motion_window)
        known = np.all(np.isfinite(w), 1) & np.all(np.isfinite(v), 1)
        # the RMS angle change the known motion makes across each window's measurement times
        sm = _motion_sigma(P, ts, w, v, dt[idx], have[idx], stations)
        sm = np.where(known & np.isfinite(sm), sm, 0.0)
        comp = np.zeros(idx.size, bool)
        if config.motion_compensation:
            # only where the motion matters (> MOTION_MIN_SIGMA sigma): at rest the velocity is noise,
            # and modelling it would only add that noise to the pose
            use = ok & known & (sm > MOTION_MIN_SIGMA * config.sigma_theta)
            Rs, ts, rr, comp = _compensate(P, a, dt[idx], Rs, ts, rr, use, w, v, stations, solve_joint)
        # the residual limit follows sigma and, for a window solved as static, the known motion
        # across it (the angles of a moving deck measured up to 20 ms apart cannot fit one pose)
        sm = np.where(comp, 0.0, sm)
        if OUTLIER_P > 0:  # one outlying angle (a reflection) left out, in each window's own motion model
            miss = config.max_residual_sigma * config.sigma_theta
            a, Rs, ts, rr, out = drop_one_outlier(P, a, Rs, ts, rr, ok & ~comp, stations, OUTLIER_P, miss)
            a, Rs, ts, rr, out_c = drop_one_outlier(P, a, Rs, ts, rr, ok & comp, stations, OUTLIER_P, miss,
                                                    dt=dt[idx], velocity=(w, v))
            if (out | out_c).any():  # the lit sets (precision, stations used) without the left-out angles
                lit[idx] = np.all(np.isfinite(a), -1)
                n_lit[idx] = lit[idx].sum(axis=(1, 2))
        limit = config.max_residual_sigma * np.hypot(config.sigma_theta, sm)
        if ok.any():
            d = pose_dop(P, np.where(ok[:, None, None], Rs, np.eye(3)), np.where(ok[:, None], ts, 0.0),
                         rho=config.rho, visible=lit[idx], stations=stations)
            ad = np.where(ok, d.adop, np.inf)
            pd = np.where(ok, d.pdop, np.inf)
        else:
            ad = pd = np.full(idx.size, np.inf)
        st = np.where(~ok, np.where(np.isin(st0, (_status.TOO_FEW_LIT, _status.LOW_REDUNDANCY)), st0,
                                    _status.SOLVER_FAILED),
                      np.where(rr > limit, _status.HIGH_RESIDUAL, _status.OK))
        st = _imprecise(st, P, Rs, ts, pd, config, stations)
        st, cand = continuity_gate(t[idx], Rs, ts, st, ad, pd, state.get("last"), state.get("jump"), config)
        state["jump"] = cand
        good = np.flatnonzero(st == _status.OK)
        if good.size:
            j = good[-1]
            state["last"] = (Rs[j].copy(), ts[j].copy(), float(t[idx][j]))
        R[idx], tr[idx], res[idx], status[idx], adop[idx], pdop[idx] = Rs, ts, rr, st, ad, pd
    has = np.isfinite(R[:, 0, 0])
    rv = np.full((W, 3), np.nan)
    if has.any():
        rv[has] = matrix_to_rotvec(R[has])
    return PoseChunk(t=t, station=np.full(W, JOINT), n_lit=n_lit, rotation=R, translation=tr, rotvec=rv,
                     status=status, residual_rms=res, adop=adop, pdop=pdop, lit=lit.any(1),
                     n_stations=have.sum(1), lit_by_station=lit.sum(-1),
                     stations_used=(lit.sum(-1) > 0).sum(1), sigma_theta=config.sigma_theta)


def auto_sigma_limit(points_body, rotation, translation, stations, rho: float) -> np.ndarray:
    """The default ``max_sigma_position`` of joint windows, per pose, in units of sigma_theta (m/rad):
    the geometric mean ``sqrt(PDOP_1 · PDOP_all)`` of the best single station's PDOP and all
    stations' together, both with every sensor lit, at the pose ``rotation (W, 3, 3)``,
    ``translation (W, 3)`` m (world). Between the two by construction: a window seen by one station
    is above it (its PDOP is at least ``PDOP_1``), one seen well by several is below. (W,) m/rad;
    inf with fewer than two stations (no limit)."""
    from ..dop import pose_dop

    W, S, n = len(rotation), len(stations), len(points_body)
    if S < 2 or W == 0:
        return np.full(W, np.inf)
    vis = np.ones((W, S, n), bool)
    d_all = np.asarray(pose_dop(points_body, rotation, translation, rho=rho, visible=vis, stations=stations).pdop)
    best = np.full(W, np.inf)
    for s in range(S):
        vis = np.zeros((W, S, n), bool)
        vis[:, s] = True
        d = np.asarray(pose_dop(points_body, rotation, translation, rho=rho, visible=vis, stations=stations).pdop)
        best = np.minimum(best, np.where(np.isfinite(d), d, np.inf))
    return np.sqrt(best * d_all)


def _imprecise(status, P, R, t, pdop, config, stations):
    """``status`` with the ok poses whose predicted 1-sigma position exceeds the run's limit
    (``config.max_sigma_position`` m, else :func:`auto_sigma_limit`) marked imprecise."""
    k = np.flatnonzero(status == _status.OK)
    if k.size == 0:
        return status
    if config.max_sigma_position is not None:
        limit = np.full(k.size, config.max_sigma_position)
    else:
        limit = auto_sigma_limit(P, R[k], t[k], stations, config.rho) * config.sigma_theta
    status = status.copy()
    status[k[pdop[k] * config.sigma_theta > limit]] = _status.IMPRECISE
    return status


def _solve_from_starts_or_track(P, a, t, startable, state, config, stations, solve_joint):
    """Joint poses of the windows ``a (F, S, n, 2)``: the startable ones from the per-station starts,
    the others from the latest earlier converged pose within ``reacquire_s`` (a startable window of
    this batch, or the track's last good pose); a window with no such pose is not solved (too few).
    Returns ``(R (F, 3, 3), t (F, 3), residual_rms (F,), solver status (F,))`` (codes of
    :mod:`layoutkit.status`; too_few_lit where not solved)."""
    F = len(a)
    Rs, ts, rr = np.full((F, 3, 3), np.nan), np.full((F, 3), np.nan), np.full(F, np.nan)
    st = np.full(F, _status.TOO_FEW_LIT, int)
    k = np.flatnonzero(startable)
    if k.size:
        sol = solve_joint(P, a[k], stations=stations)
        Rs[k], ts[k], rr[k] = np.array(sol.rotation), np.array(sol.translation), np.array(sol.residual_rms)
        st[k] = np.asarray(sol.status)
    c = np.flatnonzero(~startable)
    if c.size == 0:
        return Rs, ts, rr, st
    ok = (st == _status.OK) & (rr <= config.max_residual_sigma * config.sigma_theta)
    # the nearest earlier good start (this batch), else the track's last good pose
    src_t = t[ok]
    j = np.searchsorted(src_t, t[c], side="right") - 1
    last = state.get("last")
    R0, t0 = np.full((c.size, 3, 3), np.nan), np.full((c.size, 3), np.nan)
    age = np.full(c.size, np.inf)
    have = j >= 0
    kk = np.flatnonzero(ok)
    R0[have], t0[have], age[have] = Rs[kk[j[have]]], ts[kk[j[have]]], t[c[have]] - src_t[j[have]]
    if last is not None:
        use_last = ~have
        R0[use_last], t0[use_last], age[use_last] = last[0], last[1], t[c[use_last]] - last[2]
    go = (age >= 0) & (age <= config.reacquire_s)
    if go.any():
        g = c[go]
        sol = solve_joint(P, a[g], stations=stations, initial=(R0[go], t0[go]))
        Rs[g], ts[g], rr[g] = np.array(sol.rotation), np.array(sol.translation), np.array(sol.residual_rms)
        st[g] = np.asarray(sol.status)
    return Rs, ts, rr, st


def drop_one_outlier(points_body, angles, rotation, translation, residual_rms, test, stations, p_false: float,
                     min_miss: float = 0.0, dt=None, velocity=None):
    """Leave one outlying angle out of the windows ``test``: the externally studentized residual test
    (Belsley, Kuh & Welsch 1980, §2.1; Cook & Weisberg 1982, §2.2.2) on each window's least-squares
    fit, linearised at its solved pose. With ``m`` angles, residuals ``e``, Jacobian ``J`` (m, 6) and
    leverages ``h = diag(J (J^T J)^-1 J^T)``, leaving angle ``j`` out lowers the sum of squares to
    ``SSR_j = SSR - e_j² / (1 - h_j)``; ``F_j = (SSR - SSR_j) / (SSR_j / (m - 7))`` is F(1, m - 7)
    distributed when no angle is an outlier, whatever the noise level (the set-up's model errors
    scale both terms). A window whose largest ``F_j`` exceeds the ``1 - p_false`` quantile, and whose
    angle ``j`` alone misses by more than ``min_miss`` rad (``e_j² / (1 - h_j) > min_miss²``: the
    pipeline passes the residual limit ``max_residual_sigma · sigma_theta``, so a fit whose residuals
    are all at the noise level loses no angle), is solved again without that angle (from its pose);
    the new pose replaces the old where that solve converges. One angle at most per window (one reflecting sensor); windows with ``m - 7 < 2`` are
    not tested.

    points_body (n, 3) m; angles (W, S, n, 2) rad; rotation (W, 3, 3), translation (W, 3) m (world),
    residual_rms (W,) rad: the windows' solves; test (W,) bool; dt (W, S, 2) s and velocity
    ``(w (W, 3), v (W, 3))``: the windows' motion model (:func:`layoutkit.joint.solve_joint`), or None
    for windows solved as static. Returns ``(angles with the left-out
    angles NaN, rotation, translation, residual_rms, left_out (W,) bool)`` (new arrays)."""
    from scipy.stats import f as f_dist

    from ..joint import model_angles_jacobian, solve_joint

    a, R, t, rr = angles.copy(), rotation.copy(), translation.copy(), residual_rms.copy()
    out = np.zeros(len(a), bool)
    k = np.flatnonzero(test)
    if k.size == 0:
        return a, R, t, rr, out
    mot = {} if dt is None else {"dt": np.asarray(dt)[k], "velocity": (velocity[0][k], velocity[1][k])}
    pred, J, _ = model_angles_jacobian(points_body, R[k], t[k], stations, **mot)
    m = np.isfinite(a[k]).reshape(k.size, -1)                                   # (K, M)
    e = np.where(m, np.remainder(a[k].reshape(k.size, -1) - pred.reshape(k.size, -1) + np.pi, 2 * np.pi) - np.pi, 0.0)
    Jm = np.where(m[..., None], J.reshape(k.size, -1, 6), 0.0)                  # (K, M, 6)
    N = np.einsum("kmi,kmj->kij", Jm, Jm)
    dof = m.sum(1) - 7
    good = (dof >= 2) & (np.linalg.cond(N) < 1e12)
    Ni = np.zeros_like(N)
    Ni[good] = np.linalg.inv(N[good])
    h = np.einsum("kmi,kij,kmj->km", Jm, Ni, Jm)
    ssr = np.sum(e * e, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        ssr_j = ssr[:, None] - e * e / (1.0 - h)
        big = m & (h < 1.0 - 1e-9) & (ssr[:, None] - ssr_j > min_miss ** 2)
        F = np.where(big, (ssr[:, None] - ssr_j) / (ssr_j / np.maximum(dof, 1)[:, None]), 0.0)
    j = np.argmax(F, 1)
    q = f_dist.ppf(1.0 - p_false, 1, np.maximum(dof, 1))
    hit = np.flatnonzero(good & (F[np.arange(k.size), j] > q))
    if hit.size == 0:
        return a, R, t, rr, out
    w = k[hit]
    a2 = a[w].reshape(hit.size, -1)
    a2[np.arange(hit.size), j[hit]] = np.nan
    a2 = a2.reshape(a[w].shape)
    if mot:
        mot = {"dt": np.asarray(dt)[w], "velocity": (velocity[0][w], velocity[1][w])}
    sol = solve_joint(points_body, a2, stations=stations, initial=(R[w], t[w]), **mot)
    took = np.asarray(sol.status) == _status.OK
    w = w[took]
    a[w] = a2[took]
    R[w], t[w], rr[w] = np.asarray(sol.rotation)[took], np.asarray(sol.translation)[took], \
        np.asarray(sol.residual_rms)[took]
    out[w] = True
    return a, R, t, rr, out


def _compensate(P, a, dt, Rs, ts, rr, use, w, v, stations, solve_joint):
    """Second pass with constant body velocity across the window (world frame, left perturbation)
    for the windows ``use`` (first pass converged, velocity known). Returns the poses, residuals
    and which windows were compensated."""
    fix = np.flatnonzero(use)
    comp = np.zeros(len(Rs), bool)
    if fix.size == 0:
        return Rs, ts, rr, comp
    sol = solve_joint(P, a[fix], stations=stations, dt=dt[fix], velocity=(w[fix], v[fix]),
                      initial=(Rs[fix], ts[fix]))
    took = np.asarray(sol.status) == _status.OK
    k = fix[took]
    Rs, ts, rr = Rs.copy(), ts.copy(), rr.copy()
    Rs[k], ts[k], rr[k] = np.asarray(sol.rotation)[took], np.asarray(sol.translation)[took], \
        np.asarray(sol.residual_rms)[took]
    comp[k] = True
    return Rs, ts, rr, comp


def _motion_sigma(P, tw, w, v, dt, have, stations):
    """RMS angle change (rad) of the deck's sensors over each window's measurement times for the
    body velocity ``(w, v)``: per station and axis ``(|v| + |w| L) |dt| / r`` (L the largest sensor
    distance from the body origin, r the station's distance), RMS over the present station axes.
    (W,) rad; NaN where the velocity is unknown."""
    L = float(np.max(np.linalg.norm(P, axis=1))) if len(P) else 0.0
    speed = np.linalg.norm(v, axis=-1) + np.linalg.norm(w, axis=-1) * L            # (W,)
    org = np.array([np.asarray(st.translation, float) for st in stations])          # (S, 3)
    r = np.linalg.norm(tw[:, None, :] - org[None], axis=-1)                         # (W, S)
    d = speed[:, None, None] * np.abs(dt) / np.maximum(r, 1e-6)[..., None]          # (W, S, 2)
    m = np.broadcast_to(have[..., None], d.shape)
    n = np.maximum(m.sum((1, 2)), 1)
    return np.sqrt(np.where(m, d * d, 0.0).sum((1, 2)) / n)
