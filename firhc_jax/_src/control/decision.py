"""One decision of the receding horizon law, traced: observe, search, fallback, hold, actuate.

Everything here runs inside a trace and trusts its arguments: ``FIRHC``
checks them once, at its public boundary. ``decide`` is one loop's decision;
``decide_rows`` is the same decision for ``B`` loops at once, each row's
search run by the solver's ``batch`` (on the work pool, rows never wait for
each other's searches). Both read the controller's frozen ``Options``.
"""
from __future__ import annotations

from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from ..problem.problem import call
from ..search import solvers
from ..search.result import SearchResult
from ..search.sdfs import INT32_MAX


class ControllerState(NamedTuple):
    """What the next decision needs (a pytree: ``lax.scan`` carries it, ``vmap`` batches it)."""

    u: jax.Array  # [m] the searched input applied last, before actuate: observe's u_prev, the input held
    plan: jax.Array  # [N] int32 the last decision's sequence (all -1: none), the warm start's seed
    budget: Optional[jax.Array] = None  # [] int32 the decision's node budget (INT32_MAX: none): an argument of the
    #                                     compiled decision, so that a new max_nodes never compiles again;
    #                                     None: the controller's own (FIRHC.step fills it in)


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


def budget_of(opts) -> np.ndarray:
    """[] int32 the node budget of ``opts``'s decisions (``INT32_MAX``: none), as a state carries it."""
    max_nodes = opts.solver_options.get("max_nodes")
    return np.int32(INT32_MAX if max_nodes is None else max_nodes)


def warm_start(opts, problem, x, params, previous):
    """The first incumbents of a search: ``[N]`` or ``[C, N]`` int32 (all -1: none), or None. Under a node
    budget the previous plan shifted by one step, its last step left to the search's greedy rollout, comes
    first (docs/guide/budgets.md); then a callable ``warm_start``'s seed, or without a budget the shifted plan
    with its last input repeated (``warm_start=True``)."""
    if previous is None:
        return None
    out = []
    if opts.budgeted:
        out.append(jnp.where(previous[0] >= 0, jnp.concatenate([previous[1:], jnp.full((1,), -1, jnp.int32)]), -1))
    if callable(opts.warm_start):
        out.append(jnp.asarray(opts.warm_start(problem, x, previous, params), jnp.int32))
    elif opts.warm_start and not opts.budgeted:
        out.append(jnp.where(previous[0] >= 0, jnp.concatenate([previous[1:], previous[-1:]]), -1))
    return None if not out else out[0] if len(out) == 1 else jnp.stack(out)


def previous_plan(opts, state: ControllerState):
    """The plan the next decision's candidates come from (None: it takes none)."""
    return state.plan if opts.warm_start or opts.budgeted else None


def reserve(opts, max_nodes):
    """Nodes of the decision's budget the terminal-constrained search holds back for the fallback while it has
    found no sequence (None: all of it is the search's): half, with a fallback and a budget."""
    return max_nodes // 2 if opts.budgeted and opts.relaxed is not None else None


def _search(opts, problem, x, params, previous, max_nodes, held_back=None) -> SearchResult:
    solver = solvers.get(opts.solver)
    return solver.search(problem, x, params, warm_start(opts, problem, x, params, previous), max_nodes,
                         budgeted=opts.budgeted, reserve=held_back, **opts.search_options)


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


def solve(opts, x, params, previous, max_nodes):
    """The searches of one decision at model state ``x`` within ``max_nodes`` (``[]`` int32): ``(deciding
    result, nodes of the constrained search, used_fallback)``; the fallback searches only when needed, within
    what the first search left."""
    max_nodes = jnp.asarray(max_nodes, jnp.int32)
    result = _search(opts, opts.problem, x, params, previous, max_nodes, reserve(opts, max_nodes))
    if opts.relaxed is None:
        return result, result.nodes, jnp.zeros((), bool)

    def fall_back(_):
        left = _left(opts, max_nodes, result.nodes)
        return merged(result, _search(opts, opts.relaxed, x, params, previous, left)), jnp.ones((), bool)

    chosen, used = jax.lax.cond(result.feasible, lambda _: (result, jnp.zeros((), bool)), fall_back, None)
    return chosen, result.nodes, used


def solve_rows(opts, X, params, previous, max_nodes):
    """``solve`` for the rows of ``X`` ``[B, n]`` (``params`` leaves ``[B, ...]``, ``previous`` ``[B, N]`` or None,
    ``max_nodes`` ``[B]``),
    each row's searches by the solver's ``batch``. With a node budget no row's nodes are shared with another
    row's (``steal=False``), so every row is searched as ``solve`` searches it, node for node."""
    B = X.shape[0]
    batch = solvers.get(opts.solver).batch
    max_nodes = jnp.broadcast_to(jnp.asarray(max_nodes, jnp.int32), (B,))

    def search(problem, X, params, previous, max_nodes, n_valid, held_back=None):
        seeds = None if previous is None else jax.vmap(
            lambda x, p, prev: warm_start(opts, problem, x, p, prev))(X, params, previous)
        return batch(problem, X, params, seeds, max_nodes, n_valid, budgeted=opts.budgeted, reserve=held_back,
                     steal=not opts.budgeted, **opts.search_options)

    result = search(opts.problem, X, params, previous, max_nodes, B, reserve(opts, max_nodes))
    if opts.relaxed is None:
        return result, result.nodes, jnp.zeros((B,), bool)
    used = ~result.feasible

    def fall_back(_):  # the rows that need it first (stable order), the others with no budget
        order = jnp.argsort(~used, stable=True)
        back = jnp.argsort(order)
        rows = lambda a: a[order]  # noqa: E731
        left = jnp.where(used, _left(opts, max_nodes, result.nodes), 0)
        relaxed = search(opts.relaxed, X[order], jax.tree_util.tree_map(rows, params),
                         None if previous is None else previous[order], left[order], jnp.sum(used, dtype=jnp.int32))
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
    stage = opts.problem.cost_of_step(xm, opts.problem.next_state(xm, u_model, 0, p), u_model, 0, p)
    info = StepInfo(result=result, used_fallback=used, complete=result.complete, nodes=nodes,
                    fallback_nodes=jnp.where(used, result.nodes, 0), feasible=result.feasible & ~used,
                    held=held, stage_cost=jnp.where(held, jnp.nan, stage))
    return u_plant, ControllerState(u=u, plan=jnp.where(held, -1, result.sequence), budget=state.budget), info


def decide(opts, state: ControllerState, x, p):
    """One decision at plant state ``x``: ``(u_plant, next state, StepInfo)``."""
    xm = observed(opts, state, x, p)
    return applied(opts, state, x, xm, p, *solve(opts, xm, p, previous_plan(opts, state), state.budget))


def decide_rows(opts, state: ControllerState, X, P):
    """``decide`` for ``B`` loops at once (every argument with leading axis B)."""
    Xm = jax.vmap(lambda s, x, p: observed(opts, s, x, p))(state, X, P)
    result, nodes, used = solve_rows(opts, Xm, P, previous_plan(opts, state), state.budget)
    return jax.vmap(lambda s, x, xm, p, r, n, f: applied(opts, s, x, xm, p, r, n, f))(
        state, X, Xm, P, result, nodes, used)
