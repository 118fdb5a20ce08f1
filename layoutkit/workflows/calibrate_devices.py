"""Calibration over several devices of one recording, and whether it transfers (issue 26 item 1).

A recording (libsurvive: an HMD and a tracker; Crazyflie: one deck) gives each device's frame table
in the stations' common world frame. What the stations *are* — their poses and calibration — is
shared by every device; each device's own layout errors (sensor offsets, per-sensor latency) are
not. :func:`fit_devices` adjusts both at once with :func:`layoutkit.calibrate.bundle_adjust` by
stacking the devices' sensors into one body whose samples see only their own device's sensors
(each sample's pose is its own unknown, so the stack is exact); a device at rest contributes one
pose per static segment (:func:`layoutkit.calibrate.static_segments`) rather than one per window.

Cross-validation (:func:`cross_validate`), the test of whether the shared terms transfer:

- **device folds** (two devices or more): fit on all devices but one, then solve the held-out
  device jointly with the fitted stations and its *nominal* layout (none of its own terms were
  fitted) and compare its median per-window residual RMS with the factory stations';
- **time fold**: fit on the first half of every device's windows, evaluate the second half — with
  each device's fitted offsets and latencies, which belong to the device (a static device's
  second half is at the same pose: the fold then tests the shared terms only in time).

Verdict per fold: ``better`` / ``same`` (within :data:`SAME_TOLERANCE`) / ``worse``. A calibration
whose shared terms make any held-out evaluation worse is reported ``does_not_transfer`` and is
not what ``stations.json`` holds (:func:`layoutkit.workflows.calibrate.calibrate_files`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..layout import Layout

__all__ = ["DeviceWindows", "device_windows", "joint_residual", "fit_devices", "cross_validate",
           "SAME_TOLERANCE", "NO_FIT", "fold_verdict"]

#: A held-out residual within this fraction of the factory stations' counts as the same.
SAME_TOLERANCE = 0.01
#: Bundle-adjustment statuses with no fitted stations to evaluate (:class:`layoutkit.calibrate.BundleResult`).
NO_FIT = ("too_few", "nothing_determined")


@dataclass(frozen=True)
class DeviceWindows:
    """One device's joint windows.

    name; layout; t (W,) s window times; rows (W, S) frame-table rows (-1 = station absent);
    angles (W, S, n, 2) rad in each station's convention; start : the joint solve with the starting
    (factory) stations (:class:`layoutkit.pnp.PnPResult`, world frame); pose_of (W,) the shared pose
    of each window (static segments), static (P,) bool per pose.
    """

    name: str
    layout: Layout
    t: np.ndarray
    rows: np.ndarray
    angles: np.ndarray
    start: object
    pose_of: np.ndarray
    static: np.ndarray

    @property
    def usable(self) -> np.ndarray:
        """(W,) windows with a start pose (solved, or not converged but finite)."""
        s = self.start
        return (s.success | (s.status == 3)) & np.all(np.isfinite(s.translation), 1)


def device_windows(name: str, frames, layout: Layout, stations, *, window_s: float | None = None,
                   segments: bool = True) -> DeviceWindows:
    """A device's frame table (:class:`~layoutkit.workflows.calibrate.StationFrames`) → its joint
    windows, the factory joint solve and its static segments (``segments=False``: one pose per window)."""
    from ..calibrate import static_segments
    from ..joint import WINDOW_S, solve_joint
    from .joint_solve import window_table

    rows, tw, ang = window_table(frames, stations, WINDOW_S if window_s is None else window_s)
    start = solve_joint(layout.positions, ang, stations=stations)
    ok = (start.success | (start.status == 3)) & np.all(np.isfinite(start.translation), 1)
    if segments:
        pose_of, static = static_segments(tw, np.where(ok[:, None, None], start.rotation, np.eye(3)),
                                          np.where(ok[:, None], start.translation, 0.0), ok)
    else:
        pose_of, static = np.arange(len(tw)), np.zeros(len(tw), bool)
    return DeviceWindows(name, layout, tw, rows, ang, start, pose_of, static)


def joint_residual(dw: DeviceWindows, stations, positions=None, select=None, latency=None) -> dict:
    """Solve the device's windows (all, or ``select`` (W,) bool) jointly through ``stations`` with its
    sensor ``positions`` (default the nominal layout) and per-sensor ``latency`` (n,) s (default none;
    each angle is corrected by :func:`layoutkit.calibrate.timing_gain` x latency): ``median_rad`` of
    the per-window residual RMS over the solved windows, ``windows``, ``solved``."""
    from ..calibrate import timing_gain
    from ..joint import solve_joint

    sel = np.ones(len(dw.t), bool) if select is None else np.asarray(select, bool)
    if not sel.any():
        return {"median_rad": None, "windows": 0, "solved": 0}
    P = dw.layout.positions if positions is None else positions
    ang = dw.angles[sel]
    if latency is not None and np.any(np.asarray(latency) != 0):
        gain = np.array([timing_gain(st) for st in stations])
        ang = ang - gain[None, :, None, None] * np.asarray(latency, float)[None, None, :, None]
    r = solve_joint(P, ang, stations=stations)
    ok = r.success & np.isfinite(r.residual_rms)
    return {"median_rad": float(np.median(r.residual_rms[ok])) if ok.any() else None,
            "windows": int(sel.sum()), "solved": int(ok.sum())}


def _subsample(mask, max_windows, rng):
    idx = np.flatnonzero(mask)
    if max_windows is not None and idx.size > max_windows:
        idx = np.sort(rng.choice(idx, max_windows, replace=False))
    out = np.zeros_like(mask)
    out[idx] = True
    return out


def fit_devices(devs, stations, selects=None, *, sigma: float, max_windows: int | None = None, seed: int = 0,
                **ba_kw):
    """Bundle-adjust the shared stations and each device's own terms over the windows ``selects``
    (list of (W,) bool per device; default all) of ``devs`` (:class:`DeviceWindows`).

    At most ``max_windows`` windows per device (a random subset, ``seed``). ``ba_kw`` go to
    :func:`layoutkit.calibrate.bundle_adjust` (``sensor_offsets``, ``sensor_timing``,
    ``calibration_prior``, ``station_prior``, ``layout_sigma``, ...).
    Returns ``(BundleResult, parts)``: ``parts[name] = {"sensors": slice, "windows": (W,) bool used,
    "poses": number of body poses, "static_poses": of them at rest}``; the result's ``points_body[slice]``
    is the device's adjusted layout.
    """
    from ..calibrate import bundle_adjust

    rng = np.random.default_rng(seed)
    S = len(stations)
    N = sum(d.layout.n for d in devs)
    selects = [None] * len(devs) if selects is None else list(selects)
    P_all, A_all, pose_all, R0, t0, labels = [], [], [], [], [], []
    parts = {}
    s0 = 0
    p_next = 0
    for d, sel in zip(devs, selects):
        use = d.usable & (np.ones(len(d.t), bool) if sel is None else np.asarray(sel, bool))
        use = _subsample(use, max_windows, rng)
        idx = np.flatnonzero(use)
        a = np.full((idx.size, S, N, 2), np.nan)
        a[:, :, s0:s0 + d.layout.n] = d.angles[idx]
        poses, inv = np.unique(d.pose_of[idx], return_inverse=True)
        for q, p in enumerate(poses):                     # start of each pose: its median window
            members = idx[inv == q]
            k = members[np.argmin(np.linalg.norm(d.start.translation[members]
                                                  - np.median(d.start.translation[members], 0), axis=1))]
            R0.append(d.start.rotation[k])
            t0.append(d.start.translation[k])
        pose_all.append(p_next + inv)
        parts[d.name] = {"sensors": slice(s0, s0 + d.layout.n), "windows": use, "poses": int(poses.size),
                         "static_poses": int(np.sum(d.static[poses])) if d.static.size else 0}
        p_next += poses.size
        P_all.append(d.layout.positions)
        A_all.append(a)
        labels += [f"{d.name} {i}" for i in d.layout.ids]
        s0 += d.layout.n
    res = bundle_adjust(np.concatenate(P_all), np.concatenate(A_all), stations, sigma=sigma,
                        initial_poses=(np.stack(R0), np.stack(t0)), pose_of=np.concatenate(pose_all),
                        sensor_labels=labels, **ba_kw)
    return res, parts


def fold_verdict(factory, calibrated) -> str:
    """``better`` / ``same`` / ``worse`` (:data:`SAME_TOLERANCE`), ``undetermined`` without figures."""
    if factory is None or calibrated is None:
        return "undetermined"
    if calibrated > factory * (1.0 + SAME_TOLERANCE):
        return "worse"
    return "better" if calibrated < factory * (1.0 - SAME_TOLERANCE) else "same"


def cross_validate(devs, stations, *, sigma: float, max_windows: int | None = None, seed: int = 0,
                   time_fold: bool = True, **ba_kw) -> list:
    """The folds of the module docstring; each ``{"kind", "fit_on", "held_out", "factory_rad",
    "calibrated_rad", "ratio", "verdict", "fit_status", "fit_message"}`` (residuals: median per-window RMS
    of the held-out windows, rad)."""
    folds = []
    if len(devs) >= 2:
        for k, d in enumerate(devs):
            others = [x for j, x in enumerate(devs) if j != k]
            res, _ = fit_devices(others, stations, sigma=sigma, max_windows=max_windows, seed=seed, **ba_kw)
            fac = joint_residual(d, stations)["median_rad"]
            cal = joint_residual(d, res.stations)["median_rad"] if res.status not in NO_FIT else None
            folds.append({"kind": "device", "fit_on": [x.name for x in others], "held_out": d.name,
                          "factory_rad": fac, "calibrated_rad": cal,
                          "ratio": None if (fac is None or cal is None) else cal / fac,
                          "verdict": fold_verdict(fac, cal), "fit_status": res.status, "fit_message": res.message})
    if time_fold:
        first, second = [], []
        for d in devs:
            ok = d.usable
            if ok.sum() < 4:
                first.append(np.zeros(len(d.t), bool))
                second.append(np.zeros(len(d.t), bool))
                continue
            t_mid = np.median(d.t[ok])
            first.append(ok & (d.t <= t_mid))
            second.append(ok & (d.t > t_mid))
        res, parts = fit_devices(devs, stations, first, sigma=sigma, max_windows=max_windows, seed=seed, **ba_kw)
        for d, sel in zip(devs, second):
            fac = joint_residual(d, stations, select=sel)["median_rad"]
            cal = None
            if res.status not in NO_FIT:
                sl = parts[d.name]["sensors"]
                cal = joint_residual(d, res.stations, res.points_body[sl], select=sel,
                                     latency=res.extra["timing_s"][sl])["median_rad"]
            folds.append({"kind": "time", "fit_on": [f"{x.name} first half" for x in devs],
                          "held_out": f"{d.name} second half", "factory_rad": fac, "calibrated_rad": cal,
                          "ratio": None if (fac is None or cal is None) else cal / fac,
                          "verdict": fold_verdict(fac, cal), "fit_status": res.status, "fit_message": res.message,
                          "device_at_rest": bool(d.usable.any() and d.static.size
                                                 and np.mean(d.static[d.pose_of[d.usable]]) >= 0.9)})
    return folds
