"""The independent references of the test suite, in plain NumPy (float64): the
rollout of input sequences, the brute-force optimum over all M^N of them, and
the one cost comparison. Every test file uses these instead of its own copy.

A problem is given to them as ``step(x, u, t) -> (x_next, stage_cost)``,
vectorised over leading axes of ``x`` and ``u`` (``t`` is the step within the
horizon, 0-based), and optionally ``terminal(x_N) -> bool``.
"""
from __future__ import annotations

import itertools

import numpy as np


def rollout(step, x0, inputs, terminal=None):
    """Accumulated cost of applying ``inputs[..., t, :]`` for t = 0, 1, ... from
    ``x0`` (``+inf`` where the final state misses ``terminal``), and the final
    state. ``inputs`` is ``[N, m]`` for one sequence or ``[S, N, m]`` for S."""
    inputs = np.asarray(inputs)
    x = np.broadcast_to(np.asarray(x0, float), inputs.shape[:-2] + np.shape(x0))
    cost = np.zeros(inputs.shape[:-2])
    for t in range(inputs.shape[-2]):
        x, c = step(x, inputs[..., t, :], t)
        cost = cost + c
    if terminal is not None:
        cost = np.where(terminal(x), cost, np.inf)
    return cost, x


def brute_force(step, controls, x0, N, terminal=None):
    """``(optimal cost, index sequence)`` over every sequence of ``N`` rows of
    ``controls`` ([M, m] or [M]), by enumeration. The first optimum in
    ``itertools.product`` order is returned; ``(inf, None)`` if no sequence
    reaches ``terminal``."""
    controls = np.asarray(controls, float)
    controls = controls[:, None] if controls.ndim == 1 else controls
    seqs = sequences(len(controls), N)
    cost, _ = rollout(step, x0, controls[seqs], terminal)
    best = int(np.argmin(cost))
    return (float(cost[best]), seqs[best]) if np.isfinite(cost[best]) else (np.inf, None)


def sequences(M, N):
    """Every index sequence of length ``N`` over ``M`` inputs, ``[M^N, N]``, in
    ``itertools.product`` order."""
    return np.array(list(itertools.product(range(M), repeat=N)), int).reshape(-1, N)


def tolerance():
    """``(rtol, atol)`` of a cost comparison in this run: with x64 (the suite's
    default) 1e-9 relative, a few float64 ulps; in the float32 run (``pytest
    --float32``) 1e-5 relative (about 80 float32 ulps: the library's float32
    sums against the float64 reference) plus 1e-6 absolute for costs near 0."""
    import jax

    return (1e-9, 0.0) if jax.config.jax_enable_x64 else (1e-5, 1e-6)


def same_cost(a, b, rtol=None, atol=None):
    """Equal costs up to ``rtol`` relative plus ``atol`` (default: ``tolerance()``;
    the library and the reference evaluate the same sums at other batch shapes
    or precisions). Two infinite costs (both infeasible) are equal; finite and
    infinite never; NaN never. Scalars or arrays (then every element)."""
    default_rtol, default_atol = tolerance()
    rtol = default_rtol if rtol is None else rtol
    atol = default_atol if atol is None else atol
    a, b = np.asarray(a, float), np.asarray(b, float)
    with np.errstate(invalid="ignore"):
        close = np.where(np.isinf(a) | np.isinf(b), a == b,
                         np.abs(a - b) <= rtol * np.maximum(np.abs(a), np.abs(b)) + atol)
    return bool(np.all(close))
