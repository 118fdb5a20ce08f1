"""Lighthouse vs camera: one clock, one frame alignment, and the disagreement against its prediction.

Model (docs/live-camera.md): the camera solves the face attitude ``R_ct(t_cam)``; the lighthouse
the body attitude ``R_lh(t_dev)``; ``R_ct = X R_lh Y`` with fixed ``X`` (camera ← lighthouse) and
``Y`` (body ← face), and the clocks are related by ``t_cam = (1 + drift) t_dev + offset``.

1. **Clock.** A coarse offset from the angular-speed profiles of both streams (invariant to X and
   Y; :func:`layoutkit.live.reference.estimate_time_offset`, with a long baseline so that slow
   motion is not lost in the per-pose noise), then ``(offset, drift)`` by minimising
   ``chi2 = sum d_k^2 / p_k^2`` (disagreement over its predicted variance, X and Y re-fitted at
   every evaluation: a profile likelihood). The uncertainty is ``2 H^-1`` of that chi² (H its
   Hessian), inflated by the residuals' integrated autocorrelation (camera errors vary slowly with
   the pose, so consecutive frames are not independent). The drift: independent offsets in windows
   of ``window_s`` (>= 4 of them), a straight line through them, its uncertainty from their scatter
   (slowly varying systematic errors count); a drift that is not 3 sigma from 0, or whose sigma
   exceeds ``max_drift_sigma``, is fixed at 0 and reported as such.
2. **Alignment.** X and Y by the rotation-averaging core
   (:func:`layoutkit.rotations.fit_rotation_pair`) on the matched frames outside the face-on band.
3. **Disagreement** ``d_k = |log(R_ct,k (X R_lh(t_k) Y)^T)|`` and its prediction
   ``p_k^2 = sigma_c^2 tr(J_k J_k^T) + w_k (ADOP_k sigma_theta)^2``: the camera solver's own
   linearised error (:mod:`layoutkit.camera.uncertainty`, corner noise ``sigma_c`` from IPPE's
   residuals) plus the lighthouse DOP prediction (Chen eq. 24) of the SLERP-interpolated pose,
   ``w = (1 - u)^2 + u^2`` for interpolation weight ``u`` between two independent frames.
   Frames whose face tilt is inside ``face_on_deg`` are flagged (the tilt sign — the mirror
   branch — is nearly unobservable there and the linearisation does not hold) and left out of the
   ratio.
4. **Consistency test.** Under the model ``E[d_k^2] = p_k^2``; ``T = sum d_k^2 / p_k^2`` over the
   ``n`` frames used, with each term taken as one degree of freedom (the conservative end: an
   isotropic error would give three) and the residuals' autocorrelation inflation ``c`` (as for
   the clock), is ``c^2 chi2(n / c^2)``. ``T / n`` above its 99.9 % point ``chi2_0.999(nu) / nu``,
   ``nu = n / c^2``, means the streams disagree beyond what their predicted errors allow: status
   ``inconsistent``, never ``ok`` (another run's frames, a wrong clock, a wrong camera model).

Statuses (``summary["status"]``): ``ok`` only when the clock is ``ok`` or given and the test
passes; else ``inconsistent``, ``clock_<status>`` (the clock estimate is ``ambiguous``, has
``no_uncertainty`` — a flat chi² at its minimum: the data do not pin the clock — or found
``no_overlap``), or ``too_few_samples``; ``message`` says what it means.

Everything is a function of the two recorded streams, so ``replay`` of a session's capture
reproduces the live figures exactly.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import attitude_error, matrix_to_rotvec, rotvec_to_matrix
from ..rotations import fit_rotation_pair
from ..units import RAD2DEG

__all__ = ["ClockEstimate", "CrossCheck", "estimate_camera_clock", "camera_crosscheck", "consistency_test", "lh_at"]


@dataclass(frozen=True)
class ClockEstimate:
    """``t_cam = (1 + drift) t_dev + offset``; sigmas are 1-sigma (NaN: not estimated)."""

    offset_s: float
    drift: float
    offset_sigma_s: float
    drift_sigma: float
    drift_estimated: bool
    status: str
    message: str

    def to_device(self, t_cam):
        return (np.asarray(t_cam, float) - self.offset_s) / (1.0 + self.drift)


def lh_at(t_lh, R_lh, adop, t):
    """SLERP lighthouse attitudes at device times ``t (M,)``: ``(R (M, 3, 3), adop (M,), w (M,), ok (M,))``.

    ``w`` is the variance factor ``(1-u)^2 + u^2`` of interpolating between two independent poses.
    Outside the track or across gaps longer than 3 × the median spacing: ``ok`` False.
    """
    t = np.asarray(t, float)
    i = np.searchsorted(t_lh, t) - 1
    ok = (i >= 0) & (i < len(t_lh) - 1)
    i = np.clip(i, 0, len(t_lh) - 2)
    dt = t_lh[i + 1] - t_lh[i]
    med = float(np.median(np.diff(t_lh))) if len(t_lh) > 1 else np.inf
    ok &= dt <= 3 * med
    u = np.clip((t - t_lh[i]) / np.where(dt > 0, dt, 1.0), 0.0, 1.0)
    d = matrix_to_rotvec(R_lh[i + 1] @ np.swapaxes(R_lh[i], -1, -2))
    R = rotvec_to_matrix(d * u[:, None]) @ R_lh[i]
    a = (1 - u) * adop[i] + u * adop[i + 1]
    return R, a, (1 - u) ** 2 + u ** 2, ok


def _matched(t_lh, R_lh, adop, t_cam, R_cam, clock_offset, drift):
    t_dev = (t_cam - clock_offset) / (1.0 + drift)
    return lh_at(t_lh, R_lh, adop, t_dev)


def _chi2(params, t_lh, R_lh, adop, t_cam, R_cam, pc2, sigma_theta, body_offset=True):
    off, drift = params
    R, a, w, ok = _matched(t_lh, R_lh, adop, t_cam, R_cam, off, drift)
    if ok.sum() < max(10, 0.3 * len(t_cam)):
        return np.inf, None
    fit = fit_rotation_pair(R_cam[ok], R[ok], body_offset=body_offset, outlier_factor=None, iterations=30,
                            require_motion=False)
    p2 = pc2[ok] + w[ok] * (a[ok] * sigma_theta / RAD2DEG) ** 2
    r = fit.residual_rad ** 2 / p2
    # a bounded (Cauchy-like) cost: mirror-branch or mis-matched frames cannot dominate the clock
    return float(np.sum(np.minimum(r, 25.0)) * len(t_cam) / ok.sum()), fit


def estimate_camera_clock(t_lh, R_lh, adop, t_cam, R_cam, pc2, sigma_theta, *, max_offset_s: float | None = None,
                          max_drift_sigma: float = 1e-4, scan_s: float = 3.0, window_s: float = 10.0) -> ClockEstimate:
    """Clock offset and drift between a lighthouse and a camera attitude stream (module docstring).

    t_lh (N,), R_lh (N, 3, 3), adop (N,) deg/rad : good lighthouse poses (device time, s).
    t_cam (M,), R_cam (M, 3, 3), pc2 (M,) rad² : solved camera frames (camera clock, s) and their
    predicted attitude variance. max_offset_s : bound of the coarse search (default: any lag with
    at least half the shorter stream overlapping).
    """
    from scipy.optimize import minimize_scalar

    from .reference import PoseTrack, estimate_time_offset

    if len(t_cam) < 10 or len(t_lh) < 10:
        return ClockEstimate(np.nan, 0.0, np.nan, np.nan, False, "too_few_samples",
                             f"need >= 10 solved frames in each stream (lighthouse {len(t_lh)}, camera {len(t_cam)})")
    sub = np.unique(np.linspace(0, len(t_cam) - 1, min(len(t_cam), 300)).astype(int))

    def cost(x, idx=sub):
        return _chi2(x, t_lh, R_lh, adop, t_cam[idx], R_cam[idx], pc2[idx], sigma_theta)[0]

    # candidates: (a) the angular-speed correlation peak — sharp for fast, varied motion; (b) a
    # scan of the attitude chi² over every offset with half the camera stream overlapping, at a
    # step matched to the motion (the chi² basin is ~ noise / angular speed wide) — robust for slow
    # motion where the speed profile is lost in the noise. The lowest refined chi² wins.
    lo = t_cam[0] - t_lh[-1] + 0.5 * (t_cam[-1] - t_cam[0])
    hi = t_cam[-1] - t_lh[0] - 0.5 * (t_cam[-1] - t_cam[0])
    if max_offset_s is not None:
        lo, hi = max(lo, -max_offset_s), min(hi, max_offset_s)
    if not hi > lo:
        return ClockEstimate(np.nan, 0.0, np.nan, np.nan, False, "no_overlap",
                             "the two streams cannot overlap by half the camera stream at any clock offset")
    cands = []
    a = PoseTrack(t_lh, R_lh, None)
    b = PoseTrack(t_cam, R_cam, None)
    span = t_cam[-1] - t_cam[0]
    tau_c, peak = estimate_time_offset(a, b, max_offset=max(abs(lo), abs(hi)), step=0.01,
                                       baseline=float(np.clip(span / 30.0, 0.1, 2.0)), return_peak=True)
    if np.isfinite(tau_c) and lo <= tau_c <= hi:
        cands.append(float(tau_c))
    w = np.linalg.norm(matrix_to_rotvec(R_lh[1:] @ np.swapaxes(R_lh[:-1], -1, -2)), axis=-1) / np.maximum(
        np.diff(t_lh), 1e-9)
    w_med = float(np.median(w[np.isfinite(w)])) if len(w) else 0.0
    sig = float(np.sqrt(np.median(pc2))) if np.any(pc2 > 0) else 1e-3
    step = float(np.clip(0.5 * sig / max(w_med, 1e-9), 0.01, 0.5))
    grid, cgrid = np.zeros(0), np.zeros(0)
    if (hi - lo) / step <= 3000:
        grid = np.arange(lo, hi + 1e-12, step)
        cgrid = np.array([cost((g, 0.0)) for g in grid])
        if np.any(np.isfinite(cgrid)):
            cands.append(float(grid[int(np.nanargmin(cgrid))]))
    if not cands:
        return ClockEstimate(np.nan, 0.0, np.nan, np.nan, False, "no_overlap",
                             "no clock offset found: the streams do not overlap or hold no usable motion")
    best = None
    for c0 in cands:
        fine = c0 + np.arange(-2 * step, 2 * step + 1e-12, step / 10)
        cf = np.array([cost((g, 0.0)) for g in fine])
        g0 = float(fine[int(np.nanargmin(cf))]) if np.any(np.isfinite(cf)) else c0
        r = minimize_scalar(lambda x: cost((x, 0.0)), bounds=(g0 - step / 10, g0 + step / 10), method="bounded",
                            options={"xatol": 1e-6})
        x, fx = (float(r.x), float(r.fun)) if r.success else (g0, cost((g0, 0.0)))
        if best is None or fx < best[1]:
            best = (x, fx)
    off = best[0]
    # a second basin the data cannot reject (Δchi² < 4 on the full set, more than 5 scan steps
    # away) makes the offset ambiguous: say so rather than report a sharp but arbitrary minimum
    ambiguous = None
    if len(grid):
        scale = len(t_cam) / len(sub)
        far = np.abs(grid - off) > 5 * step
        if np.any(far & np.isfinite(cgrid)):
            k = int(np.nanargmin(np.where(far, cgrid, np.inf)))
            if (cgrid[k] - best[1]) * scale < 4.0:
                ambiguous = float(grid[k])
    full = np.arange(len(t_cam))
    r = minimize_scalar(lambda x: cost((x, 0.0), full), bounds=(off - 0.02, off + 0.02), method="bounded",
                        options={"xatol": 1e-6})
    off = float(r.x)
    h = _hessian(lambda x: cost((x[0], 0.0), full), np.array([off]), (1e-3,))
    cv = _cov_from_hessian(h)
    # camera errors are partly systematic and vary slowly with the pose: consecutive residuals are
    # correlated, so the white-noise chi² curvature is too sharp by sqrt(1 + 2 sum rho_k)
    infl = _correlation_inflation(t_lh, R_lh, adop, t_cam, R_cam, pc2, sigma_theta, off, 0.0)
    s_off = float(np.sqrt(cv[0, 0])) * infl if cv is not None else np.nan
    # drift: independent offsets in windows of >= window_s, a straight line through them; the
    # windows' scatter about the line — not the white-noise curvature — gives the uncertainty, so
    # slowly varying systematic errors count (the curvature alone gave an 8-sigma "drift")
    d, s_d, off0, s_off0, K = 0.0, np.nan, off, s_off, 0
    t_dev = t_cam - off
    K = int(min(12, np.floor((t_dev[-1] - t_dev[0]) / window_s))) if len(t_dev) > 1 else 0
    if K >= 4:
        edges = np.linspace(t_dev[0], t_dev[-1], K + 1)
        tk, ok_k = [], []
        for k in range(K):
            idx = np.flatnonzero((t_dev >= edges[k]) & (t_dev <= edges[k + 1]))
            if len(idx) < 30:
                continue
            rk = minimize_scalar(lambda x: cost((x, 0.0), idx), bounds=(off - 0.05, off + 0.05), method="bounded",
                                 options={"xatol": 1e-6})
            tk.append(float(np.mean(t_dev[idx])))
            ok_k.append(float(rk.x))
        if len(tk) >= 4:
            A = np.column_stack([np.ones(len(tk)), tk])
            coef, *_ = np.linalg.lstsq(A, np.array(ok_k), rcond=None)
            res = np.array(ok_k) - A @ coef
            s2 = float(res @ res) / (len(tk) - 2)
            C = s2 * np.linalg.inv(A.T @ A)
            d, s_d = float(coef[1]), float(np.sqrt(C[1, 1]))
            off0, s_off0 = float(coef[0]), float(np.sqrt(C[0, 0]))
            s_off = max(s_off, float(np.sqrt(s2 / len(tk))))
            K = len(tk)
    if ambiguous is not None:
        return ClockEstimate(off, 0.0, abs(ambiguous - off), s_d, False, "ambiguous",
                             f"clock offset ambiguous: {off:.3f} s and {ambiguous:.3f} s fit the data "
                             "equally well (too little motion); pass the offset if it is known")
    if not np.isfinite(s_off):
        return ClockEstimate(off, 0.0, np.nan, s_d, False, "no_uncertainty",
                             f"offset {off:.6f} s with no uncertainty: the attitude chi² has no curvature at its "
                             "minimum, so the two streams do not pin the clock (they do not show the same motion: "
                             "another run's frames, or too little motion); do not use it")
    if np.isfinite(s_d) and s_d <= max_drift_sigma and abs(d) > 3 * s_d:
        return ClockEstimate(off0, d, s_off0, s_d, True, "ok",
                             f"offset {off0:.6f} s ± {s_off0 * 1e3:.3g} ms, drift {d * 1e6:.3g} ± {s_d * 1e6:.3g} ppm "
                             f"(a line through {K} window offsets)")
    why = (f"σ {s_d * 1e6:.3g} ppm from {K} window offsets" if np.isfinite(s_d)
           else f"the session is shorter than 4 windows of {window_s:g} s")
    return ClockEstimate(off, 0.0, s_off, s_d, False, "ok",
                         f"offset {off:.6f} s ± {s_off * 1e3:.3g} ms; drift not significant in this session "
                         f"({d * 1e6:.3g} ppm, {why}): fixed at 0")


def _correlation_inflation(t_lh, R_lh, adop, t_cam, R_cam, pc2, sigma_theta, off, drift) -> float:
    """``sqrt(1 + 2 sum_k rho_k)`` of the whitened residual components (lags while rho > 0.05)."""
    _, fit = _chi2((off, drift), t_lh, R_lh, adop, t_cam, R_cam, pc2, sigma_theta)
    if fit is None:
        return 1.0
    R, a, w, ok = _matched(t_lh, R_lh, adop, t_cam, R_cam, off, drift)
    e = matrix_to_rotvec(np.swapaxes(R_cam[ok], -1, -2) @ fit.X @ R[ok] @ fit.Y)
    p = np.sqrt(pc2[ok] + w[ok] * (a[ok] * sigma_theta / RAD2DEG) ** 2)[:, None]
    return _inflation(e / p)


def _inflation(z) -> float:
    """``sqrt(1 + 2 sum_k rho_k)`` of whitened residual vectors ``z (n, 3)`` in time order."""
    z = z - z.mean(0)
    var = np.sum(z * z)
    if not var > 0 or len(z) < 20:
        return 1.0
    tot = 0.0
    for k in range(1, len(z) // 4):
        rho = float(np.sum(z[k:] * z[:-k]) / var)
        if rho < 0.05:
            break
        tot += rho
    return float(np.sqrt(1.0 + 2.0 * tot))


def _hessian(f, x, h):
    x = np.asarray(x, float)
    n = len(x)
    H = np.zeros((n, n))
    f0 = f(x)
    for i in range(n):
        for j in range(i, n):
            ei = np.zeros(n)
            ej = np.zeros(n)
            ei[i], ej[j] = h[i], h[j]
            if i == j:
                H[i, i] = (f(x + ei) - 2 * f0 + f(x - ei)) / h[i] ** 2
            else:
                H[i, j] = H[j, i] = (f(x + ei + ej) - f(x + ei - ej) - f(x - ei + ej) + f(x - ei - ej)) / (4 * h[i] * h[j])
    return H


def _cov_from_hessian(H):
    if not np.all(np.isfinite(H)):
        return None
    try:
        w = np.linalg.eigvalsh(H)
        if np.min(w) <= 0:
            return None
        return 2.0 * np.linalg.inv(H)  # chi2 = -2 log L: cov = (H / 2)^-1
    except np.linalg.LinAlgError:
        return None


def consistency_test(d, p, e=None, level: float = 0.999) -> dict:
    """Is the disagreement within its prediction? (module docstring, step 4).

    d (n,) rad : disagreement per frame; p (n,) rad : its predicted RMS (``E[d^2] = p^2``);
    e (n, 3) rad : the residual rotation vectors in time order, for the autocorrelation
    inflation (None: independent frames). Returns ``chi2_per_frame`` (``mean (d/p)^2``),
    ``bound_999`` (its ``level`` point), ``frames``, ``effective_frames``, ``inflation``,
    ``p_value`` and ``consistent``.
    """
    from scipy.stats import chi2

    d = np.asarray(d, float)
    p = np.asarray(p, float)
    good = np.isfinite(d) & np.isfinite(p) & (p > 0)
    n = int(good.sum())
    r2 = (d[good] / p[good]) ** 2
    c = 1.0
    if e is not None and n >= 20:
        c = max(1.0, _inflation(np.asarray(e, float)[good] / p[good, None]))
    nu = max(n / c ** 2, 1.0)
    T = float(np.sum(r2))
    bound = float(chi2.ppf(level, nu) / nu)
    mean = T / n if n else np.nan
    pv = float(chi2.sf(T / c ** 2, nu)) if n else np.nan
    return {"chi2_per_frame": mean, "bound_999": bound, "frames": n, "effective_frames": nu, "inflation": c,
            "p_value": pv, "consistent": bool(n and mean <= bound), "level": level}


@dataclass(frozen=True)
class CrossCheck:
    """Result of :func:`camera_crosscheck` (``summary()`` gives the JSON-ready dict, ``series`` the plots)."""

    summary: dict
    series: dict


def camera_crosscheck(lh_t, lh_R, lh_adop, sigma_theta, cam: dict, *, clock: tuple | None = None,
                      alignment: tuple | None = None, face_on_deg: float = 10.0,
                      corner_sigma_px: float | None = None, truth: dict | None = None,
                      camera_counts: dict | None = None) -> CrossCheck:
    """Compare a camera attitude stream with the lighthouse poses (module docstring).

    lh_t (N,) s device time, lh_R (N, 3, 3) body→lighthouse, lh_adop (N,) deg/rad : good poses.
    sigma_theta : rad. cam : :meth:`layoutkit.live.camera.CameraFrames.arrays`. clock : given
    ``(offset_s, drift)`` or None (estimate). alignment : given ``(X, Y)`` or None (estimate).
    truth : simulator truth (``camera.json``) to compare the estimates with.
    """
    from ..camera.rectangle import label_symmetries
    from ..camera.uncertainty import corner_sigma_from_reprojection

    counts = camera_counts or {"frames": int(len(cam["t"])), "solved": int(np.sum(cam["status"] == "ok"))}
    out = {"frames": counts.get("frames", len(cam["t"])), "solved": counts.get("solved"),
           "by_status": counts.get("by_status"), "clock_offset_s": None, "disagreement_rms_deg": None,
           "predicted_disagreement_rms_deg": None}
    ok = (cam["status"] == "ok") & np.all(np.isfinite(cam["rotation"]), axis=(1, 2))
    lh_t = np.asarray(lh_t, float)
    if ok.sum() < 10 or len(lh_t) < 10:
        out.update(status="too_few_samples",
                   message=f"{int(ok.sum())} solved camera frames and {len(lh_t)} good lighthouse poses: need >= 10 each")
        return CrossCheck(out, {})
    order = np.argsort(lh_t)
    lh_t, lh_R, lh_adop = lh_t[order], np.asarray(lh_R)[order], np.asarray(lh_adop, float)[order]
    t_cam, R_cam = cam["t"][ok], cam["rotation"][ok]
    sig_c = corner_sigma_px if corner_sigma_px is not None else corner_sigma_from_reprojection(cam["reprojection_px"][ok])
    pv = cam.get("pred_var", np.full(len(cam["t"]), np.nan))[ok]
    rp2 = cam.get("rep_pred2", np.full(len(cam["t"]), np.nan))[ok]
    rep = cam["reprojection_px"][ok]
    vf = np.nan
    if corner_sigma_px is None and np.all(np.isfinite(pv)):
        # the detector's covariance gives the shape; its scale is the a-posteriori variance factor
        # (observed / expected IPPE reprojection mean square), so systematic corner errors that
        # the line fits do not see still count
        good = np.isfinite(rp2) & np.isfinite(rep)
        if good.sum() >= 10 and np.mean(rp2[good]) > 0:
            vf = float(np.mean(rep[good] ** 2) / np.mean(rp2[good]))
        pc2 = pv * (vf if np.isfinite(vf) else 1.0)
        camera_model = (f"detector line-fit covariance x variance factor {vf:.3g} (from IPPE residuals)"
                        if np.isfinite(vf) else "detector line-fit covariance")
    elif np.isfinite(sig_c):
        pc2, camera_model = (sig_c ** 2) * cam["jj_trace"][ok], f"i.i.d. corner noise {sig_c:.3g} px"
    else:
        pc2, camera_model = np.zeros(ok.sum()), "unknown (no camera error in the prediction)"
    out["camera_error_model"] = camera_model
    out["camera_variance_factor"] = vf if np.isfinite(vf) else None
    tilt = cam["tilt"][ok]
    off_band = tilt >= np.deg2rad(face_on_deg)
    if clock is None:
        ce = estimate_camera_clock(lh_t, lh_R, lh_adop, t_cam[off_band], R_cam[off_band], pc2[off_band],
                                   sigma_theta)
    else:
        ce = ClockEstimate(float(clock[0]), float(clock[1]), np.nan, np.nan, False, "given", "clock given")
    out["clock"] = {"offset_s": ce.offset_s, "drift_ppm": ce.drift * 1e6, "offset_sigma_s": ce.offset_sigma_s,
                    "drift_sigma_ppm": ce.drift_sigma * 1e6, "drift_estimated": ce.drift_estimated,
                    "status": ce.status, "message": ce.message}
    out["clock_offset_s"] = ce.offset_s if np.isfinite(ce.offset_s) else None
    if not np.isfinite(ce.offset_s):
        out.update(status=ce.status, message=ce.message)
        return CrossCheck(out, {})
    R_l, a_l, w_l, m = lh_at(lh_t, lh_R, lh_adop, ce.to_device(t_cam))
    if alignment is None:
        use = m & off_band
        fit = fit_rotation_pair(R_cam[use], R_l[use], body_offset=True, outlier_factor=5.0,
                                require_motion=False)
        X, Y = fit.X, fit.Y
        out["alignment"] = {"status": fit.status, "message": fit.message, "estimated": True,
                            "camera_from_lighthouse_sigma_deg": float(np.degrees(fit.X_sigma_rad)),
                            "body_from_face_sigma_deg": float(np.degrees(fit.Y_sigma_rad))}
    else:
        X, Y = (np.asarray(v, float) for v in alignment)
        out["alignment"] = {"status": "given", "message": "alignment given", "estimated": False}
    out["alignment"].update(camera_from_lighthouse_rotvec_deg=np.degrees(matrix_to_rotvec(X)).tolist(),
                            body_from_face_rotvec_deg=np.degrees(matrix_to_rotvec(Y)).tolist())
    d = np.full(len(t_cam), np.nan)
    d[m] = attitude_error(R_cam[m], X @ R_l[m] @ Y)
    p2_lh = w_l * (a_l * sigma_theta / RAD2DEG) ** 2
    pred = np.sqrt(pc2 + p2_lh)
    sel = m & off_band
    rms = float(np.sqrt(np.mean(d[sel] ** 2))) if sel.any() else np.nan
    prms = float(np.sqrt(np.mean(pred[sel] ** 2))) if sel.any() else np.nan
    in_band = m & ~off_band
    mirror = in_band & (d > 5 * pred)
    test = consistency_test(d[sel], pred[sel], matrix_to_rotvec(
        np.swapaxes(R_cam[sel], -1, -2) @ X @ R_l[sel] @ Y)) if sel.sum() >= 10 else None
    out.update(
        status="ok" if sel.sum() >= 10 else "too_few_samples",
        matched=int(m.sum()), used=int(sel.sum()), face_on_frames=int(in_band.sum()),
        face_on_band_deg=face_on_deg, mirror_branch_frames=int(mirror.sum()),
        corner_sigma_px=sig_c if np.isfinite(sig_c) else None,
        disagreement_rms_deg=float(np.degrees(rms)) if np.isfinite(rms) else None,
        predicted_disagreement_rms_deg=float(np.degrees(prms)) if np.isfinite(prms) else None,
        predicted_camera_rms_deg=float(np.degrees(np.sqrt(np.mean(pc2[sel])))) if sel.any() else None,
        predicted_lighthouse_rms_deg=float(np.degrees(np.sqrt(np.mean(p2_lh[sel])))) if sel.any() else None,
        ratio=float(rms / prms) if np.isfinite(rms) and prms > 0 else None,
        disagreement_face_on_rms_deg=float(np.degrees(np.sqrt(np.mean(d[in_band] ** 2)))) if in_band.any() else None,
    )
    out["message"] = (f"{out['used']} frames outside the ±{face_on_deg:g}° face-on band: disagreement "
                      f"{out['disagreement_rms_deg']:.4g}° RMS vs predicted {out['predicted_disagreement_rms_deg']:.4g}°"
                      if out["status"] == "ok" else "fewer than 10 matched frames outside the face-on band")
    if test is not None:
        out["consistency"] = test
        if not test["consistent"]:
            out["status"] = "inconsistent"
            out["message"] = (
                f"{out['message']} ({out['ratio'] or float('nan'):.3g}x): mean (d/p)² {test['chi2_per_frame']:.4g} "
                f"is above its 99.9 % chi-square bound {test['bound_999']:.3g} (~{test['effective_frames']:.0f} "
                "independent frames), so the camera and the lighthouse do not show the same motion as modelled "
                "(another run's camera frames? a wrong clock offset, camera model or face size?); not a measure "
                "of accuracy")
    if ce.status not in ("ok", "given") and out["status"] in ("ok", "inconsistent"):
        if out["status"] == "ok":
            out["status"] = f"clock_{ce.status}"
            out["message"] = (f"{out['message']}, measured on a camera clock that is {ce.status} (see the clock's "
                              "message): not a measure of accuracy")
        else:
            out["message"] += f"; the camera clock is {ce.status} too"
    if truth:
        tt = {}
        if "clock_offset_s" in truth:
            tt["clock_offset_error_s"] = ce.offset_s - float(truth["clock_offset_s"])
            tt["clock_drift_error_ppm"] = (ce.drift - float(truth.get("clock_drift", 0.0))) * 1e6
        if "camera_from_lighthouse_rotvec" in truth:
            Xt = rotvec_to_matrix(np.asarray(truth["camera_from_lighthouse_rotvec"], float))
            tt["camera_from_lighthouse_error_deg"] = float(np.degrees(attitude_error(X, Xt)))
        if "body_from_face_rotvec" in truth:
            Yt = rotvec_to_matrix(np.asarray(truth["body_from_face_rotvec"], float))
            S = label_symmetries(4)
            tt["body_from_face_error_deg"] = float(np.degrees(min(attitude_error(Y, Yt @ s) for s in S)))
        out["truth"] = tt
    # series for plots: camera mapped into the lighthouse convention beside the lighthouse
    R_cam_lh = np.swapaxes(X, -1, -2) @ R_cam @ np.swapaxes(Y, -1, -2)
    series = {"t_dev": ce.to_device(t_cam), "rotvec_camera": matrix_to_rotvec(R_cam_lh),
              "rotvec_lighthouse": np.where(m[:, None], matrix_to_rotvec(R_l), np.nan),
              "disagreement_deg": np.degrees(d), "predicted_deg": np.degrees(pred), "face_on": ~off_band,
              "lh_t": lh_t, "lh_rotvec": matrix_to_rotvec(lh_R)}
    return CrossCheck(out, series)
