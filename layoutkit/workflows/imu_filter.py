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

__all__ = ["filter_recording", "gyro_range"]


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


def filter_recording(recording, device: str, *, config=None, stations=None, lighthouse_config=None) -> dict:
    """Run the IMU-aided filter over one device of a libsurvive recording.

    stations : optional list of :class:`~layoutkit.lighthouse.Station` in the import's order (e.g.
    calibrated ones); default the recording's own (factory). Returns a dict: ``sweeps`` (the
    :func:`layoutkit.filter.imu.run_imu_filter` output plus ``station``, ``axis``, ``angles``),
    ``body_rotation``/``body_translation`` (K, ...) the layout frame's poses, ``points_imu``,
    ``stations``, ``summary``. ValueError naming the recording for a device without IMU or light.
    """
    from ..filter.imu import ImuFilterConfig, run_imu_filter
    from ..importers.libsurvive import (device_frames, device_sweeps, layout_of, libsurvive_stations,
                                        read_lighthouse_config, read_recording)
    from ..importers.libsurvive_imu import STANDARD_GRAVITY, imu_samples
    from ..joint import solve_joint
    from .joint_solve import StationFrames, to_station_convention, window_table

    config = ImuFilterConfig() if config is None else config
    recording = Path(recording)
    rec = read_recording(recording)
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
    gyro_fit = gyro_range(tw, res, two, imu)
    if gyro_fit["counts_per_deg_s"] is not None and gyro_fit["counts_per_deg_s"] != imu["scales"]["gyro_counts_per_deg_s"]:
        imu = imu_samples(rec, device, gyro_counts_per_deg_s=gyro_fit["counts_per_deg_s"])
    R_ib, p_ib = imu["imu_rotation"], imu["imu_position"]
    P_imu = (lay.positions - p_ib) @ R_ib                       # sensors in the IMU frame
    sw = device_sweeps(rec.light[device], lay.n, station_of)
    # the start: the first window solved with >= 2 stations, inside the IMU's time span
    cand = np.flatnonzero(res.success & two & (tw > imu["t"][0] + 0.05))
    if cand.size == 0:
        raise ValueError(f"{recording}: {device}: no window solved from two stations to start the filter")
    k0 = cand[0]
    Rb, tb = res.rotation[k0], res.translation[k0]
    R0 = Rb @ R_ib
    p0 = Rb @ p_ib + tb
    near = np.abs(imu["t"] - tw[k0]) <= 0.05
    f_mean = imu["acc"][near].mean(0) if near.any() else imu["acc"][0]
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
               "gravity_from_minus_z_deg": g_angle,
               "prior_rms_median_rad": float(np.nanmedian(out["prior_rms"][acc_ok])) if acc_ok.any() else None,
               "posterior_rms_median_rad": float(np.nanmedian(out["posterior_rms"][acc_ok])) if acc_ok.any() else None}
    return {"sweeps": out, "body_rotation": Rbody, "body_translation": tbody, "points_imu": P_imu, "stations": st,
            "layout": lay, "summary": summary}
