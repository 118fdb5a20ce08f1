"""Station geometry from the capture itself (``replay --refine-stations``, issue 25 item 3).

A Crazyflie system config's station poses come from the client's own calibration and can disagree
with each other by millimetres to centimetres at the deck; then no joint pose fits both stations'
angles (their RMS residual is many sigma) although each station alone is consistent. Rather than
hiding that in ``high_residual`` flags, the stations are re-estimated from the capture: the joint
windows seen by every station (at least ``min_lit`` sensors each) in which the body is at rest or
slow (speed from the neighbouring windows' joint poses below ``max_speed``: the bundle adjustment
models each window as one pose) are bundle-adjusted (:func:`layoutkit.calibrate.bundle_adjust`:
the first station's pose held as given — the world frame —, the other stations' poses free, each
with its 1-sigma; with ``fit_calibration`` also the observable calibration terms, unobservable and
weakly observable ones held at their factory values). Poses only by default: on the Bitcraze
dataset's static captures (ten deck positions, one set-up) the poses-only refinement brings the
joint poses of a moving capture to 9 mm RMS against motion capture, poses plus calibration to
17 mm (the system config's own: 24 mm) — the calibration terms trade off against the poses there.

What a capture can say: a deck at rest fixes the other stations only through what each of them
sees of the same deck, so their poses are determined as far as the deck's 3 cm baseline allows —
large sds along the directions it does not see (reported, never hidden) but a consistent set-up at
the deck. The verdict (``contradicted``): the given set-up explains the angles only at more than
``contradiction_factor`` times the residual scale the refined one reaches (the median window's RMS
residual, in sigma). The refined stations are
used when the adjustment converged and lowered the residuals; ``stations_refined.json`` (report
folder) lets later replays use them (``--stations``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["StationRefinement", "refine_stations"]


@dataclass(frozen=True)
class StationRefinement:
    """Result of :func:`refine_stations`.

    stations : the stations to use (refined when ``applied``, else the given ones); applied : bool;
    report : JSON-able dict (samples, residual scale before / after in sigma, per station: moved
    (m, vector and norm), rotated (deg), their 1-sigma, calibration terms fitted, verdict);
    success, status ("ok", "too_few_samples", "not_converged", "no_improvement"), message.
    """

    stations: tuple
    applied: bool
    report: dict = field(default_factory=dict)
    success: bool = False
    status: str = ""
    message: str = ""


def _windows(frames, n_stations: int, window_s: float):
    from .joint_stream import JointWindower

    win = JointWindower(n_stations, window_s)
    out = []
    for f in frames:
        out.extend(win.push(f))
    return out + win.flush()


def _slow_windows(frames, P, stations, window_s, min_lit, max_speed):
    """The windows of one capture's frames seen by every station with ``min_lit`` sensors each and
    the body slower than ``max_speed``: ``(angles (K, S, n, 2), counts dict)``."""
    from ..joint import solve_joint
    from .joint_stream import window_arrays

    S = len(stations)
    ws = _windows(frames, S, window_s)
    t, ang, _, have = window_arrays(ws, len(P), S)
    lit = np.all(np.isfinite(ang), -1)
    idx = np.flatnonzero(have.all(1) & (lit.sum(-1) >= min_lit).all(1))
    counts = {"windows": len(ws), "windows_all_stations": int(idx.size), "windows_slow": 0}
    if idx.size < 3:
        return ang[:0], counts
    pos = np.asarray(solve_joint(P, ang[idx], stations=stations).translation)
    speed = np.full(idx.size, np.inf)
    dt = t[idx][2:] - t[idx][:-2]
    with np.errstate(invalid="ignore", divide="ignore"):
        speed[1:-1] = np.linalg.norm(pos[2:] - pos[:-2], axis=1) / np.where(dt > 0, dt, np.nan)
    slow = np.where(np.isfinite(speed), speed, np.inf) < max_speed
    counts["windows_slow"] = int(slow.sum())
    return ang[idx[slow]], counts


def refine_stations(frames, points_body, stations, *, sigma: float, window_s: float = 0.02, min_lit: int = 3,
                    max_speed: float = 0.05, max_samples: int = 1500, min_samples: int = 30,
                    contradiction_factor: float = 3.0, fit_calibration: bool = False) -> StationRefinement:
    """Bundle-adjust the stations on the slow joint windows of ``frames`` (module docstring).

    frames : :class:`~layoutkit.live.pipeline.AngleFrame` s in time order (their ``raw`` measured
    angles, each station's convention), or a list of such lists — several captures of the same
    station set-up (each windowed on its own: a deck at rest in several places fixes the stations
    far better than one place); points_body : (n, 3) m; stations : the S >= 2 given
    :class:`~layoutkit.lighthouse.Station` (world poses, calibrations); sigma : rad, the run's angle
    noise (the residual scale). Windows seen by every station with ``min_lit`` sensors each, speed
    (central difference of the neighbouring windows' joint positions) below ``max_speed`` m/s; at
    most ``max_samples`` of them, evenly spread over the capture.
    """
    from ..calibrate import bundle_adjust
    from ..geometry import matrix_to_rotvec
    from ..joint import solve_joint

    stations = list(stations)
    S, P = len(stations), np.asarray(points_body, float)
    given = StationRefinement(tuple(stations), False)
    if S < 2:
        return StationRefinement(tuple(stations), False, {}, False, "too_few_stations",
                                 "station geometry needs two or more stations")
    sets = [frames] if not frames or not isinstance(frames[0], (list, tuple)) else frames
    parts, per_capture = [], []
    for fr in sets:
        a_k, counts = _slow_windows(list(fr), P, stations, window_s, min_lit, max_speed)
        parts.append(a_k)
        per_capture.append(counts)
    report = {"captures": per_capture, "max_speed_m_s": max_speed}
    # evenly over the captures and over each capture's time
    total = sum(len(x) for x in parts)
    if total < min_samples:
        msg = (f"{total} window(s) seen by every station with the body slower than {max_speed:g} m/s (need "
               f"{min_samples}): the capture cannot refine the stations (a deck in constant motion); kept the given "
               "stations")
        return StationRefinement(given.stations, False, report | {"message": msg}, False, "too_few_samples", msg)
    quota = max(1, max_samples // max(1, sum(len(x) > 0 for x in parts)))
    a = np.concatenate([x[np.unique(np.linspace(0, len(x) - 1, min(quota, len(x))).astype(int))]
                        for x in parts if len(x)])
    start = solve_joint(P, a, stations=stations)
    res = bundle_adjust(P, a, stations, sigma=sigma, initial_poses=(start.rotation, start.translation),
                        fit_calibration=fit_calibration)
    report["samples"] = int(len(a))
    report["bundle_adjustment"] = {"status": res.status, "message": res.message, "evaluations": res.nfev}
    if not res.success:
        msg = f"bundle adjustment {res.status}: {res.message}; kept the given stations"
        return StationRefinement(given.stations, False, report | {"message": msg}, False, "not_converged", msg)

    def scale(r):  # the median window's RMS residual, in sigma (a few bad windows do not dominate it)
        r = np.asarray(r).reshape(len(r), -1)
        n = np.sum(np.isfinite(r), axis=1)
        per = np.sqrt(np.nansum(r ** 2, axis=1) / np.maximum(n, 1))[n > 0]
        return float(np.nanmedian(per) / sigma)

    before, after = scale(res.residual_before), scale(res.residual_after)
    contradicted = before > contradiction_factor * after
    report.update(residual_scale_before=before, residual_scale_after=after, contradicted=bool(contradicted))
    par = {p.name: p for p in res.parameters}
    per = []
    for s0, s1 in zip(stations, res.stations):
        d = np.asarray(s1.translation) - np.asarray(s0.translation)
        rot = float(np.degrees(np.linalg.norm(matrix_to_rotvec(s1.rotation @ s0.rotation.T))))
        sd = [par.get(f"station {s0.id} pose {k}") for k in ("tx", "ty", "tz", "d_rx", "d_ry", "d_rz")]
        sd_t = [None if p is None or p.std is None else p.std for p in sd[:3]]
        sd_r = [None if p is None or p.std is None else float(np.degrees(p.std)) for p in sd[3:]]
        fitted = [{"name": p.name, "value": p.value, "start": p.start, "std": p.std, "status": p.status}
                  for p in res.parameters if p.name.startswith(f"station {s0.id} axis") and p.status in ("ok", "suspect")]
        per.append({"id": s0.id, "moved_m": d.tolist(), "moved_norm_m": float(np.linalg.norm(d)),
                    "rotated_deg": rot, "sd_translation_m": sd_t, "sd_rotation_deg": sd_r,
                    "held_as_given": all(p is None or p.status == "fixed" for p in sd),
                    "calibration_fitted": fitted})
    report["stations"] = per
    if not after < before:
        msg = f"the refined stations do not explain the angles better ({after:.3g} vs {before:.3g} sigma); kept the given"
        return StationRefinement(given.stations, False, report | {"message": msg}, False, "no_improvement", msg)
    worst = max(per[1:], key=lambda p: p["moved_norm_m"])
    verdict = (f"the data contradict the given station geometry: it explains the angles at {before:.3g} sigma, the refined "
               f"one at {after:.3g} sigma" if contradicted else
               f"the given station geometry agrees with the data ({before:.3g} vs {after:.3g} sigma after refining)")
    msg = (f"{verdict}; station {worst['id']} moved {worst['moved_norm_m'] * 1e3:.1f} mm and "
           f"{worst['rotated_deg']:.2f} deg (1-sigma per coordinate "
           + ", ".join("n/a" if v is None else f"{v * 1e3:.3g}" for v in worst["sd_translation_m"])
           + " mm: a capture at rest determines the stations only as far as the deck's own size allows)")
    return StationRefinement(tuple(res.stations), True, report | {"message": msg}, True, "ok", msg)
