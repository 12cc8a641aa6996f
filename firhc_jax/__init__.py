"""firhc_jax: exact finite-input receding horizon control in JAX.

Public API (see each object's docstring; notation in ``firhc_jax.problem``):

* ``Problem``, ``quadratic_cost``: describe the problem (eqs. 1-3), with step
  indices along the horizon, a terminal cost and hard constraints.
* ``discretize``, ``linear_dynamics``, ``product_controls``, ``tracking_cost``,
  ``input_change_cost``, ``horizon_windows``: linear plants, switch-level products,
  tracking costs and references along the horizon.
* ``sdfs``: sorted depth-first search (Table 1), exact.
* ``exhaustive``: vectorised exhaustive search (the reference).
* ``FIRHC``, ``ControllerState``, ``StepInfo``, ``ClosedLoop``: the receding
  horizon law (eq. 4), one decision at a time (``init``/``step``) or a whole
  closed loop (``simulate``), which saves and plots.
* ``with_input_memory``: the switching-penalty problem transform.
* ``LinearTracking``: exact tracking MPC of a linear plant at long horizons
  (the sphere decoder as a lower bound of sDFS).
* ``solve_batch``: many states (and parameter sets) at once, over every core and device.
* ``profile``: expansion throughput of your own problem, by solver setting.
* ``clear_cache``, ``set_cache_size``, ``cache_info``: the bounded cache of
  compiled searches; ``enable_compilation_cache``: keep compilations on disk
  across runs (opt in).
* ``check_problem``, ``check_lower_bound``: sampled checks of the promises
  exactness rests on (non-negative costs, admissible bounds).
"""
from .batch import solve_batch
from . import diagnostics
from .cache import cache_info, clear_cache, set_cache_size
from .closed_loop import ClosedLoop
from .compilation_cache import enable_compilation_cache
from .controller import FIRHC, InfeasibleError
from .decision import ControllerState, StepInfo
from .diagnostics import check_lower_bound, check_problem
from .exhaustive import exhaustive
from .linear import (discretize, horizon_windows, input_change_cost, linear_dynamics, product_controls,
                     tracking_cost)
from .linear_tracking import LinearTracking
from .nodes import rollout_cost
from .problem import Problem, quadratic_cost
from .profile import profile
from .result import SearchResult
from .sdfs import sdfs
from .transforms import InputMemory, with_input_memory

__all__ = ["Problem", "quadratic_cost", "discretize", "linear_dynamics", "product_controls", "tracking_cost",
           "input_change_cost", "horizon_windows", "LinearTracking", "sdfs", "exhaustive", "SearchResult", "FIRHC",
           "ControllerState", "StepInfo", "ClosedLoop", "InfeasibleError", "InputMemory", "with_input_memory",
           "solve_batch", "clear_cache", "set_cache_size", "cache_info", "enable_compilation_cache", "check_problem",
           "check_lower_bound", "diagnostics", "profile", "rollout_cost"]
__version__ = "0.2.0"
