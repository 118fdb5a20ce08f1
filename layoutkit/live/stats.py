"""Running statistics of a pose stream with flat memory (issue #5 part 4).

- :class:`StaticGroupTracker` — detects static stretches with fixed windows of ``W`` frames and
  measures each static group's precision (Chen eq. 23) against the predicted ADOP·σθ and
  PDOP·σθ (eq. 24), in one pass with O(W) memory.
- :class:`ErrorAccumulator` — accuracy against a reference pose stream (eq. 25): RMS, max and
  mean error, with the prediction ``sqrt(mean ADOP²)·σθ`` over the same frames.
- :class:`DecimatedSeries` — a bounded time series for plots (stride doubles when full).

Streaming eq. (23). The chordal mean rotation ``R̄`` of a group is only known at its end. Each
pose is stored as ``d_i = log(R_i R_0^T)`` relative to the first window's mean ``R_0``; with
``δ = log(R̄ R_0^T)`` the per-pose error ``log(R_i R̄^T) = d_i - δ + ½ d_i × δ + O(|d|²|δ|)`` and,
because ``(d_i - δ) ⟂ (d_i × δ)``, ``|log(R_i R̄^T)|² = |d_i - δ|² + O(|d|²|δ|²)``. So
``Σ|e_i|² = Σ|d_i|² - 2 δ·Σd_i + N|δ|²`` from three running sums — equal to the batch
:func:`layoutkit.dop.precision` to a relative ``O(spread²)`` (1e-6 at 0.1°).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..dop import pose_errors, precision, predicted_precision
from ..geometry import matrix_to_rotvec, nearest_rotation
from ..units import DEG, SIGMA_THETA_PAPER

__all__ = [
    "DecimatedSeries",
    "StaticGroup",
    "StaticGroupTracker",
    "ErrorSummary",
    "ErrorAccumulator",
]


class DecimatedSeries:
    """Keeps at most ``capacity`` rows of a stream: every row until full, then every 2nd, 4th, ...

    Rows are 1-D float vectors of length ``width``; memory is ``capacity × width`` floats.
    """

    def __init__(self, width: int, capacity: int = 20000):
        if capacity < 2:
            raise ValueError(f"capacity: expected >= 2, got {capacity}")
        self.width = int(width)
        self.capacity = int(capacity)
        self._buf = np.empty((capacity, width))
        self._len = 0
        self._stride = 1
        self._seen = 0

    def extend(self, rows) -> None:
        """Append rows ``(m, width)``. Stored row ``j`` is always stream row ``j · stride``."""
        rows = np.asarray(rows, dtype=float).reshape(-1, self.width)
        idx = self._seen + np.arange(len(rows))
        self._seen += len(rows)
        while True:
            keep = rows[idx % self._stride == 0]
            if self._len + len(keep) <= self.capacity:
                break
            half = (self._len + 1) // 2  # keep the multiples of 2·stride
            self._buf[:half] = self._buf[: self._len: 2]
            self._len = half
            self._stride *= 2
        self._buf[self._len:self._len + len(keep)] = keep
        self._len += len(keep)

    @property
    def stride(self) -> int:
        return self._stride

    def array(self) -> np.ndarray:
        """(m, width) copy of the stored rows, m <= capacity."""
        return self._buf[: self._len].copy()

    def __len__(self) -> int:
        return self._len


@dataclass(frozen=True)
class StaticGroup:
    """One static group: frames ``n`` between ``t_start`` and ``t_end`` (s).

    sigma_rot_deg, sigma_trans_m : measured precision, Chen eq. (23).
    predicted_rot_deg, predicted_trans_m : ``sqrt(mean ADOP²)·σθ``, ``sqrt(mean PDOP²)·σθ`` over the
        group's frames (eq. 24). mean_rotvec (3,) rad, mean_translation (3,) m: the group's mean pose.
    """

    t_start: float
    t_end: float
    n: int
    sigma_rot_deg: float
    sigma_trans_m: float
    predicted_rot_deg: float
    predicted_trans_m: float
    mean_rotvec: tuple
    mean_translation: tuple

    def as_dict(self) -> dict:
        return asdict(self)


class _GroupSums:
    """Running sums of one static group (see module docstring)."""

    def __init__(self, R0: np.ndarray):
        self.R0 = R0
        self.n = 0
        self.sumR = np.zeros((3, 3))
        self.sum_d = np.zeros(3)
        self.sum_dd = 0.0
        self.t_mean = np.zeros(3)
        self.t_m2 = 0.0
        self.sum_a2 = 0.0
        self.sum_p2 = 0.0
        self.t_start = np.inf
        self.t_end = -np.inf

    def add(self, t, R, tr, adop, pdop) -> None:
        d = matrix_to_rotvec(R @ self.R0.T)
        m = len(t)
        self.sumR += R.sum(0)
        self.sum_d += d.sum(0)
        self.sum_dd += float(np.sum(d * d))
        # Chan et al. parallel update of mean and sum of squared deviations (Welford for batches)
        bm = tr.mean(0)
        bm2 = float(np.sum((tr - bm) ** 2))
        n_new = self.n + m
        delta = bm - self.t_mean
        self.t_m2 += bm2 + float(delta @ delta) * self.n * m / n_new
        self.t_mean = self.t_mean + delta * m / n_new
        self.n = n_new
        self.sum_a2 += float(np.sum(np.square(adop)))
        self.sum_p2 += float(np.sum(np.square(pdop)))
        self.t_start = min(self.t_start, float(t[0]))
        self.t_end = max(self.t_end, float(t[-1]))

    def mean_rotation(self) -> np.ndarray:
        return nearest_rotation(self.sumR / self.n)

    def result(self, sigma_theta: float) -> StaticGroup:
        Rm = self.mean_rotation()
        dl = matrix_to_rotvec(Rm @ self.R0.T)
        ss = self.sum_dd - 2.0 * float(dl @ self.sum_d) + self.n * float(dl @ dl)
        s_rot = np.sqrt(max(ss, 0.0) / self.n)  # Chen eq. (23), streaming form
        s_t = np.sqrt(self.t_m2 / self.n)
        return StaticGroup(
            t_start=self.t_start, t_end=self.t_end, n=self.n,
            sigma_rot_deg=float(s_rot / DEG), sigma_trans_m=float(s_t),
            predicted_rot_deg=float(np.sqrt(self.sum_a2 / self.n) * sigma_theta),  # eq. (24)
            predicted_trans_m=float(np.sqrt(self.sum_p2 / self.n) * sigma_theta),
            mean_rotvec=tuple(float(v) for v in matrix_to_rotvec(Rm)),
            mean_translation=tuple(float(v) for v in self.t_mean),
        )


class StaticGroupTracker:
    """Static-window detection and per-group precision vs prediction, O(window) memory.

    Good poses are cut into consecutive windows of ``window`` frames. A window is static when its
    own spread (eq. 23 over the window) is at most ``factor`` times the predicted precision
    (ADOP·σθ, PDOP·σθ averaged over the window) and the means of its two halves differ by at most
    ``factor`` times their expected difference under noise alone (``2·σ/sqrt(window)``), which
    catches slow drifts that hide in the spread; with absolute tolerances ``rot_tol_rad`` /
    ``trans_tol_m`` both tests use them instead. Consecutive static windows whose mean stays within the
    same tolerance (scaled by ``sqrt(1/window + 1/n_group)``, the noise of the two means) of the
    group's mean form one group; a moving window or a jump closes
    the group. Groups shorter than ``min_frames`` are discarded.

    sigma_theta : rad, angle noise used for the predictions.
    """

    def __init__(self, sigma_theta: float = SIGMA_THETA_PAPER, window: int = 120, factor: float = 4.0,
                 rot_tol_rad: float | None = None, trans_tol_m: float | None = None,
                 min_frames: int | None = None, max_groups: int = 100000):
        if window < 3:
            raise ValueError(f"window: expected >= 3 frames, got {window}")
        self.sigma_theta = float(sigma_theta)
        self.window = int(window)
        self.factor = float(factor)
        self.rot_tol = rot_tol_rad
        self.trans_tol = trans_tol_m
        self.min_frames = self.window if min_frames is None else int(min_frames)
        self.max_groups = int(max_groups)
        self._t = np.empty(window)
        self._R = np.empty((window, 3, 3))
        self._tr = np.empty((window, 3))
        self._a = np.empty(window)
        self._p = np.empty(window)
        self._k = 0
        self._group: _GroupSums | None = None
        self._tol = (np.inf, np.inf)
        self.groups: list[StaticGroup] = []
        self.windows_static = 0
        self.windows_moving = 0

    def update(self, t, rotation, translation, adop, pdop) -> None:
        """Add good poses: t (F,) s, rotation (F, 3, 3), translation (F, 3) m, adop/pdop (F,)."""
        t = np.asarray(t, float)
        i = 0
        while i < len(t):
            m = min(self.window - self._k, len(t) - i)
            sl = slice(self._k, self._k + m)
            self._t[sl] = t[i:i + m]
            self._R[sl] = rotation[i:i + m]
            self._tr[sl] = translation[i:i + m]
            self._a[sl] = adop[i:i + m]
            self._p[sl] = pdop[i:i + m]
            self._k += m
            i += m
            if self._k == self.window:
                self._close_window()
                self._k = 0

    def _tolerances(self):
        pr_deg, pt = predicted_precision(self._a, self._p, self.sigma_theta)  # Chen eq. (24)
        pr = pr_deg * DEG  # rad
        tr = self.rot_tol if self.rot_tol is not None else self.factor * pr
        tt = self.trans_tol if self.trans_tol is not None else self.factor * pt
        return tr, tt

    def _close_window(self) -> None:
        s_rot, s_t = precision(self._R, self._tr)  # eq. (23) over the window
        tol_r, tol_t = self._tolerances()
        # drift: the means of the two half windows differ by ~2·sigma/sqrt(W) when static
        h = self.window // 2
        Ra, Rb = nearest_rotation(self._R[:h].mean(0)), nearest_rotation(self._R[h:].mean(0))
        drift_r = float(np.linalg.norm(matrix_to_rotvec(Ra @ Rb.T)))
        drift_t = float(np.linalg.norm(self._tr[:h].mean(0) - self._tr[h:].mean(0)))
        k = 2.0 / np.sqrt(self.window) if self.rot_tol is None else 1.0
        static = bool(np.isfinite(tol_r) and s_rot <= tol_r and s_t <= tol_t
                      and drift_r <= k * tol_r and drift_t <= k * tol_t)
        if not static:
            self.windows_moving += 1
            self._end_group()
            return
        self.windows_static += 1
        Rw = nearest_rotation(self._R.mean(0))
        tw = self._tr.mean(0)
        g = self._group
        if g is not None:
            # the window mean must agree with the group mean to within the noise of both means
            jump_r = np.linalg.norm(matrix_to_rotvec(Rw @ g.mean_rotation().T))
            jump_t = np.linalg.norm(tw - g.t_mean)
            kk = np.sqrt(1.0 / self.window + 1.0 / g.n) if self.rot_tol is None else 1.0
            if jump_r > kk * self._tol[0] or jump_t > kk * self._tol[1]:
                self._end_group()
                g = None
        if g is None:
            g = self._group = _GroupSums(Rw)
            self._tol = (tol_r, tol_t)
        g.add(self._t, self._R, self._tr, self._a, self._p)

    def _end_group(self) -> None:
        g, self._group = self._group, None
        if g is not None and g.n >= self.min_frames and len(self.groups) < self.max_groups:
            self.groups.append(g.result(self.sigma_theta))

    def finish(self) -> list[StaticGroup]:
        """End of stream: close the open group (a partial last window is ignored)."""
        self._end_group()
        self._k = 0
        return self.groups

    def current(self) -> StaticGroup | None:
        """The open group so far (for a dashboard), or the last closed one."""
        if self._group is not None and self._group.n:
            return self._group.result(self.sigma_theta)
        return self.groups[-1] if self.groups else None


@dataclass(frozen=True)
class ErrorSummary:
    """Accuracy against a reference (Chen eq. 25) over ``n`` frames.

    rms_rot_deg, max_rot_deg, rms_trans_m, max_trans_m : error statistics.
    mean_rot_err_rad (3,), mean_trans_err_m (3,) : mean error vectors (bias; rotation as the mean
        of ``log(R_est R_ref^T)``).
    predicted_rot_deg, predicted_trans_m : ``sqrt(mean ADOP²)·σθ``, ``sqrt(mean PDOP²)·σθ`` over the
        same frames (eq. 24) — what the RMS error equals when only angle noise is present.
    ratio_rot, ratio_trans : rms / predicted.
    """

    n: int
    rms_rot_deg: float
    max_rot_deg: float
    rms_trans_m: float
    max_trans_m: float
    mean_rot_err_rad: tuple
    mean_trans_err_m: tuple
    predicted_rot_deg: float
    predicted_trans_m: float
    ratio_rot: float
    ratio_trans: float

    def as_dict(self) -> dict:
        return asdict(self)


class ErrorAccumulator:
    """Running eq. (25) errors of estimated poses against reference poses, O(1) memory plus a
    bounded :class:`DecimatedSeries` ``series`` of ``(t, e_rot_rad, e_trans_m)`` for plots."""

    def __init__(self, sigma_theta: float = SIGMA_THETA_PAPER, series_capacity: int = 20000):
        self.sigma_theta = float(sigma_theta)
        self.n = 0
        self._s_r2 = 0.0
        self._s_t2 = 0.0
        self._max_r = 0.0
        self._max_t = 0.0
        self._sum_vr = np.zeros(3)
        self._sum_vt = np.zeros(3)
        self._s_a2 = 0.0
        self._s_p2 = 0.0
        self.series = DecimatedSeries(3, series_capacity)

    def update(self, t, R_est, t_est, R_ref, t_ref, adop=None, pdop=None) -> tuple[np.ndarray, np.ndarray]:
        """Add frames (all arrays over F frames); returns the per-frame ``(e_rot_rad, e_trans_m)``."""
        t = np.asarray(t, float)
        if len(t) == 0:
            return np.zeros(0), np.zeros(0)
        e_r, e_t = pose_errors(R_est, t_est, R_ref, t_ref)  # Chen eq. (25)
        self.n += len(t)
        self._s_r2 += float(np.sum(e_r ** 2))
        self._s_t2 += float(np.sum(e_t ** 2))
        self._max_r = max(self._max_r, float(e_r.max()))
        self._max_t = max(self._max_t, float(e_t.max()))
        self._sum_vr += matrix_to_rotvec(R_est @ np.swapaxes(R_ref, -1, -2)).sum(0)
        self._sum_vt += (np.asarray(t_est) - np.asarray(t_ref)).sum(0)
        if adop is not None:
            self._s_a2 += float(np.sum(np.square(adop)))
            self._s_p2 += float(np.sum(np.square(pdop)))
        self.series.extend(np.column_stack([t, e_r, e_t]))
        return e_r, e_t

    def summary(self) -> ErrorSummary | None:
        if self.n == 0:
            return None
        n = self.n
        pr = np.sqrt(self._s_a2 / n) * self.sigma_theta
        pt = np.sqrt(self._s_p2 / n) * self.sigma_theta
        rr = np.sqrt(self._s_r2 / n) / DEG
        rt = np.sqrt(self._s_t2 / n)
        return ErrorSummary(
            n=n, rms_rot_deg=float(rr), max_rot_deg=float(self._max_r / DEG),
            rms_trans_m=float(rt), max_trans_m=float(self._max_t),
            mean_rot_err_rad=tuple(float(v) for v in self._sum_vr / n),
            mean_trans_err_m=tuple(float(v) for v in self._sum_vt / n),
            predicted_rot_deg=float(pr), predicted_trans_m=float(pt),
            ratio_rot=float(rr / pr) if pr > 0 else float("nan"),
            ratio_trans=float(rt / pt) if pt > 0 else float("nan"),
        )
