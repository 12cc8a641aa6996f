"""What a search returns, and the eager-mode checks on it."""
from __future__ import annotations

import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np


class SearchResult(NamedTuple):
    """Outcome of one search (a pytree; batched searches add a leading axis).

    ``cost`` is ``+inf`` and ``feasible`` False when no input sequence meets
    the terminal constraint; then ``sequence`` is all ``-1`` and
    ``first_input`` is NaN (for floating controls): never a made-up input.
    """

    cost: jax.Array  # [] optimal accumulated cost, +inf if infeasible
    sequence: jax.Array  # [N] int32 indices into controls, -1 if infeasible
    first_input: jax.Array  # [m] controls[sequence[0]], the input to apply (eq. 4)
    nodes: jax.Array  # [] int32 child nodes computed (the paper's count)
    feasible: jax.Array  # [] bool some sequence met the terminal constraint
    iterations: jax.Array  # [] int32 loop iterations (batched calls of dynamics)
    negative_cost: jax.Array  # [] bool a negative stage cost was met (exactness lost)
    nan_encountered: jax.Array  # [] bool a NaN state or cost was met (such nodes are discarded)


def finish(controls, cost, sequence, nodes, iterations, negative_cost, nan_encountered) -> SearchResult:
    """Assemble a ``SearchResult`` from a search's final carry."""
    feasible = jnp.isfinite(cost)
    sequence = jnp.where(feasible, sequence, -1).astype(jnp.int32)
    first = jnp.asarray(controls)[jnp.maximum(sequence[0], 0)]
    if jnp.issubdtype(controls.dtype, jnp.inexact):
        first = jnp.where(feasible, first, jnp.nan)
    return SearchResult(cost=cost, sequence=sequence, first_input=first, nodes=nodes,
                        feasible=feasible, iterations=iterations,
                        negative_cost=negative_cost, nan_encountered=nan_encountered)


def raise_on_errors(result: SearchResult) -> SearchResult:
    """In an un-jitted call, turn the result's error flags into exceptions.

    A negative stage cost raises ``ValueError`` (pruning was unsafe, so the
    answer may not be optimal). NaN states or costs only warn: those nodes were
    discarded, never treated as cheap, and the result is exact over the rest.
    Inside ``jit``/``vmap`` the flags stay in the result for the caller.
    """
    if isinstance(result.cost, jax.core.Tracer):
        return result
    negative, nan = jax.device_get((result.negative_cost, result.nan_encountered))  # one sync
    if np.any(negative):
        raise ValueError(
            "stage_cost returned a negative value during the search; sDFS is exact only for "
            "non-negative stage costs (eq. 2). Shift or square the cost so that it is >= 0.")
    if np.any(nan):
        warnings.warn("NaN states or costs were met during the search; those nodes were discarded "
                      "(treated as infeasible). Check dynamics/stage_cost near this state.",
                      RuntimeWarning, stacklevel=3)
    return result
