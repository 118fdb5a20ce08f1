"""What ``layoutkit dop`` does: the DOP of a layout at one pose and the precision it predicts.

The math is Chen et al. (2024) eqs (18)-(24) in :func:`layoutkit.dop.pose_dop`; this module picks
the lit sensors and turns ADOP/PDOP into predicted 1-sigma errors (``adop * sigma`` deg,
``pdop * sigma`` m; eq. 24 at one pose).
"""
from __future__ import annotations

import numpy as np

from ..dop import pose_dop
from ..geometry import rotvec_to_matrix
from ..layout import Layout

__all__ = ["lit_at_pose", "pose_precision"]


def lit_at_pose(layout: Layout, R: np.ndarray, t: np.ndarray, lit: str = "facing", *,
                half_angle_deg: float = 60.0) -> np.ndarray:
    """Which sensors are used, ``(n,)`` bool.

    lit : ``"all"``; ``"facing"`` (normal within ``half_angle_deg`` of the direction to the station
    and in front of it: :func:`layoutkit.visibility.facing_mask`); or comma-separated sensor ids
    (ValueError naming unknown ids). R (3, 3), t (3,) m: body pose in the station frame.
    """
    if lit == "all":
        return np.ones(layout.n, bool)
    if lit == "facing":
        from ..visibility import facing_mask

        return facing_mask(layout.positions, layout.normals, R[None], t[None], half_angle_deg=half_angle_deg)[0]
    want = [s.strip() for s in lit.split(",") if s.strip()]
    unknown = [s for s in want if s not in layout.ids]
    if unknown or not want:
        raise ValueError(f"--lit: unknown sensor ids {unknown}; the layout has {list(layout.ids)}")
    return np.isin(layout.ids, want)


def pose_precision(layout: Layout, rotvec_deg, translation_m, *, lit: str = "facing", half_angle_deg: float = 60.0,
                   rho: float, sigma: float) -> dict:
    """ADOP/PDOP at one pose and the predicted 1-sigma attitude/position errors.

    rotvec_deg (3,): body attitude in the station frame, rotation vector in degrees;
    translation_m (3,): body position, m (z = boresight); rho: same-rotor correlation in [0, 1);
    sigma: sweep-angle noise 1-sigma, rad. Returns a JSON-ready dict with ``status``/``message``
    from :class:`layoutkit.dop.DopResult` and ``success`` — or status ``"underdetermined"``
    (success False) with fewer than 4 lit sensors. ValueError for a non-finite pose.
    """
    for flag, val in (("--rotvec-deg", rotvec_deg), ("--translation-m", translation_m)):
        if not np.all(np.isfinite(np.asarray(val, float))):
            raise ValueError(f"{flag}: expected 3 finite numbers, got {' '.join(str(x) for x in val)}")
    R = rotvec_to_matrix(np.radians(np.asarray(rotvec_deg, float)))
    t = np.asarray(translation_m, float)
    v = lit_at_pose(layout, R, t, lit, half_angle_deg=half_angle_deg)
    r = pose_dop(layout.positions, R, t, rho=rho, visible=v)
    out = {"lit": [i for i, b in zip(layout.ids, v) if b], "n_lit": int(v.sum()), "rho": rho,
           "sigma_rad": sigma, "success": bool(r.success), "status": int(r.status), "message": r.message,
           "adop_deg_per_rad": float(r.adop), "pdop_m_per_rad": float(r.pdop),
           "predicted_sigma_rot_deg": float(r.adop * sigma), "predicted_sigma_trans_mm": float(r.pdop * sigma * 1e3)}
    if r.success and out["n_lit"] < 4:
        # 3 lit sensors: 6 angles for 6 unknowns — the DOP is finite, but the pose is not unique
        # (P3P has up to 4 solutions) and PnP needs 4: not "ok"
        out.update(success=False, status="underdetermined",
                   message=f"underdetermined: {out['n_lit']} lit sensors give {2 * out['n_lit']} angles for 6 pose "
                           "unknowns; the pose is not unique (P3P: up to 4 solutions) — at least 4 lit sensors are "
                           "needed; the DOP shown is of the true pose only")
    return out
