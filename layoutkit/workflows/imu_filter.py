"""The IMU-aided filter (:mod:`layoutkit.filter.imu`) on a libsurvive recording (issue 26 item 4).

Reads the recording once: the device's layout (its CONFIG), its IMU frame (CONFIG ``imu``: ``plus_x``,
``plus_z``, ``position``), its raw ``i`` lines (scaled by :func:`layoutkit.importers.libsurvive_imu.imu_samples`)
and every sweep as its own measurement at its own time (:func:`~layoutkit.importers.libsurvive.device_sweeps`,
on the same device clock). The filter starts at the first window the joint solve
(:func:`layoutkit.joint.solve_joint`, every station, the factory models) solves with two stations or
more; gravity is the accelerometer's mean over the 0.1 s around that start turned into the world
(the device is taken to be at rest there — the summary reports the angle between that gravity and
the world's -z so a moving start shows).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["filter_recording", "gyro_range", "imu_axes_from_gravity", "AXIS_FLIPS", "filter_pose_table",
           "imu_filter_devices"]


def gyro_range(tw, res, use, imu, min_pairs: int = 20) -> dict:
    """Which gyro range (:data:`layoutkit.importers.libsurvive_imu.GYRO_COUNTS_PER_DEG_S`) the device uses:
    the attitude change between consecutive joint lighthouse poses (windows ``use``, <= 50 ms apart,
    turning > 0.02 rad) against the gyro's integral over the same time at the default range; the
    least-squares ratio picks the nearest range. ``counts_per_deg_s`` None when fewer than ``min_pairs``
    pairs turned (a device at rest: the default stays)."""
    from ..geometry import matrix_to_rotvec
    from ..importers.libsurvive_imu import GYRO_COUNTS_PER_DEG_S

    R_ib = imu["imu_rotation"]
    cpd0 = imu["scales"]["gyro_counts_per_deg_s"]
    g = np.flatnonzero(res.success & use)
    est, gyr = [], []
    for a, b in zip(g[:-1], g[1:]):
        if tw[b] - tw[a] > 0.05:
            continue
        m = (imu["t"] >= tw[a]) & (imu["t"] < tw[b])
        if m.sum() < 3:
            continue
        rel = matrix_to_rotvec(R_ib.T @ res.rotation[a].T @ res.rotation[b] @ R_ib)
        if np.linalg.norm(rel) < 0.02:
            continue
        est.append(rel)
        gyr.append(imu["gyro"][m].mean(0) * (tw[b] - tw[a]))
    if len(est) < min_pairs:
        return {"pairs": len(est), "ratio": None, "counts_per_deg_s": None}
    est, gyr = np.array(est), np.array(gyr)
    k = float(np.sum(est * gyr) / np.sum(gyr * gyr))           # lighthouse / gyro at the default range
    corr = float(np.corrcoef(est.ravel(), gyr.ravel())[0, 1])
    cpd = min(GYRO_COUNTS_PER_DEG_S, key=lambda c: abs(np.log(cpd0 / k / c))) if k > 0 else None
    return {"pairs": len(est), "ratio": k, "correlation": corr, "counts_per_deg_s": cpd}


#: The IMU axes tried for a device whose CONFIG has no ``imu`` block (imu → layout): the layout's
#: own and the three half turns (the Vive HMD of ``lh1_test_cal`` reads gravity 160 deg off with the
#: layout's axes, 1 deg off turned half about z).
AXIS_FLIPS = {"layout axes": np.diag([1.0, 1.0, 1.0]), "half turn about x": np.diag([1.0, -1.0, -1.0]),
              "half turn about y": np.diag([-1.0, 1.0, -1.0]), "half turn about z": np.diag([-1.0, -1.0, 1.0])}


def imu_axes_from_gravity(R_body, f_imu, up=(0.0, 0.0, 1.0)):
    """IMU → layout rotation for a device without a CONFIG ``imu`` block: of :data:`AXIS_FLIPS`, the
    one that turns the specific force ``f_imu (3,)`` measured at rest (pointing up) closest to the
    world's ``up`` through the lighthouse attitude ``R_body`` (layout → world; libsurvive's world has
    z up). Returns ``(R (3, 3), text)``: the choice, its angle and the runner-up's. Gravity alone
    cannot tell a half turn about the vertical: when the device's vertical lies along one of its axes
    two patterns fit alike, and the text then says ``ambiguous``."""
    f = np.asarray(f_imu, float) / max(np.linalg.norm(f_imu), 1e-12)
    u = np.asarray(up, float)
    ang = {k: float(np.degrees(np.arccos(np.clip((R_body @ R @ f) @ u, -1.0, 1.0)))) for k, R in AXIS_FLIPS.items()}
    best, second = sorted(ang, key=ang.get)[:2]
    amb = "ambiguous, " if ang[second] - ang[best] < 10.0 else ""
    return AXIS_FLIPS[best], (f"no CONFIG imu block: {best} ({amb}gravity at the start {ang[best]:.1f} deg from the "
                              f"world's; next best {second}, {ang[second]:.1f} deg)")


def filter_recording(recording, device: str, *, config=None, stations=None, lighthouse_config=None,
                     rec=None) -> dict:
    """Run the IMU-aided filter over one device of a libsurvive recording.

    stations : optional list of :class:`~layoutkit.lighthouse.Station` in the import's order (e.g.
    calibrated ones); default the recording's own (factory). Returns a dict: ``sweeps`` (the
    :func:`layoutkit.filter.imu.run_imu_filter` output plus ``station``, ``axis``, ``angles``),
    ``body_rotation``/``body_translation`` (K, ...) the layout frame's poses, ``points_imu``,
    ``stations``, ``summary``. ValueError naming the recording for a device without IMU or light.
    rec : the already-read :class:`~layoutkit.importers.libsurvive.Recording` of ``recording`` (else read here).
    """
    from ..filter.imu import ImuFilterConfig, run_imu_filter
    from ..importers.libsurvive import (device_frames, device_sweeps, layout_of, libsurvive_stations,
                                        read_lighthouse_config, read_recording)
    from ..importers.libsurvive_imu import STANDARD_GRAVITY, imu_samples
    from ..joint import solve_joint
    from .joint_solve import StationFrames, window_table

    config = ImuFilterConfig() if config is None else config
    recording = Path(recording)
    rec = read_recording(recording) if rec is None else rec
    cfg_path = Path(lighthouse_config) if lighthouse_config else Path(str(recording) + ".json")
    cfg = read_lighthouse_config(cfg_path) if cfg_path.exists() else {}
    smap = libsurvive_stations(rec, cfg)
    st = list(smap.stations) if stations is None else list(stations)
    if len(st) != len(smap.stations):
        raise ValueError(f"{recording}: {len(st)} stations given, the recording has {len(smap.stations)}")
    if device not in rec.light:
        raise ValueError(f"{recording}: device {device!r} has no light events (devices: {sorted(rec.light)})")
    lay = layout_of(rec, device)

    def station_of(gen, ch):
        return smap.lh1.get(ch, ch) if gen == 1 else smap.lh2.get(ch, ch)

    fr, _ = device_frames(rec.light[device], lay.n, station_of)
    sf = StationFrames(fr.t, np.asarray([str(int(x)) for x in fr.stations()]), fr.angles)
    rows, tw, ang = window_table(sf, st, 0.02)
    res = solve_joint(lay.positions, ang, stations=st)
    two = (rows >= 0).sum(1) >= 2
    imu = imu_samples(rec, device)
    # the start: the first window solved with >= 2 stations, inside the IMU's time span
    cand = np.flatnonzero(res.success & two & (tw > imu["t"][0] + 0.05))
    if cand.size == 0:
        raise ValueError(f"{recording}: {device}: no window solved from two stations to start the filter")
    k0 = cand[0]
    Rb, tb = res.rotation[k0], res.translation[k0]
    near = np.abs(imu["t"] - tw[k0]) <= 0.05
    f_mean = imu["acc"][near].mean(0) if near.any() else imu["acc"][0]
    imu_frame_from = "CONFIG imu"
    if not (rec.configs.get(device) or {}).get("imu"):
        imu["imu_rotation"], imu_frame_from = imu_axes_from_gravity(Rb, f_mean)
    gyro_fit = gyro_range(tw, res, two, imu)
    if gyro_fit["counts_per_deg_s"] is not None and gyro_fit["counts_per_deg_s"] != imu["scales"]["gyro_counts_per_deg_s"]:
        R_keep = imu["imu_rotation"]
        imu = imu_samples(rec, device, gyro_counts_per_deg_s=gyro_fit["counts_per_deg_s"])
        imu["imu_rotation"] = R_keep
    R_ib, p_ib = imu["imu_rotation"], imu["imu_position"]
    P_imu = (lay.positions - p_ib) @ R_ib                       # sensors in the IMU frame
    sw = device_sweeps(rec.light[device], lay.n, station_of)
    R0 = Rb @ R_ib
    p0 = Rb @ p_ib + tb
    g = -(R0 @ f_mean)
    g_angle = float(np.degrees(np.arccos(np.clip(-g[2] / max(np.linalg.norm(g), 1e-12), -1, 1))))
    g = g / max(np.linalg.norm(g), 1e-12) * STANDARD_GRAVITY
    good = np.flatnonzero(res.success & two)                  # restart poses: joint windows, IMU frame
    restarts = (tw[good], res.rotation[good] @ R_ib, np.einsum("kij,j->ki", res.rotation[good], p_ib) + res.translation[good])
    out = run_imu_filter(imu["t"], imu["acc"], imu["gyro"], imu["saturated"], sw["t"], sw["station"], sw["axis"],
                         sw["angles"], st, P_imu, (tw[k0], R0, p0, g), config, restarts=restarts)
    out.update(station=sw["station"], axis=sw["axis"], angles=sw["angles"])
    Rbody = out["rotation"] @ R_ib.T
    tbody = out["position"] - np.einsum("kij,j->ki", Rbody, p_ib)
    acc_ok = out["accepted"]
    summary = {"device": device, "sweeps": out["counts"], "imu_samples": int(imu["t"].size),
               "imu_scales": imu["scales"], "gyro_range_fit": gyro_fit, "imu_dropped": imu["dropped"],
               "imu_saturated": int(imu["saturated"].sum()), "start_t": float(tw[k0]),
               "gravity_from_minus_z_deg": g_angle, "imu_frame_from": imu_frame_from,
               "prior_rms_median_rad": float(np.nanmedian(out["prior_rms"][acc_ok])) if acc_ok.any() else None,
               "posterior_rms_median_rad": float(np.nanmedian(out["posterior_rms"][acc_ok])) if acc_ok.any() else None}
    return {"sweeps": out, "body_rotation": Rbody, "body_translation": tbody, "points_imu": P_imu, "stations": st,
            "layout": lay, "summary": summary}


def filter_pose_table(result: dict):
    """The filter's per-sweep poses of the body (the layout's frame, in the stations' world) as a
    :class:`layoutkit.io.poses.PoseTable`: ``station`` = the sweep's station index (stations.json
    order); ``status`` ok = the sweep was accepted (pose after its update), ``high_residual`` = the
    chi² gate rejected it (the pose predicted from the IMU and the earlier sweeps), ``too_few_lit`` =
    fewer than ``min_sensors`` angles (the prediction), ``no_start`` = before the filter started
    (no pose), ``lost`` (no pose: the filter restarts from the next joint lighthouse pose);
    ``residual_rms`` = the sweep's residual after its update (accepted) or before it (the others);
    extra columns ``prior_residual_rms`` (rad, before the update), ``nis``, ``axis`` (LH1 axis / LH2
    plane), ``vx, vy, vz`` (m/s, world, the IMU frame's velocity)."""
    from ..geometry import matrix_to_rotvec
    from ..io.poses import PoseTable
    from ..status import HIGH_RESIDUAL, LOST, NO_START, OK, TOO_FEW_LIT

    s = result["sweeps"]
    K = len(s["t"])
    R, T = result["body_rotation"], result["body_translation"]
    has = np.all(np.isfinite(R), (1, 2)) & np.all(np.isfinite(T), 1)
    rv = np.full((K, 3), np.nan)
    rv[has] = matrix_to_rotvec(R[has])
    status = np.full(K, TOO_FEW_LIT)
    status[np.isfinite(s["nis"])] = HIGH_RESIDUAL
    status[s["accepted"]] = OK
    status[~has & ~s["lost"]] = NO_START
    status[s["lost"]] = LOST
    res = np.where(s["accepted"], s["posterior_rms"], s["prior_rms"])
    res = np.where(has, res, np.nan)
    v = s["velocity"]
    return PoseTable(s["t"], rv, T, s["station"], status, res,
                     {"prior_residual_rms": np.where(has, s["prior_rms"], np.nan), "nis": s["nis"],
                      "axis": s["axis"].astype(float), "vx": v[:, 0], "vy": v[:, 1], "vz": v[:, 2]})


def imu_filter_devices(recording, out_dir, devices, *, rec=None, stations=None, lighthouse_config=None) -> dict:
    """``layoutkit import libsurvive REC --imu-filter``: the IMU-aided filter over each of ``devices``
    that has IMU (``i``) lines and light; writes ``out_dir/<device>/imu_filter_poses.csv``
    (:func:`filter_pose_table`). stations : a stations JSON path (e.g. ``calibrate``'s) or None (the
    recording's own). Returns per device ``{"file", "sweeps": counts, "status_counts", ...}`` or
    ``{"skipped": why}`` (no IMU lines, no light, no start) — one device's problem never stops the others."""
    from ..io.poses import write_poses
    from ..io.stations import read_stations
    from ..status import NAMES

    sts = None if stations is None else list(read_stations(stations))
    out = {}
    for dev in devices:
        try:
            r = filter_recording(recording, dev, stations=sts, lighthouse_config=lighthouse_config, rec=rec)
        except ValueError as exc:
            out[dev] = {"skipped": str(exc)}
            continue
        tab = filter_pose_table(r)
        path = write_poses(Path(out_dir) / dev / "imu_filter_poses.csv", tab)
        codes, counts = np.unique(tab.status, return_counts=True)
        sm = r["summary"]
        out[dev] = {"file": str(path), "stations": "given" if stations is not None else "recording",
                    "sweeps": sm["sweeps"], "status_counts": {NAMES.get(int(c), str(int(c))): int(k)
                                                               for c, k in zip(codes, counts)},
                    "residual_before_update_median_rad": sm["prior_rms_median_rad"],
                    "residual_after_update_median_rad": sm["posterior_rms_median_rad"],
                    "gyro_range_fit": sm["gyro_range_fit"], "gravity_from_minus_z_deg": sm["gravity_from_minus_z_deg"],
                    "imu_frame_from": sm["imu_frame_from"],
                    "imu_samples": sm["imu_samples"], "imu_saturated": sm["imu_saturated"]}
    return out
