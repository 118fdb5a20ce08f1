"""The optimiser's entry points: :func:`solve` (a design problem and a spec) and :func:`optimize_layout`
(arrays of one station), both ending in :func:`layoutkit.optimize.core.optimize_stations`."""
from __future__ import annotations

import dataclasses

import numpy as np

from .._validate import as_array, check_finite
from .core import OptimizeResult, optimize_stations
from .design import DesignProblem
from .spec import OptimizeSpec

__all__ = ["solve", "optimize_layout", "sweep_k"]


def solve(problem: DesignProblem, spec: OptimizeSpec, *, progress=None, rng=None, tuning=None,
          echo=None) -> OptimizeResult:
    """Choose ``spec.k`` of the problem's candidates minimising ``spec.objective`` with a certified bound.

    Args:
        problem: :class:`~layoutkit.optimize.design.DesignProblem` — N candidates (body frame, m; tilted
            orientations included when it was built with tilt), P design poses (world frame) and S stations,
            visibility ``(P, S, N)`` bool and angle Jacobians ``(P, S, N, 2, 6)`` (Chen eqs. 10–14).
        spec: :class:`~layoutkit.optimize.spec.OptimizeSpec` — k, objective (ADOP in deg/rad, PDOP in
            m/rad; Chen eqs. 18–22 with ``rho``, eq. 19), coverage rule and fraction, ``min_spacing_m`` (m),
            fixed candidate ids, method, ``time_limit_s`` (s), seed, branch-and-bound, and ``dense``
            (adaptive pose generation over the problem's envelope, :func:`layoutkit.optimize.dense.dense_solve`).
            Its half-angle and tilt must be those the problem was built with (:meth:`DesignProblem.for_spec`).
        progress: optional callable ``(stage: str, fraction: float | None, best: float | None)``.
        rng: optional ``np.random.Generator`` used instead of ``spec.seed``.
        tuning: optional knobs of :class:`layoutkit.optimize.methods.Context` (``patience``, ``two_swap``, ...).
        echo: optional callable for one line per dense round.

    Returns:
        :class:`~layoutkit.optimize.core.OptimizeResult`: ``selected`` (k,) sorted candidate indices,
        ``value`` (the objective over the design poses; with ``dense``: over the working set of the best
        round), ``bound``, ``gap``, ``certified_by``, ``status``/``message``, per-pose ``adop`` (P,) deg/rad,
        ``pdop`` (P,) m/rad and ``n_lit`` (P,). ``info`` has ``site``, ``tilt_deg`` and ``axes`` of the
        selection when tilt is on and ``dense`` (the loop's record) with ``spec.dense``. Infeasible
        requests are a status with an explanation, not an exception.

    Example:
        >>> from layoutkit.optimize import DesignProblem, OptimizeSpec, solve
        >>> from layoutkit.optimize.instances import synthetic_instance
        >>> inst = synthetic_instance(24, 20, rng=0)
        >>> problem = DesignProblem.from_arrays(**inst)
        >>> res = solve(problem, OptimizeSpec(k=6, rho=0.8717, method="exhaustive"))
        >>> res.status, len(res.selected), res.gap == 0.0
        ('optimal', 6, True)
    """
    problem.check_spec(spec)
    kw = dict(objective=spec.objective, weights=spec.weights, rho=spec.rho, min_visible=spec.min_visible,
              method=spec.method, fixed=problem.indices(spec.fixed), conflict=problem.conflicts(spec.min_spacing_m),
              coverage_fraction=spec.coverage_fraction, progress=progress,
              branch_and_bound=spec.branch_and_bound, cliques=problem.cliques())
    if tuning:
        kw["ctx_options"] = dict(tuning)
    if spec.dense is not None:
        from .dense import dense_solve

        kw["min_visible"] = spec.min_visible + spec.dense.spare_lit  # the loop's margin (DenseSpec.spare_lit)
        res, info = dense_solve(problem, spec, kw, echo=echo)
        res = dataclasses.replace(res, info={**res.info, "dense": info})
    else:
        res = optimize_stations(problem.jac, problem.visible, spec.k, rng=spec.seed if rng is None else rng,
                                coverage=spec.coverage, time_limit=spec.time_limit_s, **kw)
    if problem.max_tilt_deg > 0 and res.success:
        sel = res.selected
        res = dataclasses.replace(res, info={**res.info, "site": problem.site[sel], "tilt_deg": problem.tilt_deg[sel],
                                             "axes": problem.candidates.normals[sel]})
    return res


def optimize_layout(positions, normals, visible, rotations, translations, k, *,
                    objective="worst-adop", rho=0.0, min_visible=4, method="pipeline", rng=None,
                    fixed=(), min_spacing=0.0, coverage_fraction=1.0, weights=None,
                    time_limit=None, progress=None, max_tilt_deg=0.0, tilt_directions=4,
                    half_angle_deg=60.0, fov_deg=120.0, branch_and_bound="auto") -> OptimizeResult:
    """Choose ``k`` of N candidate sites minimising an envelope DOP objective (design §6), from arrays.

    Args:
        positions: (N, 3) float, m — candidate sites in the body frame.
        normals: (N, 3) outward unit normals, body frame (used for tilted orientations; ``visible``
            already encodes the acceptance cone of the plain sites).
        visible: (P, N) bool — candidate lit at pose p (field of view, acceptance cone, occlusion).
        rotations: (P, 3, 3), translations: (P, 3) m — body pose in the frame of one lighthouse station at
            the origin (``p_lh = R p + t``).
        k: sensors to place.
        objective: ``<worst|mean|pNN>-<adop|pdop|weighted>`` (:func:`layoutkit.optimize.parse_objective`);
            weights: ``(a, b)`` of ADOP² (deg²) and PDOP² (m²) for ``*-weighted``.
        rho: same-rotor angle correlation (Chen eq. 19; 0.8717 measured).
        min_visible: lit sensors needed at every pose (or every pose but ``1 - coverage_fraction``).
        method: a name of :data:`layoutkit.optimize.METHODS`; rng: ``np.random.Generator`` or seed.
        fixed: candidate indices placed in advance; min_spacing: m, minimum distance between sensors.
        time_limit: s, wall budget (the relaxation included); None: unlimited, except ``"pipeline"``
            which then stops after 100 s. progress: callable ``(stage, fraction, best)``.
        max_tilt_deg: > 0 lets every site also take its normal tilted by this angle towards
            ``tilt_directions`` azimuths (one orientation per site, :mod:`layoutkit.optimize.tilt`); tilted
            orientations are lit by the acceptance cone (``half_angle_deg``) and field of view (``fov_deg``)
            test (exact for convex bodies, no occlusion). ``selected`` then indexes the expanded candidates
            (plain sites first).
        branch_and_bound: "auto" (pipeline, worst case, finite time limit: B&B on the relaxation beside the
            search, :mod:`layoutkit.optimize.bnb`) or "off".

    Returns:
        :class:`~layoutkit.optimize.core.OptimizeResult` (``selected`` (k,) indices, ``value``, ``bound``,
        ``gap``, per-pose ``adop`` (P,) deg/rad and ``pdop`` (P,) m/rad); with tilt ``info`` has ``site``,
        ``tilt_deg`` and ``axes`` of the selection. Infeasible requests are a status with an explanation.

    Example:
        >>> from layoutkit.optimize import optimize_layout
        >>> from layoutkit.optimize.instances import synthetic_instance
        >>> inst = synthetic_instance(24, 20, rng=0)   # box target, one station, 24 sites, 20 poses
        >>> res = optimize_layout(**inst, k=6, rho=0.8717, method="exhaustive")
        >>> res.status, res.selected.shape, bool(res.value >= res.bound > 0)
        ('optimal', (6,), True)
    """
    pos = as_array(positions, "positions", (None, 3))
    check_finite(pos, "positions")
    N = pos.shape[0]
    nor = as_array(normals, "normals", (N, 3))
    R = as_array(rotations, "rotations", (None, 3, 3))
    P = R.shape[0]
    t = as_array(translations, "translations", (P, 3))
    check_finite(R, "rotations")
    check_finite(t, "translations")
    vis = np.asarray(visible)
    if vis.shape != (P, N):
        raise ValueError(f"visible: expected shape ({P}, {N}), got {vis.shape}")
    problem = DesignProblem.from_arrays(pos, nor, vis.astype(bool), R, t, half_angle_deg=half_angle_deg,
                                        fov_deg=fov_deg, max_tilt_deg=max_tilt_deg, tilt_directions=tilt_directions)
    fixed = np.unique(np.asarray(fixed, int).ravel()).astype(int)
    if len(fixed) and (fixed.min() < 0 or fixed.max() >= problem.N):
        raise ValueError(f"fixed: indices must be in [0, {problem.N - 1}], got {fixed.tolist()}")
    if not 1 <= int(k) <= problem.N:
        raise ValueError(f"k: expected 1 <= k <= {problem.N} (number of candidates), got {k}")
    spec = OptimizeSpec(k=int(k), objective=objective, weights=weights, rho=rho, min_visible=min_visible,
                        coverage_fraction=coverage_fraction, min_spacing_m=min_spacing or 0.0,
                        half_angle_deg=half_angle_deg, max_tilt_deg=max_tilt_deg or 0.0,
                        tilt_directions=tilt_directions, method=method, time_limit_s=time_limit,
                        seed=None, branch_and_bound=branch_and_bound,
                        fixed=tuple(problem.candidates.ids[i] for i in fixed))
    return solve(problem, spec, progress=progress, rng=rng)


def sweep_k(positions, normals, visible, rotations, translations, ks, **kwargs):
    """Best layout for each k in ``ks``: a list of :class:`OptimizeResult` (DOP against sensor count)."""
    return [optimize_layout(positions, normals, visible, rotations, translations, int(k), **kwargs)
            for k in ks]
