"""Layout optimisation: choose k photodiode sites with a certified gap (design §6).

``solve(DesignProblem, OptimizeSpec)`` is the entry point (a mesh, envelope and candidates loaded once;
the settings in one validated object); ``optimize_layout`` the same from arrays of one station;
``METHODS`` the method registry (random, greedy, topk, relax-round, pipeline, polish, exhaustive);
objectives are parsed by ``parse_objective``.
"""
from .core import OptimizeResult, candidate_jacobians, optimize_stations, spacing_conflicts
from .coverage import CoverageReport, analyse_coverage, minimum_k
from .design import DesignProblem
from .methods import METHODS, register_method
from .objectives import Objective, parse_objective
from .solver import optimize_layout, solve, sweep_k
from .spec import DenseSpec, OptimizeSpec

__all__ = [
    "solve", "DesignProblem", "OptimizeSpec", "DenseSpec", "optimize_layout", "optimize_stations",
    "OptimizeResult", "sweep_k", "candidate_jacobians", "spacing_conflicts", "METHODS", "register_method",
    "Objective", "parse_objective", "analyse_coverage", "minimum_k", "CoverageReport",
]
