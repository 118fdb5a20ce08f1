"""Layout optimisation: choose k photodiode sites with a certified gap (design §6).

``optimize_layout`` is the entry point; ``METHODS`` the method registry (random, greedy, topk,
relax-round, pipeline, exhaustive); objectives are parsed by ``parse_objective``.
"""
from .core import OptimizeResult, candidate_jacobians, optimize_layout, optimize_stations, spacing_conflicts, sweep_k
from .coverage import CoverageReport, analyse_coverage, minimum_k
from .methods import METHODS, register_method
from .objectives import Objective, parse_objective

__all__ = [
    "optimize_layout", "optimize_stations", "OptimizeResult", "sweep_k", "candidate_jacobians",
    "spacing_conflicts", "METHODS", "register_method", "Objective", "parse_objective",
    "analyse_coverage", "minimum_k", "CoverageReport",
]
