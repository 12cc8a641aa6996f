"""Checks of a user's promises, run on sample states before a problem is trusted.

Exactness rests on two promises no search can verify as it runs: stage costs
are non-negative (sDFS only computes the nodes it does not prune, so a negative
cost inside a pruned subtree is never seen), and a ``lower_bound`` never
exceeds the true cost still to come. Both checks evaluate the problem on
states the user supplies (e.g. from a closed-loop run) and report every
violation they find; a clean report is evidence, not proof.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .cache import cached
from .checks import as_state, check_params, check_state
from .exhaustive import exhaustive
from .problem import Problem, call, positive_int


class Violation(NamedTuple):
    """One state where a promise does not hold."""

    state: int  # index into the sample states
    steps_left: int  # remaining steps (0 for a stage-cost violation)
    value: float  # the bound, or the negative stage cost
    limit: float  # the exact cost-to-go (bound check) or 0


def check_problem(problem: Problem, states, params=None) -> list[Violation]:
    """Stage costs of every input from every state ``[S, n]``; returns the
    ``(state, 0, cost, 0)`` of each negative one (empty: none found).

    ``params``: one parameter pytree for all states."""
    X = _states(states)
    params = check_params(params)
    check_state(problem, X[0], params)
    controls = jnp.asarray(problem.controls)

    def costs(x):
        def one(u):
            return call(problem.stage_cost, params, call(problem.dynamics, params, x, u), u)
        return jax.vmap(one)(controls)

    c = np.asarray(jax.jit(jax.vmap(costs))(X))  # [S, M]
    return [Violation(int(s), 0, float(c[s].min()), 0.0) for s in np.flatnonzero(np.any(c < 0, axis=1))]


def check_lower_bound(problem: Problem, states, params=None, max_steps: int | None = None,
                      rtol: float | None = None) -> list[Violation]:
    """Compare ``problem.lower_bound(x, s)`` with the exact optimal cost of the
    remaining ``s`` steps (an exhaustive search of horizon ``s`` from ``x``,
    with the problem's terminal set) for every sample state ``[S, n]`` and
    every ``s`` in ``1..max_steps`` (default: the horizon). Returns every
    ``(state, s, bound, exact)`` where the bound exceeds the exact cost by more
    than ``rtol`` relative (default: ``8 max_steps`` ulps of the coarser of
    the bound's and the costs' dtypes, at least 1e-9: an exact bound summed in
    another order is a few ulps off), or is NaN (empty: admissible on these
    samples). An inadmissible bound never crashes a search; it can prune the
    optimum, so the answer may then be suboptimal."""
    if problem.lower_bound is None:
        raise ValueError("problem has no lower_bound to check")
    X = _states(states)
    params = check_params(params)
    check_state(problem, X[0], params)
    max_steps = problem.horizon if max_steps is None else positive_int("max_steps", max_steps)
    steps = jnp.arange(1, max_steps + 1, dtype=jnp.int32)
    bounds = np.asarray(_bound_table(problem)(X, params, steps))  # [S, max_steps]
    out = []
    for s in range(1, max_steps + 1):
        short = problem.replace(horizon=s, lower_bound=None)
        exact = np.asarray(jax.vmap(lambda x, short=short: exhaustive(short, x, params=params).cost)(X))
        bound = bounds[:, s - 1]
        if rtol is None:
            rtol = max([1e-9] + [8 * max_steps * float(np.finfo(d).eps) for d in (bound.dtype, exact.dtype)
                                 if np.issubdtype(d, np.floating)])
        bad = (bound > exact + rtol * np.abs(np.where(np.isfinite(exact), exact, 0))) & ~(np.isinf(bound)
                                                                                          & np.isinf(exact))
        bad |= np.isnan(bound)  # a NaN bound prunes nothing in the searches, but it is a bug to report
        out += [Violation(int(i), s, float(bound[i]), float(exact[i])) for i in np.flatnonzero(bad)]
    return out


def _bound_table(problem: Problem):
    """``fn(X [S, n], params, steps [T]) -> [S, T]`` bounds: one jitted function per problem (jit keys the
    shapes; values are arguments)."""
    def table(X, p, steps):
        return jax.vmap(lambda x: jax.vmap(lambda s: call(problem.lower_bound, p, x, s))(steps))(X)

    return cached(("bound table", problem.key), lambda: jax.jit(table))


def _states(states) -> jax.Array:
    X = jnp.asarray(states)
    if X.ndim != 2 or X.shape[0] == 0:
        raise ValueError(f"states must be a non-empty batch of states [S, n], got shape {tuple(X.shape)}")
    X_np = np.asarray(X)  # row checks on a host copy (an eager slice of a device array costs a dispatch)
    for i in range(X.shape[0]):
        as_state(X_np[i], f"states[{i}]")
    return X
