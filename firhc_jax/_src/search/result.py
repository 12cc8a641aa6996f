"""What a search returns, and the eager-mode checks on it."""
from __future__ import annotations

import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..problem.problem import Problem
from .nodes import SearchStats


class SearchResult(NamedTuple):
    """Outcome of one search (a pytree; batched searches add a leading axis).

    ``cost`` is ``+inf`` and ``feasible`` False when no input sequence meets
    the terminal constraint; then ``sequence`` is all ``-1`` and
    ``first_input`` is NaN: never a made-up input. ``first_input`` is always
    floating (integer and boolean control sets are promoted), so that this
    holds for every control set.
    """

    cost: jax.Array  # [] optimal accumulated cost, +inf if infeasible
    sequence: jax.Array  # [N] int32 indices into controls, -1 if infeasible
    first_input: jax.Array  # [m] floating: controls[sequence[0]] (or Problem.first_input_of), the input to apply
    #                           (eq. 4); NaN if infeasible
    nodes: jax.Array  # [] int32 child nodes computed (the paper's count)
    feasible: jax.Array  # [] bool some sequence met the terminal constraint (with a finite cost)
    iterations: jax.Array  # [] int32 batched expansions of this search's nodes: sdfs: loop iterations;
    #                        solve_batch pool: slot-iterations spent on the row (shares of batched calls);
    #                        exhaustive: prefix levels + chunks x remaining levels
    negative_cost: jax.Array  # [] bool a negative stage cost was computed (exactness lost)
    nan_encountered: jax.Array  # [] bool a non-finite (NaN or inf) state or a NaN cost was computed; discarded
    overflow: jax.Array  # [] bool a finite cost plus a finite stage cost overflowed to +inf
    complete: jax.Array  # [] bool the search ran to the end (not stopped by max_nodes): the result is optimal


def finish(problem: Problem, cost, sequence, stats: SearchStats, complete, x0, params) -> SearchResult:
    """Assemble a ``SearchResult`` from a search's final state (``x0``, ``params``: its root's)."""
    feasible = jnp.isfinite(cost)
    sequence = jnp.where(feasible, sequence, -1).astype(jnp.int32)
    first = jnp.where(feasible, problem.first_input(x0, sequence, params), jnp.nan)
    return SearchResult(cost=cost, sequence=sequence, first_input=first, nodes=stats.nodes, feasible=feasible,
                        iterations=stats.iterations, negative_cost=stats.negative,
                        nan_encountered=stats.nonfinite, overflow=stats.overflow,
                        complete=jnp.asarray(complete, bool))


def alarms(result: SearchResult) -> jax.Array:
    """[] bool (traced): an error flag that ``raise_on_errors`` reports is up."""
    return jnp.any(result.negative_cost | result.nan_encountered | result.overflow)


def raise_on_errors(result: SearchResult) -> SearchResult:
    """In an un-jitted call, turn the result's error flags into exceptions.

    A negative stage cost raises ``ValueError`` (pruning was unsafe, so the
    answer may not be optimal). Non-finite states or costs, and cost
    overflow, only warn: those nodes were discarded, never treated as cheap,
    and the result is exact over the rest. Inside ``jit``/``vmap`` the flags
    stay in the result for the caller.
    """
    if isinstance(result.cost, jax.core.Tracer):
        return result
    # np.asarray reads a CPU result in place; jax.device_get is several times slower per array.
    negative, nan, overflow = (np.asarray(a) for a in (result.negative_cost, result.nan_encountered, result.overflow))
    if np.any(negative):
        raise ValueError(
            "a negative cost was computed during the search: stage_cost, or terminal_cost (added to the last "
            "step's stage cost), returned a value < 0; sDFS is exact only for non-negative costs (eq. 2). Shift "
            "or square the cost so that it is >= 0 (fj.diagnostics.check_problem samples states and names the "
            "callable that returns a negative cost).")
    if np.any(nan):
        warnings.warn("non-finite (NaN or inf) states or NaN costs were met during the search; those nodes were "
                      "discarded (treated as infeasible). Check dynamics/stage_cost near this state.",
                      RuntimeWarning, stacklevel=3)
    if np.any(overflow):
        warnings.warn("accumulated costs overflowed to +inf during the search (the cost dtype is too narrow for "
                      "these stage costs); overflowed sequences count as infinitely expensive, so a result "
                      "reported infeasible may only be too expensive. Scale the cost down or use float64.",
                      RuntimeWarning, stacklevel=3)
    return result
