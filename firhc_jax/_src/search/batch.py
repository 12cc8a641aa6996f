"""Batched search: many initial states (and parameter sets) in one compiled call.

``solve_batch(problem, X0)`` solves one problem from each row of ``X0``
``[B, n]`` and returns a ``SearchResult`` whose fields carry a leading axis B.

Parameters. With ``params`` (a pytree whose leaves have leading axis B) the
problem's callables take a parameter pytree as last argument
(``dynamics(x, u, p)``, ``stage_cost(x_next, u, p)``, ``terminal(x, p)``) and
row b is solved with ``p = params[b]``, exactly as given (dtype and value).

Solvers. ``"sdfs"`` (the default) is the shared work pool
(``firhc_jax._src.search.pool``); ``"sdfs-vmap"`` and ``"exhaustive"`` vmap ``fj.sdfs``
and ``fj.exhaustive`` over the rows.

This module checks the arguments and plans the memory: the pool stores
``lanes * (N + 1) * K * M`` nodes whatever B is, plus ``n + 2 N + m + 14``
numbers per row (``pool_memory``, ``pool_row_memory``); the vmapped solvers
need ``row_memory`` per row. A batch that would exceed ``max_memory`` bytes
is solved in chunks of rows (``lax.map``), and a pool or row that does not
fit on its own is refused before anything is compiled. Where the rows run
(devices, processes) is ``firhc_jax._src.runtime.sharding``.
"""
from __future__ import annotations

import math
import time
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
from jax.sharding import Mesh, PartitionSpec

from ..annotations import ArrayLike, PyTree
from ..checks import is_tracer, positive_int
from ..problem.callables import search_inputs
from ..problem.problem import Problem
from ..runtime.memory_cache import compiled
from ..runtime.progress import TICKS, Progress, expected_s, record, tick_python
from ..runtime.sharding import AXIS, default_parts, global_rows, mesh_of, replicated, run_parts
from . import solvers
from .exhaustive import DEFAULT_CHUNK_NODES
from .result import SearchResult, raise_on_errors
from .sdfs import DEFAULT_MAX_MEMORY, node_budget
from .solvers import DEFAULT_LANES  # noqa: F401  solve_batch's default lanes, importable here as before

# ---------------------------------------------------------------------------
# The memory plan.
# ---------------------------------------------------------------------------

def _rows_per_chunk(need: int, batch: int, max_memory: int, what: str) -> int:
    if need > max_memory:
        raise ValueError(f"{what} needs about {need:,} bytes, more than max_memory={max_memory:,}; "
                         "raise max_memory (or lower chunk_nodes / pop_width)")
    return min(batch, max_memory // need)


class _Plan(NamedTuple):
    parts: int  # shares of the rows run at once (firhc_jax._src.runtime.sharding.run_parts)
    rows_per_chunk: int  # rows a device solves at once within a part
    options: dict  # the solver's options, ``lanes`` resolved for these rows


def _plan(problem: Problem, solver: str, options: dict, n: int, itemsize: int, B: int, devices: int, parts: int,
          param_bytes: int, max_memory: int) -> _Plan:
    """How to run ``B`` rows within ``max_memory`` bytes per device: each of
    the ``parts`` running at once gets an equal share of it; fewer parts when
    one part's fixed memory (a pool) or one row would not fit its share."""
    batch_memory = solvers.get(solver).batch_memory
    while True:
        share, part_rows = max_memory // parts, -(-B // parts)
        per_device = -(-part_rows // devices)
        fixed, per_row = batch_memory(problem, n, itemsize, per_device, param_bytes, **options)
        if fixed + per_row <= share or parts == 1:
            break
        parts -= 1
    if "lanes" in options:
        options = {**options, "lanes": solvers.lanes_for(options["lanes"], per_device)}
    if fixed >= share:
        raise ValueError(f"the pool of {options['lanes']} lanes needs about {fixed:,} bytes, more than "
                         f"max_memory={max_memory:,}; lower lanes or pop_width, or raise max_memory")
    what = f"one row of solver={solver!r}"
    return _Plan(parts, _rows_per_chunk(per_row, per_device, share - fixed, what), options)


# ---------------------------------------------------------------------------
# The compiled batch.
# ---------------------------------------------------------------------------

def _device_solve(problem: Problem, X, params, max_nodes, solver: str, rows_per_chunk: int, budgeted: bool,
                  options: tuple) -> SearchResult:
    """One device's rows ``[B, n]`` (and their ``params``), in chunks of
    ``rows_per_chunk`` rows, each chunk one call of the solver's ``batch``."""
    B, R = X.shape[0], rows_per_chunk
    chunks = -(-B // R)
    batch = solvers.get(solver).batch
    budgets = jnp.broadcast_to(max_nodes, (R,))

    def split(a):  # [B, ...] -> [chunks, R, ...], padded by repeating the last row
        a = jnp.concatenate([a, jnp.broadcast_to(a[-1], (chunks * R - B,) + a.shape[1:])])
        return a.reshape((chunks, R) + a.shape[1:])

    out = jax.lax.map(lambda a: batch(problem, a[1], a[2], None, budgets, jnp.minimum(R, B - a[0] * R),
                                      budgeted=budgeted, **dict(options)),
                      (jnp.arange(chunks, dtype=jnp.int32), split(X), jax.tree_util.tree_map(split, params)))
    return jax.tree_util.tree_map(lambda a: a.reshape((chunks * R,) + a.shape[2:])[:B], out)


def _solve(problem: Problem, X, params, max_nodes, *, mesh: Mesh, solver: str, rows_per_chunk: int,
           budgeted: bool, options: tuple) -> SearchResult:
    """``[B, n]`` -> batched ``SearchResult``. The rows (and params) are padded
    to a multiple of the device count (repeating the last row) and split over
    ``mesh``; each device solves its share independently (no communication
    inside the search)."""
    B, devices = X.shape[0], mesh.devices.size
    pad = -B % devices

    def padded(a):
        return jnp.concatenate([a, jnp.broadcast_to(a[-1], (pad,) + a.shape[1:])]) if pad else a

    # check_vma=False: the searches start their loop carries from constants
    # (not device-varying), which the varying-axes check would refuse.
    shard = jax.shard_map(
        lambda Xs, ps, b: _device_solve(problem, Xs, ps, b, solver, rows_per_chunk, budgeted, options),
        mesh=mesh, in_specs=(PartitionSpec(AXIS), PartitionSpec(AXIS), PartitionSpec()),
        out_specs=PartitionSpec(AXIS), check_vma=False)
    out = shard(padded(X), jax.tree_util.tree_map(padded, params), max_nodes)
    return jax.tree_util.tree_map(lambda a: a[:B], out) if pad else out


def solve_batch(problem: Problem, X0: ArrayLike, *, solver: str = "sdfs", params: PyTree = None, pop_width: int = 1,
                lanes: int | None = None, chunk_nodes: int = DEFAULT_CHUNK_NODES,
                max_nodes: int | ArrayLike | None = None, max_memory: int = DEFAULT_MAX_MEMORY,
                devices: Sequence[jax.Device] | jax.Device | None = None, cores: int | None = None,
                progress: bool | None = None) -> SearchResult:
    """Solve ``problem`` from every row of ``X0``; exact per row.

    Args:
      problem: the ``Problem``; with ``params`` its callables take the
        parameter pytree as last argument.
      X0: ``[B, n]`` initial states.
      solver: ``"sdfs"`` (default: the shared work pool,
        ``firhc_jax._src.search.pool``), ``"sdfs-vmap"`` (plain ``jax.vmap`` of ``fj.sdfs``) or
        ``"exhaustive"`` (``jax.vmap`` of the vectorised ``fj.exhaustive``).
      params: optional pytree with leading axis B: row b is solved with
        ``params[b]``, one compiled call for all rows; new values never
        recompile.
      pop_width: K of the sDFS solvers (nodes popped per row, or per pool
        slot, per iteration).
      lanes: slots of the ``"sdfs"`` pool on each device (in each part, see
        ``cores``): each iteration expands up to ``lanes * pop_width * M``
        children in one call. Default: the rows per device and part, at most
        ``DEFAULT_LANES`` = 64. The
        best count depends on the plant and on B (2-core CPU, N = 5: at
        B = 256 64 lanes beat 16 and 256 on the linear and tank plants; at
        B = 4096 the linear plant is fastest at 256 and the tanks at 1,024;
        docs/dev/benchmark-history.md). A GPU wants far more.
      chunk_nodes: per-row ``chunk_nodes`` of ``"exhaustive"``.
      max_nodes: optional node budget per row (sDFS solvers): a row stops
        expanding before an expansion could take its count above it (as
        ``fj.sdfs``; a budget below ``pop_width * M`` expands nothing) and
        keeps its incumbent, with ``complete=False``; in the pool, slots that
        share a stolen row stop where all of them together could pass it.
        Never passed. Each row first gets ``fj.sdfs``'s budgeted seeds
        (docs/guide/budgets.md).
      max_memory: bytes the batch may use at once on each device (estimate,
        see ``row_memory``, ``pool_memory``), shared equally by the parts
        running at once; larger batches are solved in chunks of rows, and
        fewer parts run at once where one part's pool would not fit.
      devices: the devices to split the rows over (default: every device of
        the job, ``jax.devices()``: the local devices in a single process, all
        processes' devices after ``jax.distributed.initialize``); one device
        runs everything. Over several processes, every process passes the
        same ``X0`` (and ``params``) and gets the whole result, replicated on
        every device.
      cores: parts of the rows dispatched at once, each a separate execution
        of the same compiled batch on its own share of the rows (row i in
        part ``i % cores``), run side by side (``firhc_jax._src.runtime.sharding``).
        Default: on CPU devices, every core this process may use
        (``os.sched_getaffinity``) shared among the devices, so one device
        keeps all cores busy without any flag; 1 elsewhere, inside
        ``jax.jit`` and over several processes. ``cores=1`` is one
        execution. Costs, sequences and flags do not depend on it; the
        pool's node counts do (which rows share a pool), and so do the
        incumbents of pool rows cut by ``max_nodes`` where slots share them.
      progress: a bar on stderr or in the notebook: ``None`` (default)
        once the call has taken 2 s, ``True`` at once, ``False`` never. It
        never changes a result. The batch runs as one compiled call, and the
        bar shows the time elapsed and the time the last call of the same
        program took; with ``True`` and a solver that solves each row on its
        own (``"sdfs-vmap"``, ``"exhaustive"``), the bar counts the rows
        instead, solved in up to 25 chunks of one compiled call each. The
        rows of a work pool (``"sdfs"``, ``"pool"``) are never split for a
        bar: which rows share the pool decides their node counts and, under
        ``max_nodes``, their incumbents. Un-jitted, single-process calls
        only (``None`` is ``False`` there).

    Returns a ``SearchResult`` with leading axis B on every field. Un-jitted, a
    negative stage cost in any row raises ``ValueError`` (as ``fj.sdfs``).
    """
    X, params = search_inputs(problem, X0, params, batched=True)
    B, n = X.shape
    table = solvers.get(solver)
    passed = {"pop_width": pop_width, "lanes": lanes, "chunk_nodes": chunk_nodes, "max_nodes": max_nodes,
              "max_memory": max_memory}
    options = solvers.check_options(solver, {k: v for k, v in passed.items()
                                             if k in table.options or _given(v, _UNSET[k])})
    max_memory = options.pop("max_memory")
    options.pop("max_nodes", None)
    budget = node_budget(max_nodes)
    mesh = mesh_of(devices)
    traced = any(is_tracer(a) for a in (X, budget, *jax.tree_util.tree_leaves(params)))  # inside a jit
    multi = mesh.is_multi_process and not isinstance(X, jax.core.Tracer)
    if cores is None:
        parts = 1 if traced or multi else default_parts(mesh)
    else:
        parts = positive_int("cores", cores)
        if parts > 1 and (traced or multi):
            raise ValueError(f"cores={parts} splits the rows of an un-jitted, single-process call into parts "
                             "dispatched at once; inside jax.jit or over several processes pass cores=None")
    if progress not in (None, True, False):
        raise TypeError(f"progress must be None, True or False, got {progress!r}")
    if progress and (traced or multi):
        raise ValueError("progress=True reports between compiled calls of an un-jitted, single-process call; "
                         "inside jax.jit or over several processes pass progress=None")
    item = max(X.dtype.itemsize, 4)  # as fj.sdfs sizes its stack
    param_bytes = sum(a.dtype.itemsize * math.prod(a.shape[1:]) for a in jax.tree_util.tree_leaves(params))

    def runner(rows: int):  # the compiled batch of `rows` rows and its plan
        plan = _plan(problem, solver, options, n, item, rows, mesh.devices.size, min(parts, rows), param_bytes,
                     max_memory)
        return plan, compiled(_solve, problem, mesh=mesh, solver=solver, rows_per_chunk=plan.rows_per_chunk,
                              budgeted=max_nodes is not None, options=tuple(sorted(plan.options.items())))

    def solve(X, params):
        plan, run = runner(X.shape[0])
        return run_parts(run, X, params, budget, plan.parts) if plan.parts > 1 else run(X, params, budget)

    if traced or multi:
        if multi:
            X = global_rows(X, mesh)
            params = jax.tree_util.tree_map(lambda a: global_rows(a, mesh), params)
        out = solve(X, params)
        return raise_on_errors(replicated(out, mesh) if multi else out)
    key = ("solve_batch", problem.key, solver, tuple(sorted(options.items())), max_nodes is not None, n, X.dtype.str,
           parts, max_memory, mesh)
    return raise_on_errors(_in_chunks(solve, X, params, progress, key,
                                      min_rows=parts * solvers.lanes_for(options.get("lanes"), B),
                                      apart=not table.shares_rows))


def _in_chunks(solve, X, params, progress, key, min_rows: int, apart: bool) -> SearchResult:
    """``solve(X, params)`` under a bar (``progress``: True, False, None: automatic): in one call (False, None,
    and True where the rows are not solved ``apart``: the bar shows the time elapsed and the time the last call
    of the program says it takes), or (True, rows solved apart) in up to ``TICKS`` calls of equal rows (at
    least ``min_rows``; the last padded by repeating the last row), each counted as it ends. A pool's rows are
    never split: split, they would share it with other rows, and a row's node count, and its incumbent where a
    budget cuts it, depend on the rows beside it (a bar must not change a result). A batch is not split by
    default either: each chunk waits for its slowest row, and a chunk's shape compiles a program of its own
    (benchmarks/progress_bench.py)."""
    B = X.shape[0]
    chunks = bool(progress) and apart
    with Progress(B, "solve_batch", enabled=progress, counted=chunks,
                  expected=None if chunks else expected_s(key, B),
                  uncounted="progress=True counts its steps" if apart else "its rows share one work pool"):
        if not chunks:
            out = solve(X, params)
            started = time.perf_counter()  # compiled (the first call), now running
        else:
            R = max(-(-B // TICKS), min(min_rows, B))
            pad = -B % R
            rows = lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], pad, 0)]) if pad else a  # noqa: E731
            X, params = rows(X), jax.tree_util.tree_map(rows, params)
            outs, started = [], None
            for start in range(0, B, R):
                part = lambda a, start=start: a[start:start + R]  # noqa: E731
                outs.append(solve(part(X), jax.tree_util.tree_map(part, params)))
                started = started or time.perf_counter()
                if len(outs) > 1:  # the chunk before this one is done (or nearly): count its rows
                    jax.block_until_ready(outs[-2])
                    tick_python(start - 1)
            out = jax.tree_util.tree_map(lambda *a: jnp.concatenate(a)[:B], *outs)
        jax.block_until_ready(out)
        record(key, B, time.perf_counter() - started)
    return out


_UNSET = {"pop_width": 1, "lanes": None, "chunk_nodes": DEFAULT_CHUNK_NODES, "max_nodes": None}


def _given(value, unset) -> bool:
    """Whether a keyword of ``solve_batch`` was set to something other than its default (which every solver
    takes, whether or not the option is its own)."""
    return not (value is unset or (type(value) is type(unset) and value == unset))


def row_memory(problem: Problem, n: int, itemsize: int, solver: str, pop_width: int = 1,
               chunk_nodes: int = DEFAULT_CHUNK_NODES) -> int:
    """Estimated peak bytes one row needs under the vmapped solvers (``"sdfs-vmap"``: the sDFS stack,
    ``"exhaustive"``: the level chunks)."""
    given = {"pop_width": pop_width, "chunk_nodes": chunk_nodes}
    options = solvers.check_options(solver, {k: v for k, v in given.items() if k in solvers.get(solver).options})
    return solvers.get(solver).memory(problem, n, itemsize, **options)
