"""Node expansion shared by every search: all children of a batch of nodes in
one vmapped call of ``dynamics`` and ``stage_cost``, and the two rules every
search applies to them.

A child's cost is ``parent_cost + stage_cost(x_child, u)``, always accumulated
in this one place (``expand`` and ``rollout_cost``), so a sequence gets the same
cost in every search as long as ``dynamics`` and ``stage_cost`` evaluate the
same way at every batch size (elementwise code does; a batched matmul may
round differently in the last bit, see README).
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .problem import Problem, call

# Error flags, as bits of one int32 (combined with |).
NEGATIVE, NONFINITE, OVERFLOW = 1, 2, 4


class Children(NamedTuple):
    x: jax.Array  # [B, M, n] child states
    cost: jax.Array  # [B, M] accumulated costs
    key: jax.Array  # [B, M] cost + lower bound of the rest (= cost without a bound): the order and the pruning test
    bad: jax.Array  # [B, M] bool non-finite state or NaN cost: never expanded, never a solution
    flags: jax.Array  # [B, M] int32 error flags (NEGATIVE | NONFINITE | OVERFLOW)
    terminal_ok: jax.Array  # [B, M] bool terminal(x_child) (True if unconstrained)


def _one_child(problem: Problem, x, u, p):
    x_next = call(problem.dynamics, p, x, u)
    return x_next, call(problem.stage_cost, p, x_next, u)


def expand(problem: Problem, x, cost, params, *, steps_left, check_terminal: bool,
           params_batched: bool = False) -> Children:
    """Children of ``B`` nodes: ``x`` ``[B, n]``, ``cost`` ``[B]`` -> ``Children``.

    ``params``: one parameter pytree for all nodes, or (``params_batched``) one
    per node (leading axis B). ``steps_left`` (int, or int32 ``[B]``): steps
    still to come after the children, for the lower bound. ``check_terminal``
    evaluates the terminal test (only needed at depth N).
    """
    p_axis = 0 if params_batched else None
    per_input = jax.vmap(_one_child, in_axes=(None, None, 0, None))
    xs, stage = jax.vmap(per_input, in_axes=(None, 0, None, p_axis))(problem, x, jnp.asarray(problem.controls),
                                                                     params)
    stage = stage.astype(cost.dtype)
    child_cost = cost[:, None] + stage
    bad = jnp.isnan(child_cost) | jnp.any(~jnp.isfinite(xs), axis=-1)
    overflow = jnp.isinf(child_cost) & jnp.isfinite(cost)[:, None] & jnp.isfinite(stage)
    flags = ((stage < 0) * NEGATIVE | bad * NONFINITE | overflow * OVERFLOW).astype(jnp.int32)
    if check_terminal and problem.terminal is not None:
        ok = jax.vmap(jax.vmap(lambda xi, p: call(problem.terminal, p, xi), in_axes=(0, None)),
                      in_axes=(0, p_axis))(xs, params)
    else:
        ok = jnp.ones(child_cost.shape, bool)
    key = child_cost
    if problem.lower_bound is not None:
        steps = jnp.broadcast_to(jnp.asarray(steps_left, jnp.int32), x.shape[:1])
        bound = jax.vmap(jax.vmap(lambda xi, s, p: call(problem.lower_bound, p, xi, s), in_axes=(0, None, None)),
                         in_axes=(0, 0, p_axis))(xs, steps, params)
        bound = jnp.where(jnp.isnan(bound), 0, bound)  # a NaN bound (a user bug) prunes nothing: stays exact
        key = child_cost + jnp.where(steps[:, None] > 0, bound.astype(cost.dtype), 0)
    return Children(x=xs, cost=child_cost, key=key, bad=bad, flags=flags, terminal_ok=ok)


class SearchStats(NamedTuple):
    """What a search counts: the same fields in every solver (batched searches
    add a leading axis). Three bool flags, not one array: docs/xla_notes.md
    ("Tried in the third session")."""

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
    chain of levels (``Unknown MLIR failure`` at N >= 12, docs/xla_notes.md)."""
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


def rollout_cost(problem: Problem, x0, sequence, cost_dtype, params=None):
    """Cost of one input sequence ``[N]`` from ``x0``, +inf if it fails the
    terminal test, contains an out-of-range index, or meets a non-finite state.

    Returns ``(cost, flags)``; accumulates exactly as ``expand`` does. This is
    also the differentiable evaluation of a found sequence (``jax.grad`` with
    respect to ``x0`` or ``params`` works through it).
    """
    M = problem.num_controls
    in_range = jnp.all((sequence >= 0) & (sequence < M))

    def step(carry, idx):
        x, c, flags = carry
        u = jnp.asarray(problem.controls)[jnp.clip(idx, 0, M - 1)]
        x_next, s = _one_child(problem, x, u, params)
        s = s.astype(cost_dtype)
        c_next = c + s
        bad = jnp.isnan(c_next) | jnp.any(~jnp.isfinite(x_next))
        overflow = jnp.isinf(c_next) & jnp.isfinite(c) & jnp.isfinite(s)
        return (x_next, c_next, flags | ((s < 0) * NEGATIVE | bad * NONFINITE | overflow * OVERFLOW)), None

    init = (x0, jnp.zeros((), cost_dtype), jnp.zeros((), jnp.int32))
    (x_n, cost, flags), _ = jax.lax.scan(step, init, sequence)
    ok = in_range & ((flags & NONFINITE) == 0)
    if problem.terminal is not None:
        ok = ok & call(problem.terminal, params, x_n)
    return jnp.where(ok, cost, jnp.inf).astype(cost_dtype), jnp.where(in_range, flags, 0)
