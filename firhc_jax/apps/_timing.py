"""Compile, then time the loop: how every application times its closed loop.

The loop is the deployment path, ``FIRHC.simulate(..., compiled=False)``: a
Python loop of the compiled decision with each decision timed in
``solve_times``. Before it, the decision is compiled for the run's shapes and
that compilation is timed on its own, so ``compile_s`` is tracing plus
compilation and ``solve_times`` never include it. The loop runs with
Python's cyclic garbage collector paused (``fj.collector_paused``, as
``simulate(..., compiled=False)`` runs it): one collection of the run's
records took 130-160 ms inside a single decision
(docs/applications/inverter.md).
"""
from __future__ import annotations

import contextlib
import time

import jax

from ._exported import decision
from ._status import stage

# jax.monitoring's events, one per function: traced (Python to jaxpr), lowered (jaxpr to MLIR), compiled by XLA
TRACED = "/jax/core/compile/jaxpr_trace_duration"
LOWERED = "/jax/core/compile/jaxpr_to_mlir_module_duration"
BACKEND_COMPILE = "/jax/core/compile/backend_compile_duration"


@contextlib.contextmanager
def compile_events(kind: str = BACKEND_COMPILE):
    """The ``(function name, seconds)`` of every event ``kind`` inside the block (``jax.monitoring``; default:
    each XLA compilation)."""
    seen = []

    def listener(event, duration, **kw):
        if event == kind:
            seen.append((kw.get("fun_name"), duration))

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield seen
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


def timed_closed_loop(ctrl, x0, steps: int, plant=None, *, params=None, u0=None, dt=None, progress=False,
                      settings=None):
    """``(loop, compile_s)``: ``ctrl.simulate(x0, steps, plant, ..., compiled=False)`` with every decision timed,
    and ``compile_s`` the seconds to trace and compile one decision (``ctrl.step``) for these shapes.

    ``settings``: all that built ``ctrl`` besides the package's code
    (``_exported.decision``). With the compilation cache on (a folder set and
    ``jax_enable_compilation_cache`` true), the decision is
    then kept in its folder as a traced program, and a later run with the
    same settings neither traces nor lowers it (its ``compile_s`` is reading
    it back). Otherwise the loop runs the controller's own compiled decision.

    ``compile_s`` is measured on a fresh compilation: the first call of the
    decision less its time in the loop (the first step of the loop decides
    from the same state). Where this process compiled the same program
    before, that call compiles nothing (no XLA compilation is seen); the
    decision is then compiled ahead of time once more
    (``jax.jit(ctrl.step).lower(...).compile()``), which is what is timed.
    """
    state = ctrl.init(x0, u0)
    p0 = None if params is None else jax.tree_util.tree_map(lambda a: a[0], params)
    with compile_events() as seen, stage("compiling the decision"):
        t0 = time.perf_counter()
        folder = jax.config.jax_compilation_cache_dir if jax.config.jax_enable_compilation_cache else None
        decide = decision(ctrl, settings, folder, state, x0, p0) if settings and folder else ctrl._decide()
        jax.block_until_ready(decide(state, x0, p0))
        first = time.perf_counter() - t0
    plant, key, _ = ctrl._plant(plant)  # the decision was checked when traced; the plant is called as it is
    loop = ctrl._run(state, x0, steps, plant, key, params, progress, decide, dt)
    if seen:
        return loop, first - float(loop.solve_times[0])
    with stage("timing the decision's compilation"):
        t0 = time.perf_counter()
        jax.jit(ctrl.step).lower(state, x0, p0).compile()
        return loop, time.perf_counter() - t0
