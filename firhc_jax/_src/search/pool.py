"""The shared work pool: many sDFS searches, one per row of a batch, on a
fixed number of slots, every slot's nodes expanded in one call per iteration.

A plain ``jax.vmap`` of ``fj.sdfs`` runs every row's loop until the slowest
row finishes, so with node counts that differ 10x or more between rows most
lanes idle. Instead the pool keeps ``lanes`` slots. A slot holds one sDFS
stack (``firhc_jax._src.search.stack``, the store of ``fj.sdfs``, vmapped over the
slots). Every iteration each slot pops the K next nodes of its deepest live
batch (cheapest first) and the children of all slots come from one call of
``expand``: ``lanes * K * M`` children per iteration. A slot whose row is
done takes the next row's root; once every row has started, an idle slot
steals the next node of the shallowest live batch below a busy slot's top
batch, so the last and largest searches are spread over all lanes. Each node
carries its row and is pruned against that row's incumbent, shared by every
slot working on the row: exact per row by the argument of ``fj.sdfs``
(non-negative stage costs), applied to each subtree. A row that is never
stolen from is searched in ``fj.sdfs``'s order, node for node (``lanes=1``
never steals).

One iteration is ``expand_and_store`` then ``plan`` and ``take``: the nodes
of the next iteration are taken out right after the stores, so that the
stacks are written, then read (XLA then updates them in place).
``iterations`` of a row counts the slot-iterations spent on it.

Memory: ``lanes * (N + 1) * K * M`` nodes whatever the number of rows
(``pool_memory``), plus ``pool_row_memory`` per row.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..problem.callables import cost_dtype
from ..problem.problem import Problem
from . import stack as stacks
from .nodes import SearchStats, expand, no_stats
from .result import SearchResult, finish
from .sdfs import seed, settle_children, stack_memory, start_incumbent
from .stack import Popped, Stack


class Rows(NamedTuple):
    """Per-row incumbents and counters, shared by every slot working on a row."""

    cost: jax.Array  # [B] incumbent cost (+inf: none yet)
    path: jax.Array  # [B, N] int32 incumbent sequence
    stats: SearchStats  # [B] fields: nodes, slot-iterations and error flags of each row
    cut: jax.Array  # [B] int32 times a slot dropped live nodes because the row's node budget ran out


class Pool(NamedTuple):
    """S slots, each an sDFS stack (``firhc_jax._src.search.stack``, rows 1 .. N - 1 used;
    row N takes leaf batches) working on one row of the batch."""

    stack: Stack  # [S, ...] fields
    row: jax.Array  # [S] int32 row of the batch each slot works or last worked on (B: none yet)


class Work(NamedTuple):
    """What each slot expands in the next iteration (taken out of the stacks
    at the end of the previous one, so that the stacks are written, then read,
    within an iteration: XLA updates them in place; docs/dev/xla_notes.md,
    "Pop right after the push")."""

    popped: Popped  # [S, K] fields: the nodes, cheapest first (expanded where below the row's incumbent)
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


def plan(pool: Pool, rows: Rows, head, n_valid, max_nodes, L: int, steal: bool = True, reserve=None
         ) -> tuple[Pool, Rows, jax.Array, Plan]:
    """Each slot's next nodes: the K next nodes of its deepest live batch. A
    slot with none takes the next row's root (``head``: the first row not yet
    started) or, once every row has started, steals the next node of the
    shallowest live batch below another slot's deepest one (exact: the row's
    incumbent is shared). Every slot expanding a row computes up to ``L``
    children: a row stops where its slots could take its node count above
    ``budget``, and is stolen from only while every slot could join it.
    ``reserve`` (``[B]`` or None): held back from a row's budget while the
    row has no incumbent (``fj.sdfs``'s rule). Returns the pool with
    re-assigned slots emptied."""
    S, D = pool.row.shape[0], pool.stack.low.shape[1]
    B = rows.cost.shape[0]
    if reserve is not None:
        max_nodes = max_nodes - jnp.where(rows.cost < jnp.inf, 0, reserve)
    depths = jnp.arange(D, dtype=jnp.int32)
    live = pool.stack.low < incumbent(rows, pool.row)[:, None]  # [S, D]
    busy = jnp.any(live, axis=1)
    sharing = jnp.zeros((B + 1,), jnp.int32).at[jnp.where(busy, pool.row, B)].add(1)  # busy slots per row
    nodes = rows.stats.nodes.at[pool.row].get(mode="fill", fill_value=0)  # [S] of each slot's row
    budget = max_nodes.at[pool.row].get(mode="fill", fill_value=0)  # [S] of each slot's row
    spent = nodes > budget - sharing[pool.row] * L  # [S] the row's budget is out
    rows = rows._replace(cut=rows.cut.at[jnp.where(spent & busy, pool.row, B)].add(1, mode="drop"))
    live = live & ~spent[:, None]
    top = jnp.max(jnp.where(live, depths, -1), axis=1)  # [S] deepest live batch
    free = top < 0
    roomy = nodes <= budget - (sharing[pool.row] + S) * L  # [S] room for every slot on the row
    stealable = live & roomy[:, None] & (depths < top[:, None]) & steal
    can = jnp.any(stealable, axis=1)
    ranks = jnp.cumsum(jnp.stack([free, can]), axis=1, dtype=jnp.int32) - 1  # one scan for both
    free_rank, can_rank = ranks[0], ranks[1]
    root = jnp.where(free & (head + free_rank < n_valid), head + free_rank, -1)
    # A row whose seeds (a budgeted search) left too little of its budget never starts.
    late = (root >= 0) & (rows.stats.nodes.at[root].get(mode="fill", fill_value=0)
                          > max_nodes.at[root].get(mode="fill", fill_value=0) - L)
    rows = rows._replace(cut=rows.cut.at[jnp.where(late, root, B)].add(1, mode="drop"))
    root = jnp.where(late, -1, root)
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


def take(pool: Pool, todo: Plan, X, K: int) -> tuple[Pool, Work]:
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
                    key=pick(popped.key, jnp.zeros_like(popped.key[:, 0]), given.key[v, 0]),
                    path=pick(popped.path, no_path, given.path[v, 0]))
    return pool._replace(stack=stack), Work(popped=popped, depth=todo.depth)


def expand_and_store(problem: Problem, pool: Pool, rows: Rows, work: Work, params) -> tuple[Pool, Rows]:
    """Expand every slot's nodes in one call of ``expand`` (with their rows'
    parameters), then each slot's step of ``fj.sdfs`` (``settle_children``,
    vmapped over the slots) against its row's incumbent: its cheapest
    feasible leaf may improve the row's incumbent, and the other children are
    pushed as the slot's batch one depth below."""
    N = problem.horizon
    (S, K, n), B = work.popped.x.shape, rows.cost.shape[0]
    row = pool.row
    p_nodes = jax.tree_util.tree_map(lambda a: jnp.repeat(a[jnp.minimum(row, B - 1)], K, axis=0), params)
    ch = expand(problem, work.popped.x.reshape(S * K, n), work.popped.cost.reshape(S * K), p_nodes,
                steps_left=jnp.repeat(N - work.depth - 1, K), check_terminal=problem.terminal is not None,
                params_batched=True)
    ch = jax.tree_util.tree_map(lambda a: a.reshape((S, K) + a.shape[1:]), ch)  # [S, K, M, ...]
    fresh = jax.vmap(lambda _: no_stats())(row)  # [S] fields: this iteration's counts per slot
    step = jax.vmap(functools.partial(settle_children, problem))(work.popped, work.depth, ch, incumbent(rows, row),
                                                                  fresh)

    new_cost = rows.cost.at[jnp.where(step.improve, row, B)].min(step.leaf_cost, mode="drop")
    winner = step.improve & (step.leaf_cost == new_cost.at[row].get(mode="fill", fill_value=jnp.inf))
    path = rows.path.at[jnp.where(winner, row, B)].set(step.leaf_path, mode="drop")  # [S, N] each slot's leaf
    put = jnp.where(work.depth >= 0, work.depth + 1, N)  # idle slots write nothing live into the leaf row
    stack = jax.vmap(stacks.push)(pool.stack, put, step.x.astype(work.popped.x.dtype), step.cost, step.key,
                                  work.popped.path)
    at = jnp.where(work.depth >= 0, row, B)

    def flag(old, met):  # or over the slots of each row (all of them set True: duplicates agree)
        return old.at[jnp.where(met, at, B)].set(True, mode="drop")

    stats = SearchStats(nodes=rows.stats.nodes.at[at].add(step.stats.nodes, mode="drop"),
                        iterations=rows.stats.iterations.at[at].add(step.stats.iterations, mode="drop"),
                        negative=flag(rows.stats.negative, step.stats.negative),
                        nonfinite=flag(rows.stats.nonfinite, step.stats.nonfinite),
                        overflow=flag(rows.stats.overflow, step.stats.overflow))
    return pool._replace(stack=stack), rows._replace(cost=new_cost, path=path, stats=stats)


def pool_search(problem: Problem, X, params, n_valid, max_nodes, lanes: int, pop_width: int,
                budgeted: bool = False, warm_start=None, steal: bool = True, reserve=None) -> SearchResult:
    """Exact sDFS of rows ``X[:n_valid]`` of ``[B, n]`` (with ``params[b]``
    for row b) on a pool of ``lanes`` slots. ``max_nodes``: ``[]`` or
    ``[B]``, each row's node budget: a row whose node count exceeds
    ``max_nodes - K M`` is not expanded further (it never starts when that is
    negative). ``warm_start`` ``[B, N]`` or ``[B, C, N]`` (optional): each
    row's candidates, evaluated first as ``fj.sdfs`` does. ``budgeted``: each
    row first gets ``fj.sdfs``'s seeds (``firhc_jax._src.search.sdfs.seed``,
    vmapped over the rows), within its budget. ``reserve`` (``[]``, ``[B]`` or
    None): held back from each row's budget while the row has no sequence, as
    in ``fj.sdfs``'s ``search``. ``steal``: see ``plan``. Returns a batched
    result."""
    N, M, K, S = problem.horizon, problem.num_controls, pop_width, lanes
    B = X.shape[0]
    dtype = cost_dtype(problem, X[0], params, batched_params=True)
    max_nodes = jnp.broadcast_to(jnp.asarray(max_nodes, jnp.int32), (B,))
    if reserve is not None:
        reserve = jnp.broadcast_to(jnp.asarray(reserve, jnp.int32), (B,))
    own = max_nodes if reserve is None else max_nodes - reserve  # each row's budget while it has no sequence
    one = stacks.init(N + 1, K, M, N, X[0], dtype)
    pool = Pool(stack=jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (S,) + a.shape), one)._replace(
        low=jnp.full((S, N + 1), jnp.inf, dtype)), row=jnp.full((S,), B, jnp.int32))
    # A budget below one expansion stops its row before the root, as fj.sdfs stops before an iteration could
    # take the count above it: no nodes, complete=False.
    cut = (max_nodes < K * M).astype(jnp.int32)
    start = jax.vmap(lambda x, p, w, b: start_incumbent(problem, x, p, w, b, dtype, budgeted=budgeted),
                     in_axes=(0, 0, None if warm_start is None else 0, 0))(X, params, warm_start, own)
    if budgeted:
        start = jax.vmap(lambda x, p, s, b: seed(problem, x, p, s, b, pop_width=K))(X, params, start, own)
    rows = Rows(cost=start.cost, path=start.path, stats=start.stats, cut=cut)

    def next_work(pool, rows, head):
        pool, rows, head, todo = plan(pool, rows, head, n_valid, max_nodes, K * M, steal, reserve)
        pool, work = take(pool, todo, X, K)
        return pool, rows, head, work

    def body(carry):
        pool, rows, head, work = carry
        pool, rows = expand_and_store(problem, pool, rows, work, params)
        return next_work(pool, rows, head)

    def more(carry):  # a slot has work, or rows are left to start (every free slot may have drawn a late row)
        return jnp.any(carry[3].depth >= 0) | (carry[2] < n_valid)

    carry = next_work(pool, rows, jnp.array(0, jnp.int32))
    _, rows, _, _ = jax.lax.while_loop(more, body, carry)
    return jax.vmap(lambda c, path, st, cut, x, p: finish(problem, c, path, st, cut == 0, x, p))(
        rows.cost, rows.path, rows.stats, rows.cut, X, params)
