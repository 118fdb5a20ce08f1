"""What tilt would buy: a quick estimate reported beside an untilted run (issue 27, item 3).

Mounting angles are part of a layout's design, but tilt is off by default (``max_tilt_deg = 0``: a
sensor costs more to mount tilted). So that a user sees what they leave on the table, an untilted run
also asks: starting from its own layout, what does a short run with every site allowed to tilt up to
``max_tilt_deg`` towards or away from the stations (meridional tilts, ``tilt_toward="station"``)
reach on the same held-out poses? The estimate is a few polish rounds of the dense loop (local search and
kicks, no relaxation) warm-started from the untilted layout, scored on the same fresh draws as the run
itself — a lower estimate of what a full tilted run of the same budget reaches, since it searches only
near the untilted layout.
"""
from __future__ import annotations

import time

import numpy as np

__all__ = ["tilt_estimate", "TILT_ESTIMATE_DEG"]

#: the tilt of the estimate (deg): 25° is what the visor study measured to pay (docs/optimize.md)
TILT_ESTIMATE_DEG = 25.0


def tilt_estimate(problem, spec, res, heldout, *, max_tilt_deg=TILT_ESTIMATE_DEG, budget_s=None, dense_poses=2000):
    """The quick tilted estimate for untilted result ``res`` of ``spec`` on ``problem`` (module docstring).

    heldout : the run's :func:`layoutkit.optimize.heldout.heldout_estimate` (the estimate is scored on the
    same draws). budget_s : wall budget of the estimate (default: a fifth of the run's time limit, 5–60 s).
    Returns a JSON-able dict (``value``: the tilted layout's held-out value, ``untilted_value``, ``ratio``
    (untilted / tilted), ``covered_fraction``, ``tilted_sensors``, ``helps`` (ratio ≥ 1.1 at full
    coverage), ``note``), or None when it does not apply (already tilted, no envelope, no layout).
    """
    from .design import DesignProblem
    from .heldout import heldout_estimate
    from .solver import solve
    from .spec import DenseSpec

    if problem.max_tilt_deg > 0 or problem.envelope is None or heldout is None or not res.success:
        return None
    t0 = time.perf_counter()
    T = float(spec.time_limit_s or 300.0)
    budget = float(budget_s) if budget_s is not None else min(60.0, max(5.0, 0.2 * T))
    tilted = DesignProblem.load(problem.mesh, problem.envelope, candidates=problem.candidates,
                                half_angle_deg=problem.half_angle_deg, max_tilt_deg=max_tilt_deg,
                                tilt_toward="station", stations=problem.stations, max_range_m=problem.max_range_m)
    ids = [problem.candidates.ids[i] for i in res.selected]  # the plain sites keep their ids
    warm = tilted.indices(ids)
    spec_t = spec.replace(max_tilt_deg=max_tilt_deg, tilt_toward="station", method="polish", time_limit_s=budget,
                          branch_and_bound="off",
                          dense=DenseSpec(poses=int(dense_poses), coverage_poses=0, seed_poses=0, rounds=6, add=96,
                                          patience=3, later_patience=2))
    r = solve(tilted, spec_t, tuning={"warm_start": warm, "patience": 3, "two_swap": False})
    if not r.success:
        return {"max_tilt_deg": max_tilt_deg, "value": None, "helps": False, "time_s": time.perf_counter() - t0,
                "note": f"quick tilted estimate found no layout: {r.status}"}
    h = heldout_estimate(tilted, r.selected, objective=spec.objective, weights=spec.weights, rho=spec.rho,
                         min_visible=spec.min_visible, coverage=spec.coverage, draws=len(heldout["draws"]),
                         poses_per_draw=heldout["draws"][0]["poses"])
    ratio = heldout["value"] / h["value"] if h["value"] > 0 else float("nan")
    helps = bool(ratio >= 1.1 and h["covered_fraction"] >= heldout["covered_fraction"])
    n_t = int(np.sum(tilted.tilt_deg[r.selected] > 0))
    note = (f"with up to {max_tilt_deg:g}° tilt towards/away from the stations, a quick run from this layout "
            f"({time.perf_counter() - t0:.0f} s) reaches {h['value']:.5g} on the same {h['poses']} held-out poses "
            f"(covered {100 * h['covered_fraction']:.2f} %, {n_t} sensors tilted): "
            + (f"{ratio:.2f}× better; try --max-tilt-deg {max_tilt_deg:g} --tilt-toward station" if helps
               else "no clear gain"))
    return {"max_tilt_deg": max_tilt_deg, "tilt_toward": "station", "value": h["value"],
            "untilted_value": heldout["value"], "ratio": ratio, "covered_fraction": h["covered_fraction"],
            "tilted_sensors": n_t, "helps": helps, "time_s": time.perf_counter() - t0, "budget_s": budget,
            "selected_ids": [tilted.candidates.ids[i] for i in r.selected], "note": note}
