"""One status convention for every result (``success``, ``status``, ``message``).

Every result dataclass carries ``success`` (bool, or a bool array over frames/poses), ``status``
and ``message`` (plain language). ``status`` is a name from the documented set below; where a
result holds many poses (``PnPResult``, ``DopResult``, the live pipeline's ``PoseChunk``, the
``status`` column of the pose table, :mod:`layoutkit.io.poses`) it is stored as the integer
:data:`CODES` of that name, one table for all of them, so a status written by ``solve`` and one
written by ``replay`` mean the same. ``0`` / ``"ok"`` means ok, and nothing else does.

Pose statuses (:data:`NAMES`, integer code → name; :data:`DESCRIPTIONS` for messages):

====  ===============  ==========================================================================
code  name             meaning
====  ===============  ==========================================================================
0     ok               a trusted result
1     too_few_lit      fewer lit sensors or angles than the method needs (PnP: < 6 angles or < 3
                       sensors seen; live: fewer than ``min_lit`` sensors on both axes)
2     degenerate       singular geometry: collinear sensors, singular normal equations, range
                       unobservable
3     not_converged    the iteration stopped without meeting its tolerance
4     behind           the best pose puts a lit sensor behind the station (z <= 0)
5     ambiguous        two distinct poses fit equally well at the noise level (both returned)
6     invalid_angle    a seen angle is infinite or outside (0, pi) rad: garbage or wrong units
7     no_start         meets the rule, but < 4 sensors seen on both axes and no initial pose
8     high_residual    solved, but the angle residual is far above the noise (live pipeline)
9     jump             solved, but inconsistent with the recent track (live continuity gate)
10    solver_failed    the solver gave no usable pose (live pipeline; PnP's own code is 2–7)
11    low_redundancy   solved, but with too little redundancy to check itself: fewer than
                       ``MIN_ANGLES + MIN_REDUNDANCY`` = 8 seen angles for the 6 pose unknowns.
                       With 6 angles (e.g. 3 sensors) the pose fits any angles exactly, so an error
                       in one angle moves it and leaves no residual; with 7 an error shows in the
                       one residual degree of freedom but every angle's standardised residual is
                       the same, so it cannot be located (Baarda). The pose is returned, not ok.
12    imprecise        solved, but its predicted 1-sigma position (DOP with the run's sigma/rho)
                       is above the run's limit (e.g. a small deck seen by one station)
13    uncertain        tracking filter: its own 1-sigma pose is above the configured limits
14    lost             tracking filter: the innovations reject the state; re-initialising
====  ===============  ==========================================================================

Single results use names: the optimiser (``"optimal"``, ``"ok"``, ``"infeasible"``,
``"uncoverable"``, ``"no_feasible_found"``, ``"interrupted"``, ``"incomplete"``: a dense loop that ended
with some of its poses short of lit sensors), coverage (``"ok"``,
``"infeasible"``, ``"uncoverable"``), camera frames (``"ok"``, ``"degenerate"``, ``"mirrored"``,
``"failed"`` and the detector's own names). Results that may be wrong say so
(``ambiguous``, ``underdetermined``, ``inaccurate``, ``high_residual``, ``jump``, ``imprecise``).
"""
from __future__ import annotations

import numpy as np

__all__ = ["OK", "TOO_FEW_LIT", "DEGENERATE", "NOT_CONVERGED", "BEHIND", "AMBIGUOUS", "INVALID_ANGLE", "NO_START",
           "HIGH_RESIDUAL", "JUMP", "SOLVER_FAILED", "LOW_REDUNDANCY", "IMPRECISE", "UNCERTAIN", "LOST", "MIN_ANGLES",
           "MIN_REDUNDANCY",
           "NAMES", "CODES", "DESCRIPTIONS", "summarize"]

OK = 0
TOO_FEW_LIT = 1
DEGENERATE = 2
NOT_CONVERGED = 3
BEHIND = 4
AMBIGUOUS = 5
INVALID_ANGLE = 6
NO_START = 7
HIGH_RESIDUAL = 8
JUMP = 9
SOLVER_FAILED = 10
LOW_REDUNDANCY = 11
IMPRECISE = 12
UNCERTAIN = 13
LOST = 14

#: The redundancy rule (docs/pnp.md "Redundancy"): a rigid pose has 6 unknowns, so it needs
#: MIN_ANGLES = 6 seen angles (fewer: ``too_few_lit``), and MIN_REDUNDANCY = 2 more angles to check
#: itself — to detect an error in one angle (redundancy 1) and to be able to tell which angle it is
#: (redundancy 2, the least at which that is possible; whether it succeeds depends on the geometry).
#: A solved pose with 6 or 7 seen angles (over all stations of a joint solve) is ``low_redundancy``.
MIN_ANGLES = 6
MIN_REDUNDANCY = 2

#: Pose status code → name (JSON lines, reports).
NAMES = {OK: "ok", TOO_FEW_LIT: "too_few_lit", DEGENERATE: "degenerate", NOT_CONVERGED: "not_converged",
         BEHIND: "behind", AMBIGUOUS: "ambiguous", INVALID_ANGLE: "invalid_angle", NO_START: "no_start",
         HIGH_RESIDUAL: "high_residual", JUMP: "jump", SOLVER_FAILED: "solver_failed",
         LOW_REDUNDANCY: "low_redundancy", IMPRECISE: "imprecise",
         UNCERTAIN: "uncertain", LOST: "lost"}
#: Name → code.
CODES = {v: k for k, v in NAMES.items()}
#: Code → one-line description (messages).
DESCRIPTIONS = {
    OK: "ok",
    TOO_FEW_LIT: "too few angles (< 6 angles or < 3 sensors seen)",
    DEGENERATE: "degenerate geometry (collinear sensors, singular normal equations or unobservable range)",
    NOT_CONVERGED: "not converged",
    BEHIND: "behind the station (a lit sensor at z <= 0)",
    AMBIGUOUS: "ambiguous (two poses fit equally well at the noise level; both returned)",
    INVALID_ANGLE: "invalid angle (infinite or outside (0, pi) rad; degrees?)",
    NO_START: "no start (fewer than 4 sensors seen on both axes and no initial pose)",
    HIGH_RESIDUAL: "angle residual far above the noise",
    JUMP: "inconsistent with the recent track",
    SOLVER_FAILED: "no usable pose from the solver",
    LOW_REDUNDANCY: "low redundancy (fewer than 8 seen angles for 6 unknowns: the pose cannot check itself)",
    IMPRECISE: "predicted precision worse than the run's limit",
    UNCERTAIN: "filter covariance above its limits",
    LOST: "filter lost (innovations reject the state)",
}


def summarize(status, names: dict | None = None, what: str = "frames") -> str:
    """One line for an array of status codes: ``"all 12 frames ok"`` or ``"10 ok, 2 too_few_lit"``.

    names : code → text (default :data:`NAMES`).
    """
    names = NAMES if names is None else names
    s = np.asarray(status).reshape(-1)
    if s.size == 0:
        return f"no {what}"
    if np.all(s == OK):
        return f"all {s.size} {what} ok"
    codes, counts = np.unique(s, return_counts=True)
    return ", ".join(f"{int(n)} {names.get(int(c), f'status {int(c)}')}" for c, n in zip(codes, counts))
