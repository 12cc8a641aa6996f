"""Sorted depth-first search (the paper's Table 1) as one compiled while-loop.

The stack holds *peer batches*: the children pushed by one expansion, sorted so
the cheapest is on top. Each iteration pops the top ``K = pop_width`` nodes of
the top batch (the K cheapest remaining peers; ``K = 1`` is Table 1 exactly),
expands all their ``K * M`` children in one vmapped call, lets feasible leaves
improve the incumbent, and pushes the cheaper-than-incumbent non-leaf children
as a new sorted batch. Because a batch is sorted, once its top node is no
cheaper than the incumbent the whole rest of the batch is dropped in the same
iteration (Table 1 would pop and skip them one by one; the node count, which
counts computed children only, is the same).

"Cheaper" compares a node's *key*: its accumulated cost, plus, when the
problem has a ``lower_bound``, the bound on the cost still to come. Peers are
sorted by the same key. Without a bound this is the paper's algorithm node for
node; with an admissible bound it prunes more and stays exact.

Batches only ever sit on the batch they were expanded from, so depths grow
strictly from bottom to top and the stack never holds more than
``(N - 1) * K * (M - 1) + K`` live nodes: that is the fixed capacity
(``stack_memory`` gives the bytes; larger stacks are refused up front).

Pruning is exact because stage costs are non-negative: a node whose key is not
below the incumbent cannot lead to a cheaper leaf (floating-point addition of
non-negative numbers never decreases a sum). With ``prune=False`` the same
machinery visits the whole tree (exhaustive depth-first search), so a time
ratio between the two measures pruning alone.

``iterations`` counts loop iterations, one batched call of ``dynamics`` each,
in every solver. ``max_nodes`` stops the loop before an iteration could take
the node count above it; the result then holds the incumbent found so far and
``complete=False``.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .cache import compiled
from .checks import check_params, check_state, cost_dtype
from .nodes import best_leaf, expand, rollout_cost
from .problem import Problem, is_tracer, positive_int, refuse_differentiation
from .result import SearchResult, finish, raise_on_errors

INT32_MAX = 2**31 - 1
DEFAULT_MAX_MEMORY = 1 << 30  # bytes


class Stack(NamedTuple):
    """Fixed-capacity node stack. Rows ``[0, K)`` are sentinels (depth -1);
    live nodes occupy rows ``[K, K + size)``, top last.

    A node is one row of one floating buffer: state, accumulated cost, key,
    depth and path (small integers, exact in any float of at least 32 bits).
    One buffer means one dynamic slice to pop and one in-place update to push;
    with separate buffers XLA copies them every iteration to order the reads
    (docs/xla_notes.md)."""

    rows: jax.Array  # [R, n + 3 + N] x (n), cost, key, depth (root 0, sentinel -1), path from the root (N)
    top: jax.Array  # [K, n + 3 + N] copy of the top K rows, read right after each push so that the
    #                 buffer is only ever updated and then read (XLA then updates it in place, no copies)


class _Carry(NamedTuple):
    """Loop state. Every integer lives in one ``book`` vector, updated by one
    fused op per iteration (on CPU each separate small op costs a kernel launch)."""

    stack: Stack
    best_cost: jax.Array  # [] incumbent cost (+inf: none yet)
    book: jax.Array  # [4 + (N + 1) + N] int32: size, nodes, iterations, flags, level_base, best_path

    # flags: the error bits of firhc_jax.nodes. level_base[d]: stack size below the
    # live peer batch of depth d (at most one per depth is live). best_path: the incumbent.
    @property
    def size(self):
        return self.book[0]


def _book(size, nodes, iterations, flags, level_base, best_path):
    return jnp.concatenate([jnp.stack([size, nodes, iterations, flags]).astype(jnp.int32),
                            level_base.astype(jnp.int32), best_path.astype(jnp.int32)])


def stack_capacity(horizon: int, num_controls: int, pop_width: int) -> int:
    """Largest number of live nodes the stack can hold (see module docstring)."""
    return max(1, (horizon - 1) * pop_width * (num_controls - 1) + pop_width)


def stack_memory(problem: Problem, n: int, itemsize: int, pop_width: int = 1) -> int:
    """Estimated peak bytes of one sDFS: its stack (sentinels, live nodes and a
    push block, ``n + 3 + N`` numbers a row, twice for the loop's buffers) and
    one iteration's ``K M`` children."""
    N, M, K = problem.horizon, problem.num_controls, pop_width
    L, width = K * M, n + 3 + N
    return itemsize * (2 * (K + stack_capacity(N, M, K) + L) * width + 4 * L * width)


def check_memory(need: int, max_memory, what: str) -> int:
    """Refuse (``ValueError``) a search whose estimated bytes exceed ``max_memory``."""
    max_memory = positive_int("max_memory", max_memory)
    if need > max_memory:
        raise ValueError(f"{what} needs about {need:,} bytes, more than max_memory={max_memory:,}; "
                         "shorten the horizon, lower pop_width, or raise max_memory")
    return max_memory


def node_budget(max_nodes):
    """``max_nodes`` (None: unlimited) as an int32 argument of the compiled
    search (traced, so budgets never recompile; a NumPy scalar costs no device
    array per call)."""
    if max_nodes is None:
        return np.int32(INT32_MAX)
    if is_tracer(max_nodes):
        return jnp.asarray(max_nodes, jnp.int32)
    return np.int32(min(positive_int("max_nodes", max_nodes), INT32_MAX))


def _descending_order(key, keep):
    """Order of ``L`` children in a sorted push block.

    Kept children take slots ``0 .. count-1`` by descending key (the cheapest,
    and among equal keys the lowest index, in the top slot, popped first); the
    others fill the slots above. Returns ``(order, count)``: ``order[s]`` is the
    child in slot ``s``. One stable ``lax.sort`` (a pairwise ranking let XLA
    recompute child costs per comparison and gave wrong orders under fusion,
    docs/xla_notes.md).
    """
    idx = jnp.arange(key.shape[0] - 1, -1, -1, dtype=jnp.int32)  # reversed: a stable sort then puts
    k = jnp.where(keep, -key, jnp.inf)[idx]  # the higher index first (lower slot) among equal keys
    _, order = jax.lax.sort((k, idx), num_keys=1, is_stable=True)  # kept first, most expensive first
    return order, jnp.sum(keep, dtype=jnp.int32)


def _search(problem: Problem, x0, params, warm_start, budget, *, pop_width: int, prune: bool) -> SearchResult:
    N, M, K = problem.horizon, problem.num_controls, pop_width
    n, L = x0.shape[0], K * M
    dtype = cost_dtype(problem, x0, params)
    wide = jnp.promote_types(jnp.promote_types(dtype, x0.dtype), jnp.float32)  # lossless for every column
    inf = jnp.array(jnp.inf, dtype)
    capacity = K + stack_capacity(N, M, K) + L  # sentinels + live nodes + slack for the push block
    C, D, P = n, n + 1, n + 2  # columns: cost, key, depth; path from n + 3
    root = jnp.concatenate([x0.astype(wide), jnp.zeros((3 + N,), wide)])
    rows = jnp.zeros((capacity, n + 3 + N), wide).at[:, P].set(-1).at[K].set(root)
    stack = Stack(rows, jax.lax.dynamic_slice_in_dim(rows, 1, K))
    zero = jnp.array(0, jnp.int32)
    no_path = jnp.full((N,), -1, jnp.int32)
    best_cost, nodes, flags, path = inf, zero, zero, no_path
    if warm_start is not None:
        best_cost, flags = rollout_cost(problem, x0, warm_start, dtype, params)
        used = jnp.all((warm_start >= 0) & (warm_start < M))  # an all -1 warm start is no warm start
        nodes = jnp.where(used, N, 0).astype(jnp.int32)
        path = jnp.where(best_cost < inf, warm_start, no_path)
    carry = _Carry(stack, best_cost, _book(1, nodes, zero, flags, jnp.zeros((N + 1,), jnp.int32), path))
    limit = budget - L  # an iteration computes at most L children
    levels = jnp.arange(N + 1)
    modes = jnp.tile(jnp.arange(M, dtype=jnp.int32), K)  # [L] input of each child
    parent = jnp.repeat(jnp.arange(K, dtype=jnp.int32), M)  # [L] popped node of each child

    def body(c: _Carry) -> _Carry:
        s = c.stack
        old_size, nodes, iterations, flags = c.book[0], c.book[1], c.book[2], c.book[3]
        level_base, best_path = c.book[4:5 + N], c.book[5 + N:]
        popped = s.top  # [K, n + 3 + N]
        px, pc, pk = popped[:, :n].astype(x0.dtype), popped[:, C].astype(dtype), popped[:, D].astype(dtype)
        pd, ppath = popped[:, P].astype(jnp.int32), popped[:, P + 1:].astype(jnp.int32)
        depth = pd[K - 1]
        peer = pd == depth  # popped rows from the top batch (sentinels have depth -1)
        if prune:
            alive = peer & (pk < c.best_cost)
            # The batch is sorted: if its top is pruned, so is all the rest of it.
            size = jnp.where(alive[K - 1], old_size - jnp.sum(peer, dtype=jnp.int32), level_base[depth])
        else:
            alive = peer
            size = old_size - jnp.sum(peer, dtype=jnp.int32)

        child_depth = depth + 1
        ch = expand(problem, px, pc, params, steps_left=N - child_depth, check_terminal=problem.terminal is not None)
        ok = (alive[:, None] & ~ch.bad).reshape(L)
        cost, key = ch.cost.reshape(L), ch.key.reshape(L)

        leaf_cost, i, improve = best_leaf(cost, ch.terminal_ok.reshape(L), ok, child_depth == N, c.best_cost)
        best_cost = jnp.where(improve, leaf_cost, c.best_cost)
        best_path = jnp.where(improve, ppath[parent[i]].at[N - 1].set(modes[i]), best_path)

        # Non-leaves below the incumbent: one sorted batch on top of the stack.
        keep = ok & (child_depth < N) & ((key < best_cost) if prune else True)
        order, count = _descending_order(key, keep)
        child_path = jnp.where(jnp.arange(N)[None, :] == depth, modes[order][:, None], ppath[parent[order]])
        block = jnp.concatenate([ch.x.reshape(L, n)[order].astype(wide), cost[order, None].astype(wide),
                                 key[order, None].astype(wide), jnp.full((L, 1), child_depth, wide),
                                 child_path.astype(wide)], axis=1)
        rows = jax.lax.dynamic_update_slice_in_dim(s.rows, block, K + size, 0)
        top = jax.lax.dynamic_slice_in_dim(rows, size + count, K)
        met = jax.lax.reduce_or(jnp.where(alive[:, None], ch.flags, 0), axes=(0, 1))
        book = _book(size + count, nodes + M * jnp.sum(alive, dtype=jnp.int32), iterations + 1, flags | met,
                     jnp.where(levels == child_depth, size, level_base), best_path)
        return _Carry(Stack(rows, top), best_cost, book)

    out = jax.lax.while_loop(lambda c: (c.size > 0) & (c.book[1] <= limit), body, carry)
    nodes, iterations, flags, best_path = out.book[1], out.book[2], out.book[3], out.book[5 + N:]
    return finish(problem, out.best_cost, best_path, nodes, iterations, flags, out.size == 0)


def _check_warm_start(problem: Problem, warm_start):
    if warm_start is None:
        return None
    try:
        ws = warm_start if is_tracer(warm_start) else jnp.asarray(np.asarray(warm_start))
    except (TypeError, ValueError) as e:
        raise TypeError(f"warm_start must be [N] = [{problem.horizon}] integer indices into controls: {e}") from None
    if ws.shape != (problem.horizon,) or not jnp.issubdtype(ws.dtype, jnp.integer):
        raise ValueError(f"warm_start must be [N] = [{problem.horizon}] integer indices into controls, "
                         f"got shape {tuple(ws.shape)} dtype {ws.dtype}")
    if not is_tracer(ws):
        M = problem.num_controls
        if not (bool(jnp.all((ws >= 0) & (ws < M))) or bool(jnp.all(ws == -1))):
            raise ValueError(f"warm_start indices must lie in [0, {M}) (or be all -1: none), got {ws.tolist()}")
    return ws.astype(jnp.int32)


def _run(problem: Problem, x0, params, warm_start, max_nodes, pop_width, prune, max_memory) -> SearchResult:
    if not isinstance(problem, Problem):
        raise TypeError(f"problem must be a firhc_jax.Problem, got {type(problem).__name__}")
    pop_width = positive_int("pop_width", pop_width)
    refuse_differentiation(x0, params)
    if not prune and problem.tree_size() > INT32_MAX:
        raise ValueError(f"exhaustive search of M={problem.num_controls}, N={problem.horizon} has "
                         f"{problem.tree_size():,} nodes, more than the int32 node counter holds")
    params = check_params(params)
    x0 = check_state(problem, x0, params)
    check_memory(stack_memory(problem, x0.shape[0], max(x0.dtype.itemsize, 4), pop_width), max_memory,
                 f"the sDFS stack of N={problem.horizon}, M={problem.num_controls}, pop_width={pop_width}")
    ws = _check_warm_start(problem, warm_start)
    search = compiled(_search, problem, pop_width=pop_width, prune=prune)
    return raise_on_errors(search(x0, params, ws, node_budget(max_nodes)))


def sdfs(problem: Problem, x0, *, params=None, pop_width: int = 1, warm_start=None, max_nodes=None,
         max_memory: int = DEFAULT_MAX_MEMORY) -> SearchResult:
    """Exact optimal input sequence by sorted depth-first search.

    Args:
      problem: the ``Problem``.
      x0: ``[n]`` current state.
      params: optional parameter pytree passed to every callable as its last
        argument (see ``firhc_jax.problem``). New values of the same shapes and
        dtypes reuse the compiled search.
      pop_width: K, nodes popped and expanded per iteration (K * M children in
        one batched call). 1 is the paper's algorithm; larger K trades some
        pruning for fewer, wider iterations. Always exact.
      warm_start: optional ``[N]`` candidate sequence (e.g. the previous
        solution shifted by one step), evaluated first; if it meets the
        terminal test it is the initial incumbent. ``nodes`` counts its N
        nodes. All ``-1`` means none (no nodes counted).
      max_nodes: optional node budget (real-time use): the search stops before
        an iteration could compute more than ``max_nodes`` nodes in all and
        returns its incumbent with ``complete=False`` (infeasible if it has
        none yet). A traced value: changing it does not recompile.
      max_memory: bytes the stack may take (``stack_memory``); larger problems
        are refused before anything is allocated.

    Works under ``jax.jit`` and ``jax.vmap`` over ``x0`` and ``params``. In an
    un-jitted call a negative stage cost raises ``ValueError``. Not
    differentiable (a discrete search); see ``firhc_jax.nodes.rollout_cost``.
    """
    return _run(problem, x0, params, warm_start, max_nodes, pop_width, True, max_memory)


def exhaustive_dfs(problem: Problem, x0, *, params=None, pop_width: int = 1,
                   max_memory: int = DEFAULT_MAX_MEMORY) -> SearchResult:
    """Exhaustive search on the sDFS machinery with pruning switched off.

    Visits every node (``nodes == problem.tree_size()``); compare its time with
    ``sdfs`` to measure what pruning saves, like for like.
    """
    return _run(problem, x0, params, None, None, pop_width, False, max_memory)
