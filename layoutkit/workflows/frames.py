"""Frame workflows: simulate sweep-angle frames (``layoutkit simulate``) and solve them
(``layoutkit solve``). The file format itself is :mod:`layoutkit.io.frames` (THE frame table).
"""
from __future__ import annotations

import warnings

import numpy as np

from ..geometry import matrix_to_rotvec
from ..io.frames import Frames, read_frame_table, write_frame_table
from ..layout import Layout

__all__ = ["Frames", "simulate_frames", "write_frames", "read_frames", "solve_frames", "solution_table",
           "simulate_frame_file", "solve_frame_file", "static_precision", "sensor_residual_summary"]



def simulate_frames(layout: Layout, frames: int, *, seed: int, sigma: float, rho: float,
                    half_angle_deg: float = 60.0, min_lit: int = 4, rate_hz: float = 60.0,
                    quantize: bool = True, stations=None) -> Frames:
    """Static random poses on the paper's area in front of the station, ≥ ``min_lit`` lit.

    stations : optional S :class:`layoutkit.lighthouse.Station` (poses in one world frame, kind,
    calibration), e.g. from a stations JSON. The poses are then drawn in front of station 0 and kept
    where every station lights ≥ ``min_lit`` sensors; each pose gives one row per station, station s at
    ``k / rate_hz + s / (rate_hz S)`` (all within one 20 ms window, :func:`layoutkit.joint.group_windows`),
    its angles the station's forward model ``measure(p_s, calibration)`` (calibrated, distorted; the
    ideal :func:`~layoutkit.lighthouse.sweep_angles` for a station without one, exactly as without
    ``stations``) plus noise (sigma, rho per station and frame, Chen eq. 19) and, for LH1, counter
    quantisation. LH2 stations: noise on the light-plane angles, no quantisation, written as
    LH1-equivalent angles (:func:`~layoutkit.lighthouse.lh2_to_lh1_angles`, the frame table's
    convention). Truth columns: the body pose in the row's station frame (what a per-station solve
    returns; world pose = ``R_s R``, ``R_s t + T_s``).
    """
    from ..simulate import poses_in_front, simulate_angles
    from ..visibility import facing_mask

    rng = np.random.default_rng(seed)
    if len(layout.ids) < min_lit:
        raise ValueError(f"the layout has {len(layout.ids)} sensors: no pose can light the {min_lit} a frame needs")
    if stations is None:
        Rs, ts, vs = [], [], []
        n_have = n_drawn = 0
        while n_have < frames:
            R, t = poses_in_front(max(64, 2 * frames), rng)
            v = facing_mask(layout.positions, layout.normals, R, t, half_angle_deg=half_angle_deg)
            k = v.sum(1) >= min_lit
            Rs.append(R[k]); ts.append(t[k]); vs.append(v[k])
            n_have += int(k.sum())
            n_drawn += len(k)
            _check_acceptance(n_have, n_drawn, frames, min_lit, half_angle_deg)
        R = np.concatenate(Rs)[:frames]
        t = np.concatenate(ts)[:frames]
        v = np.concatenate(vs)[:frames]
        ang = simulate_angles(layout.positions, R, t, sigma=sigma, rho=rho, rng=rng, quantize=quantize)
        ang[~v] = np.nan
        return Frames(np.arange(frames) / rate_hz, ang, layout.ids, R, t)
    return _simulate_station_frames(layout, frames, list(stations), rng, sigma=sigma, rho=rho,
                                    half_angle_deg=half_angle_deg, min_lit=min_lit, rate_hz=rate_hz, quantize=quantize)


def _check_acceptance(n_have: int, n_drawn: int, frames: int, min_lit: int, half_angle_deg: float,
                      max_draws: int = 10_000_000) -> None:
    """Bounded work for the pose draws: a layout that (almost) never lights ``min_lit`` sensors at
    a pose of the area in front of the station is refused at once instead of drawing forever."""
    if n_drawn < 2000:
        return
    if n_have == 0:
        raise ValueError(f"no pose of {n_drawn} drawn in front of the station lights {min_lit} sensors of this "
                         f"layout (half-angle {half_angle_deg:g} deg): can it ever? check the normals")
    if frames * n_drawn / n_have > max_draws:
        raise ValueError(f"only {n_have} of {n_drawn} poses drawn in front of the station light {min_lit} sensors of "
                         f"this layout: {frames} frames would need ~{frames * n_drawn / n_have:.3g} draws")


def _simulate_station_frames(layout, frames, stations, rng, *, sigma, rho, half_angle_deg, min_lit, rate_hz,
                             quantize, max_rounds: int = 200) -> Frames:
    """:func:`simulate_frames` with stations (see there); ValueError when no pose in front of station 0
    lights ``min_lit`` sensors of every station."""
    from ..geometry import transform_points
    from ..lighthouse import measure, quantize_angles, sweep_angles, to_sweep_angles
    from ..noise import sample_angle_noise
    from ..simulate import poses_in_front
    from ..visibility import facing_mask

    S = len(stations)
    if S == 0:
        raise ValueError("stations: the stations file has no station")
    s0 = stations[0]
    Rw, tw, vis = [], [], []
    n_have = 0
    for _ in range(max_rounds):
        if n_have >= frames:
            break
        R, t = poses_in_front(max(64, 2 * frames), rng)          # station 0's frame
        R = np.einsum("ij,fjk->fik", s0.rotation, R)              # -> world
        t = t @ s0.rotation.T + s0.translation
        v = np.stack([facing_mask(layout.positions, layout.normals, *st.world_to_station(R, t),
                                  half_angle_deg=half_angle_deg, fov_deg=st.fov_deg) for st in stations], 1)
        k = np.all(v.sum(2) >= min_lit, 1)
        Rw.append(R[k]); tw.append(t[k]); vis.append(v[k])
        n_have += int(k.sum())
    if n_have < frames:
        raise ValueError(f"stations: only {n_have} of {frames} poses in front of station {s0.id} light >= {min_lit} "
                         "sensors of every station (do the stations look at a common volume?)")
    R, t, v = np.concatenate(Rw)[:frames], np.concatenate(tw)[:frames], np.concatenate(vis)[:frames]
    F, n = frames, layout.n
    ang = np.full((F, S, n, 2), np.nan)
    tru_R, tru_t = np.empty((F, S, 3, 3)), np.empty((F, S, 3))
    for q, st in enumerate(stations):
        Rs, ts = st.world_to_station(R, t)
        tru_R[:, q], tru_t[:, q] = Rs, ts
        p = transform_points(Rs, ts, layout.positions)
        a = (sweep_angles(p) if st.kind == "lh1" else measure(p, kind="lh2")) if st.calibration is None \
            else measure(p, st.calibration)
        a = a + sample_angle_noise(a.shape[:-1], sigma, rho, rng)
        if st.kind == "lh2":
            a = to_sweep_angles(a, "lh2")
        elif quantize:
            a = quantize_angles(a, st.rotor_rpm, st.clock_hz)
        a[~v[:, q]] = np.nan
        ang[:, q] = a
    tt = (np.arange(F)[:, None] / rate_hz + np.arange(S)[None, :] / (rate_hz * S)).ravel()
    station = np.tile(np.arange(S), F)
    return Frames(tt, ang.reshape(F * S, n, 2), layout.ids, tru_R.reshape(F * S, 3, 3), tru_t.reshape(F * S, 3),
                  station)


def write_frames(fr: Frames, path) -> None:
    """Write a frame table (:func:`layoutkit.io.frames.write_frame_table`), atomically."""
    write_frame_table(fr, path)


def read_frames(path, layout: Layout) -> Frames:
    """Read a frame table in the layout's sensor order (ValueError naming file and column)."""
    return read_frame_table(path, layout.ids)


def solution_table(res: dict, *, world: bool = False):
    """The per-frame results of :func:`solve_frames` as a pose table (:mod:`layoutkit.io.poses`):
    station-frame poses, or world-frame ones (``world=True``, when solved with stations)."""
    from ..io.poses import PoseTable

    rv, tr = (res["world_rotvec"], res["world_translation"]) if world else (res["rotvec"], res["translation"])
    return PoseTable(res["t"], rv, tr, station=res["station"], status=res["status"],
                     residual_rms=res["residual_rms"])


def _nearest_initial(t, station, ok, R, T, need):
    """For the frames ``need``, the pose of the nearest-in-time ok frame of the same station."""
    R0 = np.full((int(need.sum()), 3, 3), np.nan)
    T0 = np.full((int(need.sum()), 3), np.nan)
    idx = np.flatnonzero(need)
    for s in np.unique(station[idx]):
        good = np.flatnonzero(ok & (station == s))
        if good.size == 0:
            continue
        mine = np.flatnonzero(station[idx] == s)
        tg = t[good]
        order = np.argsort(tg)
        tg, good = tg[order], good[order]
        k = np.clip(np.searchsorted(tg, t[idx[mine]]), 1, len(tg)) if len(tg) > 1 else np.zeros(len(mine), int)
        if len(tg) > 1:
            left = np.abs(t[idx[mine]] - tg[k - 1]) <= np.abs(tg[np.minimum(k, len(tg) - 1)] - t[idx[mine]])
            k = np.where(left, k - 1, np.minimum(k, len(tg) - 1))
        R0[mine], T0[mine] = R[good[k]], T[good[k]]
    return R0, T0


def angle_residuals(layout: Layout, angles, seen, R, T, calibration=None) -> np.ndarray:
    """Measured minus predicted sweep angles ``(F, n, 2)`` rad of poses ``R (F,3,3), T (F,3)``
    (NaN where not seen or no pose); wrapped to (-pi, pi]. calibration : the station's calibration
    (predicted = its forward model, :func:`layoutkit.lighthouse.measure`; an LH2 calibration compares
    light-plane angles, the frame table's LH1-equivalent ones turned back by
    :func:`layoutkit.lighthouse.sweep_to_lh2_angles`)."""
    from ..geometry import transform_points
    from ..lighthouse import measure, sweep_angles, sweep_to_lh2_angles

    with np.errstate(invalid="ignore"):
        pts = transform_points(R, T, layout.positions)
        pred = sweep_angles(pts) if calibration is None else measure(pts, calibration)
        a = np.asarray(angles, float)
        if calibration is not None and calibration.kind == "lh2":
            a = sweep_to_lh2_angles(a)
        r = a - pred
    r = (r + np.pi) % (2 * np.pi) - np.pi
    return np.where(seen, r, np.nan)


def sensor_residual_summary(ids, res) -> list[dict]:
    """Per sensor and axis: count, mean and RMS (rad) of the residuals ``res (F, n, 2)``.

    A calibration bias of one sensor or one station axis shows here first (a mean far from 0).
    """
    out = []
    with np.errstate(invalid="ignore"):
        cnt = np.sum(np.isfinite(res), 0)
        mean = np.nanmean(np.where(cnt[None] > 0, res, 0.0), 0) if res.size else np.zeros((len(ids), 2))
        rms_ = np.sqrt(np.nanmean(np.where(cnt[None] > 0, res * res, 0.0), 0)) if res.size else np.zeros((len(ids), 2))
    for j, i in enumerate(ids):
        row = {"id": i}
        for a, ax in enumerate(("x", "y")):
            n = int(cnt[j, a])
            row[f"n_{ax}"] = n
            row[f"mean_{ax}"] = float(mean[j, a]) if n else None
            row[f"rms_{ax}"] = float(rms_[j, a]) if n else None
        out.append(row)
    return out


def static_precision(layout: Layout, angles, seen, R, T, *, min_frames: int = 10) -> dict:
    """A body at rest: noise estimated from the data and the pose scatter against its DOP prediction.

    sigma : RMS deviation of every seen angle from its own mean over the frames (the true angle is
    constant at rest), with the ``F / (F - 1)`` correction; rho : the mean product of the
    deviations of two different sensors on the same axis in the same frame over sigma² (Chen
    eq. 19's same-rotor correlation). Measured scatter: :func:`layoutkit.dop.precision` of the
    solved poses (Chen eq. 23). Predicted: ``sqrt(mean ADOP²) sigma`` and ``sqrt(mean PDOP²) sigma``
    with each frame's own seen angles (Chen eqs. 18–24) at the mean pose.
    """
    from scipy.spatial.transform import Rotation

    from ..dop import pose_dop, precision, predicted_precision
    from ..units import RAD2DEG

    F = len(R)
    if F < min_frames:
        return {"frames": F, "message": f"fewer than {min_frames} solved frames"}
    A = np.where(seen, angles, np.nan)
    cnt = seen.sum(0)
    use = cnt >= max(min_frames, F // 2)  # sensor-axes seen in at least half the frames
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # sensor-axes never seen: NaN mean, excluded below
        dev = A - np.nanmean(np.where(use[None], A, np.nan), 0)
    dev = np.where(use[None] & seen, dev, np.nan)
    m = np.isfinite(dev)
    N = m.sum()
    corr = np.sum(cnt[use] / np.maximum(cnt[use] - 1, 1)) / max(int(use.sum()), 1)
    sigma = float(np.sqrt(np.nansum(dev * dev) / max(N, 1) * corr))
    d0 = np.where(m, dev, 0.0)
    s1 = d0.sum(1)                 # (F, 2) per frame and axis
    s2 = (d0 * d0).sum(1)
    k = m.sum(1)
    pairs = k * (k - 1) / 2
    rho = float(np.sum((s1 * s1 - s2) / 2) / max(np.sum(pairs), 1) / (sigma * sigma * corr)) if sigma > 0 else 0.0
    rho_used = float(np.clip(rho, 0.0, 0.999))
    s_rot, s_t = precision(R, T)
    Rm = Rotation.from_matrix(R).mean().as_matrix()
    tm = T.mean(0)
    d = pose_dop(layout.positions, np.broadcast_to(Rm, (F, 3, 3)), np.broadcast_to(tm, (F, 3)), rho=rho_used,
                 visible=seen)
    okd = d.success
    pred_rot = pred_t = None
    if okd.any():  # Chen eq. (24)
        pred_rot, pred_t = (float(v) for v in predicted_precision(d.adop[okd], d.pdop[okd], sigma))
    meas_rot = float(s_rot * RAD2DEG)
    # the frames with the most common set of seen angles: a systematic error that depends on the
    # lit set (uncalibrated stations) inflates the scatter over all frames but not within one set
    keys = [m_.tobytes() for m_ in seen.reshape(F, -1)]
    uniq, inv, cnts = np.unique(keys, return_inverse=True, return_counts=True)
    same = inv == int(np.argmax(cnts))
    modal = None
    if same.sum() >= min_frames:
        sr, stt = precision(R[same], T[same])
        dm = pose_dop(layout.positions, Rm, tm, rho=rho_used, visible=seen[same][0])
        if dm.success:
            modal = {"frames": int(same.sum()), "measured_sigma_rot_deg": float(sr * RAD2DEG),
                     "measured_sigma_trans_m": float(stt), "predicted_sigma_rot_deg": float(predicted_precision(dm.adop, dm.pdop, sigma)[0]),
                     "predicted_sigma_trans_m": float(predicted_precision(dm.adop, dm.pdop, sigma)[1])}
    return {"frames": F, "same_lit_set": modal, "sigma_rad": sigma, "rho": rho, "rho_used": rho_used,
            "angles_used": int(N), "measured_sigma_rot_deg": meas_rot, "measured_sigma_trans_m": float(s_t),
            "predicted_sigma_rot_deg": pred_rot, "predicted_sigma_trans_m": pred_t,
            "ratio_rot": meas_rot / pred_rot if pred_rot else None,
            "ratio_trans": float(s_t) / pred_t if pred_t else None,
            "mean_rotvec": Rotation.from_matrix(Rm).as_rotvec().tolist(), "mean_translation": tm.tolist()}


def _station_calibrations(fr: Frames, stations: dict | None, use: bool) -> dict:
    """``{station index: Calibration}`` of the frame table's stations that carry one (none when
    ``use`` is False: the ideal model, ``--ignore-calibration``)."""
    if not use or not stations:
        return {}
    cals = {}
    for s in np.unique(fr.stations()):
        st = stations.get(int(s))
        if st is not None and st.calibration is not None:
            cals[int(s)] = st.calibration
    return cals


def _solve_calibrated(layout, angles, seen, cal, noise, initial=None):
    """One station's frames through its forward model (:func:`layoutkit.pnp.solve_pnp` with
    ``calibration``, i.e. :func:`layoutkit.joint.solve_joint` with one station), the planar-ambiguity
    test kept: the ideal solver with its test runs on the undistorted angles (the same geometry); a
    frame it calls ambiguous stays ``STATUS_AMBIGUOUS`` and its runner-up is refined through the model.
    angles : the frame table's LH1-equivalent angles (LH2 rows turned into light-plane angles here)."""
    from ..lighthouse import sweep_to_lh2_angles, to_sweep_angles
    from ..pnp import solve_pnp
    from ..status import AMBIGUOUS as STATUS_AMBIGUOUS, NO_START as STATUS_NO_START

    a_model = sweep_to_lh2_angles(angles) if cal.kind == "lh2" else np.asarray(angles, float)
    a_model = np.where(seen, a_model, np.nan)
    ideal = to_sweep_angles(a_model, cal.kind, cal)
    ref = solve_pnp(layout.positions, ideal, seen & np.isfinite(ideal), initial=initial, **noise)
    have = np.all(np.isfinite(ref.translation), 1) & np.all(np.isfinite(ref.rotation), (1, 2))
    ini = (np.where(have[:, None, None], ref.rotation, np.nan), np.where(have[:, None], ref.translation, np.nan))
    if initial is not None:
        ini = (np.where(have[:, None, None], ini[0], initial[0]), np.where(have[:, None], ini[1], initial[1]))
    sol = solve_pnp(layout.positions, a_model, seen, calibration=cal, initial=ini)
    status = sol.status.copy()
    # no cold start (fewer than 4 sensors on both axes): say so, so that pass 2 retries from a neighbour
    status[(ref.status == STATUS_NO_START) & ~sol.success] = STATUS_NO_START
    alt_R = np.full(sol.rotation.shape, np.nan)
    alt_T = np.full(sol.translation.shape, np.nan)
    amb = (ref.status == STATUS_AMBIGUOUS) & sol.success
    if amb.any() and ref.alt_rotation is not None:
        k = np.flatnonzero(amb)
        alt = solve_pnp(layout.positions, a_model[k], seen[k], calibration=cal,
                        initial=(ref.alt_rotation[k], ref.alt_translation[k]))
        status[k] = STATUS_AMBIGUOUS
        alt_R[k], alt_T[k] = alt.rotation, alt.translation
    return sol.rotation, sol.translation, status, sol.residual_rms, alt_R, alt_T


def _solve_by_station(layout, angles, seen, st, cals, noise, initial=None):
    """solve_pnp per station (through its calibration, if any); arrays over all frames."""
    from ..pnp import solve_pnp

    F = len(angles)
    R, T = np.full((F, 3, 3), np.nan), np.full((F, 3), np.nan)
    status, res = np.zeros(F, int), np.full(F, np.nan)
    alt_R, alt_T = np.full((F, 3, 3), np.nan), np.full((F, 3), np.nan)
    groups = [(None, np.ones(F, bool))] if not cals else [(int(s), st == s) for s in np.unique(st)]
    for s, k in groups:
        cal = cals.get(s) if s is not None else None
        ini = None if initial is None else (initial[0][k], initial[1][k])
        if cal is not None:
            out = _solve_calibrated(layout, angles[k], seen[k], cal, noise, initial=ini)
            R[k], T[k], status[k], res[k], alt_R[k], alt_T[k] = out
            continue
        sol = solve_pnp(layout.positions, angles[k], seen[k], initial=ini, **noise)
        R[k], T[k], status[k], res[k] = sol.rotation, sol.translation, sol.status, sol.residual_rms
        if sol.alt_rotation is not None:
            alt_R[k], alt_T[k] = sol.alt_rotation, sol.alt_translation
    return R, T, status, res, alt_R, alt_T


def _world_poses(R, T, ok, st, stations) -> dict:
    """The ok poses in the world frame (``world_rotvec``, ``world_translation``), the mean world
    pose per station and, with two stations, how far apart their means are."""
    from scipy.spatial.transform import Rotation

    wr = np.full((len(st), 3), np.nan)
    wt = np.full((len(st), 3), np.nan)
    per = {}
    for s in np.unique(st):
        if int(s) not in stations:
            raise ValueError(f"frame table has station {int(s)} but the stations file has {sorted(stations)}")
        S = stations[int(s)]
        k = ok & (st == s)
        if not k.any():
            continue
        Rw = np.einsum("ij,fjk->fik", S.rotation, R[k])
        tw = T[k] @ S.rotation.T + S.translation
        wr[k], wt[k] = matrix_to_rotvec(Rw), tw
        per[str(int(s))] = {"frames": int(k.sum()), "mean_rotvec": Rotation.from_matrix(Rw).mean().as_rotvec().tolist(),
                            "median_translation": np.median(tw, 0).tolist()}
    out = {"world_rotvec": wr, "world_translation": wt, "world_per_station": per}
    keys = list(per)
    if len(keys) >= 2:
        a_, b_ = per[keys[0]], per[keys[1]]
        dR = Rotation.from_rotvec(a_["mean_rotvec"]) * Rotation.from_rotvec(b_["mean_rotvec"]).inv()
        out["world_between_stations"] = {
            "stations": keys[:2], "translation_m": float(np.linalg.norm(np.subtract(a_["median_translation"], b_["median_translation"]))),
            "rotation_deg": float(np.degrees(np.linalg.norm(dR.as_rotvec())))}
    return out


def _truth_errors(layout, fr, R, T, ok, amb, alt_R, alt_T, seen, sigma, rho) -> dict:
    """Errors of the ok poses against the frame table's truth (gross failures apart; the ambiguous
    frames' candidates; with ``sigma`` the Chen eq. (24) prediction at the truth)."""
    from ..dop import GROSS_FAILURE_DEG, gross_failures, pose_dop, pose_errors, predicted_precision, rms
    from ..status import DESCRIPTIONS

    e_r, e_t = pose_errors(R[ok], T[ok], fr.truth_rotation[ok], fr.truth_translation[ok])
    # gross: > 1 deg off — with 4 coplanar lit sensors the planar two-fold ambiguity is
    # undecidable under noise for some poses (docs/pnp.md), so report them apart
    gross = gross_failures(e_r)
    good = ~gross
    out = dict(rms_rot_deg=float(np.degrees(rms(e_r))), rms_trans_m=float(rms(e_t)),
               max_rot_deg=float(np.degrees(e_r.max())),
               gross_failures=int(gross.sum()),
               gross_failures_by_status={DESCRIPTIONS[0]: int(gross.sum())},
               rms_rot_deg_without_gross=float(np.degrees(rms(e_r[good]))),
               rms_trans_m_without_gross=float(rms(e_t[good])))
    ia = np.flatnonzero(amb)
    if ia.size:  # neither candidate is reported as the pose; say how often the truth is among them
        e1, _ = pose_errors(R[ia], T[ia], fr.truth_rotation[ia], fr.truth_translation[ia])
        e2, _ = pose_errors(alt_R[ia], alt_T[ia], fr.truth_rotation[ia], fr.truth_translation[ia])
        out["gross_failures_by_status"]["ambiguous (best candidate)"] = int(np.sum(np.degrees(e1) > GROSS_FAILURE_DEG))
        out["ambiguous"] = {"frames": int(ia.size),
                            "truth_within_1deg_of_a_candidate": int(np.sum(np.degrees(np.minimum(e1, e2)) <= GROSS_FAILURE_DEG))}
    if sigma is not None:
        sel = np.flatnonzero(ok)[good]
        d = pose_dop(layout.positions, fr.truth_rotation[sel], fr.truth_translation[sel], rho=rho, visible=seen[sel])
        pr, pt = predicted_precision(d.adop, d.pdop, sigma)  # Chen eq. (24)
        out.update(predicted_rms_rot_deg=float(pr), predicted_rms_trans_m=float(pt))
    return out


def solve_frames(fr: Frames, layout: Layout, *, sigma: float | None = None, rho: float = 0.0,
                 method: str = "lm", stations: dict | None = None, static: bool = False,
                 ignore_calibration: bool = False) -> dict:
    """Solve every frame; never raises on bad frames (each gets a status).

    Pass 1 solves every frame cold; pass 2 solves the frames that meet the minimum rule but had
    no cold start (fewer than 4 sensors seen on both axes) from the nearest good pose of the same
    station. stations : optional ``{index: Station}``; the poses are then also given in the world
    frame (``world_rotvec``, ``world_translation``) and the per-station mean world poses compared.
    static : the body is at rest; add :func:`static_precision` per station.
    method : a key of :data:`layoutkit.pnp.PNP_SOLVERS`.
    Every station of ``stations`` that carries a calibration is solved through its forward model
    (:func:`layoutkit.pnp.solve_pnp` with ``calibration``: residuals minimised through ``measure``, never
    pre-corrected; LH1 and LH2); residuals are then against that model. ignore_calibration : the
    ideal model for every station (the uncalibrated comparison).
    Returns a summary dict plus per-frame arrays ``t, station, status, rotvec, translation,
    residual_rms, success``.
    """
    from ..status import AMBIGUOUS as STATUS_AMBIGUOUS, DESCRIPTIONS, LOW_REDUNDANCY as STATUS_LOW_REDUNDANCY
    from ..status import NO_START as STATUS_NO_START, OK as STATUS_OK

    seen = ~np.isnan(fr.angles)
    st = fr.stations()
    noise = {"method": method, **({} if sigma is None else {"sigma": sigma, "rho": rho})}  # the ambiguity test's noise
    cals = _station_calibrations(fr, stations, not ignore_calibration)
    R, T, status, res, alt_R, alt_T = _solve_by_station(layout, fr.angles, seen, st, cals, noise)
    need = status == STATUS_NO_START
    second = 0
    if need.any() and (status == STATUS_OK).any():
        R0, T0 = _nearest_initial(fr.t, st, status == STATUS_OK, R, T, need)
        has = np.all(np.isfinite(T0), 1)
        idx = np.flatnonzero(need)[has]
        if idx.size:
            R2, T2, s2, r2, aR2, aT2 = _solve_by_station(layout, fr.angles[idx], seen[idx], st[idx], cals, noise,
                                                         initial=(R0[has], T0[has]))
            R[idx], T[idx], status[idx], res[idx] = R2, T2, s2, r2
            alt_R[idx], alt_T[idx] = aR2, aT2
            second = int(np.sum(s2 == STATUS_OK))
    ok = status == STATUS_OK
    amb = status == STATUS_AMBIGUOUS
    names = {int(k): DESCRIPTIONS.get(int(k), str(k)) for k in np.unique(status)}
    counts = {names[int(k)]: int(v) for k, v in zip(*np.unique(status, return_counts=True))}
    rv = np.full((len(fr.t), 3), np.nan)
    # an ambiguous frame keeps its best candidate, a low-redundancy one its pose (their statuses say so)
    has_pose = ok | amb | (status == STATUS_LOW_REDUNDANCY)
    if has_pose.any():
        rv[has_pose] = matrix_to_rotvec(R[has_pose])
    # what was wrong with the input, by reason
    a = fr.angles
    with np.errstate(invalid="ignore"):
        reasons = {"angles not seen (empty)": int(np.sum(np.isnan(a))),
                   "infinite angles": int(np.sum(np.isinf(a))),
                   "angles outside (0, pi) rad": int(np.sum(np.isfinite(a) & ((a <= 0) | (a >= np.pi))))}
        big = np.isfinite(a) & (a >= np.pi)
    if big.any() and np.nanmedian(np.where(np.isfinite(a), a, np.nan)) > np.pi:
        reasons["hint"] = "most angles exceed pi: the file looks like degrees; frame tables are in radians"
    r = angle_residuals(layout, fr.angles, seen & ok[:, None, None], R, T)
    for s_, cal in cals.items():  # calibrated stations: residuals against their own model
        k = st == s_
        r[k] = angle_residuals(layout, fr.angles[k], (seen & ok[:, None, None])[k], R[k], T[k], cal)
    out = {"frames": int(len(fr.t)), "solved": int(ok.sum()), "solved_from_neighbour": second,
           "status_counts": {int(k): int(v) for k, v in zip(*np.unique(status, return_counts=True))},
           "statuses": counts, "input": reasons, "calibrated_stations": sorted(cals),
           "residual_rms_median": float(np.median(res[ok])) if ok.any() else None,
           "residual_rms_median_per_station": {str(int(q)): float(np.median(res[ok & (st == q)]))
                                               for q in np.unique(st) if (ok & (st == q)).any()},
           "residual_rms_p90": float(np.percentile(res[ok], 90)) if ok.any() else None,
           "sensor_residuals": sensor_residual_summary(layout.ids, r),
           "t": fr.t, "station": st, "rotvec": rv, "translation": np.where(has_pose[:, None], T, np.nan),
           "success": ok, "status": status, "residual_rms": np.where(has_pose, res, np.nan)}
    lit_ok = seen.all(-1).sum(1)  # sensors seen on both axes
    out["frames_with_4_lit"] = int(np.sum(lit_ok >= 4))
    out["frames_with_4_lit_solved"] = int(np.sum((lit_ok >= 4) & ok))
    if not ok.any():
        worst = max(counts, key=counts.get)
        out["message"] = f"no good pose in {len(fr.t)} frame(s); most common reason: {worst}"
    else:
        out["message"] = f"{int(ok.sum())} / {len(fr.t)} frames solved"
    if stations is not None:
        out.update(_world_poses(R, T, ok, st, stations))
    if static:
        out["static"] = {str(int(s)): static_precision(layout, fr.angles[ok & (st == s)], seen[ok & (st == s)],
                                                       R[ok & (st == s)], T[ok & (st == s)])
                         for s in np.unique(st)}
    if fr.truth_rotation is not None and ok.any():
        out.update(_truth_errors(layout, fr, R, T, ok, amb, alt_R, alt_T, seen, sigma, rho))
    return out


def simulate_frame_file(layout: Layout, frames: int, out, *, seed: int, sigma: float, rho: float,
                        quantize: bool = True, stations_path=None) -> dict:
    """What ``layoutkit simulate`` does: :func:`simulate_frames`, written to ``out`` (.csv or .npz).

    stations_path : a stations JSON (:mod:`layoutkit.io.stations`): one row per station and pose
    through each station's forward model (calibrated when the station carries a calibration).
    Returns the summary ``{out, frames, rows, mean_lit, min_lit}`` (lit sensors per row) and, with
    stations, ``stations`` (the stations used, with calibration, as in a stations JSON) and
    ``calibrated_stations`` (indices). ValueError naming the file for a bad stations JSON.
    """
    stations = None
    if stations_path is not None:
        from ..io.stations import read_stations

        stations = list(read_stations(stations_path))
    fr = simulate_frames(layout, frames, seed=seed, sigma=sigma, rho=rho, quantize=quantize, stations=stations)
    write_frames(fr, out)
    lit = np.all(np.isfinite(fr.angles), -1).sum(1)
    out_ = {"out": str(out), "frames": int(frames), "rows": int(fr.n_frames), "mean_lit": float(lit.mean()),
            "min_lit": int(lit.min())}
    if stations is not None:
        from ..io.stations import stations_to_list

        out_["stations"] = stations_to_list(stations)
        out_["calibrated_stations"] = [q for q, st in enumerate(stations) if st.calibration is not None]
        out_["truth_frame"] = "the row's station frame"
    return out_


def solve_frame_file(frames_path, layout: Layout, *, out=None, sigma: float | None = None, rho: float = 0.0,
                     method: str = "lm", filter_settings: dict | None = None, stations_path=None,
                     static: bool = False, ignore_calibration: bool = False) -> dict:
    """What ``layoutkit solve`` does: read a frame file, solve every frame, write the pose table to ``out``
    (:mod:`layoutkit.io.poses`: t, station, status, rx, ry, rz, tx, ty, tz, residual_rms; rad, m).

    filter_settings : None, or keywords of :class:`layoutkit.filter.EkfConfig` (see
    :func:`layoutkit.workflows.filter.filter_config`): the frames also go through the tracking
    filter, ``out`` then holds the filtered poses and the summary a ``filter`` entry.
    stations_path : a stations JSON; the pose table then holds world-frame poses and the summary
    compares the stations' mean world poses; stations with a calibration are solved through it
    unless ``ignore_calibration`` (:func:`solve_frames`). static : see :func:`static_precision`.
    Returns the JSON-ready summary of :func:`solve_frames` (without the per-frame arrays).
    ValueError (naming the file) for an unreadable frame file, stations file or filter settings.
    """
    from ..io.stations import read_stations

    fr = read_frames(frames_path, layout)
    stations = dict(enumerate(read_stations(stations_path))) if stations_path else None
    res = solve_frames(fr, layout, sigma=sigma, rho=rho, method=method, stations=stations, static=static,
                       ignore_calibration=ignore_calibration)
    fres = None
    if filter_settings is not None:
        from .filter import filter_config, filter_frames

        try:
            fres = filter_frames(fr, layout, filter_config(filter_settings, sigma, rho),
                                 stations=None if stations is None else [stations[i] for i in sorted(stations)])
        except ValueError as exc:
            raise ValueError(f"{frames_path}: {exc}") from None
    if out:
        from ..io.poses import write_poses

        if fres is None:
            write_poses(out, solution_table(res, world=stations is not None))
        else:
            from .filter import filter_table

            write_poses(out, filter_table(fres))
    arrays = ("t", "rotvec", "translation", "success", "status", "station", "residual_rms", "world_rotvec",
              "world_translation")
    summary = {k: v for k, v in res.items() if k not in arrays}
    summary["pose_frame"] = "world" if stations is not None else "station"
    if fres is not None:
        summary["filter"] = {k: v for k, v in fres.items()
                             if k not in ("t", "rotvec", "translation", "status", "cov_rot_deg", "cov_pos_m")}
    return summary
