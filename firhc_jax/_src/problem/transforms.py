"""Problem transforms: a new ``Problem`` built from another one.

``with_input_memory`` adds the input applied last to the model state, so that
a stage cost can charge input changes (do-mpc's ``rterm``, the FCS-MPC
switching term), the first step's against the input the plant received
before the decision.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import jax.numpy as jnp

from .auto_bound import AutoBound
from .problem import Problem


class InputMemory(NamedTuple):
    """A problem whose model state carries the last input (``with_input_memory``)."""

    problem: Problem  # on states [x, u_prev (m), switching cost of the last step (1)(, transition allowed (1))]
    observe: Callable  # observe(x, u_prev[, p]) -> [x, u_prev, 0(, 1)] for FIRHC


def with_input_memory(problem: Problem, switching_cost: Callable, transition: Callable | None = None) -> InputMemory:
    """Penalise input changes (do-mpc's ``rterm``, the FCS-MPC switching term).

    ``switching_cost(u, u_prev[, k][, p]) -> scalar >= 0`` (``k`` with
    ``step_index``; ``fj.input_change_cost`` builds one) is added to the stage cost
    of every step, the first one included (``u_prev`` there is the input
    applied last). The returned problem's state is ``[x, u_prev, s]``: the
    dynamics store the input just applied and its switching cost ``s``, which
    the stage cost adds. Use it with ``FIRHC(mem.problem, observe=mem.observe)``;
    for one search call ``sdfs(mem.problem, mem.observe(x, u_prev))``.
    Inputs are kept in the state's floating dtype.

    ``transition(u, u_prev[, k][, p]) -> bool``: optional hard constraint on
    input changes (a three-level leg must not jump from -1 to +1:
    ``lambda u, u_prev, *_: jnp.all(jnp.abs(u - u_prev) <= 1)``), checked at
    every step, the first against the input applied last. The state then
    carries one more entry, the transition's verdict, which the problem's
    ``constraint`` reads.
    """
    m = problem.input_dim
    extra = 1 if transition is None else 2  # s (and the transition's verdict)

    def split(z):
        n = z.shape[0] - m - extra
        return z[:n], z[n:n + m], z[n + m]

    def dynamics(z, u, *p):
        x, u_prev, _ = split(z)
        x_next = problem.dynamics(x, u, *p)
        uz = u.astype(z.dtype)
        parts = [x_next, uz, jnp.reshape(switching_cost(uz, u_prev, *p), (1,)).astype(z.dtype)]
        if transition is not None:
            parts.append(jnp.reshape(transition(uz, u_prev, *p), (1,)).astype(z.dtype))
        return jnp.concatenate(parts)

    steps = 2 + problem.previous_state  # ([z,] z_next, u): the states of the step, as the problem takes them

    def stage_cost(*args):
        *zs, u = args[:steps]
        return problem.stage_cost(*(split(z)[0] for z in zs), u, *args[steps:]) + split(zs[-1])[2]

    terminal = lower_bound = terminal_cost = constraint = None
    if problem.constraint is not None or transition is not None:
        def constraint(*args):
            *zs, u = args[:steps]
            ok = jnp.ones((), bool) if problem.constraint is None else \
                problem.constraint(*(split(z)[0] for z in zs), u, *args[steps:])
            return ok if transition is None else ok & (zs[-1][-1] > 0)
    if problem.terminal is not None:
        def terminal(z, *p):
            return problem.terminal(split(z)[0], *p)
    if problem.terminal_cost is not None:
        def terminal_cost(z, *p):
            return problem.terminal_cost(split(z)[0], *p)
    if isinstance(problem.lower_bound, AutoBound):
        lower_bound = "auto"  # derived from the whole wrapped model, switching cost and transitions included
    elif problem.lower_bound is not None:
        def lower_bound(z, steps_left, *p):
            return problem.lower_bound(split(z)[0], steps_left, *p)

    def observe(x, u_prev, *p):
        return jnp.concatenate([x, jnp.asarray(u_prev, x.dtype).reshape(m), jnp.zeros((1,), x.dtype),
                                jnp.ones((extra - 1,), x.dtype)])

    return InputMemory(Problem(dynamics, problem.controls, stage_cost, problem.horizon, terminal, lower_bound,
                               terminal_cost, constraint, problem.step_index,
                               previous_state=problem.previous_state), observe)
