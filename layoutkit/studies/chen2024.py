"""The Chen et al. (2024) precision study in simulation: static groups (Fig. 5, eqs. 23–24)
and dynamic runs (Table 2, eq. 25). Used by ``layoutkit study chen2024`` and
``studies/chen2024_static_precision``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..dop import pose_dop, pose_errors, predicted_precision, rms
from ..geometry import matrix_to_rotvec, rotvec_to_matrix
from ..simulate import poses_in_front, simulate_angles
from ..units import RHO_PAPER, SIGMA_THETA_PAPER
from ..visibility import facing_mask

__all__ = ["StudyConfig", "static_groups", "static_chunk", "dynamic_run", "run_chen2024", "write_outputs"]


@dataclass(frozen=True)
class StudyConfig:
    """Parameters of the Chen study (paper defaults)."""

    groups: int = 50
    frames: int = 3600
    seed: int = 0
    sigma: float = SIGMA_THETA_PAPER
    rho: float = RHO_PAPER
    quantize: bool = True
    min_lit: int = 4
    half_angle_deg: float = 60.0
    dynamic_seconds: float = 60.0
    frame_rate_hz: float = 60.0
    sensor_error_mm: float = 0.5
    chunk_frames: int = 20000


def _target():
    from ..shapes import chen_target

    return chen_target()[1]


def static_groups(cfg: StudyConfig, layout=None, progress=None, executor=None) -> list[dict]:
    """Chen §4.2 in simulation: ``cfg.groups`` static poses × ``cfg.frames`` noisy frames.

    For each group: a pose on the 3 m × 3 m area in front of the station with ≥ ``min_lit``
    sensors lit, frames solved by :func:`layoutkit.pnp.solve_pnp`, measured precision by
    eq. (23) (streaming form, :class:`layoutkit.montecarlo.ErrorSums`) against the prediction
    ADOP·σθ, PDOP·σθ of eq. (24) (rho included).

    Frames run in chunks of ``cfg.chunk_frames`` as tasks on ``executor`` (a
    :func:`layoutkit.parallel.open_executor` executor; None: in this process). Seeds:
    ``SeedSequence(cfg.seed).spawn(2)`` = (poses, frames); the frames child spawns one child per
    group and each group one per chunk, so the result is the same on any number of workers.
    progress : ``callable(frames_done)`` (increments).
    """
    from ..montecarlo import ErrorSums
    from ..parallel import chunk_plan, map_reduce_ordered
    from ..parallel.scheduler import SynchronousExecutor

    layout = layout or _target()
    ss_pose, ss_frames = np.random.SeedSequence(cfg.seed).spawn(2)
    rng = np.random.default_rng(ss_pose)
    P, N = layout.positions, layout.normals
    poses = []
    while len(poses) < cfg.groups:
        R0, t0 = poses_in_front(64, rng)
        lit = facing_mask(P, N, R0, t0, half_angle_deg=cfg.half_angle_deg)
        for R, t, v in zip(R0, t0, lit):
            if v.sum() >= cfg.min_lit and len(poses) < cfg.groups:
                poses.append((R, t, v))
    Rs = np.stack([p[0] for p in poses])
    ts = np.stack([p[1] for p in poses])
    vs = np.stack([p[2] for p in poses])
    items = [(g, c) for g, gss in enumerate(ss_frames.spawn(cfg.groups))
             for c in chunk_plan(cfg.frames, cfg.chunk_frames, gss)]
    ex = executor or SynchronousExecutor()
    shared = (P, ex.share(Rs), ex.share(ts), ex.share(vs), cfg.sigma, cfg.rho, cfg.quantize)

    def merge(acc, res):
        g, sums = res
        acc[g] = acc[g].merge(sums)
        return acc

    sums = map_reduce_ordered(ex, static_chunk, items, merge, [ErrorSums() for _ in poses], shared_args=shared,
                              progress=(lambda it, r: progress(it[1].count)) if progress else None,
                              key="chen-static")
    out = []
    for g, ((R, t, v), s) in enumerate(zip(poses, sums)):
        dop = pose_dop(P, R, t, rho=cfg.rho, visible=v)
        s_rot, s_t = s.precision()  # eq. (23)
        out.append({
            "group": g,
            "n_lit": int(v.sum()),
            "lit": [i for i in np.flatnonzero(v).tolist()],
            "rotvec_rad": matrix_to_rotvec(R).tolist(),
            "translation_m": t.tolist(),
            "adop_deg_per_rad": float(dop.adop),
            "pdop_m_per_rad": float(dop.pdop),
            "predicted_sigma_rot_deg": float(predicted_precision(dop.adop, dop.pdop, cfg.sigma)[0]),  # eq. (24)
            "simulated_sigma_rot_deg": float(np.degrees(s_rot)),
            "predicted_sigma_trans_m": float(predicted_precision(dop.adop, dop.pdop, cfg.sigma)[1]),
            "simulated_sigma_trans_m": float(s_t),
            "frames": cfg.frames,
            "gross_failures": int(s.gross + s.frames - s.solved),
        })
    return out


def static_chunk(points, Rs, ts, lit, sigma, rho, quantize, item):
    """Dask task: one chunk of one static group -> ``(group, ErrorSums)`` (no per-frame arrays)."""
    from ..montecarlo import ErrorSums, simulate_solve

    g, chunk = item
    F = chunk.count
    e, d, solved = simulate_solve(points, np.broadcast_to(Rs[g], (F, 3, 3)), np.broadcast_to(ts[g], (F, 3)),
                                  np.broadcast_to(lit[g], (F, len(points))), sigma=sigma, rho=rho,
                                  rng=chunk.rng(), quantize=quantize)
    return g, ErrorSums().add(e, d, solved)


def dynamic_run(cfg: StudyConfig, layout=None, sensor_error_mm: float = 0.0) -> dict:
    """A dynamic run against the true trajectory (Chen §4.3, eq. 25).

    The target crosses the area on a smooth path with a slow tumble, sampled at
    ``cfg.frame_rate_hz``; lit sensors change along the way (frames with < 4 lit are skipped,
    as the hardware would). ``sensor_error_mm`` perturbs the sensor coordinates the solver is
    given (RMS per axis) — an uncalibrated systematic error of the kind the paper blames for
    its dynamic errors being ten times its precision.
    """
    from ..pnp import solve_pnp

    layout = layout or _target()
    rng = np.random.default_rng(cfg.seed + 1)
    P, N = layout.positions, layout.normals
    n_f = int(cfg.dynamic_seconds * cfg.frame_rate_hz)
    tt = np.arange(n_f) / cfg.frame_rate_hz
    w = 2 * np.pi / max(cfg.dynamic_seconds, 1e-9)
    trans = np.column_stack([1.0 * np.sin(w * tt), 0.3 + 0.05 * np.sin(3 * w * tt), 2.0 + 0.8 * np.cos(w * tt)])
    rv = np.column_stack([2.6 + 0.3 * np.sin(2 * w * tt), 0.5 * np.sin(w * tt), 0.3 * np.cos(w * tt)])
    R = rotvec_to_matrix(rv)
    lit = facing_mask(P, N, R, trans, half_angle_deg=cfg.half_angle_deg)
    keep = lit.sum(1) >= cfg.min_lit
    if not keep.any():
        raise ValueError("dynamic_run: no frame of the trajectory has enough lit sensors")
    ang = simulate_angles(P, R, trans, sigma=cfg.sigma, rho=cfg.rho, rng=rng, quantize=cfg.quantize)
    P_model = P + rng.normal(scale=sensor_error_mm * 1e-3, size=P.shape)
    sol = solve_pnp(P_model, ang[keep], lit[keep])
    e_rot, e_t = pose_errors(sol.rotation, sol.translation, R[keep], trans[keep])  # eq. (25)
    dop = pose_dop(P, R[keep], trans[keep], rho=cfg.rho, visible=lit[keep])
    return {
        "sensor_error_mm": sensor_error_mm,
        "frames": int(keep.sum()),
        "frames_skipped_lt_min_lit": int((~keep).sum()),
        "time_s": tt[keep].tolist(),
        "e_rot_deg": np.degrees(e_rot).tolist(),
        "e_trans_m": e_t.tolist(),
        "rms_rot_deg": float(np.degrees(rms(e_rot))),
        "max_rot_deg": float(np.degrees(e_rot.max())),
        "rms_trans_m": float(rms(e_t)),
        "max_trans_m": float(e_t.max()),
        "predicted_rms_rot_deg": float(predicted_precision(dop.adop, dop.pdop, cfg.sigma)[0]),  # eq. (24)
        "predicted_rms_trans_m": float(predicted_precision(dop.adop, dop.pdop, cfg.sigma)[1]),
    }


def run_chen2024(cfg: StudyConfig, progress=None, executor=None) -> dict:
    """Static groups (chunked on ``executor``) and two dynamic runs (ideal, and with
    ``sensor_error_mm`` systematic error). progress : ``callable(frames_done)`` for the static part."""
    groups = static_groups(cfg, progress=progress, executor=executor)
    pred_r = np.array([g["predicted_sigma_rot_deg"] for g in groups])
    sim_r = np.array([g["simulated_sigma_rot_deg"] for g in groups])
    pred_t = np.array([g["predicted_sigma_trans_m"] for g in groups])
    sim_t = np.array([g["simulated_sigma_trans_m"] for g in groups])
    summary = {
        "groups": len(groups),
        "frames_per_group": cfg.frames,
        "median_ratio_rot": float(np.median(sim_r / pred_r)),
        "median_ratio_trans": float(np.median(sim_t / pred_t)),
        "max_abs_rel_dev_rot": float(np.max(np.abs(sim_r / pred_r - 1))),
        "max_abs_rel_dev_trans": float(np.max(np.abs(sim_t / pred_t - 1))),
        "median_sigma_rot_deg": float(np.median(sim_r)),
        "median_sigma_trans_mm": float(np.median(sim_t) * 1e3),
        "gross_failures": int(sum(g["gross_failures"] for g in groups)),
        "total_frames": int(cfg.frames * len(groups)),
    }
    dyn = [dynamic_run(cfg, sensor_error_mm=0.0)]
    if cfg.sensor_error_mm > 0:
        dyn.append(dynamic_run(cfg, sensor_error_mm=cfg.sensor_error_mm))
    return {
        "config": {k: getattr(cfg, k) for k in cfg.__dataclass_fields__},
        "summary": summary,
        "groups": groups,
        "dynamic": dyn,
        "paper": {
            "static": "attitude precision ~0.1 deg, position ~mm; ADOP·σ, PDOP·σ track measured (Fig. 5)",
            "dynamic_rms_rot_deg": [0.18, 1.07], "dynamic_rms_trans_mm": [3.5, 19.0],
            "dynamic_max_rot_deg": [0.82, 5.76], "dynamic_max_trans_mm": [11.6, 45.4],
        },
    }


def write_outputs(result: dict, out_dir) -> dict:
    """Write ``chen2024.json``, ``table.md``, ``fig5_precision.png`` and ``fig7_dynamic.png``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    from ..io.atomic import atomic_write_text
    from ..io.figures import integer_ticks, save_figure

    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "chen2024.json", json.dumps(result, indent=1))
    g = result["groups"]
    idx = np.arange(1, len(g) + 1)
    fig, ax = plt.subplots(2, 1, figsize=(10, 7), sharex=True)
    ax[0].plot(idx, [x["simulated_sigma_rot_deg"] for x in g], "o-", label="simulated σ_rot (eq. 23)")
    ax[0].plot(idx, [x["predicted_sigma_rot_deg"] for x in g], "s--", mfc="none", label="ADOP·σθ (eq. 24)")
    ax[0].set_ylabel("attitude precision [deg]")
    ax[1].plot(idx, [1e3 * x["simulated_sigma_trans_m"] for x in g], "o-", label="simulated σ_trans (eq. 23)")
    ax[1].plot(idx, [1e3 * x["predicted_sigma_trans_m"] for x in g], "s--", mfc="none", label="PDOP·σθ (eq. 24)")
    ax[1].set_ylabel("position precision [mm]")
    ax[1].set_xlabel("static group")
    for a in ax:
        a.set_yscale("log")
        a.grid(True, which="both", alpha=0.3)
        a.legend()
    s = result["summary"]
    fig.suptitle(f"Chen et al. (2024) Fig. 5 in simulation: {s['groups']} groups × {s['frames_per_group']} frames, "
                 f"ρ = {result['config']['rho']}")
    integer_ticks(ax[1], "x")
    fig.tight_layout()
    save_figure(fig, out / "fig5_precision.png", dpi=120,
                caption="Each static group: one random pose, its frames solved; simulated: spread of the solved poses "
                        "(eq. 23); predicted: DOP x sigma_theta (eq. 24).")

    fig, ax = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    for d in result["dynamic"]:
        lab = f"sensor coords error {d['sensor_error_mm']} mm"
        ax[0].plot(d["time_s"], d["e_rot_deg"], lw=0.6, label=lab)
        ax[1].plot(d["time_s"], 1e3 * np.asarray(d["e_trans_m"]), lw=0.6, label=lab)
    ax[0].set_ylabel("attitude error [deg]")
    ax[1].set_ylabel("position error [mm]")
    ax[1].set_xlabel("time [s]")
    for a in ax:
        a.grid(True, alpha=0.3)
        a.legend()
    fig.suptitle("Dynamic run against truth (eq. 25), cf. Chen Fig. 7")
    fig.tight_layout()
    save_figure(fig, out / "fig7_dynamic.png", dpi=120,
                caption="Attitude (deg) and position (mm) error of each frame of the dynamic runs against the "
                        "simulated truth (eq. 25), with and without a systematic sensor-coordinate error.")

    lines = ["| group | lit | pred σ_rot [deg] | sim σ_rot [deg] | pred σ_trans [mm] | sim σ_trans [mm] | gross |",
             "|---:|---:|---:|---:|---:|---:|---:|"]
    for x in g:
        lines.append(f"| {x['group']} | {x['n_lit']} | {x['predicted_sigma_rot_deg']:.4f} | {x['simulated_sigma_rot_deg']:.4f} "
                     f"| {1e3 * x['predicted_sigma_trans_m']:.3f} | {1e3 * x['simulated_sigma_trans_m']:.3f} | {x['gross_failures']} |")
    lines += ["", "| dynamic run | frames | RMS rot [deg] (pred) | max rot [deg] | RMS trans [mm] (pred) | max trans [mm] |",
              "|---|---:|---:|---:|---:|---:|"]
    for d in result["dynamic"]:
        lines.append(f"| sensor error {d['sensor_error_mm']} mm | {d['frames']} | {d['rms_rot_deg']:.4f} ({d['predicted_rms_rot_deg']:.4f}) "
                     f"| {d['max_rot_deg']:.3f} | {1e3 * d['rms_trans_m']:.3f} ({1e3 * d['predicted_rms_trans_m']:.3f}) | {1e3 * d['max_trans_m']:.2f} |")
    lines += ["", "Paper (Table 2, hardware): RMS 0.18–1.07 deg, 3.5–19 mm; max 0.82–5.76 deg, 11.6–45.4 mm."]
    atomic_write_text(out / "table.md", "\n".join(lines) + "\n")
    return {"json": str(out / "chen2024.json"), "table": str(out / "table.md"),
            "fig5": str(out / "fig5_precision.png"), "fig7": str(out / "fig7_dynamic.png")}
