"""Plots of the camera cross-check (matplotlib, Agg): Chen Fig. 7 style streams over time.

- ``camera_attitude.png`` — the three rotation-vector components (deg) of the lighthouse attitude
  and of the camera attitude mapped into the lighthouse frame (``X^T R_ct Y^T``), over device time;
- ``camera_disagreement.png`` — lighthouse vs camera disagreement (deg) per camera frame beside its
  predicted 1-sigma size, face-on frames (mirror-branch risk) marked.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["write_camera_plots"]


def write_camera_plots(directory, cc) -> dict:
    """Write the two PNGs for a :class:`layoutkit.live.crosscheck.CrossCheck`; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io.figures import save_figure

    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    s = cc.series
    paths = {}
    fig, ax = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    for i, name in enumerate("xyz"):
        ax[i].plot(s["lh_t"], np.degrees(s["lh_rotvec"][:, i]), "-", lw=0.8, label="lighthouse (PnP)")
        ax[i].plot(s["t_dev"], np.degrees(s["rotvec_camera"][:, i]), ".", ms=2, label="camera (rectangle face)")
        ax[i].set_ylabel(f"r_{name} (deg)")
    ax[-1].set_xlabel("device time (s)")
    ax[0].legend(loc="best", fontsize=8)
    fig.suptitle("Attitude streams: lighthouse vs camera (camera mapped into the lighthouse frame)")
    fig.tight_layout(rect=(0, 0.03, 1, 0.96))
    paths["camera_attitude"] = str(save_figure(
        fig, d / "camera_attitude.png",
        caption="Rotation-vector components (deg) of the body attitude over device time; the camera stream is "
                "mapped by the estimated clock and rotations."))
    fig, ax = plt.subplots(figsize=(9, 3.8))
    fo = s["face_on"]
    ax.plot(s["t_dev"][~fo], s["disagreement_deg"][~fo], ".", ms=2, label="disagreement")
    if fo.any():
        ax.plot(s["t_dev"][fo], s["disagreement_deg"][fo], "x", ms=3, color="tab:red",
                label="face-on band (mirror-branch risk)")
    ax.plot(s["t_dev"], s["predicted_deg"], "-", lw=1, color="k", label="predicted 1-sigma")
    ax.set_xlabel("device time (s)")
    ax.set_ylabel("disagreement (deg)")
    ax.set_title("Lighthouse vs camera attitude disagreement and its prediction")
    ax.legend(loc="best", fontsize=8)
    summ = cc.summary
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    paths["camera_disagreement"] = str(save_figure(
        fig, d / "camera_disagreement.png",
        caption=f"Per camera frame; RMS {summ.get('disagreement_rms_deg') or float('nan'):.4g} deg vs predicted "
                f"{summ.get('predicted_disagreement_rms_deg') or float('nan'):.4g} deg outside the face-on band."))
    return paths
