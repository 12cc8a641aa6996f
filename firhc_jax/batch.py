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
device keeps a pool of ``lanes`` slots. A slot holds one sDFS stack
(``firhc_jax.stack``, the store of ``fj.sdfs``, vmapped over the slots).
Every iteration each slot pops the K next nodes of its deepest live batch
(cheapest first) and the children of all slots come from one call of
``expand``: ``lanes * K * M`` children per iteration. A slot whose
row is done takes the next row's root; once every row has started, an idle
slot steals the next node of the shallowest live batch below a busy slot's
top batch, so the last and largest searches are spread over all lanes. Each node carries its row
and is pruned against that row's incumbent, shared by every slot working on
the row: exact per row by the argument of ``fj.sdfs`` (non-negative stage
costs), applied to each subtree. A row that is never stolen from is searched
in ``fj.sdfs``'s order, node for node (``lanes=1`` never steals).

One iteration is ``expand_and_store`` then ``plan`` and ``take``: the nodes
of the next iteration are taken out right after the stores, so that the
stacks are written, then read (XLA then updates them in place).
``iterations`` of a row counts the slot-iterations spent on it.

Memory. The pool stores ``lanes * (N + 1) * K * M`` nodes whatever B is, plus
``n + 2 N + m + 14`` numbers per row (``pool_memory``, ``pool_row_memory``); the
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
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .cache import compiled
from .checks import check_params, check_state, cost_dtype, strong
from .exhaustive import DEFAULT_CHUNK_NODES
from .exhaustive import memory as exhaustive_memory
from . import stack as stacks
from .nodes import SearchStats, best_leaf, expand, no_stats, tally
from .problem import Problem, positive_int, refuse_differentiation
from .result import SearchResult, finish, raise_on_errors
from .sdfs import _search as sdfs_search
from .sdfs import DEFAULT_MAX_MEMORY, node_budget, stack_memory
from .stack import Popped, Stack

SOLVERS = ("sdfs", "sdfs-vmap", "exhaustive")
DEFAULT_LANES = 64


# ---------------------------------------------------------------------------
# Validation and memory plan.
# ---------------------------------------------------------------------------

def _check_batch(X0):
    if isinstance(X0, jax.core.Tracer):
        X = X0
    else:
        try:
            X = jnp.asarray(strong(X0))
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

class Rows(NamedTuple):
    """Per-row incumbents and counters, shared by every slot working on a row."""

    cost: jax.Array  # [B] incumbent cost (+inf: none yet)
    path: jax.Array  # [B, N] int32 incumbent sequence
    stats: SearchStats  # [B] fields: nodes, slot-iterations and error flags of each row
    cut: jax.Array  # [B] int32 times a slot dropped live nodes because the row's node budget ran out


class Pool(NamedTuple):
    """S slots, each an sDFS stack (``firhc_jax.stack``, rows 1 .. N - 1 used;
    row N takes leaf batches) working on one row of the batch."""

    stack: Stack  # [S, ...] fields
    row: jax.Array  # [S] int32 row of the batch each slot works or last worked on (B: none yet)


class Work(NamedTuple):
    """What each slot expands in the next iteration (taken out of the stacks
    at the end of the previous one, so that the stacks are written, then read,
    within an iteration: XLA updates them in place; docs/xla_notes.md,
    "Pop right after the push")."""

    popped: Popped  # [S, K] fields: the nodes, cheapest first
    alive: jax.Array  # [S, K] bool to expand (below the row's incumbent)
    depth: jax.Array  # [S] int32 depth of the nodes (-1: the slot is idle)


class Plan(NamedTuple):
    """Where each slot's next nodes come from."""

    own: jax.Array  # [S] int32 pop K nodes of this row of the slot's own stack (-1: no)
    root: jax.Array  # [S] int32 start this row of the batch: expand its root (-1: no)
    victim: jax.Array  # [S] int32 steal one node from this slot (-1: no)
    robbed: jax.Array  # [S] int32 row of this slot's stack that a thief takes a node from (-1: none)
    depth: jax.Array  # [S] int32 depth of the nodes the slot expands (-1: none)


def pool_memory(problem: Problem, n: int, itemsize: int, lanes: int, pop_width: int = 1,
                param_bytes: int = 0) -> int:
    """Estimated peak bytes of the pool: ``lanes`` sDFS stacks (``fj.sdfs``'s
    ``stack_memory`` each) and the parameters gathered for the K nodes each
    slot expands (``param_bytes`` per row)."""
    return lanes * (stack_memory(problem, n, itemsize, pop_width) + pop_width * param_bytes)


def pool_row_memory(problem: Problem, n: int, itemsize: int, param_bytes: int = 0) -> int:
    """Bytes per row outside the pool: its state, its parameters, its incumbent
    and counters (N + 6 numbers) and its result (N + m + 8 numbers)."""
    return itemsize * (n + 2 * problem.horizon + problem.input_dim + 14) + param_bytes


def incumbent(rows: Rows, row):
    """Incumbent cost of each slot's row (+inf for no row)."""
    return rows.cost.at[row].get(mode="fill", fill_value=jnp.inf)


def plan(pool: Pool, rows: Rows, head, n_valid, limit) -> tuple[Pool, Rows, jax.Array, Plan]:
    """Each slot's next nodes: the K next nodes of its deepest live batch. A
    slot with none takes the next row's root (``head``: the first row not yet
    started) or, once every row has started, steals the next node of the
    shallowest live batch below another slot's deepest one (exact: the row's
    incumbent is shared). A row whose node count passed ``limit`` is not
    expanded further. Returns the pool with re-assigned slots emptied."""
    S, D = pool.row.shape[0], pool.stack.low.shape[1]
    B = rows.cost.shape[0]
    depths = jnp.arange(D, dtype=jnp.int32)
    live = pool.stack.low < incumbent(rows, pool.row)[:, None]  # [S, D]
    spent = rows.stats.nodes.at[pool.row].get(mode="fill", fill_value=0) > limit  # [S] the row's budget is out
    rows = rows._replace(cut=rows.cut.at[jnp.where(spent & jnp.any(live, axis=1), pool.row, B)].add(1, mode="drop"))
    live = live & ~spent[:, None]
    top = jnp.max(jnp.where(live, depths, -1), axis=1)  # [S] deepest live batch
    free = top < 0
    stealable = live & (depths < top[:, None])
    can = jnp.any(stealable, axis=1)
    ranks = jnp.cumsum(jnp.stack([free, can]), axis=1, dtype=jnp.int32) - 1  # one scan for both
    free_rank, can_rank = ranks[0], ranks[1]
    root = jnp.where(free & (head + free_rank < n_valid), head + free_rank, -1)
    # Free slots left without a row are thieves; the i-th thief robs the i-th slot that can be robbed.
    t_rank = free_rank - (n_valid - head)
    steals = free & (t_rank >= 0) & (t_rank < jnp.sum(can, dtype=jnp.int32))
    by_rank = jnp.zeros((S,), jnp.int32).at[jnp.where(can, can_rank, S)].set(jnp.arange(S, dtype=jnp.int32),
                                                                              mode="drop")
    victim = jnp.where(steals, by_rank[jnp.clip(t_rank, 0, S - 1)], -1)
    shallowest = jnp.argmax(stealable, axis=1).astype(jnp.int32)
    robbed = jnp.where(can & (can_rank < jnp.sum(free, dtype=jnp.int32) - (n_valid - head)), shallowest, -1)
    v = jnp.maximum(victim, 0)
    row = jnp.where(steals, pool.row[v], jnp.where(root >= 0, root, pool.row))
    depth = jnp.where(top >= 0, top, jnp.where(root >= 0, 0, jnp.where(steals, shallowest[v], -1)))
    # A slot that changes row starts empty: its batches were pruned against the old row.
    low = jnp.where((row != pool.row)[:, None], jnp.inf, pool.stack.low)
    pool = Pool(stack=pool.stack._replace(low=low), row=row)
    head = jnp.minimum(head + jnp.sum(free, dtype=jnp.int32), n_valid)
    return pool, rows, head, Plan(own=top, root=root, victim=victim, robbed=robbed, depth=depth)


def take(pool: Pool, rows: Rows, todo: Plan, X, K: int) -> tuple[Pool, Work]:
    """Take the planned nodes out of the stacks: each slot's own K, the
    roots of new rows, and the nodes thieves take from their victims."""
    pop = jax.vmap(stacks.pop, in_axes=(0, 0, None))
    stack, popped = pop(pool.stack, todo.own, K)  # [S, K]
    stack, given = pop(stack, todo.robbed, 1)  # [S, 1]: the node each robbed slot hands over
    first = (jnp.arange(K) == 0)[None, :]  # [1, K]
    is_root, thief = (todo.root >= 0)[:, None], (todo.victim >= 0)[:, None]
    v = jnp.maximum(todo.victim, 0)

    def pick(mine, root, stolen):  # [S, K, ...]: the slot's own nodes, or first a root or a stolen node
        shape = mine.shape[:2] + (1,) * (mine.ndim - 2)
        out = jnp.where((is_root & first).reshape(shape), root[:, None], mine)
        return jnp.where((thief & first).reshape(shape), stolen[:, None], out)

    root_x = X[jnp.maximum(todo.root, 0)].astype(popped.x.dtype)
    no_path = jnp.full(popped.path.shape[::2], -1, jnp.int32)  # [S, N]
    popped = Popped(x=pick(popped.x, root_x, given.x[v, 0]),
                    cost=pick(popped.cost, jnp.zeros_like(popped.cost[:, 0]), given.cost[v, 0]),
                    key=pick(popped.key, jnp.zeros_like(popped.key[:, 0]),
                             given.key[v, 0]),
                    path=pick(popped.path, no_path, given.path[v, 0]))
    alive = popped.key < incumbent(rows, pool.row)[:, None]
    return pool._replace(stack=stack), Work(popped=popped, alive=alive, depth=todo.depth)


def expand_and_store(problem: Problem, pool: Pool, rows: Rows, work: Work, params) -> tuple[Pool, Rows]:
    """Expand every slot's nodes in one call of ``expand``; each slot's
    cheapest feasible leaf may improve its row's incumbent; the other children
    are pushed as the slot's batch one depth below (pruned lazily, when
    popped)."""
    N, M = problem.horizon, problem.num_controls
    (S, K, n), B = work.popped.x.shape, rows.cost.shape[0]
    L, row, depth = K * M, pool.row, work.depth + 1  # depth of the children
    p_nodes = jax.tree_util.tree_map(lambda a: jnp.repeat(a[jnp.minimum(row, B - 1)], K, axis=0), params)
    ch = expand(problem, work.popped.x.reshape(S * K, n), work.popped.cost.reshape(S * K), p_nodes,
                steps_left=jnp.repeat(N - depth, K), check_terminal=problem.terminal is not None,
                params_batched=True)
    ch = jax.tree_util.tree_map(lambda a: a.reshape((S, K) + a.shape[1:]), ch)  # [S, K, M, ...]
    ok = (work.alive[..., None] & ~ch.bad).reshape(S, L)
    cost, key = ch.cost.reshape(S, L), ch.key.reshape(S, L)

    best = incumbent(rows, row)
    cand, leaf, improve = best_leaf(cost, ch.terminal_ok.reshape(S, L), ok, (depth == N)[:, None], best)
    new_cost = rows.cost.at[jnp.where(improve, row, B)].min(cand, mode="drop")
    winner = improve & (cand == new_cost.at[row].get(mode="fill", fill_value=jnp.inf))
    leaf_path = jax.vmap(stacks.child_path, in_axes=(0, 0, None, 0))(work.popped.path, work.depth, M, leaf)
    path = rows.path.at[jnp.where(winner, row, B)].set(leaf_path, mode="drop")  # [S, N] each slot's leaf

    keep = ok & (depth < N)[:, None]
    put = jnp.where(work.depth >= 0, depth, N)  # idle slots write nothing live into the leaf row
    stack = jax.vmap(stacks.push)(pool.stack, put, ch.x.reshape(S, L, n).astype(work.popped.x.dtype), cost,
                                  jnp.where(keep, key, jnp.inf), work.popped.path)
    slot = jax.vmap(lambda c, a: tally(no_stats(), c, a))(ch, work.alive)  # [S] fields
    at = jnp.where(work.depth >= 0, row, B)

    def flag(old, met):  # or over the slots of each row (all of them set True: duplicates agree)
        return old.at[jnp.where(met, at, B)].set(True, mode="drop")

    stats = SearchStats(nodes=rows.stats.nodes.at[at].add(slot.nodes, mode="drop"),
                        iterations=rows.stats.iterations.at[at].add(slot.iterations, mode="drop"),
                        negative=flag(rows.stats.negative, slot.negative),
                        nonfinite=flag(rows.stats.nonfinite, slot.nonfinite),
                        overflow=flag(rows.stats.overflow, slot.overflow))
    return pool._replace(stack=stack), rows._replace(cost=new_cost, path=path, stats=stats)


def _pool_search(problem: Problem, X, params, n_valid, budget, lanes: int, pop_width: int) -> SearchResult:
    """Exact sDFS of rows ``X[:n_valid]`` of ``[B, n]`` (with ``params[b]``
    for row b) on a pool of ``lanes`` slots (see ``solve_batch``). A row whose
    node count exceeds ``budget - K M`` is not expanded further. Returns a
    batched result."""
    N, M, K, S = problem.horizon, problem.num_controls, pop_width, lanes
    B = X.shape[0]
    dtype = cost_dtype(problem, X[0], params, batched_params=True)
    limit = budget - K * M
    one = stacks.init(N + 1, K, M, N, X[0], dtype)
    pool = Pool(stack=jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (S,) + a.shape), one)._replace(
        low=jnp.full((S, N + 1), jnp.inf, dtype)), row=jnp.full((S,), B, jnp.int32))
    zeros = jnp.zeros((B,), jnp.int32)
    rows = Rows(cost=jnp.full((B,), jnp.inf, dtype), path=jnp.full((B, N), -1, jnp.int32),
                stats=jax.vmap(lambda _: no_stats())(zeros), cut=zeros)

    def next_work(pool, rows, head):
        pool, rows, head, todo = plan(pool, rows, head, n_valid, limit)
        pool, work = take(pool, rows, todo, X, K)
        return pool, rows, head, work

    def body(carry):
        pool, rows, head, work = carry
        pool, rows = expand_and_store(problem, pool, rows, work, params)
        return next_work(pool, rows, head)

    carry = next_work(pool, rows, jnp.array(0, jnp.int32))
    _, rows, _, _ = jax.lax.while_loop(lambda c: jnp.any(c[3].depth >= 0), body, carry)
    return jax.vmap(lambda c, p, st, cut: finish(problem, c, p, st, cut == 0))(rows.cost, rows.path, rows.stats,
                                                                              rows.cut)


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
                                             pop_width),
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
        Default: the rows per device, at most ``DEFAULT_LANES`` = 64. The
        best count depends on the plant and on B (2-core CPU, N = 5: at
        B = 256 64 lanes beat 16 and 256 on the linear and tank plants; at
        B = 4096 the linear plant is fastest at 256 and the tanks at 1,024;
        benchmarks/RESULTS.md). A GPU wants far more.
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
    chunk_nodes = positive_int("chunk_nodes", chunk_nodes)
    if max_nodes is not None and solver == "exhaustive":
        raise ValueError("max_nodes applies to the sDFS solvers; exhaustive search always visits the whole tree")
    if pop_width != 1 and solver == "exhaustive":
        raise ValueError("pop_width applies to the sDFS solvers; solver='exhaustive' expands level by level")
    if lanes is not None and solver != "sdfs":
        raise ValueError(f"lanes sizes the work pool of solver='sdfs'; solver={solver!r} has no pool")
    if solver != "exhaustive":
        chunk_nodes = DEFAULT_CHUNK_NODES  # unused: keep the compiled batch's cache key
    budget = node_budget(max_nodes)
    refuse_differentiation(X0, params)
    X = _check_batch(X0)
    B, n = X.shape
    params = check_params(params, leading=B)
    check_state(problem, X[0], params, batched_params=True)
    mesh = _mesh(devices)
    per_device, item = -(-B // mesh.devices.size), max(X.dtype.itemsize, 4)  # as fj.sdfs sizes its stack
    param_bytes = sum(a.dtype.itemsize * math.prod(a.shape[1:]) for a in jax.tree_util.tree_leaves(params))
    if solver == "sdfs":
        lanes = min(DEFAULT_LANES, per_device) if lanes is None else positive_int("lanes", lanes)
        fixed = pool_memory(problem, n, item, lanes, pop_width, param_bytes)
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
