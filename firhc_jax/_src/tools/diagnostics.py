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

from ..annotations import ArrayLike, PyTree
from ..checks import as_batch, check_params, positive_int
from ..problem.callables import check_state
from ..problem.problem import Problem, call
from ..runtime.memory_cache import cached
from ..search.one_state import exhaustive


class Violation(NamedTuple):
    """One state where a promise does not hold."""

    state: int  # index into the sample states
    steps_left: int  # remaining steps (0 for a cost violation)
    value: float  # the bound, or the negative cost
    limit: float  # the exact cost-to-go (bound check) or 0
    source: str = ""  # the callable that broke its promise: "stage_cost", "terminal_cost" or "lower_bound"


def check_problem(problem: Problem, states: ArrayLike, params: PyTree = None,
                  per_state: bool | None = None) -> list[Violation]:
    """Stage costs of every input from every state ``[S, n]`` (at every step
    index with ``step_index``) and the terminal cost of each state; returns
    the ``(state, 0, cost, 0, source)`` of each state with a negative one,
    ``source`` the callable that returned it (``"stage_cost"``: the lowest of
    the state's stage costs; ``"terminal_cost"``); empty: none found. Steps
    that break the ``constraint`` are never searched and are skipped, and so
    are NaN costs (the searches discard those nodes).

    ``params``: as in ``check_lower_bound``."""
    X = as_batch(states, "states")
    params, p_axis = _params_form(problem, X, params, per_state)
    controls = jnp.asarray(problem.controls)
    ks = jnp.arange(problem.horizon if problem.step_index else 1, dtype=jnp.int32)

    def lowest(x, params):
        def one(u, k):
            x_next = problem.next_state(x, u, k, params)
            c = problem.cost_of_step(x, x_next, u, k, params)
            return jnp.where(problem.allowed(x, x_next, u, k, params) & ~jnp.isnan(c), c, jnp.inf)
        c = jnp.min(jax.vmap(lambda k: jax.vmap(lambda u: one(u, k))(controls))(ks))
        g = call(problem.terminal_cost, params, x) if problem.terminal_cost is not None else jnp.zeros_like(c)
        return c, g

    c, g = (np.asarray(a) for a in jax.jit(jax.vmap(lowest, in_axes=(0, p_axis)))(X, params))  # [S] each
    return sorted([Violation(int(s), 0, float(c[s]), 0.0, "stage_cost") for s in np.flatnonzero(c < 0)]
                  + [Violation(int(s), 0, float(g[s]), 0.0, "terminal_cost") for s in np.flatnonzero(g < 0)])


def check_lower_bound(problem: Problem, states: ArrayLike, params: PyTree = None, max_steps: int | None = None,
                      rtol: float | None = None, per_state: bool | None = None) -> list[Violation]:
    """Compare ``problem.lower_bound(x, s)`` with the exact optimal cost of the
    remaining ``s`` steps (an exhaustive search of horizon ``s`` from ``x``,
    with the problem's terminal set, terminal cost and constraint, and with
    ``step_index`` the last ``s`` step indices) for every sample state ``[S, n]`` and
    every ``s`` in ``1..max_steps`` (default: the horizon). Returns every
    ``(state, s, bound, exact)`` where the bound exceeds the exact cost by more
    than ``rtol`` relative (default: ``8 max_steps`` ulps of the coarser of
    the bound's and the costs' dtypes, at least 1e-9: an exact bound summed in
    another order is a few ulps off), or is NaN (empty: admissible on these
    samples). An inadmissible bound never crashes a search; it can prune the
    optimum, so the answer may then be suboptimal.

    ``params``: one parameter pytree for every state, or one row per state
    (every leaf with leading axis S, as ``fj.solve_batch`` takes them: state
    ``i`` is checked with ``params[i]``). The form the callables accept is
    used; ``per_state=True``/``False`` picks it where both fit (else a
    ``ValueError`` says they do)."""
    if problem.lower_bound is None:
        raise ValueError("problem has no lower_bound to check")
    X = as_batch(states, "states")
    params, p_axis = _params_form(problem, X, params, per_state)
    max_steps = problem.horizon if max_steps is None else positive_int("max_steps", max_steps)
    steps = jnp.arange(1, max_steps + 1, dtype=jnp.int32)
    bounds = np.asarray(_bound_table(problem, p_axis)(X, params, steps))  # [S, max_steps]
    out = []
    for s in range(1, max_steps + 1):
        short = _remaining(problem, s)
        exact = np.asarray(jax.vmap(lambda x, p, short=short: exhaustive(short, x, params=p).cost,
                                    in_axes=(0, p_axis))(X, params))
        bound = bounds[:, s - 1]
        if rtol is None:
            rtol = max([1e-9] + [8 * max_steps * float(np.finfo(d).eps) for d in (bound.dtype, exact.dtype)
                                 if np.issubdtype(d, np.floating)])
        bad = (bound > exact + rtol * np.abs(np.where(np.isfinite(exact), exact, 0))) & ~(np.isinf(bound)
                                                                                          & np.isinf(exact))
        bad |= np.isnan(bound)  # a NaN bound prunes nothing in the searches, but it is a bug to report
        out += [Violation(int(i), s, float(bound[i]), float(exact[i]), "lower_bound") for i in np.flatnonzero(bad)]
    return out


def _remaining(problem: Problem, s: int) -> Problem:
    """The problem of the last ``s`` steps: horizon ``s``, no bound, and with
    ``step_index`` the indices ``N - s .. N - 1`` (wrappers cached per problem
    and ``s``, so that repeated checks reuse their compiled searches)."""
    if not problem.step_index:
        return problem.replace(horizon=s, lower_bound=None)
    shift = problem.horizon - s

    def build():
        def shifted(fn, k_at):  # k is the argument after (x, u), or after (x, x_next, u) with previous_state
            return None if fn is None else (lambda *a: fn(*a[:k_at], a[k_at] + shift, *a[k_at + 1:]))
        after = 2 + problem.previous_state
        return problem.replace(horizon=s, lower_bound=None, dynamics=shifted(problem.dynamics, 2),
                               stage_cost=shifted(problem.stage_cost, after),
                               constraint=shifted(problem.constraint, after))

    return cached(("remaining problem", problem.key, s), build)


def _bound_table(problem: Problem, p_axis):
    """``fn(X [S, n], params, steps [T]) -> [S, T]`` bounds: one jitted function per problem and params form
    (jit keys the shapes; values are arguments)."""
    def table(X, params, steps):
        return jax.vmap(lambda x, p: jax.vmap(lambda s: call(problem.lower_bound, p, x, s))(steps),
                        in_axes=(0, p_axis))(X, params)

    return cached(("bound table", problem.key, p_axis), lambda: jax.jit(table))


def _params_form(problem: Problem, X, params, per_state):
    """``(params, vmap axis)``: ``params`` checked as one pytree for every state (axis ``None``) or as one row
    per state (axis 0), whichever the problem's callables accept; ``per_state`` decides where both do."""
    if params is None:
        return None, None
    if per_state not in (None, True, False):
        raise TypeError(f"per_state must be None, True or False, got {per_state!r}")
    S, errors, fits = X.shape[0], {}, {}
    for rows in ((False, True) if per_state is None else (per_state,)):
        try:
            p = check_params(params, leading=S if rows else None, what="params", axis="S")
            check_state(problem, X[0], p, batched_params=rows)
            fits[rows] = p
        except (TypeError, ValueError) as e:
            errors[rows] = e
    if len(fits) == 2:
        raise ValueError(f"params fit the callables both as one pytree for every state and as one row per state "
                         f"(leading axis S = {S}): pass per_state=True or per_state=False")
    if fits:
        rows, p = next(iter(fits.items()))
        return p, 0 if rows else None
    if per_state is not None:
        raise errors[per_state]
    raise type(errors[True])(f"params fit the callables neither as one pytree for every state ({errors[False]}) "
                             f"nor as one row per state with leading axis S = {S} ({errors[True]})")
