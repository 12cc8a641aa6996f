"""A synthetic plant for benchmarks: 3 states, M inputs on a spiral in the
plane, smooth nonlinear dynamics, and a ``work`` knob that adds dummy
arithmetic to each step so the per-node cost can be dialled up."""
from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from .. import Problem, quadratic_cost


@dataclasses.dataclass(frozen=True)
class SyntheticParams:
    """The benchmark's size knobs."""

    num_controls: int = 17  # M, inputs on the spiral
    work: int = 0  # dummy sine terms per step: per-node cost without changing the result


def make_problem(horizon: int, params: SyntheticParams = SyntheticParams(), dtype=None) -> Problem:
    """The benchmark problem: x = [position, velocity, heading-like state].

    Inputs are ``params.num_controls`` points on a spiral (radius 0.2..1):
    input 0 is the weakest. The quadratic cost weighs states and input effort
    so that a search from ``benchmark_state()`` visits a small fraction of the
    tree. ``dtype``: the controls' (default: JAX's default float).
    """
    num_controls, work = params.num_controls, params.work
    ang = np.linspace(0.0, 2 * np.pi, num_controls, endpoint=False)
    rad = np.linspace(0.2, 1.0, num_controls)
    controls = jnp.asarray(np.stack([np.cos(ang), np.sin(ang)], 1) * rad[:, None], dtype=dtype)  # [M, 2]

    def dynamics(x, u):
        extra = 0.0
        for k in range(work):  # dummy per-node work (does not change the result)
            extra = extra + 1e-30 * jnp.sin(x[0] * (k + 1))
        return jnp.stack([x[0] + 0.2 * x[1] + extra,
                          x[1] + 0.2 * (u[0] - jnp.sin(x[0]) - 0.1 * x[1]),
                          0.9 * x[2] + 0.2 * u[1] * jnp.cos(x[0])])

    cost = quadratic_cost(jnp.array([1.0, 0.1, 1.0]), jnp.zeros(3), 0.5)
    return Problem(dynamics, controls, cost, horizon)


def benchmark_state(dtype=None):
    """A state from which sDFS visits about 0.5% of the M = 17, N = 5 tree."""
    return jnp.asarray([0.2, 0.03, 1.0 / 3.0], dtype=dtype)
