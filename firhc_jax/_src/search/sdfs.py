"""Sorted depth-first search (the paper's Table 1) as one compiled while-loop.

Each iteration takes the ``K = pop_width`` cheapest remaining nodes of the
deepest live peer batch (``K = 1`` is Table 1 exactly), expands all their
``K * M`` children in one vmapped call, lets feasible leaves improve the
incumbent, and pushes the other children, as one batch, one depth lower
(``firhc_jax._src.search.stack``). Peers are never sorted: popping takes the cheapest
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
``complete=False``. A budgeted search first seeds its incumbent by iterative
deepening over the horizon (``seed``, docs/guide/budgets.md), within half the
budget.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..checks import is_tracer, positive_int
from ..problem.callables import cost_dtype
from ..problem.problem import Problem, call
from . import stack as stacks
from .nodes import SearchStats, best_leaf, expand, first_min, no_stats, one_child, rollout_cost, tally
from .result import SearchResult, finish
from .stack import Popped, Stack

INT32_MAX = 2**31 - 1
DEFAULT_MAX_MEMORY = 1 << 30  # bytes


class _Carry(NamedTuple):
    """Loop state. The nodes to expand are popped at the end of the previous
    iteration, right after the push: the stack's buffers are then only ever
    written and then read within an iteration, which XLA updates in place
    (read first, and it copies every buffer each iteration; docs/dev/xla_notes.md,
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
                    prune: bool = True, leaf_depth=None) -> Settled:
    """Best leaf and the batch to push: the rest of every sDFS iteration after
    ``expand``, here and in each slot of the batch pool (``firhc_jax._src.search.pool``,
    vmapped over the slots).

    ``children`` (``[K, M]`` fields) are those of the nodes ``popped`` ``[K]``
    from depth ``row``; only the nodes whose key is below the incumbent
    ``best_cost`` count (all of them with ``prune=False``). The cheapest usable
    feasible leaf improves the incumbent when strictly cheaper; the other
    children are the batch to push at depth ``row + 1``. Leaves lie at depth
    ``leaf_depth`` (default N; the seeds' shorter problems pass their own)."""
    N, M = problem.horizon, problem.num_controls
    leaf_depth = N if leaf_depth is None else leaf_depth
    K, n = popped.x.shape
    L = K * M
    bound = best_cost if prune else jnp.inf  # without pruning, only taken nodes leave the stack
    alive = popped.key < bound  # [K]
    depth = row + 1  # of the children
    ok = (alive[:, None] & ~children.bad).reshape(L)
    cost, key = children.cost.reshape(L), children.key.reshape(L)
    leaf_cost, i, improve = best_leaf(cost, children.terminal_ok.reshape(L), ok, depth == leaf_depth, best_cost)
    if prune:
        bound = jnp.where(improve, leaf_cost, bound)
    keep = ok & (depth < leaf_depth) & (key < bound)
    return Settled(x=children.x.reshape(L, n), cost=cost, key=jnp.where(keep, key, jnp.inf), leaf_cost=leaf_cost,
                   leaf_path=stacks.child_path(popped.path, row, M, i), improve=improve,
                   stats=tally(stats, children, alive))


class Incumbent(NamedTuple):
    """The best complete sequence so far and the counters behind it."""

    cost: jax.Array  # [] +inf: none yet
    path: jax.Array  # [N] int32
    stats: SearchStats


def _dfs(problem: Problem, x0, params, start: Incumbent, limit, *, pop_width: int, prune: bool = True,
         leaf_depth=None, leaves=None, reserve=None) -> tuple[Incumbent, jax.Array]:
    """The sorted DFS from the root ``x0`` with a first incumbent ``start``,
    while the node count stays at most ``limit`` before an iteration (``limit
    - reserve`` while there is no incumbent: ``search``'s reserve). Returns
    the incumbent and whether the search ran to the end. ``leaf_depth`` and
    ``leaves(children, depth) -> children`` serve the seeds' shorter problems
    (``seed``); the main search leaves them None."""
    N, M, K = problem.horizon, problem.num_controls, pop_width
    # Rows 0 .. N - 1 hold the batches of depth 0 (the root) to N - 1; row N
    # takes each leaf batch, all discarded, so every iteration pushes.
    stack = stacks.init(N + 1, K, M, N, x0, start.cost.dtype)

    def incumbent(best_cost):
        return best_cost if prune else jnp.inf  # without pruning, only taken nodes leave the stack

    def next_nodes(stack, best_cost):
        row = stacks.top(stack, incumbent(best_cost))
        stack, popped = stacks.pop(stack, row, K)
        return stack, popped, row

    def body(c: _Carry) -> _Carry:
        ch = expand(problem, c.popped.x, c.popped.cost, params, steps_left=N - c.row - 1,
                    check_terminal=problem.terminal is not None)
        if leaves is not None:
            ch = leaves(ch, c.row + 1)
        step = settle_children(problem, c.popped, c.row, ch, c.best_cost, c.stats, prune=prune,
                               leaf_depth=leaf_depth)
        best_cost = jnp.where(step.improve, step.leaf_cost, c.best_cost)
        best_path = jnp.where(step.improve, step.leaf_path, c.best_path)
        stack = stacks.push(c.stack, c.row + 1, step.x.astype(x0.dtype), step.cost, step.key, c.popped.path)
        return _Carry(*next_nodes(stack, best_cost), best_cost, best_path, step.stats)

    def more(c: _Carry):
        room = limit if reserve is None else limit - jnp.where(c.best_cost < jnp.inf, 0, reserve)
        return (c.row >= 0) & (c.stats.nodes <= room)

    carry = _Carry(*next_nodes(stack, start.cost), start.cost, start.path, start.stats)
    out = jax.lax.while_loop(more, body, carry)
    return Incumbent(out.best_cost, out.best_path, out.stats), out.row < 0


def _rollout(problem: Problem, x0, params, prefix, length, start: Incumbent) -> Incumbent:
    """``prefix[:length]`` extended to the horizon by the greedy rule: at each
    later step the child with the smallest cost plus ``lower_bound`` plus
    ``terminal_cost`` (the value of the state reached, where the problem has
    one; the last step's cost holds it already) among those the constraints
    allow and the bound does not rule out (at the last step: that meet the
    terminal test). The prefix is replayed one node a step, under the rules of
    every search (constraints, finite states; the terminal test and cost when
    it is the whole horizon); every later step expands one node (M children).
    Costs accumulate as in every search. Returns the cheaper of ``start`` and
    the extension (+inf if it dead-ends or the prefix breaks a rule)."""
    N = problem.horizon
    controls = jnp.asarray(problem.controls)

    def replay(carry, k):
        x, cost, ok, path, stats = carry
        x, s, allowed = one_child(problem, x, controls[prefix[k]], k, params)
        s = s.astype(cost.dtype)
        if problem.terminal_cost is not None:
            s = s + jnp.where(k == N - 1, call(problem.terminal_cost, params, x), 0).astype(cost.dtype)
        total = cost + s
        nonfinite = jnp.isnan(total) | jnp.any(~jnp.isfinite(x))
        met = ok & allowed  # flags as the search raises them: not for children a constraint discards
        overflow = jnp.isinf(total) & jnp.isfinite(cost) & jnp.isfinite(s)
        stats = stats._replace(nodes=stats.nodes + 1, negative=stats.negative | (met & (s < 0)),
                               nonfinite=stats.nonfinite | (met & nonfinite),
                               overflow=stats.overflow | (met & overflow))
        return x, total, met & ~nonfinite, path.at[k].set(prefix[k]), stats

    def greedy(carry, k):
        x, cost, ok, path, stats = carry
        ch = expand(problem, x[None], cost[None], params, steps_left=N - 1 - k,
                    check_terminal=problem.terminal is not None)
        usable = ~ch.bad[0] & ((k < N - 1) | ch.terminal_ok[0])
        key = jnp.where(usable, ch.key[0], jnp.inf)
        score = key
        if problem.terminal_cost is not None:  # the leaves' (k = N - 1) already holds it
            score = key + jnp.where(k < N - 1, jax.vmap(lambda xi: call(problem.terminal_cost, params, xi))(ch.x[0]),
                                    0).astype(key.dtype)
        i = first_min(score)[1]
        return (ch.x[0, i], ch.cost[0, i], ok & jnp.isfinite(key[i]), path.at[k].set(i),
                tally(stats, ch, jnp.ones((1,), bool)))

    def step(carry, k):
        return jax.lax.cond(k < length, replay, greedy, carry, k), None

    init = (x0, jnp.zeros((), start.cost.dtype), jnp.ones((), bool), jnp.full((N,), -1, jnp.int32), start.stats)
    (x, cost, ok, path, stats), _ = jax.lax.scan(step, init, jnp.arange(N, dtype=jnp.int32))
    if problem.terminal is not None:  # a whole-horizon replay meets the terminal test too (greedy's last step did)
        ok = ok & ((length < N) | call(problem.terminal, params, x))
    cost = jnp.where(ok, cost, jnp.inf)
    better = cost < start.cost
    return Incumbent(jnp.where(better, cost, start.cost), jnp.where(better, path, start.path), stats)


def seed(problem: Problem, x0, params, start: Incumbent, max_nodes, *, pop_width: int) -> Incumbent:
    """First incumbents for a budgeted search, by iterative deepening: for
    ``D = 1, 2, ...`` the exact problem of horizon D (stage costs of steps
    ``0 .. D-1`` plus the terminal cost at ``x(D)``, no terminal test; the
    constraints hold, and a node from which the ``lower_bound`` is +inf, the
    terminal set out of reach, is discarded) is solved by sDFS, and its
    sequence extended to N by ``_rollout`` seeds the search when cheaper than
    the incumbent. The seeds take at most half the budget (each level stops
    where the next node could leave no room for its extension), and none run
    where that half holds less than level 1 whole, its extension and one
    expansion (``M + N M + K M`` nodes: half of ``B(1)``, the least budget
    that guarantees anything): deepening stops after ``D = N - 1`` or at the
    first level stopped (its best so far is still extended).
    docs/guide/budgets.md states what this guarantees."""
    N, M, K = problem.horizon, problem.num_controls, pop_width
    L = K * M
    level = problem.replace(terminal=None, terminal_cost=None, lower_bound=None)
    share = jnp.asarray(max_nodes) // 2  # the seeds take at most half the budget; the full problem the rest
    none = jnp.full((N,), -1, jnp.int32)
    inf = jnp.array(jnp.inf, start.cost.dtype)

    def leaves(depth_of_leaves):
        def fn(ch, depth):
            at = jnp.broadcast_to(depth == depth_of_leaves, ch.cost.shape)
            extra = jnp.zeros_like(ch.cost)
            if problem.terminal_cost is not None:
                extra = jax.vmap(jax.vmap(lambda xi: call(problem.terminal_cost, params, xi)))(ch.x)
            bad = ch.bad
            if problem.lower_bound is not None:  # ruled out: no completion meets the terminal set
                rest = jax.vmap(jax.vmap(lambda xi: call(problem.lower_bound, params, xi, N - depth)))(ch.x)
                bad = bad | (rest == jnp.inf)
            extra = jnp.where(at, extra.astype(ch.cost.dtype), 0)
            return ch._replace(cost=ch.cost + extra, key=ch.key + extra, bad=bad)
        return fn

    def body(c):
        D, best, _ = c
        found, done = _dfs(level, x0, params, Incumbent(inf, none, best.stats), share - N * M - L, pop_width=K,
                           leaf_depth=D, leaves=leaves(D))  # leaves room for its extension
        fits = (found.cost < inf) & (found.stats.nodes + N * M <= max_nodes)
        best = best._replace(stats=found.stats)
        best = jax.lax.cond(fits, lambda: _rollout(problem, x0, params, found.path, D, best), lambda: best)
        return D + 1, best, done

    def more(c):  # no seeds where half the budget does not hold level 1, its extension and an expansion
        D, best, done = c
        return done & (D < N) & (best.stats.nodes <= share - N * M - L) & (share >= M + N * M + L)

    _, best, _ = jax.lax.while_loop(more, body, (jnp.ones((), jnp.int32), start, jnp.ones((), bool)))
    return best


def _prefix_length(sequence):
    """[] int32 the leading entries of ``sequence`` ``[N]`` that are input indices (the rest: -1)."""
    return jnp.sum(jnp.cumprod(sequence >= 0), dtype=jnp.int32)


def start_incumbent(problem: Problem, x0, params, warm_start, max_nodes, dtype, *, budgeted: bool = False
                    ) -> Incumbent:
    """The first incumbent: none, or the cheapest feasible candidate of ``warm_start`` (``[N]`` or ``[C, N]``,
    evaluated in order, each only where its nodes fit in ``max_nodes`` with those before it). A candidate is a
    sequence; all -1 is none. In a ``budgeted`` search a candidate may also be a prefix followed by -1: the
    prefix is completed to the horizon by the greedy rollout (``_rollout``: ``k + (N - k) M`` nodes for a
    prefix of k); unbudgeted, such a candidate is not evaluated."""
    N, M = problem.horizon, problem.num_controls
    start = Incumbent(jnp.array(jnp.inf, dtype), jnp.full((N,), -1, jnp.int32), no_stats())
    if warm_start is None:
        return start
    for candidate in jnp.reshape(warm_start, (-1, N)):
        if budgeted:
            k = _prefix_length(candidate)
            fits = (k > 0) & (start.stats.nodes + k + (N - k) * M <= max_nodes)
            start = jax.lax.cond(fits, lambda s, w=candidate, k=k: _rollout(problem, x0, params, w, k, s),
                                 lambda s: s, start)
            continue
        cost, flags = rollout_cost(problem, x0, candidate, dtype, params)
        used = jnp.all((candidate >= 0) & (candidate < M)) & (start.stats.nodes + N <= max_nodes)
        better = used & (cost < start.cost)
        spent = no_stats(jnp.where(used, N, 0), jnp.where(used, flags, 0))
        start = Incumbent(jnp.where(better, cost, start.cost), jnp.where(better, candidate, start.path),
                          SearchStats(start.stats.nodes + spent.nodes, start.stats.iterations,
                                      *(a | b for a, b in zip(start.stats[2:], spent[2:], strict=True))))
    return start


def search(problem: Problem, x0, params, warm_start, max_nodes, *, pop_width: int = 1, prune: bool = True,
           budgeted: bool = False, reserve=None, **_) -> SearchResult:
    """The sorted search, traced: the ``search`` of the solver table (``firhc_jax.solvers``). ``max_nodes``
    ``[]`` int32 (``INT32_MAX``: none); ``budgeted`` (static): seed the incumbent first (``seed``);
    ``reserve`` (``[]`` int32, or None: 0): nodes of ``max_nodes`` held back while the search has no
    sequence (a controller's fallback gets them): until it has one, the warm start, the seeds and the search
    stay within ``max_nodes - reserve``."""
    K = pop_width
    L = K * problem.num_controls
    own = max_nodes if reserve is None else max_nodes - reserve
    start = start_incumbent(problem, x0, params, warm_start, own, cost_dtype(problem, x0, params), budgeted=budgeted)
    if budgeted:
        start = seed(problem, x0, params, start, own, pop_width=K)
    # An iteration computes at most L children.
    out, done = _dfs(problem, x0, params, start, max_nodes - L, pop_width=K, prune=prune, reserve=reserve)
    return finish(problem, out.cost, out.path, out.stats, done, x0, params)
