"""The result of a batched pose solve, :class:`PnPResult`.

Shared by the LH1 solver (:mod:`layoutkit.pnp_lh1`), the forward-model joint solver
(:mod:`layoutkit.joint`) and their public front :func:`layoutkit.pnp.solve_pnp`; it sits below all
three so none imports another for it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import status as _status

__all__ = ["PnPResult", "concat_results"]


@dataclass(frozen=True)
class PnPResult:
    """Poses of F frames.

    rotation : (F, 3, 3), translation : (F, 3) m — ``p = R p_body + t`` in the station frame (world
        frame for the joint solve); NaN where no pose was computed (too few sensors, degenerate).
    success : (F,) bool, ``status == status.OK``.
    status : (F,) int, codes of the one status table (:data:`layoutkit.status.NAMES`).
    residual_rms : (F,) rad, RMS angle residual over the seen angles of the returned pose.
    iterations : (F,) int, Levenberg–Marquardt iterations of the returned solution.
    alt_rotation, alt_translation, alt_residual_rms : (F, 3, 3), (F, 3), (F,) — the runner-up
        distinct pose (the other planar solution) where the frame is ``ambiguous``, NaN
        elsewhere (None when the solver does not report alternatives).
    """

    rotation: np.ndarray
    translation: np.ndarray
    success: np.ndarray
    status: np.ndarray
    residual_rms: np.ndarray
    iterations: np.ndarray
    alt_rotation: np.ndarray | None = None
    alt_translation: np.ndarray | None = None
    alt_residual_rms: np.ndarray | None = None

    @property
    def message(self) -> str:
        """One-line summary of the statuses (descriptions of :data:`layoutkit.status.DESCRIPTIONS`)."""
        s = np.asarray(self.status)
        if s.size == 0:
            return "no frames"
        if np.all(s == _status.OK):
            return f"ok ({s.size} frame(s))"
        parts = [f"{int(np.sum(s == k))} {name}" for k, name in _status.DESCRIPTIONS.items() if np.any(s == k)]
        return f"{s.size} frame(s): " + ", ".join(parts)


_FIELDS = ("rotation", "translation", "success", "status", "residual_rms", "iterations")
_ALTS = ("alt_rotation", "alt_translation", "alt_residual_rms")


def concat_results(parts) -> PnPResult:
    """One :class:`PnPResult` from the results of consecutive chunks (frame axis joined).

    The runner-up fields are kept when every part has them. No parts: an empty result (F = 0).
    """
    parts = list(parts)
    if not parts:
        return PnPResult(np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0, bool),
                         np.zeros(0, int), np.zeros(0), np.zeros(0, int))
    if len(parts) == 1:  # one chunk: its arrays as they are (no copy)
        return parts[0]
    extra = ({f: np.concatenate([getattr(r, f) for r in parts]) for f in _ALTS}
             if all(r.alt_rotation is not None for r in parts) else {})
    return PnPResult(*(np.concatenate([getattr(r, f) for r in parts]) for f in _FIELDS), **extra)
