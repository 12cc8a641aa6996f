"""The receding horizon law (eq. 4) and its closed loop.

``FIRHC(problem)`` solves the finite-horizon problem at the current state and
applies the first input of the optimal sequence. ``simulate`` steps a plant
(the prediction model by default, or any other ``plant(x, u) -> x_next``) for
T steps, compiled as one ``lax.scan`` when the plant is traceable.
"""
from __future__ import annotations

import warnings
from typing import Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .exhaustive import exhaustive
from .problem import Problem, check_state
from .progress import Progress, tick, tick_python
from .result import SearchResult
from .sdfs import sdfs

_SOLVERS = {"sdfs": sdfs, "exhaustive": exhaustive}


class InfeasibleError(RuntimeError):
    """No input sequence meets the terminal constraint and no fallback is set."""


class ClosedLoop(NamedTuple):
    """A closed-loop run of T steps."""

    states: jax.Array  # [T+1, n] x(0) .. x(T)
    inputs: jax.Array  # [T, m] applied inputs (NaN from a step with no feasible input and no fallback)
    input_indices: jax.Array  # [T] int32 index into controls (-1: none)
    stage_costs: jax.Array  # [T] realised stage cost of each applied step
    predicted_costs: jax.Array  # [T] optimal cost of each step's search (+inf: infeasible)
    nodes: jax.Array  # [T] int32 nodes computed per step (fallback search included)
    feasible: jax.Array  # [T] bool the terminal constraint could be met
    used_fallback: jax.Array  # [T] bool the input came from the fallback search

    @property
    def first_infeasible_step(self) -> Optional[int]:
        """Index of the first step without a feasible sequence, or None."""
        bad = np.flatnonzero(~np.asarray(self.feasible))
        return int(bad[0]) if bad.size else None


class FIRHC:
    """Finite-input receding horizon controller.

    Args:
      problem: the ``Problem`` solved at every step.
      solver: ``"sdfs"`` (default) or ``"exhaustive"``.
      fallback: what to do when no sequence meets the terminal constraint.
        ``None`` (default): report it; ``__call__`` raises ``InfeasibleError``
        when un-jitted and the applied input is NaN in ``simulate``.
        ``"unconstrained"``: apply the optimum of the same problem without the
        terminal constraint, flagged in ``used_fallback``.
      warm_start: (sdfs only) seed each search with the previous solution
        shifted by one step (the last input repeated); exactness unchanged.
      **solver_options: passed to the solver (``pop_width`` for sdfs,
        ``method``/``chunk_nodes`` for exhaustive).
    """

    def __init__(self, problem: Problem, solver: str = "sdfs", *, fallback: Optional[str] = None,
                 warm_start: bool = False, **solver_options):
        if solver not in _SOLVERS:
            raise ValueError(f"solver must be one of {sorted(_SOLVERS)}, got {solver!r}")
        if fallback not in (None, "unconstrained"):
            raise ValueError(f"fallback must be None or 'unconstrained', got {fallback!r}")
        if warm_start and solver != "sdfs":
            raise ValueError("warm_start applies to solver='sdfs' only")
        self.problem, self.solver, self.fallback = problem, solver, fallback
        self.warm_start = bool(warm_start)
        self.solver_options = solver_options
        self._relaxed = problem.replace(terminal=None) if fallback and problem.terminal is not None else None
        self._scan_cache = {}

    def _search(self, problem, x, previous):
        opts = dict(self.solver_options)
        if self.warm_start and previous is not None:
            opts["warm_start"] = jnp.concatenate([previous[1:], previous[-1:]])
        return _SOLVERS[self.solver](problem, x, **opts)

    def solve(self, x, previous_sequence=None) -> tuple[SearchResult, jax.Array]:
        """Search at state ``x``; returns ``(result, used_fallback)``.

        ``previous_sequence`` seeds the warm start (ignored unless
        ``warm_start``; a ``-1`` sequence, i.e. infeasible, is not used).
        """
        prev = None
        if self.warm_start and previous_sequence is not None:
            prev = jnp.asarray(previous_sequence)
            prev = jnp.where(prev[0] >= 0, prev, 0)
        result = self._search(self.problem, x, prev)
        if self._relaxed is None:
            return result, jnp.array(False)

        def fall_back(_):  # only searched when needed (both run under vmap)
            relaxed = self._search(self._relaxed, x, prev)
            return relaxed._replace(nodes=result.nodes + relaxed.nodes), jnp.array(True)

        if isinstance(result.feasible, jax.core.Tracer):
            return jax.lax.cond(result.feasible, lambda _: (result, jnp.array(False)), fall_back, None)
        return (result, jnp.array(False)) if bool(result.feasible) else fall_back(None)

    def __call__(self, x, previous_sequence=None) -> tuple[jax.Array, SearchResult]:
        """The FIRHC law: ``(u, result)`` with ``u = controls[sequence[0]]`` (eq. 4)."""
        result, _ = self.solve(x, previous_sequence)
        if self.fallback is None and not isinstance(result.feasible, jax.core.Tracer) \
                and not bool(result.feasible):
            raise InfeasibleError(f"no input sequence of length {self.problem.horizon} meets the terminal "
                                  "constraint from this state; use fallback='unconstrained' or relax it")
        return result.first_input, result

    def simulate(self, x0, steps: int, plant: Optional[Callable] = None, *, progress: bool = False,
                 compiled: bool = True) -> ClosedLoop:
        """Run the closed loop for ``steps`` steps from ``x0``.

        ``plant(x, u) -> x_next`` defaults to the prediction model; it may
        differ (model error). With ``compiled=True`` the whole run is one
        ``lax.scan`` (the plant must be traceable); ``compiled=False`` steps
        an un-traceable plant from Python with a jitted search.
        """
        if not isinstance(steps, int) or isinstance(steps, bool) or steps < 1:
            raise ValueError(f"steps must be an int >= 1, got {steps!r}")
        x0 = check_state(self.problem, x0)
        plant = plant or self.problem.dynamics
        with Progress(steps, f"FIRHC[{self.solver}]", enabled=progress):
            if compiled:
                run = self._scan_cache.get((plant, steps, progress))
                if run is None:
                    run = jax.jit(lambda x: self._scan(plant, x, steps, progress))
                    self._scan_cache[(plant, steps, progress)] = run
                out = run(x0)
            else:
                out = self._python_loop(plant, x0, steps, progress)
        if self.fallback is None and not bool(jnp.all(out.feasible)):
            warnings.warn(f"closed loop: no feasible input sequence at step {out.first_infeasible_step}; "
                          "inputs are NaN from there (set fallback='unconstrained' to continue)",
                          RuntimeWarning, stacklevel=2)
        return out

    def _decide(self, x, previous):
        """One control decision: ``(u, sequence, record-without-state)``."""
        result, used = self.solve(x, previous)
        return result.first_input, result.sequence, (result.sequence[0], result.cost, result.nodes,
                                                     result.feasible & ~used, used)

    def _record(self, x_next, u, decision):
        idx, pred, nodes, feasible, used = decision
        return (x_next, u, idx, self.problem.stage_cost(x_next, u), pred, nodes, feasible, used)

    def _scan(self, plant, x0, steps, progress):
        def body(carry, k):
            x, previous = carry
            u, seq, decision = self._decide(x, previous)
            x_next = plant(x, u)
            if progress:
                tick(k)
            return (x_next, seq), self._record(x_next, u, decision)

        prev0 = jnp.full((self.problem.horizon,), -1, jnp.int32)
        _, rec = jax.lax.scan(body, (x0, prev0), jnp.arange(steps))
        return _closed_loop(x0, rec)

    def _python_loop(self, plant, x0, steps, progress):
        decide = jax.jit(self._decide)
        x, previous, records = x0, jnp.full((self.problem.horizon,), -1, jnp.int32), []
        for k in range(steps):
            u, previous, decision = decide(x, previous)
            x_next = jnp.asarray(plant(x, u), x.dtype)
            records.append(self._record(x_next, u, decision))
            x = x_next
            if progress:
                tick_python(k)
        return _closed_loop(x0, jax.tree.map(lambda *a: jnp.stack(a), *records))


def _closed_loop(x0, rec) -> ClosedLoop:
    xs, us, idx, stage, pred, nodes, feas, used = rec
    return ClosedLoop(states=jnp.concatenate([x0[None], xs]), inputs=us, input_indices=idx, stage_costs=stage,
                      predicted_costs=pred, nodes=nodes, feasible=feas, used_fallback=used)
