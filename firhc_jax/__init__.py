"""firhc_jax: exact finite-input receding horizon control in JAX.

Public API (see each object's docstring; notation in ``firhc_jax.problem``):

* ``Problem``, ``quadratic_cost``: describe the problem (eqs. 1-3).
* ``sdfs``: sorted depth-first search (Table 1), exact.
* ``exhaustive``: vectorised exhaustive search (the reference).
* ``FIRHC``: the receding horizon law (eq. 4) and its closed loop.
* ``solve_batch``: many states (and parameter sets) at once, over all local devices.
"""
from .batch import solve_batch
from .controller import FIRHC, ClosedLoop, InfeasibleError
from .exhaustive import exhaustive
from .problem import Problem, quadratic_cost
from .result import SearchResult
from .sdfs import sdfs

__all__ = ["Problem", "quadratic_cost", "sdfs", "exhaustive", "SearchResult", "FIRHC", "ClosedLoop",
           "InfeasibleError", "solve_batch"]
__version__ = "0.1.0"
