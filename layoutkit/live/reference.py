"""Reference pose streams for accuracy checks (Chen eq. 25): files, interpolation, and the time
offset and fixed frame alignment between a reference system and the lighthouse, estimated from
the data.

Model. A reference (motion capture) reports the pose of its own marker body ``M`` in its own
world ``W``: ``p_W = R_m p_M + t_m``; the lighthouse pipeline reports the layout body ``B`` in the
station frame ``L``: ``p_L = R_l p_B + t_l``. With the fixed unknowns ``X = (R_x, t_x)``
(``W → L``), ``Y = (R_y, t_y)`` (``B → M``) and a clock offset ``tau`` (reference time =
lighthouse time + tau)::

    R_l(t) = R_x R_m(t + tau) R_y
    t_l(t) = R_x (R_m(t + tau) t_y + t_m(t + tau)) + t_x

Estimation (:func:`align_reference`): ``tau`` by cross-correlating the angular speed of both
streams (invariant to X and Y), refined by minimising the rotation residual; ``R_x`` from the
relative rotations, whose rotation vectors satisfy ``log(R_l,j R_l,i^T) = R_x log(R_m,j R_m,i^T)``
then alternating chordal means for ``R_x`` and ``R_y`` — both by the one rotation-averaging core,
:func:`layoutkit.rotations.fit_rotation_pair`, that the camera cross-check uses too; then ``(t_y, t_x)`` by linear least squares. A camera attitude stream is the
rotation-only case (no translation). The simulator's TRUTH.csv is already in the station frame and
needs none of this.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .._validate import as_array
from ..geometry import matrix_to_rotvec, rotvec_to_matrix
from ..rotations import fit_rotation_pair

__all__ = [
    "PoseTrack",
    "angular_speed",
    "estimate_time_offset",
    "Alignment",
    "estimate_alignment",
    "align_reference",
]

@dataclass(frozen=True)
class PoseTrack:
    """A time-stamped pose stream.

    t : (M,) s, strictly increasing; rotation : (M, 3, 3), ``p_frame = R p_body + translation``;
    translation : (M, 3) m, or None for an attitude-only stream (camera).
    """

    t: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray | None = None

    def __post_init__(self):
        t = as_array(self.t, "t", (None,))
        R = as_array(self.rotation, "rotation", (t.shape[0], 3, 3))
        if t.shape[0] < 2:
            raise ValueError(f"PoseTrack: expected at least 2 samples, got {t.shape[0]}")
        if np.any(np.diff(t) <= 0):
            raise ValueError("PoseTrack: times must be strictly increasing")
        if self.translation is not None:
            tr = as_array(self.translation, "translation", (t.shape[0], 3))
            object.__setattr__(self, "translation", tr)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "rotation", R)

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @classmethod
    def from_reference(cls, ref) -> "PoseTrack":
        """The track of a reference stream read by :func:`layoutkit.io.poses.read_reference` (sorted;
        of repeated times the first row is kept). ValueError naming the file for a position-only
        stream (the alignment needs attitude)."""
        if ref.rotvec is None:
            raise ValueError(f"{ref.path}: a position-only reference: the alignment needs attitude columns "
                             "(rx,ry,rz or qx,qy,qz,qw or r11..r33)")
        keep = np.concatenate([[True], np.diff(ref.t) > 0])
        return cls(ref.t[keep], rotvec_to_matrix(ref.rotvec[keep]),
                   None if ref.translation is None else ref.translation[keep])

    def at(self, times, max_gap: float | None = None):
        """Interpolated poses at ``times (F,)`` s: rotations by SLERP, translations linearly.

        Returns ``(R (F, 3, 3), t (F, 3) or None, valid (F,) bool)``; invalid (NaN) outside the
        track or across a gap longer than ``max_gap`` s (default: 5 × the median sample step).
        """
        q = np.asarray(times, dtype=float)
        if max_gap is None:
            max_gap = 5.0 * float(np.median(np.diff(self.t)))
        k = np.clip(np.searchsorted(self.t, q, side="right") - 1, 0, len(self) - 2)
        t0, t1 = self.t[k], self.t[k + 1]
        valid = (q >= self.t[0]) & (q <= self.t[-1]) & (t1 - t0 <= max_gap)
        a = np.clip((q - t0) / (t1 - t0), 0.0, 1.0)
        R0, R1 = self.rotation[k], self.rotation[k + 1]
        d = matrix_to_rotvec(R1 @ np.swapaxes(R0, -1, -2))
        R = rotvec_to_matrix(a[:, None] * d) @ R0
        R[~valid] = np.nan
        tr = None
        if self.translation is not None:
            tr = (1 - a)[:, None] * self.translation[k] + a[:, None] * self.translation[k + 1]
            tr[~valid] = np.nan
        return R, tr, valid


def angular_speed(track: PoseTrack, times, baseline: float) -> np.ndarray:
    """Angular speed (rad/s) of ``track`` at ``times (F,)`` by central differences over ``baseline`` s.

    Invariant to fixed rotations on either side (``|log(X R_j Y (X R_i Y)^T)| = |log(R_j R_i^T)|``).
    NaN where the track does not cover ``t ± baseline/2``.
    """
    q = np.asarray(times, float)
    Ra, _, va = track.at(q - baseline / 2)
    Rb, _, vb = track.at(q + baseline / 2)
    w = np.full(q.shape, np.nan)
    ok = va & vb
    if ok.any():
        w[ok] = np.linalg.norm(matrix_to_rotvec(Rb[ok] @ np.swapaxes(Ra[ok], -1, -2)), axis=-1) / baseline
    return w


def estimate_time_offset(lighthouse: PoseTrack, reference: PoseTrack, *, max_offset: float | None = None,
                         step: float = 0.01, baseline: float = 0.1, return_peak: bool = False):
    """Clock offset ``tau`` (s) with reference time = lighthouse time + tau.

    Pearson correlation of both streams' angular speeds (:func:`angular_speed`) on a common
    grid of ``step`` s for every lag within ``± max_offset`` whose overlap covers at least half
    of the shorter stream, with a parabolic peak refinement. Returns NaN when the streams do not overlap or hold no rotation.
    max_offset None (default): any clock origin (a motion-capture clock hours away from the
    lighthouse's); the grids start at each stream's own first sample, so the cost does not grow
    with the offset.
    """
    from scipy.signal import correlate

    g = np.arange(lighthouse.t[0], lighthouse.t[-1], step)
    wl = angular_speed(lighthouse, g, baseline)
    gr = np.arange(reference.t[0], reference.t[-1], step)
    wr = angular_speed(reference, gr, baseline)
    if len(g) < 8 or len(gr) < 8:
        return (float("nan"), float("nan")) if return_peak else float("nan")

    def norm(w):
        w = np.where(np.isfinite(w), w, np.nan)
        w = w - np.nanmean(w)
        return np.nan_to_num(w)

    a, b = norm(wl), norm(wr)
    if not (np.any(a) and np.any(b)):
        return (float("nan"), float("nan")) if return_peak else float("nan")
    # Pearson correlation over the overlap for every lag L (b[i + L] ~ a[i]), from FFT cross
    # sums and cumulative sums; overlaps shorter than half the shorter stream are not considered
    na, nb = len(a), len(b)
    lags = np.arange(-(na - 1), nb)
    sab = correlate(b, a, mode="full", method="fft")
    i0 = np.maximum(0, -lags)
    i1 = np.minimum(na, nb - lags)
    n = (i1 - i0).astype(float)
    ca = np.concatenate([[0.0], np.cumsum(a)])
    caa = np.concatenate([[0.0], np.cumsum(a * a)])
    cb = np.concatenate([[0.0], np.cumsum(b)])
    cbb = np.concatenate([[0.0], np.cumsum(b * b)])
    sa, saa = ca[i1] - ca[i0], caa[i1] - caa[i0]
    sb, sbb = cb[i1 + lags] - cb[i0 + lags], cbb[i1 + lags] - cbb[i0 + lags]
    nn = np.maximum(n, 1.0)
    cov = sab - sa * sb / nn
    var = np.maximum((saa - sa * sa / nn) * (sbb - sb * sb / nn), 1e-300)
    c = cov / np.sqrt(var)
    # lag L in samples: gr[0] + (i + L) step ~ g[0] + i step + tau
    tau = gr[0] - g[0] + lags * step
    far = np.zeros(tau.shape, bool) if max_offset is None else np.abs(tau) > max_offset
    c[far | (n < 0.5 * min(na, nb))] = -np.inf
    k = int(np.argmax(c))
    if not np.isfinite(c[k]):
        return (float("nan"), float("nan")) if return_peak else float("nan")
    if 0 < k < len(c) - 1 and np.all(np.isfinite(c[k - 1:k + 2])):
        den = c[k - 1] - 2 * c[k] + c[k + 1]
        if den < 0:
            est = float(tau[k] + 0.5 * (c[k - 1] - c[k + 1]) / den * step)
            return (est, float(c[k])) if return_peak else est
    return (float(tau[k]), float(c[k])) if return_peak else float(tau[k])


@dataclass(frozen=True)
class Alignment:
    """Fixed transforms between a reference system and the lighthouse (module docstring).

    tau : s, reference time = lighthouse time + tau.
    R_x (3, 3), t_x (3,) m : reference world → lighthouse frame; R_y (3, 3), t_y (3,) m : layout
        body → reference marker body (translations None for attitude-only references).
    rms_rot_rad, rms_trans_m : RMS fit residuals over the samples used; n : samples used.
    tau_correlation : peak angular-speed correlation of the clock-offset estimate (NaN if tau
        was given); below 0.5 the message warns that tau is weakly determined.
    success, status ("ok", "too_few_samples", "degenerate_rotation"), message.
    """

    tau: float
    R_x: np.ndarray
    R_y: np.ndarray
    t_x: np.ndarray | None
    t_y: np.ndarray | None
    rms_rot_rad: float
    rms_trans_m: float
    n: int
    success: bool
    status: str
    message: str
    tau_correlation: float = float("nan")

    def apply(self, track: PoseTrack, times):
        """Reference poses at lighthouse ``times (F,)`` mapped into the lighthouse frame.

        Returns ``(R (F, 3, 3), t (F, 3) or None, valid (F,))``.
        """
        Rm, tm, valid = track.at(np.asarray(times, float) + self.tau)
        R = self.R_x @ Rm @ self.R_y
        t = None
        if tm is not None and self.t_x is not None:
            t = (Rm @ self.t_y + tm) @ self.R_x.T + self.t_x
        return R, t, valid

    def as_dict(self) -> dict:
        return {
            "tau_s": self.tau, "R_x_rotvec": matrix_to_rotvec(self.R_x).tolist(),
            "t_x_m": None if self.t_x is None else self.t_x.tolist(),
            "R_y_rotvec": matrix_to_rotvec(self.R_y).tolist(),
            "t_y_m": None if self.t_y is None else self.t_y.tolist(),
            "rms_rot_rad": self.rms_rot_rad, "rms_trans_m": self.rms_trans_m, "n": self.n,
            "success": self.success, "status": self.status, "message": self.message,
            "tau_correlation": self.tau_correlation,
        }


def estimate_alignment(R_l, R_m, t_l=None, t_m=None, *, min_pair_angle: float = np.deg2rad(5.0),
                       tau: float = 0.0) -> Alignment:
    """Fixed alignment from time-matched pose pairs (module docstring, no time search).

    R_l, R_m : (N, 3, 3) lighthouse and reference attitudes at the same instants;
    t_l, t_m : (N, 3) m positions, or None for attitude only.
    Relative-rotation pairs ``(i, j)`` with angles in ``[min_pair_angle, 170°]`` feed the Kabsch
    fit of ``R_x``; they must span at least two rotation axes (else status "degenerate_rotation").
    """
    R_l = as_array(R_l, "R_l", (None, 3, 3))
    R_m = as_array(R_m, "R_m", (R_l.shape[0], 3, 3))
    N = R_l.shape[0]
    eye = np.eye(3)
    if N < 3:
        return Alignment(tau, eye, eye, None, None, np.nan, np.nan, N, False, "too_few_samples",
                         f"need >= 3 time-matched samples, got {N}")
    fit = fit_rotation_pair(R_l, R_m, body_offset=True, outlier_factor=None, min_pair_angle=min_pair_angle)
    if not fit.success:
        return Alignment(tau, eye, eye, None, None, np.nan, np.nan, N, False, fit.status,
                         "the reference rotates about fewer than two axes: R_x is not observable"
                         if fit.status == "degenerate_rotation" else fit.message)
    R_x, R_y, e_rot = fit.X, fit.Y, fit.residual_rad
    t_x = t_y = None
    rms_t = np.nan
    if t_l is not None and t_m is not None:
        t_l = as_array(t_l, "t_l", (N, 3))
        t_m = as_array(t_m, "t_m", (N, 3))
        # t_l - R_x t_m = R_x R_m t_y + t_x   (linear in t_y, t_x)
        A = np.concatenate([R_x @ R_m, np.broadcast_to(eye, (N, 3, 3))], axis=-1).reshape(3 * N, 6)
        b = (t_l - t_m @ R_x.T).reshape(3 * N)
        sol, *_ = np.linalg.lstsq(A, b, rcond=None)
        t_y, t_x = sol[:3], sol[3:]
        rms_t = float(np.sqrt(np.mean(np.sum((A @ sol - b).reshape(N, 3) ** 2, -1))))
    return Alignment(tau, R_x, R_y, t_x, t_y, float(np.sqrt(np.mean(e_rot ** 2))), rms_t, N, True, "ok",
                     "ok")


def align_reference(lighthouse: PoseTrack, reference: PoseTrack, *, tau: float | None = None,
                    max_offset: float | None = None, max_samples: int = 4000) -> Alignment:
    """Estimate clock offset and fixed frames of ``reference`` against lighthouse poses.

    lighthouse : good poses of the pipeline (a decimated sample suffices); reference : the
    reference stream (translation None for attitude only). ``tau`` known → no time search.
    The correlation estimate of tau is refined by a bounded 1-D search (± 0.1 s) minimising the
    rotation and position residuals of :func:`estimate_alignment`.
    """
    from scipy.optimize import minimize_scalar

    if tau is None:
        tau0, peak = estimate_time_offset(lighthouse, reference, max_offset=max_offset, return_peak=True)
        if not np.isfinite(tau0):
            eye = np.eye(3)
            return Alignment(np.nan, eye, eye, None, None, np.nan, np.nan, 0, False, "no_time_overlap",
                             "could not estimate the clock offset (no overlap or no rotation)")
    else:
        tau0, peak = float(tau), float("nan")
    sel = np.unique(np.linspace(0, len(lighthouse) - 1, min(max_samples, len(lighthouse))).astype(int))
    tl_all = lighthouse.t[sel]
    Rl_all = lighthouse.rotation[sel]
    pl_all = None if lighthouse.translation is None else lighthouse.translation[sel]
    every = max(1, len(sel) // 800)  # the 1-D time search works on a thinner sample

    def fit(tau_, every=1):
        tl, Rl, pl = tl_all[::every], Rl_all[::every], None if pl_all is None else pl_all[::every]
        Rm, tm, v = reference.at(tl + tau_)
        if v.sum() < 3:
            eye = np.eye(3)
            return Alignment(tau_, eye, eye, None, None, np.inf, np.inf, int(v.sum()), False,
                             "too_few_samples", "too few time-matched samples")
        return estimate_alignment(Rl[v], Rm[v], None if pl is None or tm is None else pl[v],
                                  None if tm is None else tm[v], tau=tau_)

    if tau is None:
        step = 0.1  # the correlation peak is good to a few grid steps on noisy poses
        a0 = fit(tau0, every)
        r0 = a0.rms_rot_rad if a0.success and a0.rms_rot_rad > 0 else 1.0
        t0 = a0.rms_trans_m if a0.success and a0.rms_trans_m > 0 else np.nan

        def cost(x):
            # rotation and (when present) position residuals, each relative to its value at the
            # correlation estimate: positions usually pin the clock offset much more sharply
            a = fit(x, every)
            if not a.success:
                return 1e9
            c = (a.rms_rot_rad / r0) ** 2
            if np.isfinite(t0) and np.isfinite(a.rms_trans_m):
                c += (a.rms_trans_m / t0) ** 2
            return c

        res = minimize_scalar(cost, bounds=(tau0 - step, tau0 + step), method="bounded",
                              options={"xatol": 1e-4})
        if res.success and cost(res.x) <= cost(tau0):
            tau0 = float(res.x)
    out = fit(tau0)
    msg = out.message
    if out.success and peak < 0.5:
        msg = (f"clock offset weakly determined (angular-speed correlation {peak:.2f}): the motion has too "
               "little variation in angular speed; pass the offset if it is known")
    return replace(out, tau_correlation=peak, message=msg)
