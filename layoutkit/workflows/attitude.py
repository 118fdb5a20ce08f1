"""What ``layoutkit camera-attitude`` does: the attitude stream of a rectangular face from images,
a video, a capture device or a corners CSV (Zhai et al. 2014), as a JSON-able dict."""
from __future__ import annotations

import numpy as np

__all__ = ["camera_attitude"]


def camera_attitude(source, focal_length_px: float, principal_point=None, method: str = "zhai",
                    aspect_ratio: float | None = None, fps: float | None = None, max_frames: int | None = None,
                    threshold: float | None = None) -> dict:
    """Attitude stream of an image, folder, video, device index or corners CSV → JSON-able dict.

    Angles are reported in degrees (Euler Z→Y→X of Zhai §1) beside the rotation matrices.
    """
    from ..camera import euler_zyx
    from ..camera.stream import attitude_stream

    opts = {"aspect_ratio": aspect_ratio} if (method == "ippe" and aspect_ratio is not None) else {}
    det = {"threshold": threshold} if threshold is not None else None
    s = attitude_stream(source, focal_length_px, principal_point=principal_point, method=method, fps=fps,
                        max_frames=max_frames, detector_options=det, **opts)
    th = np.degrees(np.stack(euler_zyx(np.where(s.success[:, None, None], s.rotation, np.eye(3))), -1))
    frames = []
    for k in range(len(s.t)):
        frames.append({
            "t_s": s.t[k], "success": s.success[k], "status": s.status[k],
            "euler_zyx_deg": th[k] if s.success[k] else None,
            "rotation": s.rotation[k] if s.success[k] else None,
            "corners_uv_px": s.corners_uv[k], "line_fit_rms_px": s.rms_px[k],
        })
    return {"source": str(source), "method": method, "focal_length_px": focal_length_px,
            "n_frames": len(s.t), "n_solved": int(s.success.sum()), "frames": frames}
