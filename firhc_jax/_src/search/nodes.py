"""Node expansion shared by every search: all children of a batch of nodes in
one vmapped call of ``dynamics`` and ``stage_cost``, and the two rules every
search applies to them.

A child's cost is ``parent_cost + stage_cost(x_child, u[, k])``, plus
``terminal_cost(x_child)`` at depth N, always accumulated in this one place
(``expand`` and ``rollout_cost``), so a sequence gets the same
cost in every search as long as ``dynamics`` and ``stage_cost`` evaluate the
same way at every batch size (elementwise code does; a batched matmul may
round differently in the last bit, see README).
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.typing import DTypeLike

from ..annotations import ArrayLike, PyTree
from ..problem.callables import cost_dtype as dtype_of_cost
from ..problem.problem import Problem, call

# Error flags, as bits of one int32 (combined with |).
NEGATIVE, NONFINITE, OVERFLOW = 1, 2, 4


class Children(NamedTuple):
    x: jax.Array  # [B, M, n] child states
    cost: jax.Array  # [B, M] accumulated costs
    key: jax.Array  # [B, M] cost + lower bound of the rest (= cost without a bound): the order and the pruning test
    bad: jax.Array  # [B, M] bool non-finite state, NaN cost or constraint violated: never expanded, never a solution
    flags: jax.Array  # [B, M] int32 error flags (NEGATIVE | NONFINITE | OVERFLOW)
    terminal_ok: jax.Array  # [B, M] bool terminal(x_child) (True if unconstrained)


def one_child(problem: Problem, x, u, k, p):
    """``(x_next, stage cost, constraint met)`` of input ``u`` at step ``k``."""
    x_next = problem.next_state(x, u, k, p)
    return x_next, problem.cost_of_step(x, x_next, u, k, p), problem.allowed(x, x_next, u, k, p)


def _terminal_cost(problem: Problem, xs, at_leaf, p_axis, params):
    """``terminal_cost`` of the children ``[B, M, n]`` where ``at_leaf`` ``[B]``, else 0."""
    if problem.terminal_cost is None:
        return 0
    g = jax.vmap(jax.vmap(lambda xi, p: call(problem.terminal_cost, p, xi), in_axes=(0, None)),
                 in_axes=(0, p_axis))(xs, params)
    return jnp.where(at_leaf[:, None], g, 0)


def expand(problem: Problem, x, cost, params, *, steps_left, check_terminal: bool,
           params_batched: bool = False) -> Children:
    """Children of ``B`` nodes: ``x`` ``[B, n]``, ``cost`` ``[B]`` -> ``Children``.

    ``params``: one parameter pytree for all nodes, or (``params_batched``) one
    per node (leading axis B). ``steps_left`` (int, or int32 ``[B]``): steps
    still to come after the children, for the lower bound; the children's
    input has step index ``N - 1 - steps_left`` and at ``steps_left == 0`` they
    are leaves, which pay the terminal cost. ``check_terminal`` evaluates the
    terminal test (only needed at depth N).
    """
    N, B = problem.horizon, x.shape[0]
    p_axis = 0 if params_batched else None
    steps = jnp.broadcast_to(jnp.asarray(steps_left, jnp.int32), (B,))
    k = jnp.clip(N - 1 - steps, 0, N - 1)  # [B] (idle pool slots ask for depth 0: clipped, their work is dropped)
    per_input = jax.vmap(one_child, in_axes=(None, None, 0, None, None))
    xs, stage, allowed = jax.vmap(per_input, in_axes=(None, 0, None, 0, p_axis))(
        problem, x, jnp.asarray(problem.controls), k, params)
    stage = stage.astype(cost.dtype) + _terminal_cost(problem, xs, steps == 0, p_axis, params)
    child_cost = cost[:, None] + stage
    nonfinite = jnp.isnan(child_cost) | jnp.any(~jnp.isfinite(xs), axis=-1)
    overflow = jnp.isinf(child_cost) & jnp.isfinite(cost)[:, None] & jnp.isfinite(stage)
    flags = ((stage < 0) * NEGATIVE | nonfinite * NONFINITE | overflow * OVERFLOW).astype(jnp.int32)
    bad = nonfinite
    if problem.constraint is not None:  # discarded children raise no flag: a constraint may guard a model's domain
        bad, flags = nonfinite | ~allowed, jnp.where(allowed, flags, 0)
    if check_terminal and problem.terminal is not None:
        ok = jax.vmap(jax.vmap(lambda xi, p: call(problem.terminal, p, xi), in_axes=(0, None)),
                      in_axes=(0, p_axis))(xs, params)
    else:
        ok = jnp.ones(child_cost.shape, bool)
    key = child_cost
    if problem.lower_bound is not None:
        bound = jax.vmap(jax.vmap(lambda xi, s, p: call(problem.lower_bound, p, xi, s), in_axes=(0, None, None)),
                         in_axes=(0, 0, p_axis))(xs, steps, params)
        bound = jnp.where(jnp.isnan(bound), 0, bound)  # a NaN bound (a user bug) prunes nothing: stays exact
        key = child_cost + jnp.where(steps[:, None] > 0, bound.astype(cost.dtype), 0)
    return Children(x=xs, cost=child_cost, key=key, bad=bad, flags=flags, terminal_ok=ok)


class SearchStats(NamedTuple):
    """What a search counts: the same fields in every solver (batched searches
    add a leading axis). Three bool flags, not one array: docs/dev/xla_notes.md
    ("Tried and not kept", three flags against one array)."""

    nodes: jax.Array  # [] int32 child nodes computed (the paper's count)
    iterations: jax.Array  # [] int32 batched expansions (SearchResult.iterations says per solver)
    negative: jax.Array  # [] bool a negative stage cost was computed
    nonfinite: jax.Array  # [] bool a non-finite state or a NaN cost was computed
    overflow: jax.Array  # [] bool a finite cost plus a finite stage cost overflowed


def no_stats(nodes=0, flags=0) -> SearchStats:
    """Counters of a search that has not started: ``nodes`` already computed
    and error ``flags`` (bits) already met."""
    zero = jnp.zeros((), jnp.int32)
    return SearchStats(nodes=zero + nodes, iterations=zero, **_bits(jnp.asarray(flags)))


def _bits(flags):
    return {"negative": (flags & NEGATIVE) > 0, "nonfinite": (flags & NONFINITE) > 0,
            "overflow": (flags & OVERFLOW) > 0}


def tally(stats: SearchStats, children: Children, expanded) -> SearchStats:
    """The one rule for counting: ``stats`` plus one iteration that expanded
    the nodes marked in ``expanded`` ``[B]`` into ``children`` (``[B, M]``
    fields): M nodes each, and the error flags of their children."""
    M = children.cost.shape[-1]
    met = _bits(jax.lax.reduce_or(jnp.where(expanded[:, None], children.flags, 0), axes=(0, 1)))
    return SearchStats(nodes=stats.nodes + M * jnp.sum(expanded, dtype=jnp.int32), iterations=stats.iterations + 1,
                       **{k: getattr(stats, k) | v for k, v in met.items()})


def first_min(a):
    """Smallest entry along the last axis and its first index (int32). Two plain
    reductions: XLA:CPU runs a (value, index) argmin reduction as a scalar
    loop, several times slower, and fails to compile one fused into a deep
    chain of levels (``Unknown MLIR failure`` at N >= 12, docs/dev/xla_notes.md)."""
    low = jnp.min(a, axis=-1)
    idx = jnp.arange(a.shape[-1], dtype=jnp.int32)
    first = jnp.min(jnp.where(a == low[..., None], idx, a.shape[-1]), axis=-1)
    return low, jnp.minimum(first, a.shape[-1] - 1)


def best_leaf(cost, terminal_ok, usable, is_leaf, incumbent):
    """The one rule for leaves: the cheapest usable feasible leaf (first in
    order among equal costs) improves the incumbent when strictly cheaper.
    ``cost``, ``terminal_ok``, ``usable``: ``[..., L]`` over flattened
    children; ``is_leaf`` broadcasts to them. Returns ``(cost, index, improves)``."""
    leaf_cost = jnp.where(usable & terminal_ok & is_leaf, cost, jnp.inf)
    low, i = first_min(leaf_cost)
    return low, i, low < incumbent


def rollout_cost(problem: Problem, x0: ArrayLike, sequence: ArrayLike, cost_dtype: DTypeLike | None = None,
                 params: PyTree = None) -> tuple[jax.Array, jax.Array]:
    """Cost of one input sequence ``[N]`` from ``x0`` (stage costs and the
    terminal cost), +inf if it fails the terminal test or a constraint,
    contains an out-of-range index, or meets a non-finite state.

    Returns ``(cost, flags)``; accumulates exactly as ``expand`` does, in
    ``cost_dtype`` (default: the stage cost's dtype at ``x0``). This is also
    the differentiable evaluation of a found sequence (``jax.grad`` with
    respect to ``x0`` or ``params`` works through it): ``fj.rollout_cost``.
    """
    M = problem.num_controls
    if cost_dtype is None:
        cost_dtype = dtype_of_cost(problem, x0, params)
    in_range = jnp.all((sequence >= 0) & (sequence < M))

    N = problem.horizon

    def step(carry, inp):
        x, c, flags, met = carry
        k, idx = inp
        u = jnp.asarray(problem.controls)[jnp.clip(idx, 0, M - 1)]
        x_next, s, allowed = one_child(problem, x, u, k, params)
        s = s.astype(cost_dtype)
        if problem.terminal_cost is not None:
            s = s + jnp.where(k == N - 1, call(problem.terminal_cost, params, x_next), 0).astype(cost_dtype)
        c_next = c + s
        bad = jnp.isnan(c_next) | jnp.any(~jnp.isfinite(x_next))
        overflow = jnp.isinf(c_next) & jnp.isfinite(c) & jnp.isfinite(s)
        new = jnp.where(met & allowed, (s < 0) * NEGATIVE | bad * NONFINITE | overflow * OVERFLOW, 0)
        return (x_next, c_next, flags | new, met & allowed), None

    init = (x0, jnp.zeros((), cost_dtype), jnp.zeros((), jnp.int32), jnp.ones((), bool))
    (x_n, cost, flags, met), _ = jax.lax.scan(step, init, (jnp.arange(N, dtype=jnp.int32), sequence))
    ok = in_range & met & ((flags & NONFINITE) == 0)
    if problem.terminal is not None:
        ok = ok & call(problem.terminal, params, x_n)
    return jnp.where(ok, cost, jnp.inf).astype(cost_dtype), jnp.where(in_range, flags, 0)
