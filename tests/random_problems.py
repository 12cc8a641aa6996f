"""Random nonlinear finite-input problems, each with a JAX form (for the
library) and a NumPy form (for the independent brute force)."""
from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np
import reference

import firhc_jax as fj


@dataclass
class RandomProblem:
    n: int
    m: int
    M: int
    N: int
    W: np.ndarray  # [n, n]
    V: np.ndarray  # [n, m]
    b: np.ndarray  # [n]
    a: np.ndarray  # [n]
    q: np.ndarray  # [n] state weights >= 0
    r: np.ndarray  # [n] set point
    w: np.ndarray  # [m] input weights >= 0
    controls: np.ndarray  # [M, m]
    radius: float | None  # terminal set: ||x - r||^2 < radius (None: unconstrained)

    # Written elementwise (no matmul) so that batched and unbatched evaluation agree bit for bit.
    def dynamics(self, x, u, xp=jnp):
        z = self.b + sum(self.W[:, j] * x[..., j, None] for j in range(self.n)) \
            + sum(self.V[:, j] * u[..., j, None] for j in range(self.m))
        return xp.tanh(z) + self.a * x

    def stage_cost(self, x, u, xp=jnp):
        return xp.sum(self.q * (x - self.r) ** 2 + 0.1 * xp.abs(xp.sin(3 * x)), axis=-1) \
            + xp.sum(self.w * u**2, axis=-1)

    def terminal(self, x, xp=jnp):
        return xp.sum((x - self.r) ** 2, axis=-1) < self.radius

    def problem(self) -> fj.Problem:
        return fj.Problem(lambda x, u: self.dynamics(x, u), jnp.asarray(self.controls),
                          lambda x, u: self.stage_cost(x, u), self.N,
                          None if self.radius is None else (lambda x: self.terminal(x)))

    # The NumPy twin, for the brute force of tests/reference.py.
    def step(self, x, u, t=None):
        x = self.dynamics(x, u, xp=np)
        return x, self.stage_cost(x, u, xp=np)

    @property
    def terminal_np(self):
        return None if self.radius is None else (lambda x: self.terminal(x, xp=np))

    def brute_force(self, x0):
        """(optimal cost, first optimal index sequence) over every sequence, in NumPy."""
        return reference.brute_force(self.step, self.controls, x0, self.N, self.terminal_np)

    def sequence_cost(self, x0, seq):
        """NumPy cost of one index sequence (inf if it misses the terminal set)."""
        return float(reference.rollout(self.step, x0, self.controls[np.asarray(seq)], self.terminal_np)[0])


def make(seed: int, n: int, m: int, M: int, N: int, terminal: str = "none") -> RandomProblem:
    """``terminal``: "none", "loose" (usually feasible), "tight" (often infeasible)."""
    rng = np.random.default_rng(seed)
    p = RandomProblem(
        n=n, m=m, M=M, N=N,
        W=rng.normal(0, 0.8, (n, n)), V=rng.normal(0, 1.0, (n, m)), b=rng.normal(0, 0.2, n),
        a=rng.uniform(0.2, 0.9, n), q=rng.uniform(0.0, 2.0, n), r=rng.normal(0, 0.5, n),
        w=rng.uniform(0.0, 0.3, m), controls=rng.uniform(-1.5, 1.5, (M, m)), radius=None)
    if terminal != "none":
        p.radius = {"loose": 1.0, "tight": 0.02}[terminal] * n
    return p
