"""firhc_jax: exact finite-input receding horizon control in JAX.

Everything public is re-exported here; the implementation lives in ``firhc_jax._src``. Public namespaces:
``firhc_jax.solvers`` (the table of searches and their memory), ``firhc_jax.linear_tracking`` (the named
structures of ``LinearTracking``), ``firhc_jax.diagnostics`` (sampled checks of a problem's promises) and
``firhc_jax.distributed`` (multi-process batches); ``firhc_jax.models`` holds example plants.
"""
from . import diagnostics, distributed, linear_tracking, solvers  # noqa: F401  public namespaces
from ._src.control.closed_loop import ClosedLoop
from ._src.control.controller import FIRHC, InfeasibleError
from ._src.control.decision import ControllerState, StepInfo
from ._src.export import engine as _c_engine  # noqa: F401  registers FIRHC(engine="c")
from ._src.export.export import export_c
from ._src.linear.tracking import LinearTracking
from ._src.old_paths import install as _install_old_paths
from ._src.problem.formulation import (
    band_penalty,
    discretize,
    horizon_windows,
    input_change_cost,
    linear_dynamics,
    product_controls,
    tracking_cost,
)
from ._src.problem.problem import Problem, quadratic_cost
from ._src.problem.transforms import InputMemory, with_input_memory
from ._src.runtime.collector import collector_paused
from ._src.runtime.disk_cache import enable_compilation_cache
from ._src.runtime.memory_cache import cache_info, clear_cache, set_cache_size
from ._src.runtime.small_loops import enable_small_loop_kernels
from ._src.search.batch import solve_batch
from ._src.search.nodes import rollout_cost
from ._src.search.one_state import exhaustive, sdfs
from ._src.search.result import SearchResult
from ._src.tools.diagnostics import check_lower_bound, check_problem
from ._src.tools.profile import profile

__all__ = ["Problem", "quadratic_cost", "discretize", "linear_dynamics", "product_controls", "tracking_cost",
           "input_change_cost", "band_penalty", "horizon_windows", "LinearTracking", "sdfs", "exhaustive",
           "SearchResult", "FIRHC",
           "ControllerState", "StepInfo", "ClosedLoop", "InfeasibleError", "InputMemory", "with_input_memory",
           "solve_batch", "clear_cache", "set_cache_size", "cache_info", "enable_compilation_cache", "check_problem",
           "check_lower_bound", "diagnostics", "profile", "rollout_cost", "collector_paused", "export_c",
           "enable_small_loop_kernels"]
__version__ = "0.3.0"

_install_old_paths(__name__)
