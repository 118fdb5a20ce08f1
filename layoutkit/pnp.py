"""Poses from lighthouse sweep angles: the public PnP entry :func:`solve_pnp` (Chen §2, design §4).

Two paths behind one function: an ideal LH1 station goes to the fast batched solver of
:mod:`layoutkit.pnp_lh1` (POSIT / IPPE starts, Levenberg–Marquardt on the angle residuals, the
planar-ambiguity test); a station with a calibration goes through its forward model
(:func:`layoutkit.lighthouse.measure`) by :func:`layoutkit.joint.solve_joint`, which itself starts
from the fast solver. The layering is ``pnp_result`` < ``pnp_lh1`` < ``joint`` < ``pnp``: no module
imports one above it. The solver's names (statuses, thresholds, the registry) are re-exported here.
"""
from __future__ import annotations

import numpy as np

from .joint import solve_joint
from .lighthouse import Station
from .pnp_lh1 import (AMBIGUITY_LR, DEFAULT_CHUNK, MIN_ANGLES, MIN_REDUNDANCY, MIN_SENSORS, MIN_START_SENSORS,
                      PNP_SOLVERS, STATUS_AMBIGUOUS, STATUS_BEHIND, STATUS_DEGENERATE, STATUS_INVALID_ANGLE,
                      STATUS_LOW_REDUNDANCY, STATUS_NAMES, STATUS_NO_START, STATUS_NOT_CONVERGED, STATUS_OK,
                      STATUS_TOO_FEW, PnPSolver, solve_pnp_lh1, solve_pnp_lm)
from .pnp_result import PnPResult
from .units import RHO_PAPER, SIGMA_THETA_PAPER

__all__ = [
    "PnPResult", "PnPSolver", "PNP_SOLVERS", "STATUS_OK", "STATUS_TOO_FEW", "STATUS_DEGENERATE",
    "STATUS_NOT_CONVERGED", "STATUS_BEHIND", "STATUS_AMBIGUOUS", "STATUS_INVALID_ANGLE", "STATUS_NO_START",
    "STATUS_LOW_REDUNDANCY", "STATUS_NAMES", "MIN_ANGLES", "MIN_REDUNDANCY", "MIN_SENSORS", "MIN_START_SENSORS", "DEFAULT_CHUNK", "AMBIGUITY_LR",
    "solve_pnp", "solve_pnp_lm",
]


def solve_pnp(points_body, angles, visible=None, *, initial=None, max_iterations: int = 20,
              method: str = "lm", chunk_size: int = DEFAULT_CHUNK, calibration=None,
              sigma: float | None = SIGMA_THETA_PAPER, rho: float = RHO_PAPER) -> PnPResult:
    """Poses of a rigid sensor body from the sweep angles of one station, batched over frames.

    Finds per frame the pose ``p_station = R p_body + t`` minimising the sum of squared angle
    residuals over the seen angles (the maximum-likelihood pose for independent angle noise,
    Chen §3.3; residuals eqs. 6–12), see docs/pnp.md.

    Args:
        points_body: (n, 3) or (F, n, 3) float, m — sensor positions in the body frame.
        angles: (F, n, 2) or (n, 2) float, rad — ``[theta_x, theta_y]`` per sensor as
            :func:`layoutkit.lighthouse.sweep_angles` returns them (Chen eq. 2); with
            ``calibration``, the measured (distorted) angles of that station's kind (LH2: light-plane
            angles). NaN = not seen.
        visible: optional (F, n) bool per sensor or (F, n, 2) per angle; default every angle that
            is not NaN. A seen angle that is infinite or outside (0, pi) gives the frame
            :data:`STATUS_INVALID_ANGLE` (no pose), never an exception.
        initial: optional ``(rotation (F, 3, 3), translation (F, 3) m)`` start, e.g. the previous
            frame when tracking; frames where it gives no good solution fall back to the cold start.
        max_iterations: Levenberg–Marquardt iteration cap per start.
        method: a key of :data:`PNP_SOLVERS` (the CLI's choices).
        chunk_size: frames per chunk; memory stays bounded for any F.
        calibration: a :class:`layoutkit.lighthouse.Calibration` of the station, or None (ideal LH1).
            With one, the residuals are minimised through its forward model
            (:func:`layoutkit.joint.solve_joint` with one station at the origin).
        sigma: rad, angle noise of the planar-ambiguity test (default the paper's 4.014e-5, 8.28
            arcsec): two planar solutions not separable at this noise (likelihood ratio < 1000,
            :data:`AMBIGUITY_LR`) give :data:`STATUS_AMBIGUOUS` with both poses returned. None: no
            test (the lower residual wins).
        rho: same-rotor correlation of the angle noise in that test (Chen eq. 19; default 0.8717).

    Returns:
        :class:`PnPResult` with a leading frame axis F (F = 1 for (n, 2) angles): ``rotation``
        (F, 3, 3) and ``translation`` (F, 3) m in the station frame (NaN where no pose), ``status``
        (F,) codes of :mod:`layoutkit.status` (below the minimum rule of :data:`MIN_ANGLES` angles
        from :data:`MIN_SENSORS` sensors: :data:`STATUS_TOO_FEW`; solved from fewer than
        ``MIN_ANGLES + MIN_REDUNDANCY`` = 8 angles, so unable to check itself:
        :data:`STATUS_LOW_REDUNDANCY`, pose returned), ``success`` (F,) bool,
        ``residual_rms`` (F,) rad, ``iterations`` (F,). Degenerate input (too few or collinear
        sensors, NaN) gives a status, not an exception; inconsistent shapes raise ``ValueError``.

    Example (a 5-sensor body 2 m in front of the station, noise-free angles):

    >>> import numpy as np
    >>> from layoutkit.lighthouse import sweep_angles
    >>> P = np.array([[0, 0, 0], [.1, 0, 0], [0, .1, 0], [0, 0, .1], [.1, .1, .05]])
    >>> t = np.array([0.2, -0.1, 2.0])
    >>> r = solve_pnp(P, sweep_angles(P + t))
    >>> r.message, np.allclose(r.translation[0], t, atol=1e-9), np.allclose(r.rotation[0], np.eye(3), atol=1e-9)
    ('ok (1 frame(s))', True, True)
    """
    if calibration is None:
        return solve_pnp_lh1(points_body, angles, visible, initial=initial, max_iterations=max_iterations,
                             method=method, chunk_size=chunk_size, sigma=sigma, rho=rho)
    a = np.asarray(angles, float)
    a = a[None] if a.ndim == 2 else a
    st = Station(kind=calibration.kind, calibration=calibration)
    vis = None if visible is None else np.asarray(visible, bool)[:, None]
    return solve_joint(points_body, a[:, None], vis, stations=[st], initial=initial,
                       max_iterations=max(int(max_iterations), 30), chunk_size=chunk_size)
