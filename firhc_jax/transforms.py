"""Problem transforms: a new ``Problem`` built from another one.

``with_input_memory`` adds the input applied last to the model state, so that
a stage cost can charge input changes (do-mpc's ``rterm``, the FCS-MPC
switching term), the first step's against the input the plant received
before the decision.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import jax.numpy as jnp

from .problem import Problem


class InputMemory(NamedTuple):
    """A problem whose model state carries the last input (``with_input_memory``)."""

    problem: Problem  # on states [x, u_prev (m), switching cost of the last step (1)]
    observe: Callable  # observe(x, u_prev[, p]) -> [x, u_prev, 0] for FIRHC


def with_input_memory(problem: Problem, switching_cost: Callable) -> InputMemory:
    """Penalise input changes (do-mpc's ``rterm``, the FCS-MPC switching term).

    ``switching_cost(u, u_prev[, k][, p]) -> scalar >= 0`` (``k`` with
    ``step_index``; ``fj.input_change_cost`` builds one) is added to the stage cost
    of every step, the first one included (``u_prev`` there is the input
    applied last). The returned problem's state is ``[x, u_prev, s]``: the
    dynamics store the input just applied and its switching cost ``s``, which
    the stage cost adds. Use it with ``FIRHC(mem.problem, observe=mem.observe)``;
    for one search call ``sdfs(mem.problem, mem.observe(x, u_prev))``.
    Inputs are kept in the state's floating dtype.
    """
    m = problem.input_dim

    def split(z):
        n = z.shape[0] - m - 1
        return z[:n], z[n:n + m], z[n + m]

    def dynamics(z, u, *p):
        x, u_prev, _ = split(z)
        x_next = problem.dynamics(x, u, *p)
        s = switching_cost(u.astype(z.dtype), u_prev, *p)
        return jnp.concatenate([x_next, u.astype(z.dtype), jnp.reshape(s, (1,)).astype(z.dtype)])

    def stage_cost(z_next, u, *p):
        x_next, _, s = split(z_next)
        return problem.stage_cost(x_next, u, *p) + s

    terminal = lower_bound = terminal_cost = constraint = None
    if problem.terminal is not None:
        def terminal(z, *p):
            return problem.terminal(split(z)[0], *p)
    if problem.terminal_cost is not None:
        def terminal_cost(z, *p):
            return problem.terminal_cost(split(z)[0], *p)
    if problem.constraint is not None:
        def constraint(z_next, u, *p):
            return problem.constraint(split(z_next)[0], u, *p)
    if problem.lower_bound is not None:
        def lower_bound(z, steps_left, *p):
            return problem.lower_bound(split(z)[0], steps_left, *p)

    def observe(x, u_prev, *p):
        return jnp.concatenate([x, jnp.asarray(u_prev, x.dtype).reshape(m), jnp.zeros((1,), x.dtype)])

    return InputMemory(Problem(dynamics, problem.controls, stage_cost, problem.horizon, terminal, lower_bound,
                               terminal_cost, constraint, problem.step_index), observe)
