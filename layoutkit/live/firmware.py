"""A device's own position estimates beside our poses, joined as the poses are written.

A Crazyflie microSD log carries the firmware's estimates (crossing beam, state estimate;
:func:`layoutkit.importers.cfusdlog.firmware_positions`) on the same clock and in the same world
frame as the joint poses of its replay, so no alignment is needed: each estimate is interpolated
at our pose times and the distance accumulated over our ok poses. :class:`FirmwareComparison` is a
column joiner of :class:`layoutkit.live.session.LiveSession` (``names``, ``join(chunk)``,
``summary()``): its columns go into ``poses.csv`` as the chunks are written — the file is written
once.
"""
from __future__ import annotations

import numpy as np

__all__ = ["FirmwareComparison"]


class FirmwareComparison:
    """Our ok poses vs the log's own position estimates (same clock, same world frame).

    firmware : ``{label: {"t": (M,) s, "position": (M, 3) m, "event": name}}``; max_gap_s : an
    estimate is interpolated linearly at a pose time only where two estimate rows within this gap
    bracket it (NaN otherwise). Columns ``firmware_<label>_x/y/z`` (m). The summary per label:
    compared poses, RMS / median / max distance (m), mean offset (m, ours − firmware). Memory: the
    estimates, and one distance per compared pose (for the median).
    """

    def __init__(self, firmware: dict, *, max_gap_s: float = 0.05):
        self.max_gap_s = float(max_gap_s)
        self._src = {}
        for label, fw in firmware.items():
            tf = np.asarray(fw["t"], float)
            o = np.argsort(tf, kind="stable")
            self._src[label] = (fw["event"], tf[o], np.asarray(fw["position"], float)[o])
        self._dist = {label: [] for label in self._src}
        self._diff = {label: np.zeros(3) for label in self._src}
        self.names = tuple(f"firmware_{label}_{ax}" for label in self._src for ax in "xyz")

    def _at(self, label, t):
        _, tf, pf = self._src[label]
        j = np.searchsorted(tf, t)
        inside = (j > 0) & (j < len(tf))
        jj = np.clip(j, 1, max(len(tf) - 1, 1))
        gap = tf[jj] - tf[jj - 1] if len(tf) > 1 else np.full(len(t), np.inf)
        use = inside & (gap <= self.max_gap_s)
        w = np.where(use, (t - tf[jj - 1]) / np.where(gap > 0, gap, 1.0), 0.0)
        p = np.where(use[:, None], pf[jj - 1] + w[:, None] * (pf[jj] - pf[jj - 1]) if len(tf) > 1 else np.nan, np.nan)
        return p, use

    def join(self, chunk) -> dict:
        """The columns for a :class:`~layoutkit.live.posechunk.PoseChunk` (name → (F,) m); the ok
        poses' distances are accumulated."""
        out = {}
        ok = chunk.good & np.all(np.isfinite(chunk.translation), 1) & np.all(np.isfinite(chunk.rotvec), 1)
        for label in self._src:
            p, use = self._at(label, chunk.t)
            for k, ax in enumerate("xyz"):
                out[f"firmware_{label}_{ax}"] = p[:, k]
            m = use & ok
            d = chunk.translation[m] - p[m]
            self._dist[label].append(np.linalg.norm(d, axis=1))
            self._diff[label] += d.sum(0)
        return out

    def summary(self) -> dict:
        out = {}
        for label, (event, tf, _) in self._src.items():
            r = np.concatenate(self._dist[label]) if self._dist[label] else np.zeros(0)
            out[label] = {"event": event, "rows": int(len(tf)), "compared_poses": int(r.size),
                          "rms_distance_m": float(np.sqrt(np.mean(r ** 2))) if r.size else None,
                          "median_distance_m": float(np.median(r)) if r.size else None,
                          "max_distance_m": float(r.max()) if r.size else None,
                          "mean_offset_m": (self._diff[label] / r.size).tolist() if r.size else None,
                          "columns": [f"firmware_{label}_{ax}" for ax in "xyz"]}
        return out
