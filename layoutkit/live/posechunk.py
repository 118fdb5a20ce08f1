"""The pose pipeline's result: :class:`PoseChunk`, the poses of consecutive frames or joint windows
as arrays over frames (produced by :mod:`layoutkit.live.pipeline` and
:mod:`layoutkit.live.joint_stream`, consumed by :mod:`layoutkit.live.session`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import status as _status
from ..io.poses import JOINT

__all__ = ["STATUS_NAMES", "PoseChunk", "empty_pose_arrays"]

#: The statuses the live pipeline gives, by name: the codes and names of the one table,
#: :mod:`layoutkit.status`.
STATUS_NAMES = {c: _status.NAMES[c] for c in (_status.OK, _status.TOO_FEW_LIT, _status.SOLVER_FAILED,
                                               _status.HIGH_RESIDUAL, _status.JUMP, _status.AMBIGUOUS,
                                               _status.LOW_REDUNDANCY, _status.IMPRECISE)}


@dataclass(frozen=True)
class PoseChunk:
    """Poses of ``F`` consecutive frames (arrays over frames).

    t : (F,) s (frame time, X sweep sync); station : (F,) int; n_lit : (F,) int;
    rotation : (F, 3, 3), translation : (F, 3) m — body pose ``p = R p_body + t`` in the station
        (or world) frame, NaN where no pose; rotvec : (F, 3) rad;
    status : (F,) int (codes of :mod:`layoutkit.status`); residual_rms : (F,) rad (RMS angle residual of the PnP fit);
    adop : (F,) deg/rad, pdop : (F,) m/rad — Chen eq. (22) at the solved pose with its lit set
        and ``rho`` (inf where no pose); lit : (F, n) bool.
    Joint poses (``station`` = :data:`layoutkit.io.poses.JOINT`, one per window, world frame) also
    carry n_stations : (F,) int, stations in the window, and lit_by_station : (F, S) int, sensors
    lit on both axes per station; ``n_lit`` counts lit (sensor, station) pairs.
    stations_used : (F,) int, stations whose angles entered the pose (joint: a sensor lit on both
    axes; per-station: 1 where solved); None = one per solved frame.
    sigma_theta : rad, the run's angle noise: the records' predicted 1-sigma ``PDOP · sigma_theta``
    (m) and ``ADOP · sigma_theta`` (deg) (Chen eq. 24); None = not reported.
    """

    t: np.ndarray
    station: np.ndarray
    n_lit: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    rotvec: np.ndarray
    status: np.ndarray
    residual_rms: np.ndarray
    adop: np.ndarray
    pdop: np.ndarray
    lit: np.ndarray
    n_stations: np.ndarray | None = None
    lit_by_station: np.ndarray | None = None
    stations_used: np.ndarray | None = None
    sigma_theta: float | None = None

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def good(self) -> np.ndarray:
        """(F,) bool, frames with a trusted pose."""
        return self.status == _status.OK

    @property
    def success(self) -> np.ndarray:
        """(F,) bool, same as :attr:`good` (the layoutkit.status convention's name)."""
        return self.good

    @property
    def message(self) -> str:
        """One line: statuses of the chunk's frames by name (:mod:`layoutkit.status`)."""
        return _status.summarize(self.status, STATUS_NAMES)

    def records(self):
        """Yield one plain dict per frame with a pose (the ``--json-lines`` contract).

        Joint poses: ``"station": "joint"``, plus ``n_stations`` (stations in the window) and
        ``lit_by_station`` (sensors lit on both axes, per station index). Every record: ``stations_used``
        and, with ``sigma_theta``, the predicted 1-sigma ``sigma_position_m`` / ``sigma_attitude_deg``
        (null where not finite)."""
        for i in range(len(self)):
            if self.status[i] in (_status.TOO_FEW_LIT, _status.SOLVER_FAILED):
                continue
            rec = {
                "t": float(self.t[i]),
                "rotvec": [float(v) for v in self.rotvec[i]],
                "translation": [float(v) for v in self.translation[i]],
                "n_lit": int(self.n_lit[i]),
                "status": STATUS_NAMES[int(self.status[i])],
                "adop": _finite_or_none(self.adop[i]),
                "pdop": _finite_or_none(self.pdop[i]),
                "residual_rms": _finite_or_none(self.residual_rms[i]),
                "station": "joint" if self.station[i] == JOINT else int(self.station[i]),
            }
            if self.n_stations is not None:
                rec["n_stations"] = int(self.n_stations[i])
                rec["lit_by_station"] = [int(v) for v in self.lit_by_station[i]]
            rec["stations_used"] = int(self.stations_used[i]) if self.stations_used is not None else 1
            if self.sigma_theta is not None:
                rec["sigma_position_m"] = _finite_or_none(self.pdop[i] * self.sigma_theta)
                rec["sigma_attitude_deg"] = _finite_or_none(self.adop[i] * self.sigma_theta)
            yield rec


def _finite_or_none(x):
    x = float(x)
    return x if np.isfinite(x) else None


def empty_pose_arrays(n: int):
    """The result arrays of ``n`` frames or windows before solving: ``R (n, 3, 3)``, ``t (n, 3)``,
    ``residual_rms (n,)`` NaN; ``status (n,)`` too-few-lit; ``adop, pdop (n,)`` inf."""
    return (np.full((n, 3, 3), np.nan), np.full((n, 3), np.nan), np.full(n, np.nan),
            np.full(n, _status.TOO_FEW_LIT, int), np.full(n, np.inf), np.full(n, np.inf))
