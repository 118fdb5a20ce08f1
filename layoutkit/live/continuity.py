"""The live track's memory: the continuity gate and the recent body velocity of a stream of poses.

Shared by the per-station pipeline (:mod:`layoutkit.live.pipeline`) and the joint windows
(:mod:`layoutkit.live.joint_stream`): both gate their poses against the recent track (a pose that
jumps further than the motion limits and the predicted precision allow is ``jump``) and estimate
the body velocity from the recent good poses for motion compensation. Arrays over ``F`` poses in
time order; rotations ``(F, 3, 3)`` and translations ``(F, 3)`` m in one frame (station or world),
``p = R p_body + t``; the settings are the run's :class:`~layoutkit.live.pipeline.LiveConfig`
(``max_rate_deg_s``, ``max_speed_m_s``, ``gate_sigma``, ``sigma_theta``, ``reacquire_s``,
``reacquire_frames``, ``motion_window``, ``motion_window_s``).
"""
from __future__ import annotations

import numpy as np

from .. import status as _status
from ..geometry import attitude_error

__all__ = ["small_log", "recent_velocity", "motion_history", "continuity_gate"]


def small_log(D) -> np.ndarray:
    """Rotation vectors (..., 3) rad of rotation matrices D (..., 3, 3) with angle < pi."""
    s = 0.5 * np.stack([D[..., 2, 1] - D[..., 1, 2], D[..., 0, 2] - D[..., 2, 0], D[..., 1, 0] - D[..., 0, 1]], -1)
    sn = np.linalg.norm(s, axis=-1)
    ang = np.arctan2(sn, 0.5 * (np.trace(D, axis1=-2, axis2=-1) - 1.0))
    return s * np.where(sn > 1e-300, ang / np.maximum(sn, 1e-300), 1.0)[..., None]


def recent_velocity(t, R, tr, good, adop, pdop, history, config):
    """Body velocity of every frame from the recent good poses of its station (causal).

    t (F,) s, R (F, 3, 3), tr (F, 3) m: one station's poses (station frame) in time order, good (F,)
    bool the ones to use, adop/pdop (F,) their DOP; history: the previous chunk's tail (dict of
    arrays ``t, R, tr, adop, pdop``) or None. The series = history + good poses; consecutive
    entries more than ``motion_window_s`` apart, or further apart than the continuity gate allows,
    start a new segment. Frame k's velocity is the least-squares slope over the last
    ``motion_window`` entries before it (same segment as the latest, within ``motion_window_s``
    of t[k]), relative to the latest one: rotation vectors of ``R_j R_ref^T`` (left perturbation,
    station frame) and ``t_j - t_ref``. Only earlier poses enter (a frame's own noise never feeds
    back into its correction, and the result does not depend on chunking).
    Returns ``(omega (F, 3) rad/s, v (F, 3) m/s)``; NaN rows where fewer than 3
    entries qualify or the estimate exceeds ``max_rate_deg_s`` / ``max_speed_m_s``.
    """
    W = config.motion_window
    g = np.flatnonzero(good)
    if history is not None and g.size and history["t"][-1] > t[g[0]]:
        history = None  # time ran backwards (device reset): forget
    H = 0 if history is None else history["t"].size
    T, Rser, tser, aser, pser = ((x if H == 0 else np.concatenate([history[k], x])) for k, x in
                                 (("t", t[g]), ("R", R[g]), ("tr", tr[g]), ("adop", adop[g]), ("pdop", pdop[g])))
    N, F = T.size, t.size
    omega = np.full((F, 3), np.nan)
    vel = np.full((F, 3), np.nan)
    if N < 3 or F == 0:
        return omega, vel
    rate = np.deg2rad(config.max_rate_deg_s)
    k_sig = config.gate_sigma * config.sigma_theta
    dt = np.diff(T)
    step_a = np.linalg.norm(small_log(Rser[1:] @ np.swapaxes(Rser[:-1], -1, -2)), axis=-1)
    step_d = np.linalg.norm(np.diff(tser, axis=0), axis=-1)
    cons = ((dt > 0) & (dt <= config.motion_window_s)
            & (step_a <= rate * dt + k_sig * np.deg2rad(np.maximum(aser[1:], aser[:-1])))
            & (step_d <= config.max_speed_m_s * dt + k_sig * np.maximum(pser[1:], pser[:-1])))
    seg = np.concatenate([[0], np.cumsum(~cons)])
    order = np.concatenate([np.full(H, -1), g])
    e = np.searchsorted(order, np.arange(F), side="left")  # entries before each frame
    ref = np.clip(e - 1, 0, N - 1)
    j = e[:, None] - W + np.arange(W)  # (F, W), the last W entries
    jc = np.clip(j, 0, N - 1)
    age = t[:, None] - T[jc]
    m = (j >= 0) & (seg[jc] == seg[ref][:, None]) & (age >= 0) & (age <= config.motion_window_s)
    m &= (e >= 1)[:, None]
    s = np.where(m, T[jc] - T[ref][:, None], 0.0)
    cnt = m.sum(1)
    sbar = s.sum(1) / np.maximum(cnt, 1)
    ds = np.where(m, s - sbar[:, None], 0.0)
    den = np.sum(ds * ds, 1)
    y = np.concatenate([small_log(Rser[jc] @ np.swapaxes(Rser[ref], -1, -2)[:, None]),
                        tser[jc] - tser[ref][:, None]], -1)  # (F, W, 6)
    slope = np.einsum("fw,fwi->fi", ds, y) / np.where(den > 0, den, 1.0)[:, None]
    has = (cnt >= 3) & (den > 0)
    has &= (np.linalg.norm(slope[:, :3], axis=-1) <= rate) & (np.linalg.norm(slope[:, 3:], axis=-1)
                                                             <= config.max_speed_m_s)
    omega[has], vel[has] = slope[has, :3], slope[has, 3:]
    return omega, vel


def motion_history(history, t, R, tr, good, adop, pdop, size: int) -> dict | None:
    """The last ``size`` good poses of a station (after ``history``), for the next chunk's velocity."""
    g = np.flatnonzero(good)
    if history is not None and g.size and history["t"][-1] > t[g[0]]:
        history = None
    new = {"t": t[g], "R": R[g], "tr": tr[g], "adop": adop[g], "pdop": pdop[g]}
    if history is not None:
        new = {k: np.concatenate([history[k], v]) for k, v in new.items()}
    return {k: v[-size:].copy() for k, v in new.items()} if new["t"].size else history




def continuity_gate(t, R, tr, status, adop, pdop, last, cand, config):
    """Mark good poses that jump away from the last good pose (see :class:`~layoutkit.live.pipeline.LiveConfig`).

    t (F,) s, R (F, 3, 3), tr (F, 3) m, status (F,), adop/pdop (F,) of one station's frames in
    time order; last = (R, t, time) of the previous good pose or None; cand = (R, t, time, count)
    a chain of mutually consistent jumped poses or None — after ``reacquire_frames`` of them the
    chain is accepted as the new track (so a wrong reference cannot hold the gate shut for long).
    Returns ``(status, cand)``.
    """
    good = np.flatnonzero(status == _status.OK)
    if good.size == 0:
        return status, cand
    rate = np.deg2rad(config.max_rate_deg_s)
    k_sig = config.gate_sigma * config.sigma_theta

    def near(k, ref):
        dt = t[k] - ref[2]
        a = attitude_error(R[k], ref[0])
        d = np.linalg.norm(tr[k] - ref[1], axis=-1)
        return (a <= rate * dt + k_sig * np.deg2rad(adop[k])) & (d <= config.max_speed_m_s * dt + k_sig * pdop[k])

    # near() of every good pose against the good pose before it (pre[j]: good[j + 1] vs good[j]),
    # evaluated at once: the fast path's test, and in the slow path the verdict whenever the reference
    # is the previous good pose (every accepted pose: the usual case) — the same per-pose arithmetic
    # as one call per pose (same matrix products and elementwise functions), ~25 us less per pose
    pre = None
    if cand is None:
        # fast path: every good pose agrees with the good pose before it -> nothing to gate
        if last is not None:
            ref = (np.concatenate([last[0][None], R[good[:-1]]]), np.concatenate([last[1][None], tr[good[:-1]]]),
                   np.concatenate([[last[2]], t[good[:-1]]]))
            cur = good
        else:
            ref, cur = (R[good[:-1]], tr[good[:-1]], t[good[:-1]]), good[1:]
        if cur.size == 0:
            return status, None
        gap = t[cur] - ref[2]
        ok = near(cur, ref)
        if np.all(ok | (gap > config.reacquire_s) | (gap < 0)):
            return status, None
        pre = ok[1:] if last is not None else ok
    if pre is None and good.size > 1:
        pre = near(good[1:], (R[good[:-1]], tr[good[:-1]], t[good[:-1]]))
    pre = pre.tolist() if pre is not None else []
    status = status.copy()
    last_j = -2  # position in ``good`` of the reference ``last`` when it is a pose of this call
    for j, k in enumerate(good):  # slow path: sequential against the last accepted pose
        gap = t[k] - last[2] if last is not None else 0.0
        # no reference, a long gap, or time running backwards (device reset): accept and restart
        if last is None or gap > config.reacquire_s or gap < 0 or (
                pre[j - 1] if last_j == j - 1 else bool(near(k, last))):
            last, cand = (R[k], tr[k], t[k]), None
            last_j = j
            continue
        status[k] = _status.JUMP
        if cand is not None and bool(near(k, cand)):
            cand = (R[k], tr[k], t[k], cand[3] + 1)
        else:
            cand = (R[k], tr[k], t[k], 1)
        if cand[3] >= config.reacquire_frames:
            status[k] = _status.OK
            last, cand = (R[k], tr[k], t[k]), None
            last_j = j
    return status, cand
