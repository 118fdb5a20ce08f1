"""The IMU sample file ``imu.csv`` beside a capture: one owner, read and written here only.

Columns (a header line, then one row per sample, time-ordered):

    t_s, gyro_x_rad_s, gyro_y_rad_s, gyro_z_rad_s, acc_x_m_s2, acc_y_m_s2, acc_z_m_s2

``t_s`` is on the capture's clock (the replay's ``t``: for ``layoutkit import cfusdlog`` the log's
event clock, which the deck's timestamps are mapped onto); gyro is the angular rate in rad/s and
acc the specific force (accelerometer reading, +1 g up at rest) in m/s², both in the IMU's frame
(for the Crazyflie: its body frame, x forward, y left, z up — the deck layout's frame). The capture's
sidecar names the file (``extra["imu"]["file"]``, relative to the capture's folder).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .atomic import atomic_write_text

__all__ = ["IMU_FILE", "IMU_COLUMNS", "ImuSamples", "read_imu", "write_imu"]

#: default file name beside the capture
IMU_FILE = "imu.csv"
#: the header, in order
IMU_COLUMNS = ("t_s", "gyro_x_rad_s", "gyro_y_rad_s", "gyro_z_rad_s", "acc_x_m_s2", "acc_y_m_s2", "acc_z_m_s2")


@dataclass(frozen=True)
class ImuSamples:
    """IMU samples: ``t (N,)`` s (capture clock, non-decreasing), ``gyro (N, 3)`` rad/s and ``acc (N, 3)``
    m/s² (specific force), IMU frame. ``source`` says where they came from (free text)."""

    t: np.ndarray
    gyro: np.ndarray
    acc: np.ndarray
    source: str = ""

    def __post_init__(self):
        t = np.asarray(self.t, float).reshape(-1)
        g = np.asarray(self.gyro, float).reshape(-1, 3)
        a = np.asarray(self.acc, float).reshape(-1, 3)
        if not (len(t) == len(g) == len(a)):
            raise ValueError(f"ImuSamples: t, gyro, acc differ in length ({len(t)}, {len(g)}, {len(a)})")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "gyro", g)
        object.__setattr__(self, "acc", a)

    def __len__(self) -> int:
        return len(self.t)

    @property
    def rate_hz(self) -> float:
        """Median sample rate (Hz); NaN with fewer than two samples."""
        if len(self.t) < 2:
            return float("nan")
        return float(1.0 / np.median(np.diff(self.t)))

    def summary(self) -> dict:
        return {"samples": len(self), "rate_hz": self.rate_hz,
                "t_first_s": float(self.t[0]) if len(self) else None,
                "t_last_s": float(self.t[-1]) if len(self) else None, "source": self.source}


def write_imu(path, samples: ImuSamples) -> Path:
    """Write ``samples`` to ``path`` (atomically); returns the path."""
    path = Path(path)
    arr = np.column_stack([samples.t, samples.gyro, samples.acc])
    lines = [",".join(IMU_COLUMNS)]
    lines += [",".join(repr(float(v)) for v in row) for row in arr]
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path


def read_imu(path, source: str | None = None) -> ImuSamples:
    """Read an ``imu.csv``; ValueError naming the file and the column / line at fault (missing or
    renamed column, a non-numeric or non-finite value, time running backwards)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ValueError(f"{path}: cannot read the IMU file ({exc})") from None
    lines = text.splitlines()
    if not lines:
        raise ValueError(f"{path}: empty IMU file (expected the header {','.join(IMU_COLUMNS)})")
    head = [h.strip() for h in lines[0].split(",")]
    missing = [c for c in IMU_COLUMNS if c not in head]
    if missing:
        raise ValueError(f"{path}: IMU file lacks column(s) {missing} (header: {head}; expected {list(IMU_COLUMNS)})")
    idx = [head.index(c) for c in IMU_COLUMNS]
    rows = []
    for ln, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        parts = line.split(",")
        if len(parts) != len(head):
            raise ValueError(f"{path}: line {ln}: {len(parts)} fields, the header has {len(head)}")
        vals = []
        for c, i in zip(IMU_COLUMNS, idx):
            try:
                vals.append(float(parts[i]))
            except ValueError:
                raise ValueError(f"{path}: line {ln}: column {c}: not a number ({parts[i]!r})") from None
        if not all(np.isfinite(vals)):
            bad = next(c for c, v in zip(IMU_COLUMNS, vals) if not np.isfinite(v))
            raise ValueError(f"{path}: line {ln}: column {bad}: not finite")
        rows.append(vals)
    a = np.asarray(rows, float).reshape(-1, len(IMU_COLUMNS))
    if a.shape[0] > 1 and np.any(np.diff(a[:, 0]) < 0):
        k = int(np.flatnonzero(np.diff(a[:, 0]) < 0)[0])
        raise ValueError(f"{path}: column t_s: time runs backwards at data row {k + 2} (line {k + 3})")
    return ImuSamples(a[:, 0], a[:, 1:4], a[:, 4:7], str(path) if source is None else source)
