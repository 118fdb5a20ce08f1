"""Simulated scenarios for the tracking filter (docs/filter.md): filter vs frame-by-frame PnP under
dropout, a hidden station with reflections, NEES/NIS consistency, static precision vs DOP, throughput,
and the real-recording jitter comparison.

Used by ``benchmarks/bench_filter.py`` (full sizes) and ``tests/test_filter.py`` (small sizes). The
sweeps come from :func:`layoutkit.live.simulator.simulate_sweeps` (the ``fake-fpga`` motions, paper
noise with the same-rotor correlation, 50 MHz quantisation) and are fed as arrays (no byte encoding);
the frame-by-frame baseline is the live pipeline (:class:`layoutkit.live.pipeline.PosePipeline`,
batched PnP + continuity gate), the same path as ``layoutkit replay --filter none``.
"""
from __future__ import annotations

import time

import numpy as np

from ..filter import EkfConfig, SweepTracker
from ..filter.consistency import consistency, nees, pose_error, run_sweeps
from ..geometry import attitude_error, look_at_rotation, rotvec_to_matrix
from ..lighthouse import Station
from ..units import RAD2DEG
from ..workflows.filter import filter_frames

__all__ = [
    "TUMBLE_CONFIG", "second_station", "measured", "track", "frame_by_frame", "errors_of",
    "dropout_scenario", "hidden_station_scenario", "consistency_scenario", "static_scenario",
    "throughput_scenario", "replay_throughput", "real_static_jitter",
]

TUMBLE_CONFIG = dict(motion="fixed", psd_rot=1e-8, psd_pos=3e-9, hit_timing=False, init_sigma_rate=0.05,
                     init_sigma_speed=0.05)


def second_station(target=(0.0, 0.0, 2.2), position=(1.2, 0.3, 0.4)) -> Station:
    """An LH1 station at ``position`` (m, world = station 0's frame) looking at ``target``."""
    pos = np.asarray(position, float)
    return Station(id="B", rotation=look_at_rotation(np.asarray(target, float) - pos).T, translation=pos)


def measured(sw) -> np.ndarray:
    """(K, n) rad angles the decoder would return (NaN = no hit or frame lost)."""
    a = sw.measured_angles()
    a[~sw.emitted] = np.nan
    return a


def track(layout, sw, angles=None, config: EkfConfig | None = None, **tracker_kw):
    """Run :class:`SweepTracker` over every sweep of ``sw`` → :class:`FilterRun` (and the wall time, s)."""
    tr = SweepTracker(layout.positions, sw.stations, config or EkfConfig(**TUMBLE_CONFIG), **tracker_kw)
    a = measured(sw) if angles is None else angles
    t0 = time.perf_counter()
    run = run_sweeps(tr, sw.t, sw.station, sw.axis, a)
    return run, time.perf_counter() - t0


def frame_by_frame(layout, sw, angles=None):
    """The live pipeline (batched PnP per X/Y frame) over the same sweeps.

    Returns dict of arrays over frames: t, k (sweep index of the frame's X sweep), rotation,
    translation, good, adop, pdop.
    """
    from ..live.frames import SweepMeasurement
    from ..live.pipeline import LiveConfig, PosePipeline

    a = measured(sw) if angles is None else angles
    keep = np.flatnonzero(np.any(np.isfinite(a), 1) | sw.emitted)
    sweeps = [SweepMeasurement(float(sw.t[k]), int(sw.station[k]), int(sw.axis[k]), a[k], int(sw.seq[k]))
              for k in keep]
    multi = len(sw.stations) > 1
    pipe = PosePipeline(layout.positions, LiveConfig(n_sensors=layout.n, chunk_frames=2048,
                                                         chunk_seconds=float("inf")),
                        list(sw.stations) if multi else None)
    chunks = pipe.feed(sweeps) + pipe.flush(end_of_stream=True)
    out = {k: np.concatenate([getattr(c, k) for c in chunks]) for k in ("t", "rotation", "translation", "adop",
                                                                        "pdop")}
    out["good"] = np.concatenate([c.good for c in chunks])
    out["k"] = np.searchsorted(sw.t, out["t"] - 1e-9)
    return out


def errors_of(R_est, p_est, sw, k):
    """Attitude error (deg) and position error (m) of estimates at sweep indices ``k`` vs the truth."""
    Rt = rotvec_to_matrix(sw.rotvec[k])
    return attitude_error(R_est, Rt) * RAD2DEG, np.linalg.norm(p_est - sw.translation[k], axis=-1)


def _rms(x):
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def dropout_scenario(layout, *, seed: int = 0, duration: float = 60.0, dropout: float = 0.6,
                     config: EkfConfig | None = None) -> dict:
    """Tumble with ``dropout`` of the lit hits: share of time with a pose and RMS errors, filter vs PnP.

    Share of time: filter = sweeps with status "ok" / all sweeps; PnP = good frames / all frames
    (two sweeps per frame). RMS over the poses each method reports as good.
    """
    from ..live.simulator import simulate_sweeps

    sw = simulate_sweeps(layout, duration=duration, seed=seed, dropout=dropout)
    run, wall = track(layout, sw, config=config)
    ok = run.ok
    ea, ep = errors_of(rotvec_to_matrix(run.rotvec[ok]), run.translation[ok], sw, np.flatnonzero(ok))
    fb = frame_by_frame(layout, sw)
    g = fb["good"]
    pa, pp = errors_of(fb["rotation"][g], fb["translation"][g], sw, fb["k"][g])
    frames = len(sw.t) // 2
    sig = np.sqrt(np.nansum(run.pose_cov[ok][:, [0, 1, 2], [0, 1, 2]], 1)) * RAD2DEG
    sigp = np.sqrt(np.nansum(run.pose_cov[ok][:, [3, 4, 5], [3, 4, 5]], 1))
    return {
        "seed": seed, "duration_s": duration, "dropout": dropout, "sweeps": int(len(sw.t)),
        "mean_lit_hits_per_sweep": float(np.isfinite(measured(sw)).sum(1).mean()),
        "filter": {"share_with_pose": float(ok.mean()), "rms_rot_deg": _rms(ea), "rms_pos_m": _rms(ep),
                   "predicted_rot_deg": _rms(sig), "predicted_pos_m": _rms(sigp),
                   "max_rot_deg": float(ea.max()) if ea.size else None, "counters": run.counters,
                   "sweeps_per_s": len(sw.t) / wall},
        "pnp": {"share_with_pose": float(g.sum() / max(frames, 1)), "rms_rot_deg": _rms(pa), "rms_pos_m": _rms(pp),
                "good_frames": int(g.sum()), "frames": frames},
    }


def hidden_station_scenario(layout, *, seed: int = 0, duration: float = 20.0, hide_at: float = 8.0,
                            hide_s: float = 2.0, reflect_share: float = 0.01, reflect_mrad=(5.0, 50.0),
                            config: EkfConfig | None = None) -> dict:
    """Two LH1 stations; station 1 hidden for ``hide_s`` from ``hide_at``; the most often lit sensor
    reflects: ``reflect_share`` of its hits are off by a random ±(5..50) mrad.

    Jumps: per update the pose correction per axis in units of that axis' prior 1-sigma (a correction
    the filter's own covariance did not allow shows up as > 3); also the error vs truth in units of
    the posterior 1-sigma around the hidden interval. Outliers: injected, rejected (by the angle or
    sweep gate), and angles rejected that were not injected.
    """
    from ..live.simulator import simulate_sweeps

    rng = np.random.default_rng([seed, 12])
    sw = simulate_sweeps(layout, duration=duration, seed=seed, stations=[Station(), second_station()])
    a = measured(sw)
    hidden = (sw.station == 1) & (sw.t >= hide_at) & (sw.t < hide_at + hide_s)
    a[hidden] = np.nan
    j = int(np.argmax(np.isfinite(a).sum(0)))
    hit = np.flatnonzero(np.isfinite(a[:, j]))
    bad = hit[rng.random(hit.size) < reflect_share]
    a[bad, j] += rng.choice([-1.0, 1.0], bad.size) * rng.uniform(*reflect_mrad, bad.size) * 1e-3
    tr = SweepTracker(layout.positions, sw.stations, config or EkfConfig(**TUMBLE_CONFIG))
    rej_bad, rej_other = [], 0
    bad_set = set(bad.tolist())
    missed_untracked = 0
    # run sweep by sweep to see which angles each update dropped
    from ..filter.consistency import Sweep

    outs = []
    for k in range(len(sw.t)):
        o = tr.push(Sweep(float(sw.t[k]), int(sw.station[k]), int(sw.axis[k]), a[k], "lh1"))
        outs.append(o)
        if o is None or o.correction is None and not o.sweep_rejected:
            if k in bad_set:
                missed_untracked += 1  # the filter was not tracking yet: nothing to reject
            continue
        if k in bad_set:
            rej_bad.append(o.rejected > 0 or o.sweep_rejected)
            rej_other += max(o.rejected - 1, 0)
        else:
            rej_other += o.rejected
    have = np.array([o is not None for o in outs])
    corr = np.array([o.correction if o is not None and o.correction is not None else np.full(6, np.nan)
                     for o in outs])
    prior = np.array([o.prior_sigma if o is not None and o.prior_sigma is not None else np.full(6, np.nan)
                      for o in outs])
    jump = np.abs(corr) / prior
    rv = np.array([o.rotvec if o is not None else np.full(3, np.nan) for o in outs])
    p = np.array([o.translation if o is not None else np.full(3, np.nan) for o in outs])
    cov = np.array([o.pose_cov if o is not None else np.full((6, 6), np.nan) for o in outs])
    e = pose_error(rv, p, sw.rotvec, sw.translation)
    z = np.abs(e) / np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    around = (sw.t >= hide_at - 0.5) & (sw.t < hide_at + hide_s + 1.0)
    sig = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    during = hidden | ((sw.t >= hide_at) & (sw.t < hide_at + hide_s))
    ok = np.array([o is not None and o.ok for o in outs])
    return {
        "seed": seed, "duration_s": duration, "hidden_s": [hide_at, hide_at + hide_s], "reflecting_sensor": j,
        "share_with_pose": float(ok.mean()),
        "max_correction_over_prior_sigma": float(np.nanmax(jump)),
        "corrections_over_3_prior_sigma": int(np.nansum(jump > 3)),
        "updates": int(np.isfinite(jump[:, 0]).sum()),
        "max_error_over_sigma_around_hidden": float(np.nanmax(z[around])),
        "share_error_within_3_sigma": float(np.nanmean(z[have] <= 3)),
        "sigma_rot_deg_before_hidden": float(np.nanmax(sig[(sw.t >= hide_at - 0.5) & (sw.t < hide_at), :3]) * RAD2DEG),
        "sigma_rot_deg_max_hidden": float(np.nanmax(sig[during, :3]) * RAD2DEG),
        "sigma_pos_m_before_hidden": float(np.nanmax(sig[(sw.t >= hide_at - 0.5) & (sw.t < hide_at), 3:])),
        "sigma_pos_m_max_hidden": float(np.nanmax(sig[during, 3:])),
        "rms_rot_deg": _rms(np.linalg.norm(e[ok, :3], axis=1) * RAD2DEG),
        "rms_pos_m": _rms(np.linalg.norm(e[ok, 3:], axis=1)),
        "outliers_injected": int(bad.size), "outliers_while_tracking": int(len(rej_bad)),
        "outliers_before_first_start": missed_untracked, "outliers_rejected": int(np.sum(rej_bad)),
        "good_angles_rejected": int(rej_other), "angles_used": tr.counters.angles_used,
        "counters": tr.counters.as_dict(),
    }


def consistency_scenario(layout, *, runs: int = 50, duration: float = 10.0, warm_up_s: float = 1.0,
                         every: int = 12, seed0: int = 1000, dropout: float = 0.0,
                         config: EkfConfig | None = None) -> dict:
    """NEES / NIS over ``runs`` independent tumbles (seeds ``seed0 + i``): NEES at every ``every``-th
    sweep after ``warm_up_s``, NIS of every sweep update after it (docs/filter.md "Consistency")."""
    from ..live.simulator import simulate_sweeps

    NE, NI, DO = [], [], []
    for r in range(runs):
        sw = simulate_sweeps(layout, duration=duration, seed=seed0 + r, dropout=dropout)
        run, _ = track(layout, sw, config=config)
        e = pose_error(run.rotvec, run.translation, sw.rotvec, sw.translation)
        ne = nees(e, run.pose_cov)
        start = int(np.searchsorted(sw.t, sw.t[0] + warm_up_s))
        NE.append(ne[start::every])
        NI.append(np.where(run.dof > 0, run.nis, np.nan)[start:])
        DO.append(run.dof[start:])
    L = min(len(x) for x in NE)
    L2 = min(len(x) for x in NI)
    res = consistency(np.array([x[:L] for x in NE]), np.array([x[:L2] for x in NI]),
                      np.array([x[:L2] for x in DO]))
    out = res.as_dict()
    out.update(duration_s=duration, warm_up_s=warm_up_s, dropout=dropout,
               anees_min=float(res.anees.min()), anees_max=float(res.anees.max()))
    return out


def static_scenario(layout, *, runs: int = 50, duration: float = 10.0, seed0: int = 2000) -> dict:
    """Static body, ``duration`` s: spread of the filter's final pose over ``runs`` seeds (static
    detector + zero-velocity updates on) vs the frame DOP bound / sqrt(frames).

    Bounds per frame at the true pose with the lit set: Chen eq. (18) (``dop.pose_dop``, the
    covariance of the unweighted least-squares PnP with correlated noise) and the Cramér–Rao bound
    ``(J^T R^-1 J)^-1`` with R of eq. (19) (what an estimator that weights by the correlation —
    the filter — can reach). Compared as sqrt(trace) of the attitude / position blocks.
    """
    from ..dop import pose_dop
    from ..live.simulator import simulate_sweeps
    from ..noise import angle_correlation

    from ..filter.models import PlainSweepModel

    cfg = EkfConfig(**{**TUMBLE_CONFIG, "zupt": True})
    e2, s2, b18, bcr, lits = [], [], [], [], []
    for r in range(runs):
        sw = simulate_sweeps(layout, duration=duration, seed=seed0 + r, motion="static")
        run, _ = track(layout, sw, config=cfg)
        last = int(np.flatnonzero(run.has_output)[-1])
        e = pose_error(run.rotvec[last:last + 1], run.translation[last:last + 1], sw.rotvec[last:last + 1],
                       sw.translation[last:last + 1])[0]
        e2.append([e[:3] @ e[:3], e[3:] @ e[3:]])
        d = np.diagonal(run.pose_cov[last])
        s2.append([d[:3].sum(), d[3:].sum()])
        # per-frame bounds at this run's (static) true pose with its lit set
        lit = np.all(np.isfinite(sw.angles_true[:2]), 0)
        R0 = rotvec_to_matrix(sw.rotvec[0])
        sig2 = sw.info["sigma"] ** 2
        H18 = pose_dop(layout.positions, R0, sw.translation[0], rho=sw.info["rho"], visible=lit).cov * sig2
        J = PlainSweepModel().jacobian(layout.positions[lit], R0, sw.translation[0], Station()).reshape(-1, 6)
        Rm = angle_correlation(int(lit.sum()), sw.info["rho"]) * sig2
        Hcr = np.linalg.inv(J.T @ np.linalg.solve(Rm, J))
        frames = len(sw.t) // 2
        b18.append([np.trace(H18[:3, :3]) / frames, np.trace(H18[3:, 3:]) / frames])
        bcr.append([np.trace(Hcr[:3, :3]) / frames, np.trace(Hcr[3:, 3:]) / frames])
        lits.append(int(lit.sum()))
    e2, s2, b18, bcr = (np.array(x) for x in (e2, s2, b18, bcr))
    rms = np.sqrt(e2.mean(0))
    own = np.sqrt(s2.mean(0))
    B18 = np.sqrt(b18.mean(0))
    BCR = np.sqrt(bcr.mean(0))
    return {
        "runs": runs, "duration_s": duration, "frames": frames, "lit_min_max": [min(lits), max(lits)],
        "measured_rot_deg": float(rms[0] * RAD2DEG), "measured_pos_m": float(rms[1]),
        "filter_sigma_rot_deg": float(own[0] * RAD2DEG), "filter_sigma_pos_m": float(own[1]),
        "dop18_over_sqrt_frames_rot_deg": float(B18[0] * RAD2DEG), "dop18_over_sqrt_frames_pos_m": float(B18[1]),
        "crb_over_sqrt_frames_rot_deg": float(BCR[0] * RAD2DEG), "crb_over_sqrt_frames_pos_m": float(BCR[1]),
        "ratio_measured_to_dop18": [float(x) for x in rms / B18],
        "ratio_measured_to_dop18_per_run": [float(x) for x in np.sqrt(np.mean(e2 / b18, 0))],
        "ratio_measured_to_crb": [float(x) for x in rms / BCR],
        "ratio_filter_sigma_to_dop18": [float(x) for x in own / B18],
        "sampling_error_1sigma": float(1 / np.sqrt(2 * 3 * runs)),
        "note": "RMS over runs of |final error| (3 axes) vs sqrt(mean over runs of trace(bound)/frames); "
                "each run has its own static pose and lit set; *_per_run: sqrt(mean over runs of "
                "|error|^2 / (trace(bound)/frames)), every run weighted alike",
    }


def throughput_scenario(layout, *, duration: float = 30.0, rounds: int = 5, seed: int = 3) -> dict:
    """Filter sweeps per second on one core (median of ``rounds``), arrays in (no decoding)."""
    from ..live.simulator import simulate_sweeps

    sw = simulate_sweeps(layout, duration=duration, seed=seed)
    rates, cpu = [], []
    for _ in range(rounds):
        c0 = time.process_time()
        _, wall = track(layout, sw)
        cpu.append(len(sw.t) / (time.process_time() - c0))
        rates.append(len(sw.t) / wall)
    sweep_rate = 1.0 / sw.info["slot_s"]
    med = float(np.median(rates))
    medc = float(np.median(cpu))
    return {"sweeps": int(len(sw.t)), "rounds": rounds, "sweeps_per_s_median": med,
            "sweeps_per_s_all": rates, "live_sweeps_per_s": sweep_rate, "x_real_time": med / sweep_rate,
            "sweeps_per_cpu_s_median": medc, "x_real_time_per_cpu_s": medc / sweep_rate,
            "load_average_1min": _loadavg()}


def replay_throughput(layout, *, duration: float = 30.0, rounds: int = 5, seed: int = 3) -> dict:
    """``replay`` of a simulated capture with ``--filter ekf`` vs ``none`` (same run, interleaved
    rounds, medians): wall time of the whole replay and the filter's own share (sweeps/s)."""
    import tempfile
    from pathlib import Path

    from ..live.simulator import run_fake_fpga, simulate_stream
    from ..live.pipeline import LiveConfig
    from ..workflows.live import replay_capture

    with tempfile.TemporaryDirectory() as tmp:
        cap = Path(tmp) / "cap.bin"
        chunks, sw = simulate_stream(layout, duration=duration, seed=seed)
        run_fake_fpga(chunks, out=cap, sidecar={"protocol": "layoutkit", "layout": layout.to_dict()})
        walls = {"none": [], "ekf": []}
        fsec, fcpu, fsweeps = [], [], 0
        for _ in range(rounds):
            for name in ("none", "ekf"):
                opts = LiveConfig(filter=EkfConfig(**TUMBLE_CONFIG) if name == "ekf" else None)
                t0 = time.perf_counter()
                s = replay_capture(cap, layout, options=opts)
                walls[name].append(time.perf_counter() - t0)
                if name == "ekf":
                    fsec.append(s["filter"]["filter_seconds"])
                    fcpu.append(s["filter"]["filter_cpu_seconds"])
                    fsweeps = s["filter"]["counters"]["sweeps"]
    med = {k: float(np.median(v)) for k, v in walls.items()}
    rate = 1.0 / sw.info["slot_s"]
    return {"capture_s": duration, "sweeps": fsweeps, "rounds": rounds, "wall_s_median": med,
            "replay_x_real_time": {k: duration / v for k, v in med.items()},
            "filter_sweeps_per_s_in_replay": fsweeps / float(np.median(fsec)),
            "filter_x_real_time_in_replay": fsweeps / float(np.median(fsec)) / rate,
            "filter_sweeps_per_cpu_s_in_replay": fsweeps / float(np.median(fcpu)),
            "filter_x_real_time_per_cpu_s": fsweeps / float(np.median(fcpu)) / rate,
            "load_average_1min": _loadavg()}


def _loadavg():
    import os

    try:
        return os.getloadavg()[0]
    except OSError:
        return None


def real_static_jitter(frames_path, layout_path, stations_path, *, zupt: bool = False, warm_up_s: float = 1.0,
                       psd: float = 1e-8) -> dict:
    """Filtered vs frame-by-frame pose jitter on a real recording at rest (per station, its frame).

    frames_path / layout_path / stations_path : what ``layoutkit import libsurvive`` writes. Each
    station's frames alone (the two stations' surveyed poses disagree by centimetres, more than
    the angles allow, so no joint world frame): frame-by-frame PnP, and the filter with that
    station's calibration. The filter's angle sigma is the median frame-by-frame RMS residual of
    that station (the per-sensor model error, 4x the timing noise, dominates and is not common to
    the sweep: rho = 0) — said in the result. Jitter = precision of Chen eq. (23) over the frames
    after ``warm_up_s`` (RMS rotation-vector norm / RMS position deviation from the mean).
    """
    from dataclasses import replace

    from ..dop import precision
    from ..io.stations import read_stations
    from ..layout import load_layout
    from ..workflows.frames import read_frames, solve_frames

    lay = load_layout(layout_path)
    fr = read_frames(frames_path, lay)
    sts = read_stations(stations_path)
    st_idx = np.zeros(len(fr.t), int) if getattr(fr, "station", None) is None else np.asarray(fr.station, int)
    out = {"frames_path": str(frames_path), "zupt": zupt, "warm_up_s": warm_up_s, "stations": {}}
    for s in np.unique(st_idx):
        m = st_idx == s
        F = len(fr.t)
        sub = replace(fr, **{k: (getattr(fr, k)[m] if isinstance(getattr(fr, k), np.ndarray) and len(getattr(fr, k)) == F
                                 else getattr(fr, k)) for k in ("t", "angles", "truth_rotation", "truth_translation")},
                      station=np.zeros(int(m.sum()), int))
        res = solve_frames(sub, lay)
        pok = np.asarray(res["success"])
        sigma = float(np.nanmedian(np.asarray(res["residual_rms"])[pok]))
        cfg = EkfConfig(sigma_theta=sigma, rho=0.0, motion="fixed", psd_rot=psd, psd_pos=psd, zupt=zupt,
                        init_sigma_rate=0.05, init_sigma_speed=0.05)
        f = filter_frames(sub, lay, cfg, stations=[replace(sts[int(s)], rotation=np.eye(3), translation=np.zeros(3))])
        ok = f["status"] == 0
        late = sub.t >= sub.t[0] + warm_up_s
        row = {"frames": int(m.sum()), "span_s": float(sub.t[-1] - sub.t[0]), "sigma_used_rad": sigma,
               "pnp_ok": int(pok.sum()), "filter_ok": int(ok.sum()), "filter_counters": f["counters"]}
        for name, good, rv, tr in (("pnp", pok & late, res["rotvec"], res["translation"]),
                                   ("filter", ok & late, f["rotvec"], f["translation"])):
            if good.sum() >= 3:
                r, p = precision(rotvec_to_matrix(rv[good]), tr[good])
                row[f"{name}_jitter_rot_deg"] = float(r) * RAD2DEG
                row[f"{name}_jitter_pos_mm"] = float(p) * 1e3
                row[f"{name}_samples"] = int(good.sum())
        if ok.any():
            j = np.flatnonzero(ok)[-1]
            row["filter_final_sigma_rot_deg"] = [float(v) for v in f["cov_rot_deg"][j]]
            row["filter_final_sigma_pos_mm"] = [float(v) * 1e3 for v in f["cov_pos_m"][j]]
        out["stations"][int(s)] = row
    return out
