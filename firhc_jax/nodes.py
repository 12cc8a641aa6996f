"""Node expansion shared by every search: all children of a batch of nodes in
one vmapped call of ``dynamics`` and ``stage_cost``.

A child's cost is ``parent_cost + stage_cost(x_child, u)``, always accumulated
in this one place, so a sequence has the same cost bit for bit in every search.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .problem import Problem


class Children(NamedTuple):
    x: jax.Array  # [B, M, n] child states
    cost: jax.Array  # [B, M] accumulated costs
    bad: jax.Array  # [B, M] bool NaN in state or cost: never expanded, never a solution
    negative: jax.Array  # [B, M] bool stage cost < 0
    terminal_ok: jax.Array  # [B, M] bool terminal(x_child) (True if unconstrained)


def _one_child(problem: Problem, x, u):
    x_next = problem.dynamics(x, u)
    return x_next, problem.stage_cost(x_next, u)


def expand(problem: Problem, x, cost, check_terminal: bool) -> Children:
    """Children of ``B`` nodes: ``x`` ``[B, n]``, ``cost`` ``[B]`` -> ``Children``.

    ``check_terminal`` evaluates the terminal test (only needed at depth N).
    """
    per_input = jax.vmap(_one_child, in_axes=(None, None, 0))
    xs, stage = jax.vmap(per_input, in_axes=(None, 0, None))(problem, x, jnp.asarray(problem.controls))
    stage = stage.astype(cost.dtype)
    child_cost = cost[:, None] + stage
    bad = jnp.isnan(child_cost) | jnp.any(jnp.isnan(xs), axis=-1)
    if check_terminal and problem.terminal is not None:
        ok = jax.vmap(jax.vmap(problem.terminal))(xs)
    else:
        ok = jnp.ones(child_cost.shape, bool)
    return Children(x=xs, cost=child_cost, bad=bad, negative=stage < 0, terminal_ok=ok)


def rollout_cost(problem: Problem, x0, sequence, cost_dtype):
    """Cost of one input sequence ``[N]`` from ``x0``, +inf if it fails the
    terminal test, contains an out-of-range index, or meets a NaN.

    Returns ``(cost, negative, nan)``; accumulates exactly as ``expand`` does.
    """
    M = problem.num_controls
    in_range = jnp.all((sequence >= 0) & (sequence < M))

    def step(carry, idx):
        x, c, neg, nan = carry
        u = jnp.asarray(problem.controls)[jnp.clip(idx, 0, M - 1)]
        x_next, s = _one_child(problem, x, u)
        s = s.astype(cost_dtype)
        c_next = c + s
        return (x_next, c_next, neg | (s < 0), nan | jnp.isnan(c_next) | jnp.any(jnp.isnan(x_next))), None

    init = (x0, jnp.zeros((), cost_dtype), jnp.zeros((), bool), jnp.zeros((), bool))
    (x_n, cost, neg, nan), _ = jax.lax.scan(step, init, sequence)
    ok = in_range & ~nan
    if problem.terminal is not None:
        ok = ok & problem.terminal(x_n)
    return jnp.where(ok, cost, jnp.inf).astype(cost_dtype), neg & in_range, nan & in_range
