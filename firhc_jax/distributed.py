"""Multi-process batches: joining a JAX job (``initialize``, ``job_settings``), the command line's ``.npy`` and
``.npz`` files (``load_states``, ``load_params``, ``save_states``, ``save_result``, ``load_result``), a local
launcher of P processes (``launch_local``) and ``exit_on_failure``. ``fj.solve_batch`` and
``FIRHC.simulate_batch`` need none of them: after ``jax.distributed.initialize`` they use every device of the
job."""
from ._src.runtime.sharding import usable_cores
from ._src.tools.distributed import (
    DEFAULT_TIMEOUT,
    ENV_COORDINATOR,
    ENV_NUM_PROCESSES,
    ENV_PROCESS_ID,
    STATES_KEY,
    exit_on_failure,
    free_port,
    initialize,
    job_settings,
    launch_local,
    load_params,
    load_result,
    load_states,
    save_result,
    save_states,
)

__all__ = ["initialize", "job_settings", "load_states", "load_params", "save_states", "save_result", "load_result",
           "launch_local", "exit_on_failure", "free_port", "usable_cores", "STATES_KEY", "DEFAULT_TIMEOUT",
           "ENV_COORDINATOR", "ENV_NUM_PROCESSES", "ENV_PROCESS_ID"]
