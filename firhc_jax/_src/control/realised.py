"""What a closed loop cost the plant (``ClosedLoop.realised_cost``).

Each decision predicts a cost over its horizon; the plant pays only the first step of each, on its own
states. Summed over a run this is the figure to compare controllers by: the problem's stage cost of every
plant state reached and the input applied to reach it, at step index 0 (the step a decision applies) with
that step's parameters, and optionally the terminal cost of the last state.
"""
from __future__ import annotations

import jax
import numpy as np

from ..checks import check_params
from ..problem.callables import check_state
from ..problem.problem import Problem, call


def realised_cost(run, problem: Problem, params=None, terminal_cost: bool = False):
    """The sum of ``run``'s stage costs priced by ``problem`` (a float; ``[B]`` for a batched run)."""
    if not isinstance(problem, Problem):
        raise TypeError(f"problem must be a firhc_jax.Problem, got {type(problem).__name__}")
    if not isinstance(terminal_cost, (bool, np.bool_)):
        raise TypeError(f"terminal_cost must be True or False, got {terminal_cost!r}")
    if terminal_cost and problem.terminal_cost is None:
        raise ValueError("terminal_cost=True, but the problem has no terminal_cost")
    states, inputs = np.asarray(run.states), np.asarray(run.inputs)  # [(B,) T+1, n], [(B,) T, m']
    lead = inputs.shape[:-1]
    if inputs.shape[-1] != problem.input_dim:
        raise ValueError(f"the run's inputs have {inputs.shape[-1]} columns, the problem's inputs m = "
                         f"{problem.input_dim}: price the run with the problem whose inputs were applied")
    params = check_params(params, leading=lead, axis="B, T" if run.batched else "T")
    check_state(problem, states.reshape(-1, states.shape[-1])[0],
                jax.tree_util.tree_map(lambda a: a[(0,) * len(lead)], params))
    per_step = jax.tree_util.tree_map(lambda a: a.reshape((-1,) + a.shape[len(lead):]), params)
    stage = jax.vmap(lambda x, x_next, u, p: problem.cost_of_step(x, x_next, u, 0, p))(
        states[..., :-1, :].reshape(-1, states.shape[-1]), states[..., 1:, :].reshape(-1, states.shape[-1]),
        inputs.reshape(-1, inputs.shape[-1]), per_step)
    total = np.asarray(stage, np.float64).reshape(lead).sum(axis=-1)
    if terminal_cost:  # of the last state, with the last step's parameters
        loops = (slice(None),) * (len(lead) - 1)
        last = jax.tree_util.tree_map(lambda a: a[loops + (-1,)].reshape((-1,) + a.shape[len(lead):]), params)
        final = jax.vmap(lambda x, p: call(problem.terminal_cost, p, x))(
            states[loops + (-1,)].reshape(-1, states.shape[-1]), last)
        total = total + np.asarray(final, np.float64).reshape(lead[:-1])
    return total if run.batched else float(total)
