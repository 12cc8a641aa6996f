"""The closed-loop runner: a decision function and a plant, driven for T steps.

``decide(state, x, p) -> (u, state, StepInfo)`` and ``plant(x, u, p) -> x``
are pure functions; for a batch of loops both take and return arrays with a
leading axis B (the runner does not care). ``run_compiled`` drives them as
one compiled ``lax.scan`` (or, with a progress bar, as one compiled chunk of
steps dispatched again and again from Python, the bar moved between chunks:
a host callback inside the scan costs more than cheap steps,
docs/dev/xla_notes.md; each chunk writes its steps into the run's records, which
it updates in place). ``run_python`` drives an already compiled decision from a
Python loop, timing each decision, for plants that cannot be traced. Both
return a time-major ``ClosedLoop`` (``states`` ``[T+1, ...]``).

The compiled functions are cached under the caller's ``key``: equal keys
must mean equal ``decide`` and ``plant``.
"""
from __future__ import annotations

import functools
import time
import warnings
from typing import Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils

from ..checks import is_tracer
from ..problem.problem import call
from ..runtime.collector import collector_paused
from ..runtime.memory_cache import cached
from ..runtime.progress import Progress, chunked, due, interval, record, tick_python
from ..runtime.sharding import default_parts, join_rows, mesh_of, on_stream, same_on_every_process, split_rows
from .closed_loop import ClosedLoop
from .decision import StepInfo


def run_compiled(decide: Callable, plant: Callable, runs: list, steps: int, *, key, progress: Optional[bool],
                 label: str, ticks_per_step: int = 1, on_held: Callable | None = None) -> list[ClosedLoop]:
    """``steps`` steps of each run ``(state, x0, params)`` in ``runs`` (``params`` leaves ``[steps, ...]``,
    row k: step k) as compiled scans, one ``ClosedLoop`` each. Several runs (parts of a batch of loops) are
    dispatched each on its own execution stream, so they run side by side on the CPU's cores
    (``firhc_jax._src.runtime.sharding``). ``progress`` (True, False, None: automatic) as
    ``firhc_jax._src.runtime.progress`` says: a bar labelled ``label``, moved by ``ticks_per_step`` per step
    done where the run goes in chunks; there ``on_held(step)`` is called once, at the end of the chunk that
    holds the first held step (of any loop; a run in one piece is one program: no moment to call it)."""
    traced = any(map(is_tracer, jax.tree_util.tree_leaves(runs)))
    rate_key, units = ("closed loop", key), steps * ticks_per_step
    chunks = not traced and chunked(progress, rate_key, units)
    with Progress(units, label, enabled=False if traced else progress, counted=chunks):
        outs, started = (functools.partial(_in_chunks, on_held=on_held) if chunks else _whole)(
            decide, plant, runs, steps, key, ticks_per_step)
        if not traced:
            jax.block_until_ready(outs)
            record(rate_key, units, time.perf_counter() - started)
    return outs


def _whole(decide, plant, runs: list, steps: int, key, ticks_per_step: int):
    """``run_compiled``'s runs as one compiled scan each: ``(runs, when the first was dispatched)``."""
    run = cached(("closed loop", key, steps), lambda: jax.jit(lambda s, x, p: _with_x0(
        x, _scan(decide, plant, (s, x), p, 0, steps)[1], jnp.full((steps,) + _batch(x), jnp.nan))))
    outs = [_dispatch(0, len(runs), run, *runs[0])]
    started = time.perf_counter()  # compiled (the first call), now running
    return outs + [_dispatch(i, len(runs), run, *r) for i, r in enumerate(runs[1:], 1)], started


def _in_chunks(decide, plant, runs: list, steps: int, key, ticks_per_step: int, on_held: Callable | None):
    """``run_compiled``'s runs as chunks of ``interval(steps)`` steps, the bar moved after each (and
    ``on_held`` called at the first held step's): ``(runs, when the first chunk was dispatched)``."""
    length = interval(steps)
    chunks = -(-steps // length)

    def padded(params):  # the last chunk's extra steps repeat the last row
        if params is None or chunks * length == steps:
            return params
        return jax.tree.map(lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], chunks * length - steps, 0)]), params)

    # One trace of the chunk's steps serves the records' shapes and the chunk (jit keeps it per signature).
    scan = cached(("closed loop steps", key, length),
                  lambda: jax.jit(functools.partial(_scan, decide, plant, length=length), inline=True))
    run = cached(("closed loop chunk", key, length),
                 lambda: jax.jit(functools.partial(_chunk_into, scan), donate_argnums=1))
    empty = cached(("closed loop records", key, length, chunks),
                   lambda: jax.jit(functools.partial(_records, scan, chunks=chunks)))
    finish = cached(("closed loop finish", steps), lambda: jax.jit(functools.partial(_finish, steps=steps)))
    carries, params = [(s, x) for s, x, _ in runs], [padded(p) for _, _, p in runs]
    recs = [_dispatch(i, len(runs), empty, c, p) for i, (c, p) in enumerate(zip(carries, params, strict=True))]
    firsts, last, started, held_seen = [None] * len(runs), None, None, on_held is None
    for start in range(0, steps, length):
        for i, (carry, p) in enumerate(zip(carries, params, strict=True)):
            carries[i], recs[i], firsts[i] = _dispatch(i, len(runs), run, carry, recs[i], p, np.int32(start))
            started = started or time.perf_counter()  # compiled (the first call), now running
        if last is not None:  # the chunk before this one is done (or nearly): move the bar
            held_seen = _report(*last, held_seen, on_held)
        last = min(start + length, steps) * ticks_per_step - 1, [c[1] for c in carries], list(firsts), steps
    _report(*last, held_seen, on_held)
    return [finish(x0, r) for (_, x0, _), r in zip(runs, recs, strict=True)], started


def run_loops(decide: Callable, plant: Callable, state, X0, params, steps: int, *, key, progress: Optional[bool],
              label: str, on_held: Callable | None = None) -> ClosedLoop:
    """``steps`` steps of B loops (``state``, ``X0`` and ``params`` leaves with leading axis B, params
    ``[B, steps, ...]``; ``decide`` and ``plant`` batched), loop-major (``[B, ...]`` fields). Process i of a
    job of P runs loops i, i + P, ... and every process gets all of them; within a process the loops run in
    parts, one per CPU core and per local device (part j on device j % D), side by side."""
    B = X0.shape[0]
    traced = any(map(is_tracer, jax.tree_util.tree_leaves((state, X0, params))))
    processes = 1 if traced else jax.process_count()
    if processes > 1:
        same_on_every_process((state, X0, params), "the loops' X0, u0 or params")
        state, X0, params = split_rows((state, X0, params), processes)[jax.process_index()]
    devices = jax.local_devices()
    mine = X0.shape[0]
    parts = 1 if traced else min(mine, len(devices) * default_parts(mesh_of(tuple(devices))))
    shares = split_rows((state, X0, params), parts) if parts > 1 else [(state, X0, params)]
    runs = [(s, x, None if p is None else jax.tree.map(lambda a: jnp.swapaxes(a, 0, 1), p)) for s, x, p in shares]
    if len(devices) > 1:  # part j runs on device j % D (its inputs put there), the devices side by side
        runs = [jax.device_put(r, devices[j % len(devices)]) for j, r in enumerate(runs)]
    outs = run_compiled(decide, plant, runs, steps, key=key, progress=progress, label=label, ticks_per_step=mine,
                        on_held=on_held)
    outs = [batch_major(jax.device_put(o, devices[0]) if len(devices) > 1 else o) for o in outs]
    out = join_rows(outs, mine) if parts > 1 else outs[0]
    if processes == 1:
        return out
    every = multihost_utils.process_allgather(out)  # [P, loops of a process, ...] fields
    return join_rows([jax.tree.map(lambda a, i=i: a[i], every) for i in range(processes)], B)


def _dispatch(i: int, parts: int, fn: Callable, *args):
    """``fn(*args)``, on execution stream ``i + 1`` when there are several parts."""
    if parts == 1:
        return fn(*args)
    with on_stream(i):
        return fn(*args)


def _batch(x) -> tuple:
    """The leading batch axes of a state ``[n]`` or ``[B, n]``."""
    return tuple(np.shape(x)[:-1])


def _scan(decide, plant, carry, params, start, length):
    """Steps ``start`` .. ``start + length - 1`` (parameter rows ``start`` ..): ``(carry, ClosedLoop)``
    whose ``states`` are the states after each step (only what a ``ClosedLoop`` keeps is stacked: each
    stacked output costs time per step)."""
    def body(carry, p):
        # Barriers keep the decision and the plant apart, as in a user's loop of the compiled step and a
        # jitted plant: XLA fuses (and rounds) each the same way there and here.
        state, x = jax.lax.optimization_barrier(carry)
        u, state, info = decide(state, x, p)
        x_next = plant(*jax.lax.optimization_barrier((x, u)), p)
        return (state, x_next), (x_next, u, _kept(info))

    rows = None if params is None else jax.tree.map(lambda a: jax.lax.dynamic_slice_in_dim(a, start, length),
                                                     params)
    carry, (xs, us, info) = jax.lax.scan(body, carry, rows, length=length)
    return carry, closed_loop(xs, us, info, None)


def run_python(decide: Callable, plant: Callable, state, x0, params, steps: int, *, progress: Optional[bool],
               label: str, on_held: Callable | None = None) -> ClosedLoop:
    """``steps`` steps of the compiled ``decide`` from Python, each decision timed (``solve_times``), with
    Python's cyclic garbage collector paused, under a bar labelled ``label`` (``progress``: True, False, None:
    automatic); ``plant`` is called as it is (jit it, or each of its operations is one eager dispatch a
    step). ``on_held(step)`` is called once, right after the first held decision."""
    x = x0
    host = None if params is None else jax.tree.map(np.asarray, params)  # rows as views: no dispatch each
    rows = [None if host is None else jax.tree.map(lambda a, k=k: a[k, ...], host) for k in range(steps)]
    decide(state, x, rows[0])  # compiles the decision for these shapes, so that solve_times never count it
    records, times = [], []
    with Progress(steps, label, enabled=progress), collector_paused():  # no collection inside a decision
        for k in range(steps):
            t0 = time.perf_counter()
            u, state, info = jax.block_until_ready(decide(state, x, rows[k]))
            times.append(time.perf_counter() - t0)
            x_next = plant(x, u, rows[k])
            if not hasattr(x_next, "shape") or tuple(np.shape(x_next)) != x.shape:
                raise TypeError(f"plant(x, u[, p]) must return the next plant state of shape {tuple(x.shape)} "
                                f"like x0, got {type(x_next).__name__} of shape {np.shape(x_next)} at step {k}")
            x = x_next if ready(x_next) and x_next.dtype == x.dtype else np.asarray(x_next, x.dtype)
            records.append((x, u, _kept(info)))  # each field is read back to the host once (held: here, kept)
            if on_held is not None and np.asarray(info.held):
                on_held(k)
                on_held = None
            if due(k, steps):
                tick_python(k)
    # Stacked on the host, one device array per field: an eager jnp.stack of T arrays compiles a
    # T-operand concatenation per field on a run's first call.
    stacked = jax.tree.map(lambda *a: jnp.asarray(np.stack(a)), *records)
    return _with_x0(x0, closed_loop(*stacked, None), jnp.asarray(times))


def first_held_warning(u_safe: bool, stacklevel: int) -> Callable:
    """``on_held(step)`` for the runners: a ``RuntimeWarning`` that names the first held step as the run
    meets it (``warn_held`` counts them after the run)."""
    def on_held(step: int) -> None:
        what = "u_safe" if u_safe else "the input applied last"
        warnings.warn(f"closed loop: no feasible input sequence found (or its first input was not finite) at "
                      f"step {step}, the first such step; {what} is held there and at any later such step "
                      "(the run goes on; a count follows it)", RuntimeWarning, stacklevel=stacklevel)
    return on_held


def warn_held(held, decisions: int, u_safe: bool) -> None:
    """A ``RuntimeWarning`` after a run with held steps."""
    if is_tracer(held):
        return
    where = np.argwhere(np.asarray(held))
    if where.size:
        what = "u_safe" if u_safe else "the input applied last"
        first = where[0].tolist()
        at = f"step {first[0]}" if len(first) == 1 else f"loop {first[0]}, step {first[1]}"
        warnings.warn(f"closed loop: no feasible input sequence found (or its first input was not finite) "
                      f"at {len(where)} of {decisions} steps (first: {at}); {what} was held there, flagged in "
                      "ClosedLoop.held", RuntimeWarning, stacklevel=3)


def user_plant(plant: Callable) -> Callable:
    """``plant(x, u[, p])`` as the runner calls it, ``(x, u, p)``."""
    return lambda x, u, p: call(plant, p, x, u)


def ready(a) -> bool:
    """An argument a compiled function takes as it is: a real NumPy array, or a JAX array (or tracer)
    without weak type (a weakly typed one would compile a second function for the same shapes)."""
    if type(a) is np.ndarray:
        return a.dtype.kind in "biuf"
    return isinstance(a, jax.Array) and not a.weak_type


def _kept(info: StepInfo) -> StepInfo:
    """The parts of a ``StepInfo`` a ``ClosedLoop`` keeps (the rest is not stacked)."""
    return info._replace(result=info.result._replace(
        first_input=None, nodes=None, feasible=None, iterations=None, negative_cost=None, nan_encountered=None,
        overflow=None, complete=None))


def _report(tick: int, x, firsts, steps: int, held_seen: bool, on_held) -> bool:
    """Move the bar to ``tick`` once the chunk that computed ``x`` is done; then, until one is seen, call
    ``on_held`` with the chunk's first held step (``firsts``: each run's, -1: none; a step from ``steps`` on
    pads the last chunk). Returns whether a held step has been seen."""
    if not is_tracer(x):
        jax.block_until_ready(x)
    tick_python(tick)
    if held_seen or any(map(is_tracer, firsts)):
        return held_seen
    held = [int(f) for f in firsts if 0 <= int(f) < steps]
    if held:
        on_held(min(held))
    return bool(held)


def _records(scan, carry, params, chunks: int) -> ClosedLoop:
    """Zeroed records of ``chunks`` runs of ``scan`` (a chunk of steps), which the chunks write in place."""
    one = jax.eval_shape(scan, carry, params, np.int32(0))[1]
    return jax.tree.map(lambda a: jnp.zeros((chunks * a.shape[0],) + a.shape[1:], a.dtype), one)


def _chunk_into(scan, carry, records: ClosedLoop, params, start):
    """``scan``'s chunk of steps from ``start``, its records written into ``records`` (donated: updated in
    place) from row ``start``, and ``[]`` int32 the chunk's first held step (of any loop; -1: none)."""
    carry, rec = scan(carry, params, start)
    steps = rec.held.shape[0]
    at = jnp.where(rec.held, jnp.arange(steps, dtype=jnp.int32).reshape((steps,) + (1,) * (rec.held.ndim - 1)), steps)
    first = jnp.min(at)  # a plain min: XLA:CPU runs an argmax as a scalar loop (nodes.first_min)
    first = jnp.where(first < steps, start + first, -1)
    return carry, jax.tree.map(lambda whole, part: jax.lax.dynamic_update_slice_in_dim(whole, part, start, 0),
                               records, rec), first


def _finish(x0, records: ClosedLoop, steps: int) -> ClosedLoop:
    """The run of ``steps`` steps from the chunks' records (the last chunk's steps past ``steps`` dropped)."""
    loop = jax.tree.map(lambda a: a[:steps], records)
    return _with_x0(x0, loop, jnp.full((steps,) + _batch(x0), jnp.nan))


def _with_x0(x0, loop: ClosedLoop, times) -> ClosedLoop:
    """``loop`` with ``x0`` before its states and these ``solve_times``."""
    return loop._replace(states=jnp.concatenate([jnp.asarray(x0)[None], loop.states]), solve_times=times)


def closed_loop(xs, us, info: StepInfo, times) -> ClosedLoop:
    """The ``ClosedLoop`` of stacked steps ``[T, ...]``, ``states`` the states after each step (``x0`` not
    included)."""
    plans = jnp.where(info.held[..., None], -1, info.result.sequence)  # -1 where held, found or not
    return ClosedLoop(states=xs, inputs=us, input_indices=plans[..., 0], stage_costs=info.stage_cost,
                      predicted_costs=info.result.cost, nodes=info.nodes, fallback_nodes=info.fallback_nodes,
                      feasible=info.feasible, used_fallback=info.used_fallback, complete=info.complete,
                      held=info.held, plans=plans, solve_times=times)


def batch_major(loop: ClosedLoop) -> ClosedLoop:
    """A time-major run of B loops (``[T, B, ...]`` fields) with loop first: ``[B, T, ...]``."""
    return jax.tree.map(lambda a: jnp.moveaxis(a, 0, 1), loop)
