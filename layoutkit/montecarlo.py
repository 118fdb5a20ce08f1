"""Chunked Monte-Carlo of the measurement chain: simulate sweep angles, solve PnP, accumulate errors.

Each chunk is a pure function of its arguments and its own seed (``SeedSequence.spawn``), so it can
run on any Dask worker; it returns an :class:`ErrorSums` (a few numbers and two fixed histograms,
~20 kB), never per-frame arrays. Merged in chunk order (``layoutkit.parallel.map_reduce_ordered``)
the totals do not depend on the number of workers, and memory stays flat for any frame count.

Streaming precision (Chen eq. 23): with ``e_i`` the rotation vector of ``R_i R_true^T`` and
``d_i = t_i - t_true``, the group's spread about its mean is
``σ_rot² = mean|e_i|² - |mean e_i|²`` (the paper's mean rotation vector, exact to first order in
the spread) and ``σ_t² = mean|d_i|² - |mean d_i|²`` (exact) — from four running sums.
Accuracy (eq. 25) is ``RMS|e_i|``, ``RMS|d_i|`` against truth; the prediction is
``sqrt(mean ADOP²)·σθ`` (eq. 24) over the same frames.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .dop import gross_failures
from .geometry import attitude_error
from .parallel.sketch import LogHistogram
from .units import RAD2DEG

__all__ = ["ErrorSums", "frame_errors", "simulate_solve", "good_frames"]

# histogram ranges: attitude error 1e-7..10 deg, position error 1e-9..10 m, 100 bins per decade
_ROT_RANGE = (1e-7, 10.0)
_T_RANGE = (1e-9, 10.0)


def _hist_rot():
    return LogHistogram(*_ROT_RANGE, 100)


def _hist_t():
    return LogHistogram(*_T_RANGE, 100)


@dataclass
class ErrorSums:
    """Mergeable sums over solved frames (see the module docstring).

    frames : frames attempted; solved : frames the solver returned; gross : solved frames that are
    gross failures by :func:`layoutkit.dop.gross_failures` (not in the sums; a gross failure in the
    reports is gross or unsolved, the same rule); n : frames in the sums; sum_e (3,), sum_e2 : rotation-error vector (rad) and its
    squared norm; sum_d (3,), sum_d2 : position error (m); sum_adop2, sum_pdop2 : ADOP² (deg²/rad²),
    PDOP² (m²/rad²) of the same frames; hist_rot_deg, hist_t_m : error-magnitude sketches.
    """

    frames: int = 0
    solved: int = 0
    gross: int = 0
    n: int = 0
    sum_e: np.ndarray = field(default_factory=lambda: np.zeros(3))
    sum_e2: float = 0.0
    sum_d: np.ndarray = field(default_factory=lambda: np.zeros(3))
    sum_d2: float = 0.0
    sum_adop2: float = 0.0
    sum_pdop2: float = 0.0
    hist_rot_deg: LogHistogram = field(default_factory=_hist_rot)
    hist_t_m: LogHistogram = field(default_factory=_hist_t)

    def add(self, e_rotvec, d, solved, adop=None, pdop=None) -> "ErrorSums":
        """Add frames: e_rotvec (F, 3) rad, d (F, 3) m, solved (F,) bool; adop, pdop (F,) or scalars."""
        e_rotvec = np.asarray(e_rotvec, float).reshape(-1, 3)
        d = np.asarray(d, float).reshape(-1, 3)
        solved = np.asarray(solved, bool).ravel()
        F = len(solved)
        ang = np.linalg.norm(e_rotvec, axis=1)
        good = good_frames(e_rotvec, solved)
        gross = solved & ~good
        self.frames += F
        self.solved += int(solved.sum())
        self.gross += int(gross.sum())
        self.n += int(good.sum())
        e, dd = e_rotvec[good], d[good]
        self.sum_e = self.sum_e + e.sum(0)
        self.sum_e2 += float(np.einsum("ij,ij->", e, e))
        self.sum_d = self.sum_d + dd.sum(0)
        self.sum_d2 += float(np.einsum("ij,ij->", dd, dd))
        if adop is not None:
            a = np.broadcast_to(np.asarray(adop, float), (F,))[good]
            p = np.broadcast_to(np.asarray(pdop, float), (F,))[good]
            self.sum_adop2 += float(np.dot(a, a))
            self.sum_pdop2 += float(np.dot(p, p))
        self.hist_rot_deg.add(ang[good] * RAD2DEG)
        self.hist_t_m.add(np.linalg.norm(dd, axis=1))
        return self

    def merge(self, o: "ErrorSums") -> "ErrorSums":
        return ErrorSums(self.frames + o.frames, self.solved + o.solved, self.gross + o.gross, self.n + o.n,
                         self.sum_e + o.sum_e, self.sum_e2 + o.sum_e2, self.sum_d + o.sum_d,
                         self.sum_d2 + o.sum_d2, self.sum_adop2 + o.sum_adop2, self.sum_pdop2 + o.sum_pdop2,
                         self.hist_rot_deg.merge(o.hist_rot_deg), self.hist_t_m.merge(o.hist_t_m))

    def precision(self) -> tuple[float, float]:
        """``(σ_rot rad, σ_t m)``: spread about the mean (Chen eq. 23, streaming form)."""
        if self.n < 2:
            return float("nan"), float("nan")
        me, md = self.sum_e / self.n, self.sum_d / self.n
        return (float(np.sqrt(max(self.sum_e2 / self.n - me @ me, 0.0))),
                float(np.sqrt(max(self.sum_d2 / self.n - md @ md, 0.0))))

    def rms(self) -> tuple[float, float]:
        """``(RMS attitude error rad, RMS position error m)`` against truth (eq. 25)."""
        if self.n < 1:
            return float("nan"), float("nan")
        return float(np.sqrt(self.sum_e2 / self.n)), float(np.sqrt(self.sum_d2 / self.n))

    def predicted_rms(self, sigma: float) -> tuple[float, float]:
        """``(sqrt(mean ADOP²)·σ deg, sqrt(mean PDOP²)·σ m)`` over the same frames (eq. 24)."""
        if self.n < 1:
            return float("nan"), float("nan")
        return float(np.sqrt(self.sum_adop2 / self.n) * sigma), float(np.sqrt(self.sum_pdop2 / self.n) * sigma)

    def as_dict(self, sigma: float | None = None) -> dict:
        sr, st = self.precision()
        rr, rt = self.rms()
        out = {"frames": self.frames, "solved": self.solved, "unsolved": self.frames - self.solved,
               "gross_failures": self.gross + (self.frames - self.solved), "frames_used": self.n,
               "precision_rot_deg": sr * RAD2DEG, "precision_trans_m": st,
               "rms_rot_deg": rr * RAD2DEG, "rms_trans_m": rt,
               "abs_error_rot_deg": self.hist_rot_deg.as_dict(), "abs_error_trans_m": self.hist_t_m.as_dict()}
        if sigma is not None and self.sum_adop2 > 0:
            pr, pt = self.predicted_rms(sigma)
            out.update(predicted_rms_rot_deg=pr, predicted_rms_trans_m=pt,
                       ratio_rot=out["rms_rot_deg"] / pr, ratio_trans=rt / pt)
        return out


def good_frames(e_rotvec, solved) -> np.ndarray:
    """Frames that count (``(F,)`` bool): solved and not a gross failure (:func:`layoutkit.dop.gross_failures`)."""
    return ~gross_failures(np.linalg.norm(np.asarray(e_rotvec, float), axis=-1), success=solved)


def frame_errors(R_est, t_est, R_true, t_true):
    """Rotation-error vectors ``(F, 3)`` rad of ``R_est R_true^T`` and position errors ``(F, 3)`` m."""
    D = np.asarray(R_est) @ np.swapaxes(np.asarray(R_true), -1, -2)
    s = 0.5 * np.stack([D[..., 2, 1] - D[..., 1, 2], D[..., 0, 2] - D[..., 2, 0], D[..., 1, 0] - D[..., 0, 1]], -1)
    ang = attitude_error(R_est, R_true)
    ns = np.linalg.norm(s, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        e = np.where(ns > 0, s / ns, 0.0) * ang[..., None]
    return e, np.asarray(t_est, float) - np.asarray(t_true, float)


def simulate_solve(points, R, t, lit, *, sigma, rho, rng, quantize=True, rotor_rpm=None, clock_hz=None):
    """Simulate frames at poses ``R (F, 3, 3), t (F, 3)`` (station frame), solve them, return errors.

    points : (n, 3) body frame, m; lit : (F, n) bool. Returns ``(e_rotvec (F, 3), d (F, 3), solved (F,))``;
    a frame that did not solve (status) or came out behind the station counts as not solved.
    """
    from .pnp import solve_pnp
    from .simulate import simulate_angles

    kw = {}
    if rotor_rpm is not None:
        kw["rotor_rpm"] = rotor_rpm
    if clock_hz is not None:
        kw["clock_hz"] = clock_hz
    ang = simulate_angles(points, R, t, sigma=sigma, rho=rho, rng=rng, quantize=quantize, **kw)
    sol = solve_pnp(points, ang, lit)
    solved = np.asarray(sol.success, bool) & (np.asarray(sol.translation)[:, 2] > 0)
    e, d = frame_errors(np.where(solved[:, None, None], sol.rotation, np.eye(3)), np.where(
        solved[:, None], sol.translation, t), R, t)
    return e, d, solved
