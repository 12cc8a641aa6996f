"""One decision of the receding horizon law, traced: observe, search, fallback, hold, actuate.

Everything here runs inside a trace and trusts its arguments: ``FIRHC``
checks them once, at its public boundary. ``decide`` is one loop's decision;
``decide_rows`` is the same decision for ``B`` loops at once, each row's
search run by the solver's ``batch`` (on the work pool, rows never wait for
each other's searches). Both read the controller's frozen ``Options``.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..problem.problem import call
from ..search import solvers
from ..search.result import SearchResult
from ..search.sdfs import INT32_MAX


class ControllerState(NamedTuple):
    """What the next decision needs (a pytree: ``lax.scan`` carries it, ``vmap`` batches it)."""

    u: jax.Array  # [m] the searched input applied last, before actuate: observe's u_prev, the input held
    plan: jax.Array  # [N] int32 the last decision's sequence (all -1: none), the warm start's seed


class StepInfo(NamedTuple):
    """What one decision did (``FIRHC.step``); ``ClosedLoop`` holds these stacked over the steps."""

    result: SearchResult  # the deciding search: the fallback's when used_fallback
    used_fallback: jax.Array  # [] bool the input came from the fallback search
    complete: jax.Array  # [] bool every search behind the decision ran to the end (not stopped by max_nodes)
    nodes: jax.Array  # [] int32 nodes of the terminal-constrained search
    fallback_nodes: jax.Array  # [] int32 nodes of the fallback search (0 when not used)
    feasible: jax.Array  # [] bool the terminal-constrained search found a sequence
    held: jax.Array  # [] bool no input found: the safe input (u_safe, else the last input) was applied
    stage_cost: jax.Array  # [] model stage cost of the applied step (NaN when held)

    @property
    def decision_nodes(self) -> jax.Array:
        """[] int32 nodes of the whole decision, both searches: at most ``max_nodes``."""
        return self.nodes + self.fallback_nodes


def max_nodes_of(opts) -> jax.Array:
    """[] int32 the decision's node budget (``INT32_MAX``: none)."""
    max_nodes = opts.solver_options.get("max_nodes")
    return jnp.asarray(INT32_MAX if max_nodes is None else max_nodes, jnp.int32)


def warm_start(opts, problem, x, params, previous):
    """[N] int32 the seed of a search (all -1: none), or None without warm starts."""
    if not opts.warm_start or previous is None:
        return None
    if callable(opts.warm_start):
        return jnp.asarray(opts.warm_start(problem, x, previous, params), jnp.int32)
    shifted = jnp.concatenate([previous[1:], previous[-1:]])
    return jnp.where(previous[0] >= 0, shifted, -1)


def _search(opts, problem, x, params, previous, max_nodes) -> SearchResult:
    solver = solvers.get(opts.solver)
    return solver.search(problem, x, params, warm_start(opts, problem, x, params, previous), max_nodes,
                         budgeted=opts.budgeted, **opts.search_options)


def merged(first: SearchResult, relaxed: SearchResult) -> SearchResult:
    """The fallback's result with the first search's iterations added, its error flags kept, and
    ``complete`` only if both ran to the end (a constrained search stopped early has not proven
    infeasibility)."""
    return relaxed._replace(iterations=first.iterations + relaxed.iterations,
                            negative_cost=first.negative_cost | relaxed.negative_cost,
                            nan_encountered=first.nan_encountered | relaxed.nan_encountered,
                            overflow=first.overflow | relaxed.overflow, complete=first.complete & relaxed.complete)


def _left(opts, max_nodes, spent):
    """The fallback's budget: what the first search left of the decision's (no budget: none)."""
    return jnp.maximum(max_nodes - spent, 0) if opts.budgeted else max_nodes


def solve(opts, x, params, previous):
    """The searches of one decision at model state ``x``: ``(deciding result, nodes of the constrained
    search, used_fallback)``; the fallback searches only when needed, within what the first search left."""
    max_nodes = max_nodes_of(opts)
    result = _search(opts, opts.problem, x, params, previous, max_nodes)
    if opts.relaxed is None:
        return result, result.nodes, jnp.zeros((), bool)

    def fall_back(_):
        left = _left(opts, max_nodes, result.nodes)
        return merged(result, _search(opts, opts.relaxed, x, params, previous, left)), jnp.ones((), bool)

    chosen, used = jax.lax.cond(result.feasible, lambda _: (result, jnp.zeros((), bool)), fall_back, None)
    return chosen, result.nodes, used


def solve_rows(opts, X, params, previous):
    """``solve`` for the rows of ``X`` ``[B, n]`` (``params`` leaves ``[B, ...]``, ``previous`` ``[B, N]``),
    each row's searches by the solver's ``batch``. With a node budget no row's nodes are shared with another
    row's (``steal=False``), so every row is searched as ``solve`` searches it, node for node."""
    B = X.shape[0]
    batch = solvers.get(opts.solver).batch
    max_nodes = jnp.broadcast_to(max_nodes_of(opts), (B,))

    def search(problem, X, params, previous, max_nodes, n_valid):
        seeds = None if not opts.warm_start else jax.vmap(
            lambda x, p, prev: warm_start(opts, problem, x, p, prev))(X, params, previous)
        return batch(problem, X, params, seeds, max_nodes, n_valid, budgeted=opts.budgeted,
                     steal=not opts.budgeted, **opts.search_options)

    result = search(opts.problem, X, params, previous, max_nodes, B)
    if opts.relaxed is None:
        return result, result.nodes, jnp.zeros((B,), bool)
    used = ~result.feasible

    def fall_back(_):  # the rows that need it first (stable order), the others with no budget
        order = jnp.argsort(~used, stable=True)
        back = jnp.argsort(order)
        rows = lambda a: a[order]  # noqa: E731
        left = jnp.where(used, _left(opts, max_nodes, result.nodes), 0)
        relaxed = search(opts.relaxed, X[order], jax.tree_util.tree_map(rows, params), previous[order],
                         left[order], jnp.sum(used, dtype=jnp.int32))
        relaxed = jax.tree_util.tree_map(lambda a: a[back], relaxed)
        both = jax.vmap(merged)(result, relaxed)
        return jax.tree_util.tree_map(lambda a, b: jnp.where(used.reshape((B,) + (1,) * (a.ndim - 1)), a, b),
                                      both, result)

    chosen = jax.lax.cond(jnp.any(used), fall_back, lambda _: result, None)
    return chosen, result.nodes, used


def observed(opts, state: ControllerState, x, p):
    """The model state the search starts from."""
    return call(opts.observe, p, x, state.u) if opts.observe else x


def applied(opts, state: ControllerState, x, xm, p, result: SearchResult, nodes, used):
    """``(u_plant, next state, StepInfo)`` from the deciding search. A non-finite input (a
    ``first_input_of`` returning NaN or inf) is no input: the safe input replaces it."""
    held = ~result.feasible | ~jnp.all(jnp.isfinite(result.first_input))
    u = jnp.where(held, state.u if opts.u_safe is None else opts.u_safe, result.first_input)
    u_plant = call(opts.actuate, p, x, u) if opts.actuate else u
    u_model = jnp.asarray(opts.problem.controls)[jnp.maximum(result.sequence[0], 0)]
    stage = opts.problem.cost_of_step(opts.problem.next_state(xm, u_model, 0, p), u_model, 0, p)
    info = StepInfo(result=result, used_fallback=used, complete=result.complete, nodes=nodes,
                    fallback_nodes=jnp.where(used, result.nodes, 0), feasible=result.feasible & ~used,
                    held=held, stage_cost=jnp.where(held, jnp.nan, stage))
    return u_plant, ControllerState(u=u, plan=jnp.where(held, -1, result.sequence)), info


def decide(opts, state: ControllerState, x, p):
    """One decision at plant state ``x``: ``(u_plant, next state, StepInfo)``."""
    xm = observed(opts, state, x, p)
    previous = state.plan if opts.warm_start else None
    return applied(opts, state, x, xm, p, *solve(opts, xm, p, previous))


def decide_rows(opts, state: ControllerState, X, P):
    """``decide`` for ``B`` loops at once (every argument with leading axis B)."""
    Xm = jax.vmap(lambda s, x, p: observed(opts, s, x, p))(state, X, P)
    result, nodes, used = solve_rows(opts, Xm, P, state.plan)
    return jax.vmap(lambda s, x, xm, p, r, n, f: applied(opts, s, x, xm, p, r, n, f))(
        state, X, Xm, P, result, nodes, used)
