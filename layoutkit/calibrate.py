"""Self-calibration: bundle adjustment of station poses, station calibration and sensor offsets.

About 1000 lines, one problem kept together on purpose: the column layout, the analytic sparse
Jacobian, the Schur-complement LM, the covariance and the per-parameter report all index the
same parameter vector; split, each piece would re-derive that layout.

Unknowns (``scipy.optimize.least_squares``, trust-region reflective, ``lsmr`` on the sparse
Jacobian, robust ``soft_l1`` loss on the normalised angle residuals):

- the body pose of every sample ``k`` (``p_world = R_k (p_i + o_i) + t_k``), 6 each;
- the pose of every station but the gauge station (default: the first station's pose is held as
  given, which fixes the world frame; with a reference pose table all stations are free and the
  reference fixes frame and scale), 6 each;
- each station's calibration parameters (:data:`layoutkit.lighthouse.MODEL_PARAMS` of its kind,
  both axes) with a weak Gaussian prior around the starting values (``calibration_prior`` rad);
- optionally per-sensor position offsets ``o_i`` (m), bounded by ``offset_bound`` with a
  Gaussian prior ``offset_prior`` (the positions a user measured by hand).

Poses are parametrised as left increments from the start, ``R = exp([x]x) R_0``; the analytic
Jacobian (:func:`layoutkit.lighthouse.measure_jacobian` chained through the poses, the SO(3) left
Jacobian for ``x``) fills a fixed sparsity pattern (:func:`jacobian_sparsity`); ``jacobian="2-point"``
instead lets scipy difference the model over that pattern (``jac_sparsity``), a cross-check.

Uncertainty: the covariance of the global parameters is the inverse of the Schur complement of the
per-sample pose blocks in ``J^T J`` (J the loss-weighted Jacobian at the solution), scaled by the
residual variance. When the sensor positions are not adjusted, the layout's own uncertainty
(``layout_sigma``, default ``offset_prior``, per coordinate) is carried as a *consider* term (Schmidt):
an unmodelled sensor offset ``d_o`` moves the estimate by ``-H^-1 H_go d_o``, so its covariance adds
``H^-1 C C^T H^-1 layout_sigma^2`` with ``C`` the Schur-reduced cross-information of the global
columns with the offsets. Noise averages down over repeated samples; a layout error does not (it is the
same in every sample of a static capture), which is why a static capture's white-noise sigmas alone
are far too small. Observability (per calibration parameter, prior sd ``sigma_0``):

- ``unobservable``: in the null space, or the posterior sd from noise alone exceeds ``0.5 sigma_0``
  (the data carry less than 3x the prior's information);
- ``weakly_observable``: passes that, but the sd including the layout consider term exceeds
  ``0.5 sigma_0`` — the data would fix it only if the layout were exact (it is confounded with sensor
  offsets and poses; e.g. tilt, curve and gib from one static pose).

Both are held at their starting (factory) values and the problem re-solved without them, until no
parameter fails (never returned as a fitted value). A fitted parameter of a station that came with a
calibration that lands more than :data:`SUSPECT_SIGMAS` reported sds from that factory value is
``suspect`` (value and sd returned: the data and the factory value disagree; check the station's
model, pose or the layout). Every global parameter also reports ``correlation``: its multiple
correlation with all other unknowns, ``sqrt(1 - 1 / (H_jj Sigma_jj))`` (1 = a linear combination of
them).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .geometry import right_jacobian_so3, rotvec_to_matrix
from .lighthouse import CALIBRATION_PARAMS, MODEL_PARAMS, Calibration, check_station_ids, measure_jacobian

__all__ = ["BA_PARAMS", "BundleResult", "ParameterEstimate", "bundle_adjust", "jacobian_sparsity", "to_ba", "from_ba",
           "station_to_ba", "station_from_ba", "static_segments", "timing_gain", "STATIC_POSITION_TOL",
           "STATIC_ROTATION_TOL", "PRIOR_DOMINATED"]

UNOBSERVABLE_RATIO = 0.5
#: Status of a device's own sensor term (offset, latency) whose sd exceeds UNOBSERVABLE_RATIO of its
#: prior: it is a prior-constrained unknown, so it is adjusted (never held), but its value is set
#: mostly by the prior — the data carry less than 3x the prior's information about it.
PRIOR_DOMINATED = "prior_dominated"
#: The Schur LM stops when this many accepted steps together lowered the cost by less than STALL_RTOL of it.
STALL_ITERATIONS = 10
STALL_RTOL = 1e-6
#: A body that stays within these of a segment's first pose (after a 9-sample running median) is at
#: rest there: ~10x the per-window scatter of the static Vive devices of ``lh1_test_cal`` (0.4 mm,
#: 0.23 deg: the lit set changes from window to window), far below any real motion.
STATIC_POSITION_TOL = 5e-3
STATIC_ROTATION_TOL = np.deg2rad(1.0)
#: A fitted calibration parameter this many reported sds from its factory value is ``suspect``.
SUSPECT_SIGMAS = 5.0


@dataclass(frozen=True)
class ParameterEstimate:
    """One global parameter: ``name`` (e.g. ``station 1 axis 0 phase``), ``value``, ``std`` (None when not
    fitted; includes the layout consider term), ``start``, ``unit``, ``status`` ("ok", "suspect",
    "weakly_observable", "unobservable" or "fixed"; module docstring; a sensor offset / latency:
    "ok" or :data:`PRIOR_DOMINATED`, adjusted either way), ``correlation``: multiple
    correlation with all other unknowns at the last solve where it was free (None if never free)."""

    name: str
    value: float
    std: float | None
    start: float
    unit: str
    status: str
    correlation: float | None = None


@dataclass(frozen=True)
class BundleResult:
    """Result of :func:`bundle_adjust`.

    stations : adjusted :class:`Station` list; points_body : (n, 3) adjusted sensor positions;
    rotation (K, 3, 3), translation (K, 3): sample poses (world); parameters : list of
    :class:`ParameterEstimate`; residual_before / residual_after : (K, S, n, 2) rad (NaN = no
    angle), before = with the starting parameters and each sample's best pose under them;
    success, status ("ok", "not_converged", "too_few", "nothing_determined": every free parameter
    held as unobservable, nothing adjusted), message; nfev; sigma_scale: sqrt of the
    residual variance in units of the given sigma.
    """

    stations: list
    points_body: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    parameters: list
    residual_before: np.ndarray
    residual_after: np.ndarray
    success: bool
    status: str
    message: str
    nfev: int = 0
    sigma_scale: float = float("nan")
    extra: dict = field(default_factory=dict)


def _wrap(a):
    return (a + np.pi) % (2.0 * np.pi) - np.pi


#: Calibration columns as adjusted: the gib and ogee sinusoids as linear cos/sin components
#: (``g sin(xi + gamma) = g cos(gamma) sin(xi) + g sin(gamma) cos(xi)``) — no sign/phase ambiguity
#: and no singular phase at zero magnitude, so their uncertainties are Gaussian.
BA_PARAMS = ("phase", "tilt", "curve", "gib_cos", "gib_sin", "ogee_cos", "ogee_sin")
_MIN_MAG = 1e-15


def to_ba(params):
    """Model parameters ``(..., 7)`` → adjusted columns :data:`BA_PARAMS`."""
    p = np.asarray(params, float)
    out = p.copy()
    out[..., 3], out[..., 4] = p[..., 4] * np.cos(p[..., 3]), p[..., 4] * np.sin(p[..., 3])
    out[..., 5], out[..., 6] = p[..., 6] * np.cos(p[..., 5]), p[..., 6] * np.sin(p[..., 5])
    return out


def from_ba(cols):
    """Adjusted columns → model parameters (magnitudes >= 0, phases in (-pi, pi])."""
    c = np.asarray(cols, float)
    out = c.copy()
    out[..., 4], out[..., 3] = np.maximum(np.hypot(c[..., 3], c[..., 4]), _MIN_MAG), np.arctan2(c[..., 4], c[..., 3])
    out[..., 6], out[..., 5] = np.maximum(np.hypot(c[..., 5], c[..., 6]), _MIN_MAG), np.arctan2(c[..., 6], c[..., 5])
    return out


def station_to_ba(params, kind):
    """A station's model parameters ``(2, 7)`` → adjusted columns; for LH2 the phase column holds
    ``phase_common = (phase_0 + phase_1) / 2`` (axis 0 row) and ``phase_diff = (phase_1 - phase_0) / 2``
    (axis 1 row): a common LH2 phase is exactly a rotation of the station about its y axis."""
    out = to_ba(params)
    if kind == "lh2":
        p = np.asarray(params, float)
        out[0, 0], out[1, 0] = 0.5 * (p[0, 0] + p[1, 0]), 0.5 * (p[1, 0] - p[0, 0])
    return out


def station_from_ba(cols, kind):
    """Inverse of :func:`station_to_ba`."""
    out = from_ba(cols)
    if kind == "lh2":
        c = np.asarray(cols, float)
        out[0, 0], out[1, 0] = c[0, 0] - c[1, 0], c[0, 0] + c[1, 0]
    return out


def _ba_names(kind):
    names = [list(BA_PARAMS), list(BA_PARAMS)]
    if kind == "lh2":
        names[0][0], names[1][0] = "phase_common", "phase_diff"
    return names


def _dc_to_ba(dc, model):
    """Chain rule: d angle / d model params ``(m, 7)`` → d angle / d :data:`BA_PARAMS`."""
    out = dc.copy()
    for ip, im in ((3, 4), (5, 6)):
        ph, mag = model[ip], model[im]
        f_ph_over_mag = dc[:, ip] / mag
        out[:, ip] = dc[:, im] * np.cos(ph) - f_ph_over_mag * np.sin(ph)
        out[:, im] = dc[:, im] * np.sin(ph) + f_ph_over_mag * np.cos(ph)
    return out


def static_segments(t, rotation, translation, ok=None, *, position_tol: float = STATIC_POSITION_TOL,
                    rotation_tol: float = STATIC_ROTATION_TOL, min_samples: int = 10, smooth: int = 9):
    """Which samples share one body pose: runs of samples at rest.

    t : (K,) s; rotation (K, 3, 3), translation (K, 3) m: per-sample solved poses (world frame);
    ok : (K,) bool, samples with a pose (others never join a segment). The poses are smoothed by a
    running median over ``smooth`` samples (the per-window scatter of a static device is mostly
    lit-set changes, not motion); in time order a segment takes the following samples while the
    smoothed pose stays within ``position_tol`` (m) and ``rotation_tol`` (rad) of the segment's first
    one. A segment of at least ``min_samples`` samples is one pose; every other sample is its own.
    Returns ``pose_of (K,)`` int (pose index of each sample, poses numbered in time order) and
    ``static (P,)`` bool (the pose is a segment at rest).
    """
    from scipy.ndimage import median_filter

    from .geometry import matrix_to_rotvec

    t = np.asarray(t, float)
    K = t.size
    R = np.asarray(rotation, float)
    T = np.asarray(translation, float)
    ok = np.ones(K, bool) if ok is None else np.asarray(ok, bool)
    ok = ok & np.all(np.isfinite(T), 1) & np.all(np.isfinite(R), (1, 2))
    order = np.argsort(t, kind="stable")
    g = order[ok[order]]                                  # samples with a pose, in time order
    label = np.full(K, -1)
    if g.size:
        rv = matrix_to_rotvec(R[g] @ R[g[0]].T)           # small within a segment at rest
        size = max(1, min(int(smooth), g.size))
        sm_t = median_filter(T[g], size=(size, 1), mode="nearest")
        sm_r = median_filter(rv, size=(size, 1), mode="nearest")
        seg, a = 0, 0
        for q in range(g.size):
            if (np.linalg.norm(sm_t[q] - sm_t[a]) > position_tol or np.linalg.norm(sm_r[q] - sm_r[a]) > rotation_tol):
                seg, a = seg + 1, q
            label[g[q]] = seg
    pose_of = np.full(K, -1)
    static = []
    nxt = 0
    counts = np.bincount(label[label >= 0]) if np.any(label >= 0) else np.zeros(0, int)
    seen: dict = {}
    for k in order:
        lab = label[k]
        if lab >= 0 and counts[lab] >= min_samples:
            if lab not in seen:
                seen[lab] = nxt
                static.append(True)
                nxt += 1
            pose_of[k] = seen[lab]
        else:
            pose_of[k] = nxt
            static.append(False)
            nxt += 1
    return pose_of, np.asarray(static, bool)


def timing_gain(station) -> float:
    """d angle / d sensor latency of ``station``'s angles, rad/s: a sensor that reports its hit
    ``tau`` s late reads the rotor ``omega tau`` further on. libsurvive's angles grow with the hit
    time on both LH1 axes and both LH2 planes (checked on the real recordings: +377 rad/s LH1, +328 rad/s
    on an LH2 channel); ours are ``theta = pi/2 + a`` (LH1: ``+omega``) and ``alpha = -a`` (LH2:
    ``-omega``); ``omega = 2 pi rotor_rpm / 60``."""
    omega = 2.0 * np.pi * float(station.rotor_rpm) / 60.0
    return omega if station.kind == "lh1" else -omega


class _Problem:
    """Index bookkeeping and the residual/Jacobian of one bundle adjustment (private)."""

    def __init__(self, P, ang, stations, *, sigma, free_cal, free_station, offsets, offset_prior,
                 calibration_prior, cal_start, reference, reference_sigma, pose_of=None, timing=False,
                 timing_prior=1e-7, offset_sensors=None, station_prior=None):
        self.P0 = P
        self.n = P.shape[0]
        self.ang = ang
        self.S = ang.shape[1]
        self.pose_of = np.arange(ang.shape[0]) if pose_of is None else np.asarray(pose_of, int)
        self.K = int(self.pose_of.max()) + 1 if self.pose_of.size else 0   # poses (columns)
        self.stations = stations
        self.sigma = sigma
        mask = np.isfinite(ang)
        self.obs = np.nonzero(mask)                               # (k, s, i, ax): k a sample
        self.kp = self.pose_of[self.obs[0]]                       # the pose of each observation
        self.meas = ang[mask]
        # free station-pose components (s, c), c = 0..2 rotation increment, 3..5 translation; a bare
        # station index frees all six
        self.free_station = [tuple(f) if isinstance(f, tuple) else (int(f), c) for f in free_station
                             for c in ((None,) if isinstance(f, tuple) else range(6))]
        self.free_station = [(int(a), int(b)) for a, b in self.free_station]
        self.free_cal = free_cal                                  # list of (s, ax, j)
        self.offsets = offsets
        self.offset_prior = offset_prior
        self.calibration_prior = calibration_prior
        self.cal_start = cal_start                                # (S, 2, 7)
        self.reference = reference
        self.reference_sigma = reference_sigma
        self.timing = bool(timing)
        self.timing_prior = float(timing_prior)
        #: d angle / d latency per station, rad/s (module docstring: +omega for LH1 theta, -omega for LH2 alpha)
        self.timing_gain = np.array([timing_gain(st) for st in stations])
        # which sensors carry offset / timing columns (default all; a device's sensors only when one
        # device of several is adjusted)
        self.adj = np.arange(self.n) if offset_sensors is None else np.asarray(offset_sensors, int)
        self.adj_col = np.full(self.n, -1)
        self.adj_col[self.adj] = np.arange(self.adj.size)
        na = self.adj.size
        # column layout
        self.c_pose = 0
        self.c_st = 6 * self.K
        self.c_cal = self.c_st + len(self.free_station)
        self.c_off = self.c_cal + len(free_cal)
        self.c_tim = self.c_off + (3 * na if offsets else 0)
        self.N = self.c_tim + (na if self.timing else 0)
        self.st_col = {sc: self.c_st + q for q, sc in enumerate(self.free_station)}
        self.st_free = sorted({sc[0] for sc in self.free_station})
        self.cal_col = {key: self.c_cal + q for q, key in enumerate(free_cal)}
        self.m_data = len(self.meas)
        self.m_cal = len(free_cal)
        self.m_off = 3 * na if offsets else 0
        self.m_tim = na if self.timing else 0
        self.m_ref = 0
        if reference is not None:
            self.ref_k = np.flatnonzero(reference[2])
            self.m_ref = 6 * len(self.ref_k)
        self.station_prior = station_prior                      # (rad, m) or None (free)
        self.m_stp = len(self.free_station) if station_prior is not None else 0
        self._stp_sd = (np.array([station_prior[c // 3] for _, c in self.free_station], float)
                        if station_prior is not None else None)
        self.M = self.m_data + self.m_cal + self.m_off + self.m_tim + self.m_stp + self.m_ref

    # ---------------------------------------------------------------- unpack
    def unpack(self, x, R0, t0, RS0, TS0):
        K = self.K
        xp = x[: 6 * K].reshape(K, 6)
        R = rotvec_to_matrix(xp[:, :3]) @ R0
        t = t0 + xp[:, 3:]
        RS, TS = RS0.copy(), TS0.copy()
        for s in self.st_free:
            v = self.station_increment(x, s)
            RS[s] = rotvec_to_matrix(v[:3]) @ RS0[s]
            TS[s] = TS0[s] + v[3:]
        cal = self.cal_start.copy()
        for (s, ax, j), c in self.cal_col.items():
            cal[s, ax, j] = x[c]
        off = np.zeros((self.n, 3))
        if self.offsets:
            off[self.adj] = x[self.c_off:self.c_tim].reshape(-1, 3)
        return R, t, RS, TS, cal, off

    def station_increment(self, x, s):
        """Station ``s``'s pose increment (6,): rotation vector (left) and translation, 0 where held."""
        v = np.zeros(6)
        for c in range(6):
            col = self.st_col.get((s, c))
            if col is not None:
                v[c] = x[col]
        return v

    def tau_of(self, x):
        """Per-sensor latency (n,) s (zero where not adjusted)."""
        tau = np.zeros(self.n)
        if self.timing:
            tau[self.adj] = x[self.c_tim:self.c_tim + self.adj.size]
        return tau

    def predict(self, R, t, RS, TS, cal, off, jacobian, tau=None):
        """Predicted angle per observation and (optionally) the Jacobian pieces."""
        _, s, i, ax = self.obs
        k = self.kp
        P = self.P0 + off
        pw = np.einsum("mij,mj->mi", R[k], P[i]) + t[k]
        pred = np.empty(len(k))
        parts = {} if jacobian else None
        for q, st in enumerate(self.stations):
            sel = np.flatnonzero(s == q)
            if sel.size == 0:
                continue
            ps = np.einsum("ji,mj->mi", RS[q], pw[sel] - TS[q])  # R_s^T (p_w - T_s)
            model = station_from_ba(cal[q], st.kind)              # (2, 7) model parameters
            c = Calibration(model, st.kind, st.calibration.gib_argument if st.calibration else "ideal")
            a, dp, dc = measure_jacobian(ps[:, None, :], c, jacobian=jacobian)
            axs = ax[sel]
            pred[sel] = a[np.arange(sel.size), 0, axs]
            if tau is not None:
                pred[sel] += self.timing_gain[q] * tau[i[sel]]
            if jacobian:
                aps = dp[np.arange(sel.size), 0, axs]             # (m, 3) d angle / d p_s
                aw = aps @ RS[q].T                                 # d angle / d p_world
                own = dc[np.arange(sel.size), 0, axs]
                dcs = np.zeros((sel.size, 2, own.shape[-1]))      # d angle / d column (axis row, j)
                for k_ax in (0, 1):
                    m_ax = axs == k_ax
                    dcs[m_ax, k_ax] = _dc_to_ba(own[m_ax], model[k_ax])
                if st.kind == "lh2":                               # phase_common / phase_diff
                    dphi = own[:, 0]
                    dcs[:, 0, 0] = dphi
                    dcs[:, 1, 0] = np.where(axs == 0, -dphi, dphi)
                parts[q] = (sel, aw, pw[sel] - TS[q], dcs)
        return pred, pw, parts

    # ---------------------------------------------------------------- residual & Jacobian
    def residual(self, x, base):
        R, t, RS, TS, cal, off = self.unpack(x, *base)
        pred, _, _ = self.predict(R, t, RS, TS, cal, off, False, self.tau_of(x))
        return self._stack(x, pred, R, t, cal, off)

    def _stack(self, x, pred, R, t, cal, off):
        r = [_wrap(self.meas - pred) / self.sigma]
        if self.m_cal:
            r.append(np.array([(cal[s, ax, j] - self.cal_start[s, ax, j]) / self.calibration_prior[j]
                               for (s, ax, j) in self.free_cal]))
        if self.m_off:
            r.append(off[self.adj].ravel() / self.offset_prior)
        if self.m_tim:
            r.append(x[self.c_tim:self.c_tim + self.m_tim] / self.timing_prior)
        if self.m_stp:
            r.append(x[self.c_st:self.c_cal] / self._stp_sd)
        if self.m_ref:
            Rr, tr = self.reference[0][self.ref_k], self.reference[1][self.ref_k]
            from .geometry import matrix_to_rotvec
            e_rot = matrix_to_rotvec(R[self.ref_k] @ np.swapaxes(Rr, 1, 2))
            e_t = t[self.ref_k] - tr
            r.append(np.column_stack([e_rot / self.reference_sigma[0], e_t / self.reference_sigma[1]]).ravel())
        return np.concatenate(r)

    def pattern(self):
        """(rows, cols) of the nonzeros: the ``jac_sparsity`` structure."""
        _, s, i, ax = self.obs
        k = self.kp
        m = np.arange(self.m_data)
        rows, cols = [], []
        for c in range(6):
            rows.append(m)
            cols.append(6 * k + c)
        for (q, c), col in self.st_col.items():
            sel = np.flatnonzero(s == q)
            rows.append(sel)
            cols.append(np.full(sel.size, col))
        for (q, a, j), c0 in self.cal_col.items():
            both = self.stations[q].kind == "lh2" and j == 0
            sel = np.flatnonzero((s == q) & ((ax == a) | both))
            rows.append(sel)
            cols.append(np.full(sel.size, c0))
        ja = self.adj_col[i]
        ma = m[ja >= 0]
        if self.offsets:
            for c in range(3):
                rows.append(ma)
                cols.append(self.c_off + 3 * ja[ja >= 0] + c)
        if self.timing:
            rows.append(ma)
            cols.append(self.c_tim + ja[ja >= 0])
        r0 = self.m_data
        if self.m_cal:
            rows.append(r0 + np.arange(self.m_cal))
            cols.append(self.c_cal + np.arange(self.m_cal))
            r0 += self.m_cal
        if self.m_off:
            rows.append(r0 + np.arange(self.m_off))
            cols.append(self.c_off + np.arange(self.m_off))
            r0 += self.m_off
        if self.m_tim:
            rows.append(r0 + np.arange(self.m_tim))
            cols.append(self.c_tim + np.arange(self.m_tim))
            r0 += self.m_tim
        if self.m_stp:
            rows.append(r0 + np.arange(self.m_stp))
            cols.append(self.c_st + np.arange(self.m_stp))
            r0 += self.m_stp
        if self.m_ref:
            for q, kk in enumerate(self.ref_k):
                for a in range(6):
                    for b in range(6):
                        rows.append(np.array([r0 + 6 * q + a]))
                        cols.append(np.array([6 * kk + b]))
        return np.concatenate(rows), np.concatenate(cols)

    def jacobian(self, x, base):
        from scipy.sparse import coo_matrix

        R, t, RS, TS, cal, off = self.unpack(x, *base)
        _, pw, parts = self.predict(R, t, RS, TS, cal, off, True)
        _, s, i, ax = self.obs
        k = self.kp
        K = self.K
        Jl = right_jacobian_so3(-x[: 6 * K].reshape(K, 6)[:, :3])  # left Jacobian J_l(x) = J_r(-x)
        rows, cols, vals = [], [], []
        aw_all = np.zeros((self.m_data, 3))
        for q, (sel, aw, qv, dc) in parts.items():
            aw_all[sel] = aw
            if q in self.st_free:
                xs = self.station_increment(x, q)[:3]
                Js = np.cross(aw, qv) @ right_jacobian_so3(-xs)
                for c in range(6):
                    col = self.st_col.get((q, c))
                    if col is not None:
                        rows.append(sel); cols.append(np.full(sel.size, col))
                        vals.append(-Js[:, c] if c < 3 else aw[:, c - 3])
            for (qq, a, j), c0 in self.cal_col.items():
                if qq != q:
                    continue
                m = (ax[sel] == a) | (self.stations[q].kind == "lh2" and j == 0)
                rows.append(sel[m]); cols.append(np.full(int(m.sum()), c0)); vals.append(-dc[m, a, j])
        lever = pw - t[k]
        Jr = np.einsum("mi,mij->mj", np.cross(lever, aw_all), Jl[k])
        m_idx = np.arange(self.m_data)
        for c in range(3):
            rows.append(m_idx); cols.append(6 * k + c); vals.append(-Jr[:, c])
        for c in range(3):
            rows.append(m_idx); cols.append(6 * k + 3 + c); vals.append(-aw_all[:, c])
        ja = self.adj_col[i]
        ma = ja >= 0
        if self.offsets:
            Jo = np.einsum("mi,mij->mj", aw_all[ma], R[k[ma]])
            for c in range(3):
                rows.append(m_idx[ma]); cols.append(self.c_off + 3 * ja[ma] + c); vals.append(-Jo[:, c])
        if self.timing:
            rows.append(m_idx[ma]); cols.append(self.c_tim + ja[ma]); vals.append(-self.timing_gain[s[ma]])
        vals = [v / self.sigma for v in vals]                    # residual = (meas - pred) / sigma
        r0 = self.m_data
        if self.m_cal:
            rows.append(r0 + np.arange(self.m_cal)); cols.append(self.c_cal + np.arange(self.m_cal))
            vals.append(np.array([1.0 / self.calibration_prior[j] for (_, _, j) in self.free_cal]))
            r0 += self.m_cal
        if self.m_off:
            rows.append(r0 + np.arange(self.m_off)); cols.append(self.c_off + np.arange(self.m_off))
            vals.append(np.full(self.m_off, 1.0 / self.offset_prior))
            r0 += self.m_off
        if self.m_tim:
            rows.append(r0 + np.arange(self.m_tim)); cols.append(self.c_tim + np.arange(self.m_tim))
            vals.append(np.full(self.m_tim, 1.0 / self.timing_prior))
            r0 += self.m_tim
        if self.m_stp:
            rows.append(r0 + np.arange(self.m_stp)); cols.append(self.c_st + np.arange(self.m_stp))
            vals.append(1.0 / self._stp_sd)
            r0 += self.m_stp
        if self.m_ref:
            Rr = self.reference[0][self.ref_k]
            from .geometry import matrix_to_rotvec
            e = matrix_to_rotvec(R[self.ref_k] @ np.swapaxes(Rr, 1, 2))
            # d log(exp(x) R0 Rr^T) / dx = J_l(e)^-1 J_l(x), J_l(v) = J_r(-v)
            Jref = np.linalg.solve(right_jacobian_so3(-e), Jl[self.ref_k])
            for q, kk in enumerate(self.ref_k):
                Jk = Jref[q]
                for a in range(3):
                    for b in range(3):
                        rows.append(np.array([r0 + 6 * q + a])); cols.append(np.array([6 * kk + b]))
                        vals.append(np.array([Jk[a, b] / self.reference_sigma[0]]))
                for a in range(3):
                    rows.append(np.array([r0 + 6 * q + 3 + a])); cols.append(np.array([6 * kk + 3 + a]))
                    vals.append(np.array([1.0 / self.reference_sigma[1]]))
        return coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(self.M, self.N)).tocsr()


def jacobian_sparsity(problem: _Problem):
    """The sparsity pattern (``scipy.sparse`` 0/1 matrix) passed to ``least_squares(jac_sparsity=...)``."""
    from scipy.sparse import coo_matrix

    r, c = problem.pattern()
    return coo_matrix((np.ones(r.size), (r, c)), shape=(problem.M, problem.N)).tocsr()


def _pose_blocks(Jp, K):
    """The K diagonal 6 × 6 blocks (K, 6, 6) of ``Jp^T Jp`` for the per-sample pose columns ``Jp``
    (M, 6K) (each sample's pose couples only to itself: the rest of ``Jp^T Jp`` is zero)."""
    Hpp = (Jp.T @ Jp).tocsr()
    blocks = np.zeros((K, 6, 6))
    rows = np.arange(K) * 6
    for a in range(6):
        for b in range(6):
            blocks[:, a, b] = np.asarray(Hpp[rows + a, rows + b]).ravel()
    return blocks


def _global_covariance(J, K):
    """Covariance (up to the residual variance) of the global columns: inverse Schur complement of
    the per-sample 6 × 6 pose blocks of ``J^T J``."""
    Jc = J.tocsc()
    Jp, Jg = Jc[:, : 6 * K], Jc[:, 6 * K:]
    if Jg.shape[1] == 0:                                       # every global parameter held
        return np.zeros((0, 0)), np.zeros(0, bool)
    Hgg = (Jg.T @ Jg).toarray()
    Hgp = (Jg.T @ Jp).toarray().reshape(Jg.shape[1], K, 6)
    inv = np.linalg.pinv(_pose_blocks(Jp, K))
    red = Hgg - np.einsum("gki,kij,hkj->gh", Hgp, inv, Hgp)
    red = 0.5 * (red + red.T)
    d = np.sqrt(np.maximum(np.diag(red), 1e-300))
    w, V = np.linalg.eigh(red / np.outer(d, d))
    keep = w > 1e-12 * max(w.max(), 1e-300)
    cov_n = (V[:, keep] / w[keep]) @ V[:, keep].T
    null = np.zeros(len(d), bool)
    if np.any(~keep):
        null = np.any(np.abs(V[:, ~keep]) > 0.1, axis=1)
    return cov_n / np.outer(d, d), null


def _consider_covariance(Jw, Jo, K, cov, chunk: int = 2048):
    """Covariance (absolute, parameter units) the unadjusted sensor offsets add to the global columns.

    Jw : (M, 6K + G) weighted Jacobian of the adjusted problem; Jo : (M, 3n) weighted Jacobian of the
    same rows w.r.t. the sensor offsets (zero on prior rows); cov : (G, G) the global covariance of
    :func:`_global_covariance` (the inverse Schur-reduced information). An offset error ``d_o`` moves
    the estimate by ``-Sigma C d_o`` with ``C = H_go - H_gp H_pp^-1 H_po`` (sample poses eliminated), so
    per unit offset variance the consider term is ``Sigma C C^T Sigma`` (multiply by ``layout_sigma^2``).
    The sample poses are eliminated ``chunk`` samples at a time (memory bounded for any K).
    """
    Jc = Jw.tocsc()
    Jg = Jc[:, 6 * K:]
    Joc = Jo.tocsc()
    Cr = (Jg.T @ Joc).toarray()                                # H_go, then minus the pose parts
    for k0 in range(0, K, chunk):                              # bounded memory for any K
        k1 = min(K, k0 + chunk)
        Jp = Jc[:, 6 * k0: 6 * k1]
        kk = k1 - k0
        Hpo = (Jp.T @ Joc).toarray().reshape(kk, 6, -1)
        Hgp = (Jg.T @ Jp).toarray().reshape(Jg.shape[1], kk, 6)
        Cr -= np.einsum("gki,kij,kjo->go", Hgp, np.linalg.pinv(_pose_blocks(Jp, kk)), Hpo)
    A = cov @ Cr
    return A @ A.T


def bundle_adjust(points_body, angles, stations, *, sigma: float, initial_poses, fit_calibration: bool = True,
                  sensor_offsets: bool = False, offset_prior: float = 1e-3, offset_bound: float = 5e-3,
                  calibration_prior: float = 0.1, reference=None, reference_sigma=(1e-3, 1e-3),
                  gauge_station: int = 0, loss: str = "soft_l1", f_scale: float = 3.0, max_nfev: int = 200,
                  solver: str = "schur", jacobian: str = "analytic", before=None,
                  layout_sigma: float | None = None, pose_of=None, sensor_timing: bool = False,
                  timing_prior: float = 1e-7, sensor_labels=None, adjusted_sensors=None,
                  station_prior=None, hold_station_prior: bool = True) -> BundleResult:
    """Bundle adjustment of K samples seen by S stations (module docstring).

    points_body : (n, 3) m, the layout as measured; angles : (K, S, n, 2) rad, measured (distorted)
    angles in each station's convention, NaN = not seen; stations : S :class:`Station` (start
    poses in the world frame, kind, start calibration or None = zero); sigma : angle noise (rad),
    the residual scale; initial_poses : ``(R (K, 3, 3), t (K, 3))`` world-frame start of every sample
    (e.g. :func:`layoutkit.joint.solve_joint` with the starting stations). reference : optional
    ``(R (K, 3, 3), t (K, 3), have (K,))`` reference poses in the world frame (then no station is
    held fixed); reference_sigma : (rad, m). calibration_prior : prior sd of each calibration
    parameter around its start (rad); gib and ogee phases get pi. ``before`` : optional (K, S, n, 2)
    residuals to report as "before" (default: the residuals at the start).
    solver : "schur" (default: Levenberg–Marquardt whose step eliminates the 6 × 6 sample-pose
    blocks exactly — the Schur complement; robust loss by iterative reweighting) or
    "least_squares" (``scipy.optimize.least_squares``, trf + lsmr over the sparse problem;
    ``jacobian="2-point"`` differences it over :func:`jacobian_sparsity`). Both minimise the same cost
    (``loss`` on the angle residuals in units of sigma, ``f_scale`` sigmas); the tests check they agree.
    layout_sigma : m, 1-sigma of each sensor coordinate when ``sensor_offsets`` is off (default
    ``offset_prior``; 0 = the layout is exact): carried as a consider term in every reported sd and in
    the ``weakly_observable`` test (module docstring).
    pose_of : optional (K,) int, the body pose of each sample (default: one pose per sample); samples
        that share a pose (a static segment: the body did not move) share its 6 unknowns. Then
        ``initial_poses`` and the returned ``rotation``/``translation`` are per pose, and a
        ``reference`` is per pose too.
    sensor_timing : also adjust a per-sensor latency ``tau_i`` (s; prior sd ``timing_prior``): the
        sensor's angles read ``timing_gain(station) * tau_i`` more (:func:`timing_gain`).
    sensor_labels : optional n names for the sensor parameters (e.g. ``"HMD 3"`` when several devices'
        sensors are stacked into one body, each device's samples seeing only its own sensors).
    adjusted_sensors : optional indices of the sensors whose offsets / timing are adjusted (default
        all); the others are held as given (e.g. a device used only through its known layout).
    station_prior : optional ``(rad, m)`` prior sd of each free station's pose around its start (the
        start is itself a solution, e.g. libsurvive's ``LH_POSE``): directions the data do not
        determine stay where they were instead of absorbing the devices' own errors. None: free.
    hold_station_prior : with ``station_prior``, hold a station term whose posterior sd exceeds
        ``UNOBSERVABLE_RATIO`` x its prior at the start (True, the default), or keep every station term
        adjusted as a prior-constrained unknown (False: the maximum a posteriori estimate, the prior
        pulling each term toward the given pose by its information; such a term is reported
        ``prior_dominated`` rather than held).
    """
    from scipy.optimize import least_squares

    P = np.asarray(points_body, float)
    ang = np.asarray(angles, float)
    K, S, n = ang.shape[:3]
    stations = list(stations)
    check_station_ids(stations)
    pose_of = np.arange(K) if pose_of is None else np.asarray(pose_of, int)
    if pose_of.shape != (K,) or (K and pose_of.min() < 0):
        raise ValueError(f"pose_of: expected {K} non-negative pose indices, got shape {pose_of.shape}")
    R0 = np.asarray(initial_poses[0], float).copy()
    t0 = np.asarray(initial_poses[1], float).copy()
    Kp = R0.shape[0]
    if K and pose_of.max() >= Kp:
        raise ValueError(f"pose_of: index {pose_of.max()} but only {Kp} initial poses")
    good = np.all(np.isfinite(R0), (1, 2)) & np.all(np.isfinite(t0), 1)
    good_s = good[pose_of]
    ang = np.where(good_s[:, None, None, None], ang, np.nan)
    R0[~good], t0[~good] = np.eye(3), 0.0
    if np.sum(np.isfinite(ang)) < 6 * max(int(good.sum()), 1) + 20 or good_s.sum() < 2:
        z = np.full(ang.shape, np.nan)
        return BundleResult(stations, P, R0, t0, [], z, z, False, "too_few",
                            f"too few samples with a start pose ({int(good_s.sum())} of {K})")
    adj = np.arange(n) if adjusted_sensors is None else np.asarray(adjusted_sensors, int)
    labels = [str(i) for i in range(n)] if sensor_labels is None else [str(x) for x in sensor_labels]
    RS0 = np.stack([st.rotation for st in stations])
    TS0 = np.stack([st.translation for st in stations])
    cal_start = np.stack([station_to_ba(st.calibration.params if st.calibration is not None
                                        else np.zeros((2, len(CALIBRATION_PARAMS))), st.kind) for st in stations])
    prior = np.full(len(BA_PARAMS), float(calibration_prior))
    free_station = [(s, c) for s in range(S) if reference is not None or s != gauge_station for c in range(6)]
    st_prior = None if station_prior is None else np.asarray(station_prior, float)
    free_cal = []
    if fit_calibration:
        for s, st in enumerate(stations):
            names = MODEL_PARAMS[st.kind]
            for ax in (0, 1):
                for j, name in enumerate(CALIBRATION_PARAMS):
                    if name in names and not (st.kind == "lh2" and ax == 0 and j == 0):
                        free_cal.append((s, ax, j))   # (LH2 phase_common is the station's yaw: never free)
    fixed: set = set()
    weak: set = set()
    lsig = float(offset_prior if layout_sigma is None else layout_sigma)
    consider = (not sensor_offsets) and lsig > 0
    base = (R0, t0, RS0, TS0)
    x0_full = None
    before_res = before
    corr_seen: dict = {}
    st_held: set = set()
    st_weak: set = set()
    prev = None
    for attempt in range(len(free_cal) + len(free_station) + 1):
        cal_list = [c for c in free_cal if c not in fixed]
        st_list = [c for c in free_station if c not in st_held]
        pb = _Problem(P, ang, stations, sigma=sigma, free_cal=cal_list, free_station=st_list,
                      offsets=sensor_offsets, offset_prior=offset_prior, calibration_prior=prior,
                      cal_start=cal_start, reference=reference, reference_sigma=reference_sigma,
                      pose_of=pose_of, timing=sensor_timing, timing_prior=timing_prior, offset_sensors=adj,
                      station_prior=station_prior)
        K = pb.K                                              # poses (the columns), from here on
        x0 = np.zeros(pb.N)
        for (s, ax, j), c in pb.cal_col.items():
            x0[c] = cal_start[s, ax, j]
        if x0_full is not None:                               # warm start from the previous pass
            x0[: 6 * K] = x0_full[: 6 * K]
            for key, c in pb.st_col.items():
                x0[c] = x0_full[prev.st_col[key]]
            for key, c in pb.cal_col.items():
                x0[c] = x0_full[prev.cal_col[key]]
            tail = pb.N - pb.c_off                            # offsets and timing: same length every pass
            if tail:
                x0[pb.c_off:] = x0_full[len(x0_full) - tail:]
        if before_res is None:
            before_res = _residual_grid(pb, x0, base)
        lo = np.full(pb.N, -np.inf)
        hi = np.full(pb.N, np.inf)
        if sensor_offsets:
            lo[pb.c_off:pb.c_tim], hi[pb.c_off:pb.c_tim] = -offset_bound, offset_bound
        if solver == "schur":
            sol = _schur_lm(pb, x0, base, lo, hi, loss, f_scale, max_nfev)
        else:
            # dense exact trust-region steps while J fits in ~100 MB, else lsmr (slow to converge
            # on this problem: the sample poses couple to every global parameter)
            small = pb.M * pb.N <= 12_000_000
            jac = (lambda x: pb.jacobian(x, base).toarray()) if small else (lambda x: pb.jacobian(x, base))
            kw = dict(jac=jac if jacobian == "analytic" else "2-point",
                      x_scale="jac", loss=loss, f_scale=f_scale, method="trf",
                      tr_solver="exact" if small else "lsmr", max_nfev=max_nfev, bounds=(lo, hi))
            if jacobian != "analytic":
                kw["jac_sparsity"] = jacobian_sparsity(pb)
                kw["tr_solver"] = "lsmr"
            sol = least_squares(lambda x: pb.residual(x, base), x0, **kw)
        J = pb.jacobian(sol.x, base)
        # loss weighting as least_squares does (rho'(z) for z = (r / f_scale)^2), for the covariance
        r = pb.residual(sol.x, base)
        z = (r / f_scale) ** 2
        wts = _loss_weights(r, pb.m_data, loss, f_scale)
        from scipy.sparse import diags
        Jw = diags(np.sqrt(wts)) @ J
        cov, null = _global_covariance(Jw, K)
        rd = r[: pb.m_data]
        dof = max(pb.m_data - (pb.N - pb.m_cal - pb.m_off - pb.m_tim - pb.m_stp), 1)
        s2 = float(np.sum(wts[: pb.m_data] * rd * rd) / dof)
        std_noise = np.sqrt(np.maximum(np.diag(cov), 0) * s2)
        if consider:                                   # the unadjusted layout's error (module docstring)
            from scipy.sparse import csr_matrix, vstack

            twin = _Problem(P, ang, stations, sigma=sigma, free_cal=cal_list, free_station=st_list,
                            offsets=True, offset_prior=lsig, calibration_prior=prior, cal_start=cal_start,
                            reference=reference, reference_sigma=reference_sigma, pose_of=pose_of,
                            timing=sensor_timing, timing_prior=timing_prior, offset_sensors=adj,
                            station_prior=station_prior)
            xt = np.concatenate([sol.x[: pb.c_off], np.zeros(3 * adj.size), sol.x[pb.c_off:]])
            Jt = twin.jacobian(xt, base).tocsr()
            Jo = vstack([diags(np.sqrt(wts[: pb.m_data])) @ Jt[: pb.m_data, twin.c_off:twin.c_tim],
                         csr_matrix((pb.M - pb.m_data, 3 * adj.size))])
            cov_tot = cov * s2 + _consider_covariance(Jw, Jo, K, cov) * lsig ** 2
        else:
            cov_tot = cov * s2
        std = np.sqrt(np.maximum(np.diag(cov_tot), 0))
        hjj = np.asarray(Jw.tocsc()[:, 6 * K:].power(2).sum(0)).ravel()
        with np.errstate(divide="ignore", invalid="ignore"):
            corr = np.sqrt(np.clip(1.0 - 1.0 / (hjj * np.diag(cov)), 0.0, 1.0))
        newly = set()
        for (s, ax, j), c in pb.cal_col.items():
            gi = c - 6 * K
            corr_seen[(s, ax, j)] = float(corr[gi])
            if null[gi] or std_noise[gi] > UNOBSERVABLE_RATIO * prior[j]:
                newly.add((s, ax, j))
            elif std[gi] > UNOBSERVABLE_RATIO * prior[j]:
                newly.add((s, ax, j))
                weak.add((s, ax, j))
        newly_st = set()
        if st_prior is not None and hold_station_prior:  # the same rule for station poses with a prior
            for (s, c), col in pb.st_col.items():
                gi = col - 6 * K
                lim = UNOBSERVABLE_RATIO * st_prior[c // 3]
                if null[gi] or std_noise[gi] > lim:
                    newly_st.add((s, c))
                elif std[gi] > lim:
                    newly_st.add((s, c))
                    st_weak.add((s, c))
        x0_full, prev = sol.x, pb
        if not newly and not newly_st:
            break
        fixed |= newly
        st_held |= newly_st
    R, t, RS, TS, cal, off = pb.unpack(sol.x, *base)
    after = _residual_grid(pb, sol.x, base)
    params = []
    names_st = ("d_rx", "d_ry", "d_rz", "tx", "ty", "tz")  # rotation: change from the start
    for s in range(S):
        for q in range(6):
            c0 = pb.st_col.get((s, q))
            if c0 is None:
                val = (0.0 if q < 3 else TS0[s, q - 3])
                held = "fixed" if (s, q) not in st_held else ("weakly_observable" if (s, q) in st_weak else "unobservable")
                params.append(ParameterEstimate(f"station {stations[s].id} pose {names_st[q]}", float(val), None,
                                                float(val), "rad" if q < 3 else "m", held))
            else:
                gi = c0 - 6 * K
                val = sol.x[c0] if q < 3 else TS[s, q - 3]
                st0 = 0.0 if q < 3 else TS0[s, q - 3]
                bad = bool(null[gi])
                dominated = (st_prior is not None and not hold_station_prior and not bad
                             and std[gi] > UNOBSERVABLE_RATIO * st_prior[q // 3])
                params.append(ParameterEstimate(f"station {stations[s].id} pose {names_st[q]}", float(val),
                                                None if bad else float(std[gi]), float(st0), "rad" if q < 3 else "m",
                                                "unobservable" if bad else PRIOR_DOMINATED if dominated else "ok",
                                                float(corr[gi])))

    def fitted_status(s, value, start, sd):
        """'suspect' when a station that came with a (factory) calibration lands far from it."""
        far = sd is not None and abs(value - start) > SUSPECT_SIGMAS * sd
        return "suspect" if (stations[s].calibration is not None and far) else "ok"

    def held_status(s, keys):
        if any(k in weak for k in keys):
            return "weakly_observable"
        return "unobservable" if any(k in fixed for k in keys) else "fixed"

    for s, st in enumerate(stations):
        for ax in (0, 1):
            for j, name in enumerate(_ba_names(st.kind)[ax]):
                if CALIBRATION_PARAMS[j] not in MODEL_PARAMS[st.kind]:
                    continue
                key = (s, ax, j)
                nm = f"station {st.id} axis {ax} {name}"
                if key in pb.cal_col:
                    gi = pb.cal_col[key] - 6 * K
                    params.append(ParameterEstimate(nm, float(cal[s, ax, j]), float(std[gi]), float(cal_start[s, ax, j]),
                                                    "rad", fitted_status(s, cal[s, ax, j], cal_start[s, ax, j], std[gi]),
                                                    float(corr[gi])))
                else:
                    lh2_yaw = st.kind == "lh2" and ax == 0 and j == 0
                    params.append(ParameterEstimate(nm, float(cal[s, ax, j]), None, float(cal_start[s, ax, j]), "rad",
                                                    "unobservable" if lh2_yaw else held_status(s, [key]),
                                                    corr_seen.get(key)))
            # derived magnitude/phase of the two sinusoids, std by first-order propagation
            for ia, ib, mname, pname in ((3, 4, "gib_mag", "gib_phase"), (5, 6, "ogee_mag", "ogee_phase")):
                if CALIBRATION_PARAMS[ib] not in MODEL_PARAMS[st.kind]:
                    continue
                a_, b_ = cal[s, ax, ia], cal[s, ax, ib]
                mag, ph = float(np.hypot(a_, b_)), float(np.arctan2(b_, a_))
                m0 = station_from_ba(cal_start[s], st.kind)[ax]
                ka, kb = pb.cal_col.get((s, ax, ia)), pb.cal_col.get((s, ax, ib))
                if ka is None or kb is None:
                    st_ = held_status(s, [(s, ax, ia), (s, ax, ib)])
                    params.append(ParameterEstimate(f"station {st.id} axis {ax} {mname}", mag, None, float(m0[ib]), "rad", st_))
                    params.append(ParameterEstimate(f"station {st.id} axis {ax} {pname}", ph, None, float(m0[ia]), "rad", st_))
                    continue
                g = np.array([ka, kb]) - 6 * K
                C2 = cov_tot[np.ix_(g, g)]
                u = np.array([a_, b_]) / max(mag, 1e-300)
                sd_mag = float(np.sqrt(max(u @ C2 @ u, 0.0)))
                v = np.array([-b_, a_]) / max(mag, 1e-300) ** 2
                sd_ph = float(np.sqrt(max(v @ C2 @ v, 0.0)))
                ok_ph = mag > 3.0 * sd_mag
                params.append(ParameterEstimate(f"station {st.id} axis {ax} {mname}", mag, sd_mag, float(m0[ib]), "rad",
                                                fitted_status(s, mag, m0[ib], sd_mag)))
                dph = float(_wrap(ph - m0[ia]))
                params.append(ParameterEstimate(f"station {st.id} axis {ax} {pname}", ph, sd_ph if ok_ph else None,
                                                float(m0[ia]), "rad",
                                                fitted_status(s, m0[ia] + dph, m0[ia], sd_ph) if ok_ph else "unobservable"))
    if sensor_offsets:
        for q, i in enumerate(adj):
            for c in range(3):
                gi = pb.c_off + 3 * q + c - 6 * K
                bad = bool(null[gi]) or std[gi] > UNOBSERVABLE_RATIO * offset_prior
                params.append(ParameterEstimate(f"sensor {labels[i]} offset {'xyz'[c]}", float(off[i, c]),
                                                None if null[gi] else float(std[gi]), 0.0, "m",
                                                PRIOR_DOMINATED if bad else "ok"))
    tau = pb.tau_of(sol.x)
    if sensor_timing:
        for q, i in enumerate(adj):
            gi = pb.c_tim + q - 6 * K
            bad = bool(null[gi]) or std[gi] > UNOBSERVABLE_RATIO * timing_prior
            params.append(ParameterEstimate(f"sensor {labels[i]} timing", float(tau[i]),
                                            None if null[gi] else float(std[gi]), 0.0, "s",
                                            PRIOR_DOMINATED if bad else "ok"))
    new_st = []
    for s, st in enumerate(stations):
        c = Calibration(station_from_ba(cal[s], st.kind), st.kind, st.calibration.gib_argument if st.calibration else "ideal")
        new_st.append(replace(st, rotation=RS[s], translation=TS[s], calibration=c))
    R = np.where(good[:, None, None], R, np.nan)
    t = np.where(good[:, None], t, np.nan)
    status = "ok" if sol.status > 0 else "not_converged"
    cnt = {k: sum(p.status == k for p in params) for k in ("unobservable", "weakly_observable", "suspect",
                                                            PRIOR_DOMINATED)}
    msg = (f"{sol.message.strip()} ({sol.nfev} evaluations); residual scale {np.sqrt(s2):.3g} sigma; "
           f"{cnt['unobservable']} parameter(s) unobservable, {cnt['weakly_observable']} weakly observable "
           f"(held at their start), {cnt['suspect']} suspect")
    n_st_pd = sum(p.status == PRIOR_DOMINATED and p.name.startswith("station") for p in params)
    if cnt[PRIOR_DOMINATED] - n_st_pd:
        msg += (f"; {cnt[PRIOR_DOMINATED] - n_st_pd} sensor term(s) adjusted but set mostly by their prior "
                f"(sd > {UNOBSERVABLE_RATIO:g} prior: {PRIOR_DOMINATED})")
    if n_st_pd:
        msg += (f"; {n_st_pd} station pose term(s) adjusted under the station prior but set mostly by it "
                f"({PRIOR_DOMINATED})")
    if pb.N == 6 * K:                                          # nothing left to adjust: say so, never "ok"
        status = "nothing_determined"
        n_weak = len(weak) + len(st_weak)
        n_free = len(free_cal) + len(free_station)
        msg = (f"the {int(good_s.sum())} samples determine none of the {n_free} free parameter(s) "
               f"({n_free - n_weak} unobservable, {n_weak} weakly observable; all held at their start): "
               f"nothing adjusted")
    return BundleResult(new_st, P + off, R, t, params, before_res, after, status == "ok", status, msg,
                        int(sol.nfev), float(np.sqrt(s2)), {"cost": float(sol.cost), "timing_s": tau})


def _loss_weights(r, m_data, loss, f_scale):
    """IRLS weights ``rho'(z)``, ``z = (r / f_scale)²`` on the data rows (priors: 1)."""
    w = np.ones_like(r)
    z = (r[:m_data] / f_scale) ** 2
    if loss == "soft_l1":
        w[:m_data] = 1.0 / np.sqrt(1.0 + z)
    elif loss == "huber":
        w[:m_data] = np.where(z <= 1.0, 1.0, 1.0 / np.sqrt(np.maximum(z, 1e-300)))
    elif loss != "linear":
        raise ValueError(f"loss: expected 'linear', 'soft_l1' or 'huber', got {loss!r}")
    return w


def _robust_cost(r, m_data, loss, f_scale):
    z = (r[:m_data] / f_scale) ** 2
    if loss == "soft_l1":
        data = f_scale ** 2 * np.sum(2.0 * (np.sqrt(1.0 + z) - 1.0))
    elif loss == "huber":
        data = f_scale ** 2 * np.sum(np.where(z <= 1.0, z, 2.0 * np.sqrt(z) - 1.0))
    else:
        data = np.sum(r[:m_data] ** 2)
    return 0.5 * (data + np.sum(r[m_data:] ** 2))


def _schur_lm(pb: _Problem, x0, base, lo, hi, loss, f_scale, max_iter):
    """Levenberg–Marquardt with the sample-pose blocks eliminated exactly (Schur complement).

    Normal equations ``H = J^T W J``, ``b = J^T W r`` (W the IRLS weights); with pose blocks
    ``H_pp`` (K 6 × 6), ``H_pg``, ``H_gg``: ``S = H_gg - H_gp H_pp^-1 H_pg``,
    ``S dg = -(b_g - H_gp H_pp^-1 b_p)``, ``dp = -H_pp^-1 (b_p + H_pg dg)``; damping
    ``lambda diag(H)``. Stops when a step lowers the cost by less than 1e-10 of it, or when the last
    :data:`STALL_ITERATIONS` accepted steps together lowered it by less than :data:`STALL_RTOL` of it
    or by less than 0.5 (the cost is half the chi-square: the parameters moved by well under one
    standard deviation; a robust cost on real data creeps on by tiny steps along the weakly
    determined directions).
    Returns a namespace like ``least_squares``'s result (x, status, nfev, message, cost).
    """
    from types import SimpleNamespace

    K = pb.K
    x = np.clip(x0, lo, hi)
    r = pb.residual(x, base)
    cost = _robust_cost(r, pb.m_data, loss, f_scale)
    lam = 1e-4
    nfev, status, msg = 1, 0, "iteration limit reached"
    idx = np.arange(K) * 6
    history = [cost]
    for it in range(max_iter):
        J = pb.jacobian(x, base).tocsc()
        w = _loss_weights(r, pb.m_data, loss, f_scale)
        Jw = J.multiply(np.sqrt(w)[:, None]).tocsc()
        rw = np.sqrt(w) * r
        H = (Jw.T @ Jw).tocsr()
        b = Jw.T @ rw
        Hpp = np.zeros((K, 6, 6))
        for a in range(6):
            for c in range(6):
                Hpp[:, a, c] = np.asarray(H[idx + a, idx + c]).ravel()
        Hpg = H[: 6 * K, 6 * K:].toarray().reshape(K, 6, -1)
        Hgg = H[6 * K:, 6 * K:].toarray()
        bp, bg = b[: 6 * K].reshape(K, 6), b[6 * K:]
        improved = False
        for _ in range(12):
            Dp = np.einsum("kii->ki", Hpp) * lam + 1e-12
            Hd = Hpp + Dp[:, :, None] * np.eye(6)
            Hinv = np.linalg.inv(Hd)
            Sg = Hgg + np.diag(np.diag(Hgg) * lam + 1e-12) - np.einsum("kag,kab,kbh->gh", Hpg, Hinv, Hpg)
            rhs = bg - np.einsum("kag,kab,kb->g", Hpg, Hinv, bp)
            try:
                dg = -np.linalg.solve(Sg, rhs)
            except np.linalg.LinAlgError:
                dg = -np.linalg.lstsq(Sg, rhs, rcond=None)[0]
            dp = -np.einsum("kab,kb->ka", Hinv, bp + np.einsum("kag,g->ka", Hpg, dg))
            xn = np.clip(x + np.concatenate([dp.ravel(), dg]), lo, hi)
            rn = pb.residual(xn, base)
            nfev += 1
            cn = _robust_cost(rn, pb.m_data, loss, f_scale)
            if cn < cost:
                gain = cost - cn
                x, r, cost = xn, rn, cn
                lam = max(lam / 10.0, 1e-12)
                improved = True
                break
            lam *= 10.0
        if not improved:
            status, msg = 2, "no step lowers the cost (converged to working precision)"
            break
        history.append(cost)
        if gain <= 1e-10 * cost:
            status, msg = 1, f"converged (relative cost change {gain / max(cost, 1e-300):.1e})"
            break
        if len(history) > STALL_ITERATIONS and history[-1 - STALL_ITERATIONS] - cost <= max(STALL_RTOL * cost, 0.5):
            status, msg = 1, (f"converged (the last {STALL_ITERATIONS} steps lowered the cost by "
                              f"{(history[-1 - STALL_ITERATIONS] - cost) / max(cost, 1e-300):.1e} of it)")
            break
    return SimpleNamespace(x=x, status=status, nfev=nfev, message=msg, cost=cost)


def _residual_grid(pb: _Problem, x, base) -> np.ndarray:
    """Angle residuals (rad) at ``x`` on the (K, S, n, 2) grid, NaN where no angle."""
    R, t, RS, TS, cal, off = pb.unpack(x, *base)
    pred, _, _ = pb.predict(R, t, RS, TS, cal, off, False, pb.tau_of(x))
    out = np.full(pb.ang.shape, np.nan)
    out[pb.obs] = _wrap(pb.meas - pred)
    return out
