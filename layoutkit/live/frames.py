"""What every protocol decoder produces: one decoded rotor sweep (the contract between the
protocol decoders and the pose pipeline).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["SweepMeasurement", "DecodeStats"]


@dataclass(frozen=True)
class SweepMeasurement:
    """One decoded sweep of one station's rotor.

    t : float, s — time of the sweep's sync (zero) in the capture's time base (seconds since
        the capture started, device clock); the same time base as a simulator's TRUTH.csv.
    station : int — station index in the set-up (0-based).
    axis : int — LH1: 0 = X sweep (theta_x), 1 = Y sweep (theta_y). LH2: light plane 0 / 1.
    angles : (n,) float, rad — sweep angle of every sensor of the layout, NaN where not hit.
    seq : int | None — frame sequence number when the protocol carries one.
    kind : "lh1" or "lh2".
    """

    t: float
    station: int
    axis: int
    angles: np.ndarray
    seq: int | None = None
    kind: str = "lh1"


@dataclass
class DecodeStats:
    """Running counters of a decoder (mutable, owned by one decoder)."""

    bytes_in: int = 0
    good: int = 0
    bad: int = 0
    dropped: int = 0
    resyncs: int = 0
    skipped_bytes: int = 0
    resets: int = 0  # device restarts seen (sequence restarted)
    errors: int = 0  # internal decoder errors caught by the never-raise guard (should stay 0)
    reasons: dict = field(default_factory=dict)  # what could not be placed, by reason → count

    def drop(self, reason: str, k: int = 1) -> None:
        """Count ``k`` pulses / sweeps the decoder could not place, under ``reason``."""
        if k:
            self.dropped += int(k)
            self.reasons[reason] = self.reasons.get(reason, 0) + int(k)

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        d["reasons"] = dict(self.reasons)
        return d
