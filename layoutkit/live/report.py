"""Validation report of a live or replayed run: ``report.json`` and PNG plots (matplotlib, Agg).

- ``precision.png`` — Chen Fig. 5 style: measured precision (eq. 23) of every static group beside
  the prediction ADOP·σθ / PDOP·σθ (eq. 24), attitude (deg) and position (mm).
- ``errors.png`` — Chen Fig. 7 style: attitude (deg) and position (mm) error against the truth /
  reference (eq. 25) over time, with the predicted RMS level.
- ``dop.png`` — ADOP, PDOP and lit sensors over time.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..io.atomic import atomic_write_text
from ..io.figures import integer_ticks, save_figure
from ..io.jsonfile import to_jsonable
from ..units import RAD2DEG as DEG, SIGMA_THETA_PAPER

__all__ = ["write_report"]





def _plot_precision(groups: list, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    k = np.arange(1, len(groups) + 1)
    mr = np.array([g["sigma_rot_deg"] for g in groups])
    pr = np.array([g["predicted_rot_deg"] for g in groups])
    mt = np.array([g["sigma_trans_m"] for g in groups]) * 1e3
    pt = np.array([g["predicted_trans_m"] for g in groups]) * 1e3
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    for a, m, p, lab in ((ax[0], mr, pr, "attitude precision (deg)"), (ax[1], mt, pt, "position precision (mm)")):
        a.plot(k, m, "o-", ms=4, label="measured (eq. 23)")
        a.plot(k, p, "s--", ms=4, label="predicted DOP·σθ (eq. 24)")
        a.set_xlabel("static group")
        a.set_ylabel(lab)
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    for a in ax:
        integer_ticks(a, "x")
    fig.suptitle("Precision per static group: measured vs predicted (Chen Fig. 5 style)")
    fig.tight_layout()
    save_figure(fig, path, dpi=120, caption=f"{len(groups)} static groups of the run; measured: spread of the "
                "poses in the group (eq. 23); predicted: DOP x sigma_theta at the group's pose (eq. 24).")


def _plot_errors(series: dict, summaries: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 1, figsize=(10, 5.5), sharex=True)
    for name, s in series.items():
        if s is None or len(s) == 0:
            continue
        s = np.asarray(s)
        ax[0].plot(s[:, 0], s[:, 1] * DEG, lw=0.6, label=f"{name}")
        ax[1].plot(s[:, 0], s[:, 2] * 1e3, lw=0.6, label=f"{name}")
        e = summaries.get(name) or {}
        if e.get("predicted_rot_deg"):
            ax[0].axhline(e["predicted_rot_deg"], ls="--", lw=1, color="k", label=f"{name}: predicted RMS")
            ax[0].axhline(e["rms_rot_deg"], ls=":", lw=1, color="r", label=f"{name}: measured RMS")
        if e.get("predicted_trans_m") and not e.get("attitude_only"):
            ax[1].axhline(e["predicted_trans_m"] * 1e3, ls="--", lw=1, color="k", label=f"{name}: predicted RMS")
            ax[1].axhline(e["rms_trans_m"] * 1e3, ls=":", lw=1, color="r", label=f"{name}: measured RMS")
    ax[0].set_ylabel("attitude error (deg)")
    ax[1].set_ylabel("position error (mm)")
    ax[1].set_xlabel("t (s)")
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(fontsize=7, loc="upper right")
    fig.suptitle("Pose error against the reference over time (Chen eq. 25, Fig. 7 style)")
    fig.tight_layout()
    save_figure(fig, path, dpi=120, caption="Angle of the rotation between solved and reference attitude (deg) and "
                "distance between positions (mm), per good frame (decimated); dashed: predicted RMS, "
                "dotted: measured RMS.")


def _plot_dop(dop: np.ndarray, sigma_theta: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(3, 1, figsize=(10, 6), sharex=True)
    ax[0].plot(dop[:, 0], dop[:, 1] * sigma_theta, lw=0.6)
    ax[0].set_ylabel("ADOP·σθ (deg)")
    ax[1].plot(dop[:, 0], dop[:, 2] * sigma_theta * 1e3, lw=0.6)
    ax[1].set_ylabel("PDOP·σθ (mm)")
    ax[2].plot(dop[:, 0], dop[:, 3], lw=0.6)
    ax[2].set_ylabel("lit sensors (count)")
    ax[2].set_xlabel("t (s)")
    integer_ticks(ax[2], "y")
    for a in ax:
        a.grid(alpha=0.3)
    fig.suptitle("Predicted precision and lit sensors over the run")
    fig.tight_layout()
    save_figure(fig, path, dpi=120, caption="ADOP and PDOP (Chen eqs. 18-22) of each good frame times the angle noise "
                "sigma_theta, i.e. the predicted 1-sigma attitude (deg) and position (mm) precision; bottom: lit "
                "sensors per frame.")


def write_report(directory, summary: dict, *, error_series: dict | None = None, dop_series=None) -> dict:
    """Write ``report.json`` and the plots into ``directory``; returns the written paths.

    summary : run summary (from :mod:`layoutkit.workflows.live`); error_series : name →
    (m, 3) array of ``(t s, e_rot rad, e_trans m)``; dop_series : (m, 4) ``(t, adop, pdop, n_lit)``.
    """
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    paths = {"json": str(d / "report.json")}
    groups = summary.get("static_groups") or []
    if groups:
        _plot_precision(groups, d / "precision.png")
        paths["precision_png"] = str(d / "precision.png")
    series = {k: v for k, v in (error_series or {}).items() if v is not None and len(v)}
    if series:
        sums = {"truth": summary.get("truth")}
        for k in ("reference", "camera"):
            r = summary.get(k) or {}
            if r.get("errors"):
                sums[k] = dict(r["errors"], attitude_only=r.get("attitude_only", False))
        _plot_errors(series, sums, d / "errors.png")
        paths["errors_png"] = str(d / "errors.png")
    if dop_series is not None and len(dop_series):
        _plot_dop(np.asarray(dop_series), summary.get("sigma_theta_rad", SIGMA_THETA_PAPER), d / "dop.png")
        paths["dop_png"] = str(d / "dop.png")
    poses = d / "poses.csv"
    if poses.exists():
        paths["poses_csv"] = str(poses)
    out = dict(summary, report=paths)
    atomic_write_text(d / "report.json", json.dumps(to_jsonable(out), indent=2) + "\n")
    return paths
