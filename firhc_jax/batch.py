"""Batched search: many initial states (and parameter sets) in one compiled call.

``solve_batch(problem, X0)`` solves one problem from each row of ``X0``
``[B, n]`` and returns a ``SearchResult`` whose fields carry a leading axis B.

Parameters. With ``params`` (a pytree whose leaves have leading axis B) the
problem's callables take a parameter pytree as last argument
(``dynamics(x, u, p)``, ``stage_cost(x_next, u, p)``, ``terminal(x, p)``) and
row b is solved with ``p = params[b]``, exactly as given (dtype and value):
the pool gathers each node's row of ``params`` before expanding it.

The work pool (``solver="sdfs"``, the default). A plain ``jax.vmap`` of
``fj.sdfs`` runs every row's loop until the slowest row finishes, so with node
counts that differ 10x or more between rows most lanes idle. Instead each
device keeps a pool of ``lanes`` slots. A slot holds one sDFS stack: at most
one live peer batch per depth, as in ``fj.sdfs``, so it stores at most
``(N - 1) K M`` nodes. Every iteration each slot pops the K next nodes of its
deepest live batch (cheapest first) and the children of all slots come from
one call of ``expand``: ``lanes * K * M`` children per iteration. A slot whose
row is done takes the next row's root; once every row has started, an idle
slot steals the next node of the shallowest live batch below a busy slot's
top batch, so the last and largest searches are spread over all lanes. Each node carries its row
and is pruned against that row's incumbent, shared by every slot working on
the row: exact per row by the argument of ``fj.sdfs`` (non-negative stage
costs), applied to each subtree. A row that is never stolen from is searched
in ``fj.sdfs``'s order, node for node.

Memory. The pool stores ``lanes * (N - 1) * K * M`` nodes whatever B is, plus
``n + N + 5`` numbers per row (``pool_memory``, ``pool_row_memory``); the
vmapped solvers need ``row_memory`` per row. A batch that would exceed
``max_memory`` bytes is solved in chunks of rows (``lax.map``), and a pool or
row that does not fit on its own is refused before anything is compiled.

Devices. The rows are split over a 1-D mesh of every device of the job
(``jax.devices()``; over all processes after ``jax.distributed.initialize``)
with ``shard_map``; each device runs its own pool (or vmap) on its share, with
no communication inside the search. Over several processes the rows enter as
one global array (laid out as a single process's jit would lay them out) and
the result is all-gathered at the end, so every process reads all of it.
"""
from __future__ import annotations

import functools
import math
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .cache import compiled
from .checks import check_params, check_state, cost_dtype, strong
from .exhaustive import DEFAULT_CHUNK_NODES
from .exhaustive import memory as exhaustive_memory
from .nodes import NEGATIVE, NONFINITE, OVERFLOW, best_leaf, expand, first_min
from .problem import Problem, positive_int, refuse_differentiation
from .result import SearchResult, finish, raise_on_errors
from .sdfs import _search as sdfs_search
from .sdfs import node_budget, stack_memory

SOLVERS = ("sdfs", "sdfs-vmap", "exhaustive")
DEFAULT_MAX_MEMORY = 1 << 30  # bytes
DEFAULT_LANES = 64


# ---------------------------------------------------------------------------
# Validation and memory plan.
# ---------------------------------------------------------------------------

def _check_batch(X0):
    if isinstance(X0, jax.core.Tracer):
        X = X0
    else:
        try:
            X = strong(np.asarray(X0) if not isinstance(X0, jax.Array) else X0)
        except (TypeError, ValueError) as e:
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
    """Estimated peak bytes one row needs under the vmapped solvers: the sDFS
    stack (``fj.sdfs``'s ``stack_memory``) or the exhaustive search's level
    chunks (``fj.exhaustive``'s ``memory``)."""
    if solver == "sdfs-vmap":
        return stack_memory(problem, n, itemsize, pop_width)
    return exhaustive_memory(problem, n, itemsize, chunk_nodes)


def _rows_per_chunk(need: int, batch: int, max_memory: int, what: str) -> int:
    if need > max_memory:
        raise ValueError(f"{what} needs about {need:,} bytes, more than max_memory={max_memory:,}; "
                         "raise max_memory (or lower chunk_nodes / pop_width)")
    return min(batch, max_memory // need)


# ---------------------------------------------------------------------------
# The shared work pool.
# ---------------------------------------------------------------------------

class _Pool(NamedTuple):
    """S slots, each holding one sDFS stack stored by depth: at most one live
    peer batch per depth (as in ``fj.sdfs``), so the batch of depth t has a
    fixed place, level t - 1. A batch is stored as expanded (unsorted) and
    never rewritten: nodes leave it in pop order, cheapest first (ties: lowest
    index, the order of ``fj.sdfs``), and each level only keeps the cost and
    index of its next node. A batch is live while that cost is below the row's
    incumbent, so pruning the rest of a batch costs nothing. Node i of the
    batch of depth d + 1 is input ``i % M`` applied to the ``i // M``-th node
    popped at depth d, whose path is kept in ``paths``."""

    x: jax.Array  # [S, N-1, L, n] level t: the batch of depth t + 1
    cost: jax.Array  # [S, N-1, L] keys as expanded: cost (+ lower bound, if any); +inf: discarded
    g: Any  # [S, N-1, L] accumulated costs, only with a lower bound (else ``cost`` is the cost); None
    next_cost: jax.Array  # [S, N-1] key of each batch's next node in pop order (+inf: none)
    next_idx: jax.Array  # [S, N-1] int32 its index in the batch
    paths: jax.Array  # [S, N, K, N] int32 [:, d, j]: inputs leading to the j-th node popped at depth d
    row: jax.Array  # [S] int32 row the slot works on (B: none)


class _Rows(NamedTuple):
    """Per-row incumbents and counters, shared by every slot working on a row."""

    cost: jax.Array  # [B] incumbent cost (+inf: none yet)
    path: jax.Array  # [B, N] int32 incumbent sequence
    counts: jax.Array  # [B, 6] int32 nodes, slot-iterations, negative stage costs, non-finite, overflow, cut
    #                    (cut: live nodes dropped because the row's node budget ran out)


class _Plan(NamedTuple):
    """What each slot expands next, decided from per-slot and per-level
    scalars only. Deciding and expanding are pipelined through the loop carry
    (the plan for iteration i + 1 is made at the end of iteration i): the big
    node arrays are then read at the start of an iteration, before they are
    updated in place, and the plan reaches the per-node work as materialised
    buffers. Otherwise XLA:CPU copies the node arrays every iteration and
    recomputes the plan's derivation (~100 ops) inside every per-node fusion
    (measured: 2.1e7 -> 2.6e7 nodes/s on the synthetic plant, 256 lanes)."""

    depth: jax.Array  # [S] int32 depth of the nodes to expand (-1: nothing to do)
    level: jax.Array  # [S] int32 pop the next K nodes of this level's batch (-1: no)
    root: jax.Array  # [S] int32 expand this row's root (-1: no)
    victim: jax.Array  # [S] int32 expand the next node of this slot's robbed batch (-1: no)
    robbed: jax.Array  # [S] int32 level whose next node a thief takes (-1: none)


def pool_capacity(problem: Problem, lanes: int, pop_width: int = 1) -> int:
    """Nodes the pool stores: ``lanes * (N - 1) * K * M``, whatever B is."""
    return lanes * (problem.horizon - 1) * pop_width * problem.num_controls


def pool_memory(problem: Problem, n: int, itemsize: int, lanes: int, pop_width: int = 1) -> int:
    """Estimated peak bytes of the pool: its stored nodes (n + 1 numbers each)
    and one iteration's ``lanes * K * M`` children (n + 4), twice for the
    loop's buffers."""
    children = lanes * pop_width * problem.num_controls
    per_node = n + (2 if problem.lower_bound is not None else 1)
    return itemsize * 2 * (pool_capacity(problem, lanes, pop_width) * per_node + children * (n + 4))


def pool_row_memory(problem: Problem, n: int, itemsize: int, param_bytes: int = 0) -> int:
    """Bytes per row outside the pool: its state, its parameters and its result
    (N + 7 numbers)."""
    return itemsize * (n + problem.horizon + 7) + param_bytes


def _next_after(batch, cost, idx):
    """The node of ``batch`` ``[S, L]`` that follows ``(cost, idx)`` in pop
    order (cost, then index): its ``(cost, index)``, cost +inf if none."""
    i = jnp.arange(batch.shape[-1], dtype=jnp.int32)
    after = (batch > cost[:, None]) | ((batch == cost[:, None]) & (i > idx[:, None]))
    return first_min(jnp.where(after, batch, jnp.inf))


def _take(a, i):
    """``a[s, i[s], ...]`` for every slot s: ``a`` ``[S, D, ...]``, ``i`` ``[S]``."""
    return jnp.take_along_axis(a, i.reshape(i.shape + (1,) * (a.ndim - 1)), axis=1)[:, 0]


def _put(a, i, v):
    """``a`` with ``a[s, i[s]] = v[s]``: ``a`` ``[S, D, ...]``; ``i[s]`` outside
    ``[0, D)`` leaves slot s unchanged."""
    at = jnp.arange(a.shape[1]) == i[:, None]
    return jnp.where(at.reshape(at.shape + (1,) * (a.ndim - 2)), jnp.expand_dims(v, 1), a)


def _materialised(pred, fn, *args):
    """``fn(*args)`` with its outputs materialised before any use. XLA:CPU fuses
    cheap producers into each consumer, recomputing them per element (here a
    ~100-op per-slot derivation inside every per-node fusion: 2.6e7 -> 2.9e7
    nodes/s on the synthetic plant, 256 lanes), and drops
    ``lax.optimization_barrier`` before fusing; the outputs of a conditional
    are always materialised. Both branches are ``fn``: ``pred`` only has to be
    a traced (not constant) boolean."""
    return jax.lax.cond(pred, fn, lambda *a: fn(*a), *args)


def _node_paths(paths, depth, idx, M: int):
    """Paths ``[S, ..., N]`` of nodes ``idx`` ``[S, ...]`` of each slot's batch of
    depth ``depth`` ``[S]`` (1..N; N: the children expanded this iteration)."""
    parent = jnp.take_along_axis(_take(paths, depth - 1), (idx // M).reshape(idx.shape[0], -1)[..., None], axis=1)
    parent = parent.reshape(idx.shape + (paths.shape[-1],))
    at = jnp.arange(paths.shape[-1]) == (depth - 1).reshape((-1,) + (1,) * idx.ndim)
    return jnp.where(at, (idx % M)[..., None], parent)


def _pool_search(problem: Problem, X, params, n_valid, budget, lanes: int, pop_width: int,
                 steal: bool) -> SearchResult:
    """Exact sDFS of rows ``X[:n_valid]`` of ``[B, n]`` (with ``params[b]``
    for row b) on a pool of ``lanes`` slots (see ``solve_batch``). A row whose
    node count exceeds ``budget - K M`` is not expanded further. Returns a
    batched result."""
    N, M, K, S = problem.horizon, problem.num_controls, pop_width, lanes
    (B, n), L = X.shape, K * M
    dtype = cost_dtype(problem, X[0], params, batched_params=True)
    bounded = problem.lower_bound is not None
    limit = budget - L
    inf = jnp.array(jnp.inf, dtype)
    levels = jnp.arange(N - 1, dtype=jnp.int32)
    first = jnp.arange(K) == 0  # [K]

    def incumbent(rows, row):
        return rows.cost.at[row].get(mode="fill", fill_value=jnp.inf)

    def plan(pool: _Pool, rows: _Rows, head):
        """Each slot's next nodes: the K next nodes of its deepest live batch;
        a free slot takes the next row's root or, once every row has started,
        the next node of the shallowest live batch below another slot's top
        batch (exact: the row's incumbent is shared)."""
        live = pool.next_cost < incumbent(rows, pool.row)[:, None]  # [S, N-1]
        spent = rows.counts.at[pool.row, 0].get(mode="fill", fill_value=0) > limit  # [S] row's budget is out
        cut = spent & jnp.any(live, axis=1)
        rows = rows._replace(counts=rows.counts.at[jnp.where(cut, pool.row, B), 5].add(1, mode="drop"))
        live = live & ~spent[:, None]
        top = jnp.max(jnp.where(live, levels, -1), axis=1, initial=-1)  # [S] deepest live batch
        free = top < 0
        if steal and N > 2:
            stealable = live & (levels < top[:, None])
            can = jnp.any(stealable, axis=1)
            ranks = jnp.cumsum(jnp.stack([free, can]), axis=1, dtype=jnp.int32) - 1  # one scan for both
            free_rank, can_rank = ranks[0], ranks[1]
        else:
            free_rank = jnp.cumsum(free, dtype=jnp.int32) - 1
        root = jnp.where(free & (head + free_rank < n_valid), head + free_rank, -1)
        row = jnp.where(root >= 0, root, pool.row)
        depth = jnp.where(top >= 0, top + 1, jnp.where(root >= 0, 0, -1))
        victim = robbed = jnp.full((S,), -1, jnp.int32)
        if steal and N > 2:
            t_rank = free_rank - (n_valid - head)  # rank among the free slots left without a row
            steals = free & (t_rank >= 0) & (t_rank < jnp.sum(can, dtype=jnp.int32))
            by_rank = jnp.zeros((S,), jnp.int32).at[jnp.where(can, can_rank, S)].set(
                jnp.arange(S, dtype=jnp.int32), mode="drop")
            victim = jnp.where(steals, by_rank[jnp.clip(t_rank, 0, S - 1)], -1)
            shallowest = jnp.argmax(stealable, axis=1).astype(jnp.int32)
            robbed = jnp.where(can & (can_rank < jnp.sum(free, dtype=jnp.int32) - (n_valid - head)), shallowest, -1)
            row = jnp.where(steals, pool.row[jnp.maximum(victim, 0)], row)
            depth = jnp.where(steals, shallowest[jnp.maximum(victim, 0)] + 1, depth)
        # A slot that changes row starts empty: its batches were pruned against the old row.
        pool = pool._replace(next_cost=jnp.where((row != pool.row)[:, None], inf, pool.next_cost), row=row)
        head = jnp.minimum(head + jnp.sum(free, dtype=jnp.int32), n_valid)
        return pool, rows, head, _Plan(depth=depth, level=top, root=root, victim=victim, robbed=robbed)

    def take_out(pool: _Pool, rows: _Rows, todo: _Plan):
        """The planned nodes of every slot ``(x [S, K, n], cost [S, K], alive
        [S, K])``, and the pool without them."""
        best = incumbent(rows, pool.row)  # [S]
        own, level = todo.level >= 0, jnp.maximum(todo.level, 0)
        batch, c, i = _take(pool.cost, level), _take(pool.next_cost, level), _take(pool.next_idx, level)
        idx, pc = [], []
        for _ in range(K):
            idx.append(i)
            pc.append(c)
            c, i = _next_after(batch, c, i)
        idx, pc = jnp.stack(idx, 1), jnp.stack(pc, 1)  # [S, K] keys
        alive = own[:, None] & (pc < best[:, None])  # a prefix: keys ascend
        if bounded:
            pc = jnp.take_along_axis(_take(pool.g, level), idx, axis=1)  # [S, K] costs
        px = jnp.take_along_axis(_take(pool.x, level), idx[..., None], axis=1)  # [S, K, n]
        path = _node_paths(pool.paths, level + 1, idx, M)  # [S, K, N]
        at = own[:, None] & (levels == level[:, None])
        next_cost = jnp.where(at, c[:, None], pool.next_cost)  # the rest of a pruned batch stays pruned
        next_idx = jnp.where(at, i[:, None], pool.next_idx)

        is_root = (todo.root >= 0)[:, None] & first
        px = jnp.where(is_root[..., None], X[jnp.maximum(todo.root, 0)][:, None], px)
        pc = jnp.where(is_root, 0, pc)
        alive = jnp.where((todo.root >= 0)[:, None], is_root, alive)
        depth = todo.depth  # planned from the same incumbents: a planned slot expands >= 1 node
        if steal and N > 2:
            # Every robbed slot hands over the next node of its robbed batch and moves past it.
            r_level = jnp.maximum(todo.robbed, 0)
            r_cost, r_idx = _take(pool.next_cost, r_level), _take(pool.next_idx, r_level)
            r_g = jnp.take_along_axis(_take(pool.g, r_level), r_idx[:, None], axis=1)[:, 0] if bounded else r_cost
            r_x = jnp.take_along_axis(_take(pool.x, r_level), r_idx[:, None, None], axis=1)[:, 0]  # [S, n]
            r_path = _node_paths(pool.paths, r_level + 1, r_idx, M)  # [S, N]
            after_cost, after_idx = _next_after(_take(pool.cost, r_level), r_cost, r_idx)
            at = (todo.robbed >= 0)[:, None] & (levels == r_level[:, None])
            next_cost = jnp.where(at, after_cost[:, None], next_cost)
            next_idx = jnp.where(at, after_idx[:, None], next_idx)
            thief, v = (todo.victim >= 0)[:, None] & first, jnp.maximum(todo.victim, 0)
            px = jnp.where(thief[..., None], r_x[v][:, None], px)
            pc = jnp.where(thief, r_g[v][:, None], pc)
            alive = jnp.where((todo.victim >= 0)[:, None], thief, alive)
            path = jnp.where(thief[..., None], r_path[v][:, None], path)
        pool = pool._replace(next_cost=next_cost, next_idx=next_idx, paths=_put(pool.paths, depth, path))
        return pool, px, pc, alive

    def work(pool: _Pool, rows: _Rows, todo: _Plan):
        """Take the planned nodes out of the pool, expand those of every slot in
        one call, let leaves improve their rows' incumbents, push each slot's
        children as its new top batch (pruned lazily, when popped)."""
        best, depth = incumbent(rows, pool.row), todo.depth  # [S]
        pool, px, pc, alive = _materialised(jnp.any(depth >= 0), take_out, pool, rows, todo)
        child_depth, row = depth + 1, pool.row
        p_nodes = jax.tree_util.tree_map(lambda a: jnp.repeat(a[jnp.minimum(row, B - 1)], K, axis=0), params)
        ch = expand(problem, px.reshape(S * K, n), pc.reshape(S * K), p_nodes,
                    steps_left=jnp.repeat(N - child_depth, K), check_terminal=problem.terminal is not None,
                    params_batched=True)
        cx, cost, key = ch.x.reshape(S, L, n), ch.cost.reshape(S, L), ch.key.reshape(S, L)
        parent_alive = jnp.repeat(alive, M, axis=1)  # [S, L]
        ok = parent_alive & ~ch.bad.reshape(S, L)

        # Leaves: each slot's cheapest feasible leaf may improve its row's incumbent.
        cand, leaf, improve = best_leaf(cost, ch.terminal_ok.reshape(S, L), ok, (child_depth == N)[:, None], best)
        new_cost = rows.cost.at[jnp.where(improve, row, B)].min(cand, mode="drop")
        winner = improve & (cand == incumbent(rows._replace(cost=new_cost), row))
        path = rows.path.at[jnp.where(winner, row, B)].set(
            _node_paths(pool.paths, jnp.full((S,), N), leaf, M), mode="drop")

        # Non-leaves: the slot's new top batch, at level `depth`.
        batch = jnp.where(ok, key, inf)
        put = jnp.where((depth >= 0) & (child_depth < N), depth, N)  # N: nothing stored
        nc, ni = first_min(batch)
        pool = pool._replace(x=_put(pool.x, put, cx), cost=_put(pool.cost, put, batch),
                             g=_put(pool.g, put, cost) if bounded else None,
                             next_cost=_put(pool.next_cost, put, nc), next_idx=_put(pool.next_idx, put, ni))
        flags = jnp.where(parent_alive, ch.flags.reshape(S, L), 0)
        counts = jnp.stack([M * jnp.sum(alive, axis=1, dtype=jnp.int32), jnp.ones((S,), jnp.int32)]
                           + [jnp.sum((flags & bit) > 0, axis=1, dtype=jnp.int32) for bit in (NEGATIVE, NONFINITE,
                                                                                                 OVERFLOW)]
                           + [jnp.zeros((S,), jnp.int32)], 1)
        rows = _Rows(cost=new_cost, path=path,
                     counts=rows.counts.at[jnp.where(depth >= 0, row, B)].add(counts, mode="drop"))
        return pool, rows

    def body(carry):
        pool, rows, head, todo = carry
        pool, rows = work(pool, rows, todo)
        pool, rows, head, todo = plan(pool, rows, head)
        return pool, rows, head, todo

    def pending(carry):
        return jnp.any(carry[3].depth >= 0)

    pool = _Pool(x=jnp.zeros((S, N - 1, L, n), X.dtype), cost=jnp.full((S, N - 1, L), inf),
                 g=jnp.full((S, N - 1, L), inf) if bounded else None,
                 next_cost=jnp.full((S, N - 1), inf), next_idx=jnp.zeros((S, N - 1), jnp.int32),
                 paths=jnp.full((S, N, K, N), -1, jnp.int32), row=jnp.full((S,), B, jnp.int32))
    rows = _Rows(cost=jnp.full((B,), inf), path=jnp.full((B, N), -1, jnp.int32), counts=jnp.zeros((B, 6), jnp.int32))
    pool, rows, head, todo = plan(pool, rows, jnp.array(0, jnp.int32))
    _, rows, _, _ = jax.lax.while_loop(pending, body, (pool, rows, head, todo))
    c = rows.counts
    flags = (c[:, 2] > 0) * NEGATIVE | (c[:, 3] > 0) * NONFINITE | (c[:, 4] > 0) * OVERFLOW
    return jax.vmap(lambda *a: finish(problem, *a))(rows.cost, rows.path, c[:, 0], c[:, 1], flags, c[:, 5] == 0)


# ---------------------------------------------------------------------------
# The compiled batch.
# ---------------------------------------------------------------------------

def _per_row(problem: Problem, solver: str, pop_width: int, chunk_nodes: int, budget) -> Callable:
    if solver == "exhaustive":
        from .exhaustive import exhaustive
        return lambda a: exhaustive(problem, a[0], params=a[1], chunk_nodes=chunk_nodes)
    return lambda a: sdfs_search(problem, a[0], a[1], None, budget, pop_width=pop_width, prune=True)


def _device_solve(problem: Problem, X, params, budget, solver: str, pop_width: int, chunk_nodes: int,
                  rows_per_chunk: int, lanes: int) -> SearchResult:
    """One device's rows ``[B, n]`` (and their ``params``), in chunks of
    ``rows_per_chunk`` rows: a pool search per chunk (``"sdfs"``) or a vmapped
    per-row search."""
    if solver != "sdfs":
        return jax.lax.map(_per_row(problem, solver, pop_width, chunk_nodes, budget), (X, params),
                           batch_size=rows_per_chunk)
    B, R = X.shape[0], rows_per_chunk
    chunks = -(-B // R)

    def split(a):  # [B, ...] -> [chunks, R, ...], padded by repeating the last row
        a = jnp.concatenate([a, jnp.broadcast_to(a[-1], (chunks * R - B,) + a.shape[1:])])
        return a.reshape((chunks, R) + a.shape[1:])

    out = jax.lax.map(lambda a: _pool_search(problem, a[1], a[2], jnp.minimum(R, B - a[0] * R), budget, lanes,
                                             pop_width, True),
                      (jnp.arange(chunks, dtype=jnp.int32), split(X), jax.tree_util.tree_map(split, params)))
    return jax.tree_util.tree_map(lambda a: a.reshape((chunks * R,) + a.shape[2:])[:B], out)


def _solve(problem: Problem, X, params, budget, *, mesh: Mesh, solver: str, pop_width: int, chunk_nodes: int,
           rows_per_chunk: int, lanes: int) -> SearchResult:
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
        lambda Xs, ps, b: _device_solve(problem, Xs, ps, b, solver, pop_width, chunk_nodes, rows_per_chunk, lanes),
        mesh=mesh, in_specs=(PartitionSpec(_AXIS), PartitionSpec(_AXIS), PartitionSpec()),
        out_specs=PartitionSpec(_AXIS), check_vma=False)
    out = shard(padded(X), jax.tree_util.tree_map(padded, params), budget)
    return jax.tree_util.tree_map(lambda a: a[:B], out) if pad else out


_AXIS = "rows"


def _mesh(devices) -> Mesh:
    """1-D mesh over ``devices`` (default: every device of the job,
    ``jax.devices()``: the local devices in a single process). Meshes over the
    same devices compare equal, so the compiled batch is reused."""
    if devices is None:
        devices = jax.devices()
    elif isinstance(devices, (str, bytes, jax.Device)) or not isinstance(devices, (list, tuple, np.ndarray)):
        raise TypeError(f"devices must be a list of jax devices (e.g. jax.devices()[:2]) or None, got {devices!r}")
    devices = list(devices)
    if not devices:
        raise ValueError("devices is empty; pass None for all devices of the job (jax.devices())")
    for i, d in enumerate(devices):
        if not isinstance(d, jax.Device):
            raise TypeError(f"devices[{i}] must be a jax device (from jax.devices()), got {d!r}")
    if len(set(devices)) != len(devices):
        raise ValueError(f"devices lists a device more than once: {devices}")
    if len({d.platform for d in devices}) > 1:
        raise ValueError(f"devices mixes platforms: {sorted({d.platform for d in devices})}")
    return Mesh(np.array(devices), (_AXIS,))


def _global_rows(X, mesh: Mesh):
    """Multi-process mesh: every process's ``X`` (the same rows everywhere) as
    one global array over ``mesh``; a fingerprint of the rows is
    compared across processes first, so that differing ``X0`` fail loudly."""
    import hashlib

    from jax.experimental import multihost_utils

    if isinstance(X, jax.Array) and not X.is_fully_addressable and not X.is_fully_replicated:
        raise ValueError("X0 is a jax.Array sharded over several processes; pass the same host (NumPy) array "
                         "[B, n] on every process")
    host = np.asarray(X)
    digest = np.frombuffer(hashlib.sha256(host.tobytes()).digest(), np.uint8)
    fingerprint = np.concatenate([np.array(host.shape, np.int64).view(np.uint8), digest])
    every = np.asarray(multihost_utils.process_allgather(fingerprint))  # [processes, 48]
    if not np.all(every == every[0]):
        differ = np.flatnonzero(np.any(every != every[0], axis=1)).tolist()
        raise ValueError(f"X0 differs between processes (processes {differ} differ from process 0): every "
                         "process must pass the same batch (X0 and params)")
    # The layout a single process's jit picks for the same call (rows split when they divide evenly, else
    # replicated and padded inside): the same partitioned program, hence bit-identical results.
    spec = PartitionSpec(_AXIS) if host.shape[0] % mesh.devices.size == 0 else PartitionSpec()
    return jax.make_array_from_callback(host.shape, NamedSharding(mesh, spec), lambda i: host[i])


@functools.partial(jax.jit, static_argnames="mesh")
def _replicated(tree, mesh: Mesh):
    """``tree`` replicated over every device of ``mesh`` (an all-gather across
    processes), so that each process can read the whole result."""
    return jax.lax.with_sharding_constraint(tree, NamedSharding(mesh, PartitionSpec()))


def solve_batch(problem: Problem, X0, *, solver: str = "sdfs", params=None, pop_width: int = 1,
                lanes: int | None = None, chunk_nodes: int = DEFAULT_CHUNK_NODES, max_nodes=None,
                max_memory: int = DEFAULT_MAX_MEMORY, devices=None) -> SearchResult:
    """Solve ``problem`` from every row of ``X0``; exact per row.

    Args:
      problem: the ``Problem``; with ``params`` its callables take the
        parameter pytree as last argument.
      X0: ``[B, n]`` initial states.
      solver: ``"sdfs"`` (default: the shared work pool, see the module
        docstring), ``"sdfs-vmap"`` (plain ``jax.vmap`` of ``fj.sdfs``) or
        ``"exhaustive"`` (``jax.vmap`` of the vectorised ``fj.exhaustive``).
      params: optional pytree with leading axis B: row b is solved with
        ``params[b]``, one compiled call for all rows; new values never
        recompile.
      pop_width: K of the sDFS solvers (nodes popped per row, or per pool
        slot, per iteration).
      lanes: slots of the ``"sdfs"`` pool on each device: each iteration
        expands up to ``lanes * pop_width * M`` children in one call.
        Default: the rows per device, at most ``DEFAULT_LANES`` = 64: on CPU
        wider iterations gained nothing on the tanks and hopper and were up
        to 3x slower on the synthetic plant (measured on 2 cores, see
        docs/batch.md). A GPU wants far more.
      chunk_nodes: per-row ``chunk_nodes`` of ``"exhaustive"``.
      max_nodes: optional node budget per row (sDFS solvers): a row stops
        expanding once its count could pass it and keeps its incumbent, with
        ``complete=False``. In the pool, slots that share a stolen row check
        the budget each iteration, so such a row may pass it by at most
        ``(lanes - 1) * pop_width * M`` nodes.
      max_memory: bytes the batch may use at once on each device (estimate,
        see ``row_memory``, ``pool_memory``); larger batches are solved in
        chunks of rows.
      devices: the devices to split the rows over (default: every device of
        the job, ``jax.devices()``: the local devices in a single process, all
        processes' devices after ``jax.distributed.initialize``); one device
        runs everything. Over several processes, every process passes the
        same ``X0`` (and ``params``) and gets the whole result, replicated on
        every device.

    Returns a ``SearchResult`` with leading axis B on every field. Un-jitted, a
    negative stage cost in any row raises ``ValueError`` (as ``fj.sdfs``).
    """
    if not isinstance(problem, Problem):
        raise TypeError(f"problem must be a firhc_jax.Problem, got {type(problem).__name__}")
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {list(SOLVERS)}, got {solver!r}")
    pop_width = positive_int("pop_width", pop_width)
    max_memory = positive_int("max_memory", max_memory)
    if max_nodes is not None and solver == "exhaustive":
        raise ValueError("max_nodes applies to the sDFS solvers; exhaustive search always visits the whole tree")
    budget = node_budget(max_nodes)
    refuse_differentiation(X0, params)
    X = _check_batch(X0)
    B, n = X.shape
    params = check_params(params, leading=B)
    check_state(problem, X[0], params, batched_params=True)
    mesh = _mesh(devices)
    per_device, item = -(-B // mesh.devices.size), X.dtype.itemsize
    param_bytes = sum(a.dtype.itemsize * math.prod(a.shape[1:]) for a in jax.tree_util.tree_leaves(params))
    if solver == "sdfs":
        lanes = min(DEFAULT_LANES, per_device) if lanes is None else positive_int("lanes", lanes)
        fixed = pool_memory(problem, n, item, lanes, pop_width)
        if fixed >= max_memory:
            raise ValueError(f"the pool of {lanes} lanes needs about {fixed:,} bytes, more than "
                             f"max_memory={max_memory:,}; lower lanes or pop_width, or raise max_memory")
        rows = _rows_per_chunk(pool_row_memory(problem, n, item, param_bytes), per_device, max_memory - fixed,
                               "one row")
    else:
        lanes = None  # unused: keep the compiled batch's cache key
        need = row_memory(problem, n, item, solver, pop_width, chunk_nodes) + param_bytes
        rows = _rows_per_chunk(need, per_device, max_memory, f"one row of solver={solver!r}")
    multi = mesh.is_multi_process and not isinstance(X, jax.core.Tracer)
    if multi:
        X = _global_rows(X, mesh)
        params = jax.tree_util.tree_map(lambda a: _global_rows(a, mesh), params)
    run = compiled(_solve, problem, mesh=mesh, solver=solver, pop_width=pop_width, chunk_nodes=chunk_nodes,
                   rows_per_chunk=rows, lanes=lanes)
    out = run(X, params, budget)
    return raise_on_errors(_replicated(out, mesh) if multi else out)
