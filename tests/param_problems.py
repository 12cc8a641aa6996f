"""Random problems whose every number is a parameter: one compiled search per
shape serves every draw, so the property tests compile once per strategy.

The input values themselves are parameters too: the problem's control set is
the indices ``0..M-1`` and ``p["U"][i]`` is the input vector of index ``i``.
Each problem has a NumPy twin for the independent brute force.
"""
from __future__ import annotations

import functools

import jax.numpy as jnp
import numpy as np
from hypothesis import strategies as st
from reference import brute_force, rollout, same_cost, sequences, tolerance  # noqa: F401 (same_cost: re-exported)

import firhc_jax as fj

SHAPES = ((1, 1, 3, 4), (2, 2, 4, 3), (3, 1, 2, 6), (2, 3, 5, 3))  # (n, m, M, N)


def dynamics(x, u, p, xp=jnp):
    """Elementwise (no matmul) so that every batch size rounds alike."""
    v = p["U"][u[..., 0].astype(int)] if xp is jnp else u
    n, m = p["W"].shape[-1], p["V"].shape[-1]
    z = p["b"] + sum(p["W"][:, j] * x[..., j, None] for j in range(n)) \
        + sum(p["V"][:, j] * v[..., j, None] for j in range(m))
    return xp.tanh(z) + p["a"] * x


def stage_cost(x, u, p, xp=jnp):
    v = p["U"][u[..., 0].astype(int)] if xp is jnp else u
    return xp.sum(p["q"] * (x - p["r"]) ** 2 + 0.1 * xp.abs(xp.sin(3 * x)), axis=-1) + xp.sum(p["w"] * v**2, axis=-1)


def terminal(x, p, xp=jnp):
    return xp.sum((x - p["r"]) ** 2, axis=-1) < p["radius"]


@functools.lru_cache(maxsize=None)
def problem(shape, constrained: bool = True, lower_bound=None) -> fj.Problem:
    """The one problem of this shape (same callables every call: one compile)."""
    n, m, M, N = shape
    return fj.Problem(dynamics, jnp.arange(M, dtype=jnp.float32), stage_cost, N,
                      terminal if constrained else None, lower_bound)


def from_random(rp) -> tuple[fj.Problem, dict]:
    """A problem of tests/random_problems.py as ``(problem, params)`` of this module: the same numbers, the same
    arithmetic, but as parameters, so that every such problem of one shape shares one compiled search."""
    params = {"W": rp.W, "V": rp.V, "b": rp.b, "a": rp.a, "q": rp.q, "r": rp.r, "w": rp.w, "U": rp.controls,
              "radius": np.float64(1e30 if rp.radius is None else rp.radius)}  # unused without one
    return problem((rp.n, rp.m, rp.M, rp.N), rp.radius is not None), as_jax(params)


def draw_params(rng: np.random.Generator, shape, tightness: str = "loose") -> dict:
    n, m, M, N = shape
    radius = {"loose": 1.0, "tight": 0.02, "none": np.inf}[tightness] * n
    return {"W": rng.normal(0, 0.8, (n, n)), "V": rng.normal(0, 1.0, (n, m)), "b": rng.normal(0, 0.2, n),
            "a": rng.uniform(0.2, 0.9, n), "q": rng.uniform(0.0, 2.0, n), "r": rng.normal(0, 0.5, n),
            "w": rng.uniform(0.0, 0.3, m), "U": rng.uniform(-1.5, 1.5, (M, m)),
            "radius": np.float64(min(radius, 1e30))}


def as_jax(params: dict, dtype=None) -> dict:
    """The parameters as JAX arrays (default: JAX's float, float64 with x64 and float32 without)."""
    return {k: jnp.asarray(v, dtype) for k, v in params.items()}


def as_seen(params: dict, x0):
    """``(params, x0)`` as NumPy float64 holding the values the library computes with (rounded to float32 in
    the float32 run), for the reference."""
    return {k: np.asarray(v, np.float64) for k, v in as_jax(params).items()}, np.asarray(jnp.asarray(x0), np.float64)


def numpy_step(params):
    """The NumPy twin's ``step(x, u, t)`` for tests/reference.py (``u``: the input vector)."""
    def step(x, u, t=None):
        x = dynamics(x, u, params, xp=np)
        return x, stage_cost(x, u, params, xp=np)
    return step


def cost_to_go(shape, params, x, steps):
    """Brute-force optimal cost of ``steps`` steps from ``x`` (+inf if the
    terminal set cannot be reached), NumPy float64, and the best sequence."""
    return brute_force(numpy_step(params), params["U"], x, steps, lambda z: terminal(z, params, xp=np))


def sequence_cost(params, x0, seq):
    """NumPy cost of one index sequence (+inf if it misses the terminal set)."""
    return float(rollout(numpy_step(params), x0, params["U"][np.asarray(seq)],
                         lambda z: terminal(z, params, xp=np))[0])


@st.composite
def cases(draw, tightness=("none", "loose", "tight"), shapes=SHAPES):
    """(shape, params, x0) with every number random; ``shapes``: a subset of
    SHAPES where each shape's compiles are costly."""
    shape = draw(st.sampled_from(shapes))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    params = draw_params(rng, shape, draw(st.sampled_from(tightness)))
    x0 = np.asarray(draw(st.lists(st.floats(-1, 1), min_size=shape[0], max_size=shape[0])))
    return shape, params, x0


def check_optimal(result, shape, params, x0, name=""):
    """``result`` (one ``SearchResult``) is the optimum over every sequence of the horizon from ``x0``, by
    brute force in float64 on the values the library saw (``as_seen``), up to ``tolerance()``; its sequence
    achieves its cost; infeasible means sequence -1 and a NaN input.

    In the float32 run a final state within ``1e-4`` of the terminal set's edge (in squared distance) counts as
    either side: the search's float32 states and the reference's may fall on different sides. The returned cost
    then lies between the optimum over the sequences surely inside and the one over those maybe inside. With
    x64 the margin is 0 and the check is the plain optimum."""
    import jax

    assert result.cost.dtype == jnp.asarray(0.0).dtype, (name, result.cost.dtype)  # float32 without x64
    params, x0 = as_seen(params, x0)
    seqs = sequences(shape[2], shape[3])
    costs, finals = rollout(numpy_step(params), x0, params["U"][seqs])
    edge = np.sum((finals - params["r"]) ** 2, axis=-1) - params["radius"]  # < 0: inside
    margin = 0.0 if jax.config.jax_enable_x64 else 1e-4
    high = float(np.min(costs, initial=np.inf, where=edge < -margin))  # the optimum among the surely inside
    low = float(np.min(costs, initial=np.inf, where=edge < margin))  # ... among the maybe inside
    rtol, atol = tolerance()
    cost, feasible = float(result.cost), bool(result.feasible)
    seq = np.asarray(result.sequence)
    if np.isfinite(high):
        assert feasible, (name, "infeasible, but", high)
    if not np.isfinite(low):
        assert not feasible, (name, "feasible", cost, "but no sequence is")
    if feasible:
        assert low - rtol * abs(low) - atol <= cost <= high + rtol * abs(high) + atol, (name, cost, low, high)
        i = int(np.ravel_multi_index(tuple(seq), (shape[2],) * shape[3]))  # its row of sequences(M, N)
        assert same_cost(costs[i], cost) and edge[i] < margin, (name, "the sequence costs", costs[i], cost)
    else:
        assert np.all(seq == -1) and np.all(np.isnan(np.asarray(result.first_input))), name
