"""Precision versus accuracy of solved poses, from the angles alone (issue 26 item 5).

Precision is the scatter the angle noise causes; accuracy is how far the model (layout, stations)
is from the truth. Without a reference the two separate like this:

- **within one lit set** (a body at rest, the windows that saw exactly the same angles): the poses
  scatter by the noise only — compare with the DOP prediction (Chen eq. 24);
- **across lit sets**: each lit set carries its own systematic error (every sensor's position or
  its station model is off by a fixed amount), so the lit-set mean poses spread apart. That spread
  over the within-set scatter says how much of the scatter a user sees is systematic;
- **per-sensor residual bias**: the mean residual of each sensor's angle (per station and axis)
  over many windows, significant when it exceeds 3 standard errors; and the smallest sensor
  offsets that explain it, ``delta_i = argmin sum |r - J_i delta_i|²`` over all windows where the
  sensor was seen, with ``J_i = d angle / d p_body`` at the solved poses (the poses already took
  the part of the error a rigid motion explains; singular directions below :data:`RCOND` of the
  largest — along the ray of a sensor only one station sees — get no offset). Its median is the "your layout's sensor
  positions are off by ~x mm" of the report — or, equivalently for the angles, the stations'
  models are off by that much at those sensors (the data cannot tell the two apart).
"""
from __future__ import annotations

import numpy as np

__all__ = ["precision_accuracy", "MIN_WINDOWS"]

#: Fewest windows per lit set (and per sensor, for its bias) that count.
MIN_WINDOWS = 10
#: Singular values below this fraction of the largest are not used in the per-sensor offset fit.
RCOND = 0.05


def _pose_spread(R, t):
    """RMS rotation (rad) and position (m) deviation of poses about their chordal mean."""
    from ..dop import precision

    r, p = precision(R, t)
    return float(r), float(p)


def precision_accuracy(positions, stations, rotation, translation, angles, *, ok=None, ids=None,
                       at_rest: bool | None = None, sigma: float | None = None, rho: float = 0.0,
                       dt=None, velocity=None) -> dict:
    """The split of the module docstring for a set of solved windows.

    positions : (n, 3) m body-frame sensors; stations : S stations (world frame, calibration);
    rotation (F, 3, 3), translation (F, 3) m: the solved world poses; angles (F, S, n, 2) rad in
    each station's convention (NaN = not seen); ok (F,) the windows to use (default: finite poses);
    ids : n sensor ids; at_rest : the body did not move (None: decided by
    :func:`layoutkit.calibrate.static_segments`, >= 90 % of the windows in one static segment);
    sigma, rho : angle noise for the DOP prediction of the within-lit-set scatter (optional);
    dt, velocity : the motion compensation the poses were solved with (optional, as
    :func:`layoutkit.joint.model_angles_jacobian`).
    Returns a JSON-ready dict (``message`` is the one-line summary).
    """
    from ..calibrate import static_segments
    from ..joint import model_angles_jacobian
    from ..units import RAD2DEG

    P = np.asarray(positions, float)
    R = np.asarray(rotation, float)
    T = np.asarray(translation, float)
    A = np.asarray(angles, float)
    F, S, n = A.shape[:3]
    ids = [str(i) for i in range(n)] if ids is None else [str(i) for i in ids]
    fin = np.all(np.isfinite(T), 1) & np.all(np.isfinite(R), (1, 2))
    ok = fin if ok is None else (np.asarray(ok, bool) & fin)
    g = np.flatnonzero(ok)
    out: dict = {"windows": int(g.size)}
    if g.size < MIN_WINDOWS:
        out["message"] = f"fewer than {MIN_WINDOWS} solved windows: no precision/accuracy split"
        return out
    Rg, Tg, Ag = R[g], T[g], A[g]
    dtg = None if dt is None else np.asarray(dt, float)[g]
    velg = None if velocity is None else (np.asarray(velocity[0])[g], np.asarray(velocity[1])[g])
    pred, J, _ = model_angles_jacobian(P, Rg, Tg, stations, dt=dtg, velocity=velg)
    res = (Ag - pred + np.pi) % (2 * np.pi) - np.pi                  # (F, S, n, 2)
    seen = np.isfinite(res)
    # d angle / d p_body = (d angle / d p_world) R  (the translation columns of the pose Jacobian)
    Jb = np.einsum("fsnkj,fji->fsnki", J[..., 3:], Rg)               # (F, S, n, 2, 3)
    # ---- per-sensor bias and the smallest offsets that explain it
    cnt = seen.sum(0)                                                 # (S, n, 2)
    r0 = np.where(seen, res, 0.0)
    mean = np.where(cnt > 0, r0.sum(0) / np.maximum(cnt, 1), np.nan)
    var = np.where(cnt > 1, (np.where(seen, (res - mean) ** 2, 0.0)).sum(0) / np.maximum(cnt - 1, 1), np.nan)
    se = np.sqrt(var / np.maximum(cnt, 1))
    signif = (cnt >= MIN_WINDOWS) & (np.abs(mean) > 3 * se)
    offsets = np.full((n, 3), np.nan)
    for i in range(n):
        m = seen[:, :, i, :]
        if m.sum() < 2 * MIN_WINDOWS:
            continue
        Ji = Jb[:, :, i][m]                                            # (m, 3)
        ri = res[:, :, i][m]
        # truncated: a sensor seen by one station only has no information along that station's ray
        # (its third singular value is pose jitter, ~1e-3 of the others): minimum norm there
        offsets[i] = np.linalg.lstsq(Ji, ri, rcond=RCOND)[0]
    have = np.all(np.isfinite(offsets), 1)
    mag = np.linalg.norm(offsets[have], axis=1)
    sensor_rows = []
    for s, st in enumerate(stations):
        for i in range(n):
            for k, ax in enumerate("xy"):
                if cnt[s, i, k] >= MIN_WINDOWS:
                    sensor_rows.append({"station": str(st.id), "sensor": ids[i], "axis": ax, "n": int(cnt[s, i, k]),
                                        "mean_rad": float(mean[s, i, k]), "se_rad": float(se[s, i, k]),
                                        "significant": bool(signif[s, i, k])})
    out["sensor_bias"] = {
        "sensor_axes": len(sensor_rows), "significant": int(sum(r["significant"] for r in sensor_rows)),
        "rms_mean_rad": float(np.sqrt(np.mean([r["mean_rad"] ** 2 for r in sensor_rows]))) if sensor_rows else None,
        "per_sensor_axis": sensor_rows}
    out["sensor_offsets"] = {
        "sensors": int(have.sum()),
        "median_mm": float(np.median(mag) * 1e3) if mag.size else None,
        "p90_mm": float(np.percentile(mag, 90) * 1e3) if mag.size else None,
        "max_mm": float(mag.max() * 1e3) if mag.size else None,
        "per_sensor_mm": {ids[i]: (offsets[i] * 1e3).tolist() for i in np.flatnonzero(have)},
        "note": "the smallest sensor moves (body frame) that explain each sensor's residuals at the solved poses; "
                "a station-model error at that sensor's directions looks the same"}
    # ---- precision within one lit set vs spread across lit sets (a body at rest)
    if at_rest is None:
        pose_of, static = static_segments(np.arange(g.size, dtype=float), Rg, Tg)
        big_pose = int(np.argmax(np.bincount(pose_of)))
        at_rest = bool(static[big_pose] and np.mean(pose_of == big_pose) >= 0.9)
    out["at_rest"] = bool(at_rest)
    if at_rest:
        keys = [m.tobytes() for m in seen.reshape(g.size, -1)]
        uniq, inv, counts = np.unique(keys, return_inverse=True, return_counts=True)
        big = np.flatnonzero(counts >= MIN_WINDOWS)
        within_r, within_p, nw, means_R, means_t, wts = [], [], 0, [], [], []
        from ..dop import pose_dop, predicted_precision
        from ..geometry import nearest_rotation

        pred_r, pred_p = [], []
        for b in big:
            sel = inv == b
            sr, sp = _pose_spread(Rg[sel], Tg[sel])
            k = int(sel.sum())
            within_r.append(sr ** 2 * k)
            within_p.append(sp ** 2 * k)
            nw += k
            means_R.append(nearest_rotation(Rg[sel].mean(0)))
            means_t.append(Tg[sel].mean(0))
            wts.append(k)
            if sigma is not None:
                f0 = np.flatnonzero(sel)[0]
                d = pose_dop(P, means_R[-1], means_t[-1], rho=rho, stations=stations,
                             visible=np.isfinite(Ag[f0]))
                if np.all(np.isfinite([d.adop, d.pdop])):
                    pr, pp = predicted_precision(d.adop, d.pdop, sigma)
                    pred_r.append(float(pr) ** 2 * k)
                    pred_p.append(float(pp) ** 2 * k)
        tot_r, tot_p = _pose_spread(Rg, Tg)
        prec = None
        across = None
        if big.size:
            prec = {"lit_sets": int(big.size), "windows": int(nw),
                    "rotation_sd_deg": float(np.sqrt(np.sum(within_r) / nw) * RAD2DEG),
                    "position_sd_mm": float(np.sqrt(np.sum(within_p) / nw) * 1e3)}
            if pred_r:
                prec["predicted_rotation_sd_deg"] = float(np.sqrt(np.sum(pred_r) / np.sum(wts[:len(pred_r)])))
                prec["predicted_position_sd_mm"] = float(np.sqrt(np.sum(pred_p) / np.sum(wts[:len(pred_p)])) * 1e3)
        if big.size >= 2:
            w = np.asarray(wts, float)
            ar, ap = _pose_spread(np.repeat(np.stack(means_R), w.astype(int), 0), np.repeat(np.stack(means_t), w.astype(int), 0))
            across = {"lit_sets": int(big.size), "rotation_spread_deg": float(ar * RAD2DEG),
                      "position_spread_mm": float(ap * 1e3)}
        out["precision_within_lit_set"] = prec
        out["spread_across_lit_sets"] = across
        out["scatter_all_windows"] = {"rotation_sd_deg": float(tot_r * RAD2DEG), "position_sd_mm": float(tot_p * 1e3),
                                      "lit_sets": int(uniq.size)}
    # ---- the one line
    parts = []
    if mag.size:
        parts.append(f"the residuals put the layout's sensor positions (or the station models at them) off by "
                     f"~{np.median(mag) * 1e3:.2f} mm (median over {mag.size} sensors, 90 % below "
                     f"{np.percentile(mag, 90) * 1e3:.2f} mm)")
    if at_rest and out.get("precision_within_lit_set") and out.get("scatter_all_windows"):
        pw, sa = out["precision_within_lit_set"], out["scatter_all_windows"]
        if pw["position_sd_mm"] > 0:
            ratio = sa["position_sd_mm"] / pw["position_sd_mm"]
            tail = ("the rest is systematic (lit-set dependent)" if ratio > 1.5
                    else "the scatter is the noise")
            parts.append(f"at rest the position scatter over all windows is {sa['position_sd_mm']:.3g} mm, "
                         f"{ratio:.1f}x the {pw['position_sd_mm']:.3g} mm within one lit set (noise): {tail}")
    out["message"] = "; ".join(parts) if parts else "not enough windows per sensor for a bias estimate"
    return out
