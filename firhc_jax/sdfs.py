"""Sorted depth-first search (the paper's Table 1) as one compiled while-loop.

Each iteration takes the ``K = pop_width`` cheapest remaining nodes of the
deepest live peer batch (``K = 1`` is Table 1 exactly), expands all their
``K * M`` children in one vmapped call, lets feasible leaves improve the
incumbent, and pushes the other children, as one batch, one depth lower
(``firhc_jax.stack``). Peers are never sorted: popping takes the cheapest
remaining node (ties: the lowest input index, the order of a stable sort), so
the nodes come out in Table 1's order. Once a batch's cheapest remaining node
is no cheaper than the incumbent, the rest of the batch is dropped at once
(Table 1 would pop and skip them one by one; the node count, which counts
computed children only, is the same).

"Cheaper" compares a node's *key*: its accumulated cost, plus, when the
problem has a ``lower_bound``, the bound on the cost still to come. Peers are
ordered by the same key. Without a bound this is the paper's algorithm node
for node; with an admissible bound it prunes more and stays exact.

Pruning is exact because stage costs are non-negative: a node whose key is not
below the incumbent cannot lead to a cheaper leaf (floating-point addition of
non-negative numbers never decreases a sum). With ``prune=False`` the same
machinery visits the whole tree (exhaustive depth-first search), so a time
ratio between the two measures pruning alone.

Memory: one batch per depth, ``(N + 1) K M`` nodes (``stack_memory``; larger
stacks are refused up front). ``iterations`` counts loop iterations, one
batched call of ``dynamics`` each (``SearchResult.iterations`` for the other
solvers). ``max_nodes`` stops the loop before an iteration could take the
node count above it; the result then holds the incumbent found so far and
``complete=False``.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .cache import compiled
from .checks import check_params, check_state, cost_dtype
from . import stack as stacks
from .nodes import SearchStats, best_leaf, expand, no_stats, rollout_cost, tally
from .problem import Problem, is_tracer, positive_int, refuse_differentiation
from .result import SearchResult, finish, raise_on_errors
from .stack import Popped, Stack

INT32_MAX = 2**31 - 1
DEFAULT_MAX_MEMORY = 1 << 30  # bytes


class _Carry(NamedTuple):
    """Loop state. The nodes to expand are popped at the end of the previous
    iteration, right after the push: the stack's buffers are then only ever
    written and then read within an iteration, which XLA updates in place
    (read first, and it copies every buffer each iteration; docs/xla_notes.md,
    "Pop right after the push")."""

    stack: Stack
    popped: Popped  # the K nodes to expand next
    row: jax.Array  # [] int32 the row they came from (-1: none; the search is over)
    best_cost: jax.Array  # [] incumbent cost (+inf: none yet)
    best_path: jax.Array  # [N] int32 incumbent sequence
    stats: SearchStats


def stack_memory(problem: Problem, n: int, itemsize: int, pop_width: int = 1) -> int:
    """Estimated peak bytes of one sDFS: its stack (``N + 1`` rows of ``K M``
    nodes, ``n + 2`` numbers each, twice for the loop's buffers, plus the
    parents' paths) and one iteration's ``K M`` children."""
    N, M, K = problem.horizon, problem.num_controls, pop_width
    L = K * M
    return itemsize * (2 * (N + 1) * L * (n + 2) + 4 * L * (n + 2)) + 4 * 2 * (N + 1) * K * N


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


class Settled(NamedTuple):
    """One iteration's outcome for one stack (``settle_children``)."""

    x: jax.Array  # [L, n] children: the batch to push one depth below
    cost: jax.Array  # [L] accumulated costs
    key: jax.Array  # [L] keys; +inf: never to expand (a leaf, a bad child, a dead parent's, not below the incumbent)
    leaf_cost: jax.Array  # [] cheapest usable feasible leaf (+inf: none)
    leaf_path: jax.Array  # [N] int32 its sequence
    improve: jax.Array  # [] bool it is strictly cheaper than the incumbent
    stats: SearchStats  # the counters with this iteration added


def settle_children(problem: Problem, popped: Popped, row, children, best_cost, stats: SearchStats, *,
                    prune: bool = True) -> Settled:
    """Best leaf and the batch to push: the rest of every sDFS iteration after
    ``expand``, here and in each slot of the batch pool (``firhc_jax.pool``,
    vmapped over the slots).

    ``children`` (``[K, M]`` fields) are those of the nodes ``popped`` ``[K]``
    from depth ``row``; only the nodes whose key is below the incumbent
    ``best_cost`` count (all of them with ``prune=False``). The cheapest usable
    feasible leaf improves the incumbent when strictly cheaper; the other
    children are the batch to push at depth ``row + 1``."""
    N, M = problem.horizon, problem.num_controls
    K, n = popped.x.shape
    L = K * M
    bound = best_cost if prune else jnp.inf  # without pruning, only taken nodes leave the stack
    alive = popped.key < bound  # [K]
    depth = row + 1  # of the children
    ok = (alive[:, None] & ~children.bad).reshape(L)
    cost, key = children.cost.reshape(L), children.key.reshape(L)
    leaf_cost, i, improve = best_leaf(cost, children.terminal_ok.reshape(L), ok, depth == N, best_cost)
    if prune:
        bound = jnp.where(improve, leaf_cost, bound)
    keep = ok & (depth < N) & (key < bound)
    return Settled(x=children.x.reshape(L, n), cost=cost, key=jnp.where(keep, key, jnp.inf), leaf_cost=leaf_cost,
                   leaf_path=stacks.child_path(popped.path, row, M, i), improve=improve,
                   stats=tally(stats, children, alive))


def _search(problem: Problem, x0, params, warm_start, budget, *, pop_width: int, prune: bool) -> SearchResult:
    N, M, K = problem.horizon, problem.num_controls, pop_width
    L = K * M
    dtype = cost_dtype(problem, x0, params)
    inf = jnp.array(jnp.inf, dtype)
    # Rows 0 .. N - 1 hold the batches of depth 0 (the root) to N - 1; row N
    # takes each leaf batch, all discarded, so every iteration pushes.
    stack = stacks.init(N + 1, K, M, N, x0, dtype)
    best_cost, best_path, stats = inf, jnp.full((N,), -1, jnp.int32), no_stats()
    if warm_start is not None:
        cost, flags = rollout_cost(problem, x0, warm_start, dtype, params)
        # An all -1 warm start is no warm start; one whose N nodes do not fit in the budget is not evaluated.
        used = jnp.all((warm_start >= 0) & (warm_start < M)) & (N <= budget)
        best_cost = jnp.where(used, cost, inf)
        stats = no_stats(jnp.where(used, N, 0), jnp.where(used, flags, 0))
        best_path = jnp.where(best_cost < inf, warm_start, best_path)
    limit = budget - L  # an iteration computes at most L children

    def incumbent(best_cost):
        return best_cost if prune else inf  # without pruning, only taken nodes leave the stack

    def next_nodes(stack, best_cost):
        row = stacks.top(stack, incumbent(best_cost))
        stack, popped = stacks.pop(stack, row, K)
        return stack, popped, row

    def body(c: _Carry) -> _Carry:
        ch = expand(problem, c.popped.x, c.popped.cost, params, steps_left=N - c.row - 1,
                    check_terminal=problem.terminal is not None)
        step = settle_children(problem, c.popped, c.row, ch, c.best_cost, c.stats, prune=prune)
        best_cost = jnp.where(step.improve, step.leaf_cost, c.best_cost)
        best_path = jnp.where(step.improve, step.leaf_path, c.best_path)
        stack = stacks.push(c.stack, c.row + 1, step.x.astype(x0.dtype), step.cost, step.key, c.popped.path)
        return _Carry(*next_nodes(stack, best_cost), best_cost, best_path, step.stats)

    carry = _Carry(*next_nodes(stack, best_cost), best_cost, best_path, stats)
    out = jax.lax.while_loop(lambda c: (c.row >= 0) & (c.stats.nodes <= limit), body, carry)
    return finish(problem, out.best_cost, out.best_path, out.stats, out.row < 0, x0, params)


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
        nodes. All ``-1`` means none (no nodes counted); so does a
        ``max_nodes`` below N (its nodes would not fit in the budget).
      max_nodes: optional node budget (real-time use): ``nodes <= max_nodes``
        always (a warm start's N nodes included). The search stops before an
        iteration could take the count above it and returns its incumbent
        with ``complete=False`` (infeasible if it has none yet). A traced
        value: changing it does not recompile.
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

    Visits every node (``nodes == problem.tree_size()``) whatever the problem's
    ``lower_bound`` says (it is not used: a ``+inf`` bound would otherwise keep
    nodes off the stack); compare its time with ``sdfs`` to measure what
    pruning saves, like for like.
    """
    return _run(problem.replace(lower_bound=None), x0, params, None, None, pop_width, False, max_memory)
