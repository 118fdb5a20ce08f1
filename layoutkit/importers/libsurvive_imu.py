"""libsurvive's raw IMU lines (``<dev> i <mask> <timecode> ax ay az gx gy gz ...``) as physical samples.

On the device clock of :func:`layoutkit.importers.libsurvive.device_frames` (the light's), in the IMU
frame the device's CONFIG gives (``imu``: ``plus_x``, ``plus_z``, ``position`` in the layout frame), for
the IMU-aided filter (:mod:`layoutkit.filter.imu`, :mod:`layoutkit.workflows.imu_filter`).
"""
from __future__ import annotations

import numpy as np

from ..units import STANDARD_GRAVITY
from .libsurvive import Recording, _device_time

__all__ = ["ACC_COUNTS_PER_G", "GYRO_COUNTS_PER_DEG_S", "STANDARD_GRAVITY", "IMU_SATURATION", "imu_frame",
           "imu_samples"]

#: Raw accelerometer counts per g of the 16-bit IMU ranges ±2/4/8/16 g. The device's range is the one
#: whose 1 g matches the median magnitude of its quietest samples (the tracker of
#: ``index-yank-up-down`` and the HMD read ~8190 counts at rest: ±4 g; the Knuckles ~4170: ±8 g).
ACC_COUNTS_PER_G = (16384.0, 8192.0, 4096.0, 2048.0)
#: Raw gyro counts per deg/s of the 16-bit ranges ±250/500/1000/2000 deg/s. Which one a device uses is
#: not in the recording: :func:`layoutkit.workflows.imu_filter.gyro_range` takes the range whose
#: rates match the lighthouse attitude changes of the moving device (``index-yank-up-down``'s tracker:
#: 0.27x the gyro integral at 16.4 counts/(deg/s), corr 0.91 over 78 window pairs: ±500, 65.5).
GYRO_COUNTS_PER_DEG_S = (131.072, 65.536, 32.768, 16.384)
#: Raw counts at which the IMU saturates.
IMU_SATURATION = 32767


def imu_frame(config: dict):
    """The IMU's frame in the device (layout) frame from a CONFIG's ``imu`` entry (``plus_x``,
    ``plus_z``, ``position``): ``(R (3, 3) imu → layout, p (3,) m)``; identity if absent."""
    imu = (config or {}).get("imu") or {}
    try:
        x = np.asarray(imu.get("plus_x", [1, 0, 0]), float)
        z = np.asarray(imu.get("plus_z", [0, 0, 1]), float)
        p = np.asarray(imu.get("position", [0, 0, 0]), float)
    except (TypeError, ValueError):
        return np.eye(3), np.zeros(3)
    x = x / np.linalg.norm(x)
    z = z - x * (x @ z)
    z = z / np.linalg.norm(z)
    return np.column_stack([x, np.cross(z, x), z]), p


def imu_samples(rec: Recording, device: str, gyro_counts_per_deg_s: float | None = None):
    """The device's raw ``i`` lines as physical samples on the device clock of :func:`device_frames`.

    Returns a dict: ``t (N,)`` s, ``acc (N, 3)`` m/s² (specific force, IMU frame: counts / the range of
    :data:`ACC_COUNTS_PER_G` that matches 1 g at rest, times the CONFIG's ``acc_scale``, minus its
    ``acc_bias`` — in m/s²: so the magnitude at rest is 9.8 m/s² on the tracker, the HMD and the
    Knuckles; read as g it would be 8.2-10.3), ``gyro (N, 3)`` rad/s (counts /
    ``gyro_counts_per_deg_s``, default ±500 deg/s of :data:`GYRO_COUNTS_PER_DEG_S`, minus the CONFIG's
    ``gyro_bias`` in rad/s), ``saturated (N,)`` (an axis at the raw limit), the IMU frame
    (:func:`imu_frame`), ``scales`` and ``dropped`` (samples off the clock). Time: the IMU's 48 MHz
    timecode unwrapped with the light's (one device clock); samples more than 0.1 s off the median
    offset to the host clock are dropped (the HMD of ``lh1_test_cal`` writes its first IMU samples,
    before the light starts, with a timecode 16.5 s behind). ValueError naming the recording when the
    device has no IMU samples or no light events.
    """
    rows = rec.imu.get(device)
    if not rows:
        raise ValueError(f"{rec.path}: device {device!r} has no IMU ('i') lines")
    if device not in rec.light:
        raise ValueError(f"{rec.path}: device {device!r} has no light events to put its IMU on their clock")
    _, t = _device_time(rec.light[device], rows)
    a = np.asarray(rows, float)
    lag = t - a[:, 0]
    keep = np.abs(lag - np.median(lag)) < 0.1
    t, a = t[keep], a[keep]
    order = np.argsort(t, kind="stable")
    cfg = rec.configs.get(device, {}) or {}
    imu = cfg.get("imu") or {}
    acc_scale = np.asarray(imu.get("acc_scale", cfg.get("acc_scale", [1, 1, 1])), float)
    acc_bias = np.asarray(imu.get("acc_bias", cfg.get("acc_bias", [0, 0, 0])), float)
    gyro_bias = np.asarray(imu.get("gyro_bias", cfg.get("gyro_bias", [0, 0, 0])), float)
    raw_a, raw_g = a[:, 2:5], a[:, 5:8]
    # the accelerometer range: 1 g = the median magnitude of the quietest fifth of the samples
    quiet = np.linalg.norm(raw_g - np.median(raw_g, 0), axis=1)
    q = quiet <= np.percentile(quiet, 20)
    one_g = float(np.median(np.linalg.norm(raw_a[q], axis=1)))
    acc_cpg = min(ACC_COUNTS_PER_G, key=lambda c: abs(np.log(one_g / c)))
    if gyro_counts_per_deg_s is None:
        gyro_cpd, how = GYRO_COUNTS_PER_DEG_S[1], "default (±500 deg/s)"
    else:
        gyro_cpd, how = float(gyro_counts_per_deg_s), "given"
    acc = raw_a / acc_cpg * STANDARD_GRAVITY * acc_scale - acc_bias
    gyro = np.deg2rad(raw_g / gyro_cpd) - gyro_bias
    sat = np.any(np.abs(raw_a) >= IMU_SATURATION, 1) | np.any(np.abs(raw_g) >= IMU_SATURATION, 1)
    R, p = imu_frame(cfg)
    return {"t": t[order], "acc": acc[order], "gyro": gyro[order], "saturated": sat[order],
            "imu_rotation": R, "imu_position": p, "dropped": int(np.sum(~keep)),
            "scales": {"acc_counts_per_g": acc_cpg, "acc_one_g_counts_at_rest": one_g,
                       "gyro_counts_per_deg_s": gyro_cpd, "gyro_scale_from": how}}
