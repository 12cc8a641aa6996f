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

Batches only ever sit on the batch they were expanded from, so depths grow
strictly from bottom to top and the stack never holds more than
``(N - 1) * K * (M - 1) + K`` live nodes: that is the fixed capacity.

Pruning is exact because stage costs are non-negative: a node whose
accumulated cost is not below the incumbent cannot lead to a cheaper leaf
(floating-point addition of non-negative numbers never decreases a sum).
With ``prune=False`` the same machinery visits the whole tree (exhaustive
depth-first search), so a time ratio between the two measures pruning alone.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .nodes import expand, rollout_cost
from .problem import Problem, check_state, cost_dtype
from .result import SearchResult, finish, raise_on_errors


class Stack(NamedTuple):
    """Fixed-capacity node stack. Rows ``[0, K)`` are sentinels (depth -1);
    live nodes occupy rows ``[K, K + size)``, top last.

    A node is one row of one floating buffer: state, accumulated cost, depth and
    path (small integers, exact in any float of at least 32 bits). One buffer
    means one dynamic slice to pop and one in-place update to push; with
    separate buffers XLA copies them every iteration to order the reads."""

    rows: jax.Array  # [R, n + 2 + N] x (n), cost, depth (root 0, sentinel -1), path from the root (N)
    top: jax.Array  # [K, n + 2 + N] copy of the top K rows, read right after each push so that the
    #                 buffer is only ever updated and then read (XLA then updates it in place, no copies)


class _Carry(NamedTuple):
    """Loop state. Every integer lives in one ``book`` vector, updated by one
    fused op per iteration (on CPU each separate small op costs a kernel launch)."""

    stack: Stack
    best_cost: jax.Array  # [] incumbent cost (+inf: none yet)
    book: jax.Array  # [4 + (N + 1) + N] int32: size, nodes, iterations, flags, level_base, best_path

    # flags: bit 0 a negative stage cost was met, bit 1 a NaN. level_base[d]: stack
    # size below the live peer batch of depth d (at most one per depth is live).
    # best_path: the incumbent sequence.
    @property
    def size(self):
        return self.book[0]


def _book(size, nodes, iterations, flags, level_base, best_path):
    return jnp.concatenate([jnp.stack([size, nodes, iterations, flags]).astype(jnp.int32),
                            level_base.astype(jnp.int32), best_path.astype(jnp.int32)])


def stack_capacity(horizon: int, num_controls: int, pop_width: int) -> int:
    """Largest number of live nodes the stack can hold (see module docstring)."""
    return max(1, (horizon - 1) * pop_width * (num_controls - 1) + pop_width)


def check_pop_width(pop_width) -> int:
    """``pop_width`` as an int >= 1, or a ValueError naming it (shared by the batched solvers)."""
    if isinstance(pop_width, bool) or not isinstance(pop_width, int) or pop_width < 1:
        raise ValueError(f"pop_width must be an int >= 1, got {pop_width!r}")
    return pop_width


def _descending_order(cost, keep):
    """Order of ``L`` children in a sorted push block.

    Kept children take slots ``0 .. count-1`` by descending cost (the cheapest,
    and among equal costs the lowest index, in the top slot, popped first); the
    others fill the slots above. Returns ``(order, count)``: ``order[s]`` is the
    child in slot ``s``.

    One ``lax.sort`` kernel, whose operands XLA materialises. A sort-free
    pairwise ranking was tried and dropped: XLA fuses the child-cost arithmetic
    into each of the ``L^2`` comparisons, which is slow for large ``L`` (4x at
    L = 136) and, worse, evaluated inconsistently across vectorised and scalar
    loop paths, so the ranks stopped being a permutation (wrong answers at
    pop_width 2, found by the property tests).
    """
    idx = jnp.arange(cost.shape[0] - 1, -1, -1, dtype=jnp.int32)  # reversed: a stable sort then puts
    key = jnp.where(keep, -cost, jnp.inf)[idx]  # the higher index first (lower slot) among equal costs
    _, order = jax.lax.sort((key, idx), num_keys=1, is_stable=True)  # kept first, most expensive first
    return order, jnp.sum(keep, dtype=jnp.int32)


def _search(problem: Problem, x0, warm_start, pop_width: int, prune: bool) -> SearchResult:
    N, M, K = problem.horizon, problem.num_controls, pop_width
    n, L = x0.shape[0], K * M
    dtype = cost_dtype(problem, x0)
    wide = jnp.promote_types(jnp.promote_types(dtype, x0.dtype), jnp.float32)  # lossless for every column
    inf = jnp.array(jnp.inf, dtype)
    capacity = K + stack_capacity(N, M, K) + L  # sentinels + live nodes + slack for the push block
    root = jnp.concatenate([x0.astype(wide), jnp.zeros((2 + N,), wide)])
    rows = jnp.zeros((capacity, n + 2 + N), wide).at[:, n + 1].set(-1).at[K].set(root)
    stack = Stack(rows, jax.lax.dynamic_slice_in_dim(rows, 1, K))
    zero = jnp.array(0, jnp.int32)
    no_path = jnp.full((N,), -1, jnp.int32)
    carry = _Carry(stack, inf, _book(1, zero, zero, zero, jnp.zeros((N + 1,), jnp.int32), no_path))
    if warm_start is not None:
        ws_cost, ws_neg, ws_nan = rollout_cost(problem, x0, warm_start, dtype)
        path = jnp.where(ws_cost < inf, warm_start, no_path)
        carry = _Carry(stack, ws_cost, _book(1, N, zero, _flags(ws_neg, ws_nan), jnp.zeros((N + 1,), jnp.int32),
                                             path))
    levels = jnp.arange(N + 1)
    modes = jnp.tile(jnp.arange(M, dtype=jnp.int32), K)  # [L] input of each child
    parent = jnp.repeat(jnp.arange(K, dtype=jnp.int32), M)  # [L] popped node of each child

    def body(c: _Carry) -> _Carry:
        s = c.stack
        old_size, nodes, iterations, flags = c.book[0], c.book[1], c.book[2], c.book[3]
        level_base, best_path = c.book[4:5 + N], c.book[5 + N:]
        popped = s.top  # [K, n + 2 + N]
        px, pc = popped[:, :n].astype(x0.dtype), popped[:, n].astype(dtype)
        pd, ppath = popped[:, n + 1].astype(jnp.int32), popped[:, n + 2:].astype(jnp.int32)
        depth = pd[K - 1]
        peer = pd == depth  # popped rows from the top batch (sentinels have depth -1)
        if prune:
            alive = peer & (pc < c.best_cost)
            # The batch is sorted: if its top is pruned, so is all the rest of it.
            size = jnp.where(alive[K - 1], old_size - jnp.sum(peer, dtype=jnp.int32), level_base[depth])
        else:
            alive = peer
            size = old_size - jnp.sum(peer, dtype=jnp.int32)

        ch = expand(problem, px, pc, check_terminal=problem.terminal is not None)
        ok = (alive[:, None] & ~ch.bad).reshape(L)
        cost = ch.cost.reshape(L)
        child_depth = depth + 1

        # Leaves: the cheapest feasible one below the incumbent (first in (pop, mode) order).
        leaf_cost = jnp.where(ok & ch.terminal_ok.reshape(L) & (child_depth == N), cost, inf)
        i = jnp.argmin(leaf_cost)
        improve = leaf_cost[i] < c.best_cost
        best_cost = jnp.where(improve, leaf_cost[i], c.best_cost)
        best_path = jnp.where(improve, ppath[parent[i]].at[N - 1].set(modes[i]), best_path)

        # Non-leaves below the incumbent: one sorted batch on top of the stack.
        keep = ok & (child_depth < N) & ((cost < best_cost) if prune else True)
        order, count = _descending_order(cost, keep)
        child_path = jnp.where(jnp.arange(N)[None, :] == depth, modes[order][:, None], ppath[parent[order]])
        block = jnp.concatenate([ch.x.reshape(L, n)[order].astype(wide), cost[order, None].astype(wide),
                                 jnp.full((L, 1), child_depth, wide), child_path.astype(wide)], axis=1)
        rows = jax.lax.dynamic_update_slice_in_dim(s.rows, block, K + size, 0)
        top = jax.lax.dynamic_slice_in_dim(rows, size + count, K)
        met = jnp.max(jnp.where(alive[:, None], _flags(ch.negative, ch.bad), 0))
        book = _book(size + count, nodes + M * jnp.sum(alive, dtype=jnp.int32), iterations + 1, flags | met,
                     jnp.where(levels == child_depth, size, level_base), best_path)
        return _Carry(Stack(rows, top), best_cost, book)

    out = jax.lax.while_loop(lambda c: c.size > 0, body, carry)
    nodes, iterations, flags, best_path = out.book[1], out.book[2], out.book[3], out.book[5 + N:]
    return finish(problem.controls, out.best_cost, best_path, nodes, iterations, (flags & 1) > 0, (flags & 2) > 0)


def _flags(negative, nan):
    return negative.astype(jnp.int32) | (nan.astype(jnp.int32) << 1)


_search_jit = jax.jit(_search, static_argnames=("pop_width", "prune"))


def _check_warm_start(problem: Problem, warm_start):
    if warm_start is None:
        return None
    ws = warm_start if isinstance(warm_start, jax.core.Tracer) else jnp.asarray(warm_start)
    if ws.shape != (problem.horizon,) or not jnp.issubdtype(ws.dtype, jnp.integer):
        raise ValueError(f"warm_start must be [N] = [{problem.horizon}] integer indices into controls, "
                         f"got shape {tuple(ws.shape)} dtype {ws.dtype}")
    if not isinstance(ws, jax.core.Tracer):
        M = problem.num_controls
        if bool(jnp.any((ws < 0) | (ws >= M))):
            raise ValueError(f"warm_start indices must lie in [0, {M}), got {ws.tolist()}")
    return ws.astype(jnp.int32)


def sdfs(problem: Problem, x0, *, pop_width: int = 1, warm_start=None) -> SearchResult:
    """Exact optimal input sequence by sorted depth-first search.

    Args:
      problem: the ``Problem``.
      x0: ``[n]`` current state.
      pop_width: K, nodes popped and expanded per iteration (K * M children in
        one batched call). 1 is the paper's algorithm; larger K trades some
        pruning for fewer, wider iterations. Always exact.
      warm_start: optional ``[N]`` candidate sequence (e.g. the previous
        solution shifted by one step), evaluated first; if it meets the
        terminal test it is the initial incumbent. ``nodes`` counts its N nodes.

    Works under ``jax.jit`` and ``jax.vmap`` over ``x0``. In an un-jitted call
    a negative stage cost raises ``ValueError``.
    """
    pop_width = check_pop_width(pop_width)
    x0 = check_state(problem, x0)
    ws = _check_warm_start(problem, warm_start)
    return raise_on_errors(_search_jit(problem, x0, ws, pop_width=pop_width, prune=True))


def exhaustive_dfs(problem: Problem, x0, *, pop_width: int = 1) -> SearchResult:
    """Exhaustive search on the sDFS machinery with pruning switched off.

    Visits every node (``nodes == problem.tree_size()``); compare its time with
    ``sdfs`` to measure what pruning saves, like for like.
    """
    pop_width = check_pop_width(pop_width)
    x0 = check_state(problem, x0)
    return raise_on_errors(_search_jit(problem, x0, None, pop_width=pop_width, prune=False))
