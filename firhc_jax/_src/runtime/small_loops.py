"""``fj.enable_small_loop_kernels``: an explicit, process-wide opt-in to XLA:CPU's one-kernel small loops.

XLA:CPU runs a while loop one thunk per fusion, about 0.35 us an iteration for a small search. Its
``SmallWhileLoopHoistingPass`` compiles a loop whose buffers fall below a byte threshold (1 kB by default)
into one kernel instead, 0.03 us an iteration, and XLA's YNNPACK dot fusions keep a loop with matrix products
out of it. Both are settable only for the whole process, through ``XLA_FLAGS`` read when JAX starts its CPU
backend, and the larger threshold slows the work pool of ``fj.solve_batch`` (its loop holds scatters, which
the pass skips, but the threshold also reaches its other loops). So the library never sets them by itself:
a process that makes single decisions (a controller's loop, a compiled closed loop) calls this once, first.
"""
from __future__ import annotations

import os

FLAGS = ("--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold={threshold}",
         "--xla_cpu_experimental_ynn_fusion_type=-LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT")


def enable_small_loop_kernels(byte_threshold: int = 1_000_000_000) -> str:
    """Let XLA:CPU compile every while loop below ``byte_threshold`` bytes into one kernel, in this process.

    Call it before the process's first JAX computation (before any array is made on the CPU): it adds two
    flags to ``XLA_FLAGS``, which JAX reads once, when it starts its backend; afterwards a ``RuntimeError``
    says so. What it changes, measured on the performance page ("One eager decision", "Small loop
    kernels"): single searches and decisions and the step of a compiled closed loop run several times
    faster; ``fj.solve_batch`` and ``simulate_batch`` run slower. The flags reach every program of the
    process, the user's own included. Returns the new ``XLA_FLAGS``.
    """
    if isinstance(byte_threshold, bool) or not isinstance(byte_threshold, int) or byte_threshold < 1:
        raise ValueError(f"byte_threshold must be a positive int, got {byte_threshold!r}")
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized():
        raise RuntimeError("enable_small_loop_kernels() must come before this process's first JAX computation: "
                           "JAX reads XLA_FLAGS once, when it starts its CPU backend, and it has started. Call it "
                           "first thing (after import), or set XLA_FLAGS='" +
                           " ".join(FLAGS).format(threshold=byte_threshold) + "' before starting Python")
    kept = [f for f in os.environ.get("XLA_FLAGS", "").split()
            if not f.startswith(("--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=",
                                 "--xla_cpu_experimental_ynn_fusion_type="))]
    os.environ["XLA_FLAGS"] = " ".join(kept + [f.format(threshold=byte_threshold) for f in FLAGS])
    return os.environ["XLA_FLAGS"]
