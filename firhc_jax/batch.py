"""Batched search: many initial states (and parameter sets) in one compiled call.

``solve_batch(problem, X0)`` solves one problem from each row of ``X0``
``[B, n]`` and returns a ``SearchResult`` whose fields carry a leading axis B.

Parameters. With ``params`` (a pytree whose leaves have leading axis B) the
problem's callables take a parameter pytree as last argument
(``dynamics(x, u, p)``, ``stage_cost(x_next, u, p)``, ``terminal(x, p)``) and
row b is solved with ``p = params[b]``. The core searches know nothing of
parameters: the batch is solved on an *augmented* problem whose state is
``[x, p_flat]`` (the parameters flattened into the state's dtype, carried
unchanged by the augmented dynamics). Every row then runs the same compiled
code whatever its parameter values, and a parameter set is just more state.

Memory. Every solver states what one row (or the pool) needs; a batch that
would exceed ``max_memory`` bytes is solved in chunks of rows (``lax.map``),
and a single row that does not fit is refused before anything is compiled.
"""
from __future__ import annotations

import math
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec

from .exhaustive import DEFAULT_CHUNK_NODES, exhaustive, plan
from .problem import Problem, check_state
from .result import SearchResult, raise_on_errors
from .sdfs import _check_pop_width, sdfs, stack_capacity

SOLVERS = ("sdfs", "sdfs-vmap", "exhaustive")
DEFAULT_MAX_MEMORY = 1 << 30  # bytes


# ---------------------------------------------------------------------------
# Parameters carried in the state.
# ---------------------------------------------------------------------------

class _Layout(NamedTuple):
    """Static description of one row of ``params`` (hashable: a cache key)."""

    treedef: Any
    shapes: tuple  # per leaf, without the batch axis
    dtypes: tuple  # per leaf

    @property
    def size(self) -> int:
        return sum(math.prod(s) for s in self.shapes)

    def unflatten(self, flat):
        """``[P]`` slice of an augmented state -> one row's parameter pytree."""
        leaves, start = [], 0
        for shape, dtype in zip(self.shapes, self.dtypes, strict=True):
            size = math.prod(shape)
            leaves.append(flat[start:start + size].reshape(shape).astype(dtype))
            start += size
        return jax.tree_util.tree_unflatten(self.treedef, leaves)


def _flatten_params(params, batch: int, dtype):
    """``params`` (leaves ``[B, ...]``) -> ``(layout, [B, P] array in dtype)``."""
    leaves, treedef = jax.tree_util.tree_flatten(params)
    paths = [jax.tree_util.keystr(k) for k, _ in jax.tree_util.tree_flatten_with_path(params)[0]]
    if not leaves:
        raise ValueError("params has no array leaves; pass params=None for a problem without parameters")
    arrays = []
    for path, leaf in zip(paths, leaves, strict=True):
        a = leaf if isinstance(leaf, jax.core.Tracer) else jnp.asarray(leaf)
        if not (jnp.issubdtype(a.dtype, jnp.floating) or jnp.issubdtype(a.dtype, jnp.integer)
                or a.dtype == jnp.bool_):
            raise TypeError(f"params leaf {path or '(root)'} must be real numeric, got dtype {a.dtype}")
        if a.ndim == 0 or a.shape[0] != batch:
            raise ValueError(f"params leaf {path or '(root)'} must have leading axis B = {batch} (one entry per "
                             f"row of X0), got shape {tuple(a.shape)}")
        arrays.append(a)
    layout = _Layout(treedef, tuple(a.shape[1:] for a in arrays), tuple(jnp.dtype(a.dtype) for a in arrays))
    flat = jnp.concatenate([a.reshape(batch, -1).astype(dtype) for a in arrays], axis=1)
    return layout, flat


def _augmented(problem: Problem, layout: _Layout, n: int) -> Problem:
    """The problem on ``[x, p_flat]`` states. Cached on ``problem`` so that the
    same callables (hence the same compiled search) serve every call."""
    cache = problem.__dict__.setdefault("_batch_augmented", {})
    key = (layout, n)
    if key not in cache:
        def split(xa):
            return xa[:n], layout.unflatten(xa[n:])

        def dynamics(xa, u):
            x, p = split(xa)
            return jnp.concatenate([problem.dynamics(x, u, p), xa[n:]])

        def stage_cost(xa, u):
            x, p = split(xa)
            return problem.stage_cost(x, u, p)

        terminal = None
        if problem.terminal is not None:
            def terminal(xa):
                return problem.terminal(*split(xa))

        cache[key] = Problem(dynamics, problem.controls, stage_cost, problem.horizon, terminal)
    return cache[key]


def _check_with_params(problem: Problem, layout: _Layout, x0, p0):
    """Run the core's callable checks with row 0's parameters bound, so that a
    mistake is reported against the user's ``f(..., p)`` before compiling.
    Done once per (layout, state shape and dtype), like ``check_state``."""
    key = (layout, tuple(x0.shape), jnp.dtype(x0.dtype))
    done = problem.__dict__.setdefault("_batch_checked", set())
    if key in done:
        return
    bound = Problem(lambda x, u: problem.dynamics(x, u, p0), problem.controls,
                    lambda x, u: problem.stage_cost(x, u, p0), problem.horizon,
                    None if problem.terminal is None else (lambda x: problem.terminal(x, p0)))
    try:
        check_state(bound, x0)
    except (TypeError, ValueError) as e:
        raise type(e)(f"{e} (with params: the callables are called as dynamics(x, u, p), "
                      "stage_cost(x_next, u, p), terminal(x, p))") from e
    done.add(key)


# ---------------------------------------------------------------------------
# Validation and memory plan.
# ---------------------------------------------------------------------------

def _check_batch(X0):
    if isinstance(X0, jax.core.Tracer):
        X = X0
    else:
        try:
            X = jnp.asarray(X0)
        except TypeError as e:
            raise TypeError(f"X0 must be a numeric array [B, n]: {e}") from None
    if X.ndim != 2:
        raise ValueError(f"X0 must be a 2-D batch of states [B, n], got shape {tuple(X.shape)}; "
                         "for one state use fj.sdfs")
    if X.shape[0] == 0:
        raise ValueError("X0 is an empty batch (B = 0)")
    if not jnp.issubdtype(X.dtype, jnp.floating):
        raise TypeError(f"X0 must have a floating dtype, got {X.dtype}")
    if not isinstance(X, jax.core.Tracer):
        bad = np.flatnonzero(~np.all(np.isfinite(np.asarray(X)), axis=1))
        if bad.size:
            raise ValueError(f"X0 contains NaN or inf in rows {bad[:10].tolist()}{' ...' if bad.size > 10 else ''}")
    return X


def row_memory(problem: Problem, n: int, itemsize: int, solver: str, pop_width: int = 1,
               chunk_nodes: int = DEFAULT_CHUNK_NODES) -> int:
    """Estimated peak bytes one row needs under the vmapped solvers.

    ``sdfs-vmap``: its node stack (``stack_capacity`` rows of ``n + 2 + N``
    numbers, twice for the loop's double buffer) plus one iteration's children
    and their ``L x L`` ranking (``L = K M``). ``exhaustive``: three copies of
    the largest level chunk (``chunk_nodes`` nodes of ``n + 4`` numbers).
    """
    N, M, K = problem.horizon, problem.num_controls, pop_width
    w = n + 2 + N
    if solver == "sdfs-vmap":
        L = K * M
        rows = K + stack_capacity(N, M, K) + L
        return itemsize * (2 * rows * w + L * L + 4 * L * w)
    p = plan(problem, chunk_nodes)
    leaves = p.chunk * M ** (N - p.split)
    return itemsize * (3 * leaves * (n + 4) + M**p.split * (n + 2))


def _rows_per_chunk(need: int, batch: int, max_memory: int, what: str) -> int:
    if need > max_memory:
        raise ValueError(f"{what} needs about {need:,} bytes, more than max_memory={max_memory:,}; "
                         "raise max_memory (or lower chunk_nodes / pop_width)")
    return min(batch, max_memory // need)


# ---------------------------------------------------------------------------
# The compiled batch.
# ---------------------------------------------------------------------------

def _per_row(problem: Problem, solver: str, pop_width: int, chunk_nodes: int) -> Callable:
    if solver == "exhaustive":
        return lambda x: exhaustive(problem, x, chunk_nodes=chunk_nodes)
    return lambda x: sdfs(problem, x, pop_width=pop_width)


def _solve(problem: Problem, X, mesh: Mesh, solver: str, pop_width: int, chunk_nodes: int,
           rows_per_chunk: int) -> SearchResult:
    """``[B, n]`` -> batched ``SearchResult``. The rows are padded to a multiple
    of the device count (repeating the last row) and split over ``mesh``; each
    device runs its share independently (no communication inside the search):
    a vmapped per-row search over chunks of ``rows_per_chunk`` rows."""
    B, devices = X.shape[0], mesh.devices.size
    pad = -B % devices
    if pad:
        X = jnp.concatenate([X, jnp.broadcast_to(X[-1], (pad, X.shape[1]))])
    one = _per_row(problem, solver, pop_width, chunk_nodes)
    # check_vma=False: the searches start their loop carries from constants
    # (not device-varying), which the varying-axes check would refuse.
    shard = jax.shard_map(lambda Xs: jax.lax.map(one, Xs, batch_size=rows_per_chunk), mesh=mesh,
                          in_specs=PartitionSpec(_AXIS), out_specs=PartitionSpec(_AXIS), check_vma=False)
    out = shard(X)
    return jax.tree_util.tree_map(lambda a: a[:B], out) if pad else out


_solve_jit = jax.jit(_solve, static_argnames=("mesh", "solver", "pop_width", "chunk_nodes", "rows_per_chunk"))


_AXIS = "rows"


def _mesh(devices) -> Mesh:
    """1-D mesh over ``devices`` (default: every local device). Meshes over the
    same devices compare equal, so the compiled batch is reused."""
    devices = list(jax.local_devices() if devices is None else devices)
    if not devices:
        raise ValueError("devices is empty; pass None for all local devices")
    return Mesh(np.array(devices), (_AXIS,))


def solve_batch(problem: Problem, X0, *, solver: str = "sdfs", params=None, pop_width: int = 1,
                chunk_nodes: int = DEFAULT_CHUNK_NODES, max_memory: int = DEFAULT_MAX_MEMORY,
                devices=None) -> SearchResult:
    """Solve ``problem`` from every row of ``X0``; exact per row.

    Args:
      problem: the ``Problem``; with ``params`` its callables take the
        parameter pytree as last argument.
      X0: ``[B, n]`` initial states.
      solver: ``"sdfs"`` (default), ``"sdfs-vmap"`` (plain ``jax.vmap`` of
        ``fj.sdfs``) or ``"exhaustive"`` (``jax.vmap`` of the vectorised
        ``fj.exhaustive``).
      params: optional pytree with leading axis B: row b is solved with
        ``params[b]``, one compiled call for all rows.
      pop_width: K of the sDFS solvers (nodes popped per row per iteration).
      chunk_nodes: per-row ``chunk_nodes`` of ``"exhaustive"``.
      max_memory: bytes the batch may use at once on each device (estimate,
        see ``row_memory``); larger batches are solved in chunks of rows.
      devices: the devices to split the rows over (default: all local
        devices, ``jax.local_devices()``); one device runs everything.

    Returns a ``SearchResult`` with leading axis B on every field. Un-jitted, a
    negative stage cost in any row raises ``ValueError`` (as ``fj.sdfs``).
    """
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {list(SOLVERS)}, got {solver!r}")
    pop_width = _check_pop_width(pop_width)
    if isinstance(max_memory, bool) or not isinstance(max_memory, int) or max_memory < 1:
        raise ValueError(f"max_memory must be an int >= 1 (bytes), got {max_memory!r}")
    X = _check_batch(X0)
    B, n = X.shape
    if params is not None:
        layout, flat = _flatten_params(params, B, X.dtype)
        _check_with_params(problem, layout, X[0], layout.unflatten(flat[0]))
        problem, X = _augmented(problem, layout, n), jnp.concatenate([X, flat], axis=1)
    check_state(problem, X[0])
    mesh = _mesh(devices)
    if solver == "sdfs":
        solver = "sdfs-vmap"
    need = row_memory(problem, X.shape[1], X.dtype.itemsize, solver, pop_width, chunk_nodes)
    rows = _rows_per_chunk(need, -(-B // mesh.devices.size), max_memory, f"one row of solver={solver!r}")
    return raise_on_errors(_solve_jit(problem, X, mesh=mesh, solver=solver, pop_width=pop_width,
                                      chunk_nodes=chunk_nodes, rows_per_chunk=rows))
