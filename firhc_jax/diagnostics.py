"""Sampled checks of the promises exactness rests on: non-negative stage costs (``check_problem``) and an
admissible lower bound (``check_lower_bound``), each returning a list of ``Violation``."""
from ._src.tools.diagnostics import Violation, check_lower_bound, check_problem

__all__ = ["check_problem", "check_lower_bound", "Violation"]
