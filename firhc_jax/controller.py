"""The receding horizon law (eq. 4) and its closed loop.

``FIRHC(problem)`` solves the finite-horizon problem at the current state and
applies the first input of the optimal sequence. ``simulate`` steps a plant
for T steps, compiled as one ``lax.scan`` (``compiled=True``) or from Python
with a jitted decision and per-step solve times (``compiled=False``).

The closed loop separates plant and model (the do-mpc split):

* ``plant(x, u[, p]) -> x_next``: the simulated system (default: the model's
  ``dynamics``). Its state may differ from the model's.
* ``observe(x, u_prev[, p]) -> x_model``: what the controller sees, from the
  plant state and the input it chose last (the searched input, before
  ``actuate``; default: the plant state).
  ``with_input_memory`` builds one that feeds ``u_prev`` to a switching penalty.
* ``actuate(x, u[, p]) -> u_plant``: the input the plant receives, from the
  searched input (default: ``u``): combine it with inputs set by a fixed law,
  or gate it (valves sealed in flight).

With ``params`` (leaves with leading axis ``steps``) step k calls every
callable, the problem's and these, with ``params[k]``: a reference trajectory,
time-varying weights. New values of the same shapes never recompile.
"""
from __future__ import annotations

import time
import warnings
from typing import Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .cache import cached
from .checks import as_state, check_params, check_state, params_spec
from .exhaustive import exhaustive
from .problem import Problem, call, input_dtype, is_tracer, positive_int
from .progress import Progress, tick, tick_python
from .result import SearchResult
from .sdfs import sdfs

_SOLVERS = {"sdfs": sdfs, "exhaustive": exhaustive}
_OPTIONS = {"sdfs": {"pop_width", "max_nodes", "max_memory"}, "exhaustive": {"method", "chunk_nodes", "pop_width"}}


class InfeasibleError(RuntimeError):
    """No input sequence meets the terminal constraint and no fallback is set."""


class ClosedLoop(NamedTuple):
    """A closed-loop run of T steps."""

    states: jax.Array  # [T+1, n] plant states x(0) .. x(T)
    inputs: jax.Array  # [T, m'] inputs applied to the plant (after actuate); NaN when no input was found
    input_indices: jax.Array  # [T] int32 index into controls of the searched input (-1: none)
    stage_costs: jax.Array  # [T] model stage cost of the applied step, stage_cost(dynamics(x_model, u), u)
    predicted_costs: jax.Array  # [T] optimal cost of each step's search (+inf: infeasible)
    nodes: jax.Array  # [T] int32 nodes of the terminal-constrained search
    fallback_nodes: jax.Array  # [T] int32 nodes of the fallback search (0 when not used)
    feasible: jax.Array  # [T] bool the terminal constraint could be met
    used_fallback: jax.Array  # [T] bool the input came from the fallback search
    complete: jax.Array  # [T] bool every search behind the decision ran to the end (not stopped by max_nodes)
    solve_times: jax.Array  # [T] seconds per decision (compiled=False only; NaN in a compiled scan)

    @property
    def first_infeasible_step(self) -> Optional[int]:
        """Index of the first step without a feasible sequence, or None."""
        bad = np.flatnonzero(~np.asarray(self.feasible))
        return int(bad[0]) if bad.size else None


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


class FIRHC:
    """Finite-input receding horizon controller.

    Args:
      problem: the ``Problem`` solved at every step.
      solver: ``"sdfs"`` (default) or ``"exhaustive"``.
      fallback: what to do when no sequence meets the terminal constraint.
        ``None`` (default): report it; ``__call__`` raises ``InfeasibleError``
        when un-jitted and the applied input is NaN in ``simulate``.
        ``"unconstrained"``: apply the optimum of the same problem without the
        terminal constraint (and without its lower bound, whose ``+inf`` no
        longer holds), flagged in ``used_fallback``. A ``Problem`` (same
        horizon and inputs): apply its optimum instead, e.g. the relaxed
        problem with a bound of its own.
      warm_start: (sdfs only) ``True``: seed each search with the previous
        solution shifted by one step (the last input repeated). A callable
        ``warm_start(problem, x, previous, params) -> [N]`` int sequence (all
        -1: none) picks the seed itself (``previous``: the last decision's
        sequence; ``problem``: the one being searched, main or fallback).
        Exactness unchanged: a seed only sets the first incumbent.
      observe, actuate: plant/model maps of the closed loop (module docstring).
      **solver_options: passed to the solver: ``pop_width``, ``max_nodes``,
        ``max_memory`` for sdfs; ``method``, ``chunk_nodes``, ``pop_width``
        for exhaustive. Unknown options are refused here.
    """

    def __init__(self, problem: Problem, solver: str = "sdfs", *, fallback=None,
                 warm_start=False, observe: Optional[Callable] = None, actuate: Optional[Callable] = None,
                 **solver_options):
        if not isinstance(problem, Problem):
            raise TypeError(f"problem must be a firhc_jax.Problem, got {type(problem).__name__}")
        if solver not in _SOLVERS:
            raise ValueError(f"solver must be one of {sorted(_SOLVERS)}, got {solver!r}")
        unknown = set(solver_options) - _OPTIONS[solver]
        if unknown:
            raise TypeError(f"unknown option(s) {sorted(unknown)} for solver={solver!r}; "
                            f"it accepts {sorted(_OPTIONS[solver])}")
        if isinstance(fallback, Problem):
            if (fallback.horizon, fallback.num_controls) != (problem.horizon, problem.num_controls):
                raise ValueError(f"a fallback Problem needs the problem's horizon and inputs (N={problem.horizon}, "
                                 f"M={problem.num_controls}), got N={fallback.horizon}, M={fallback.num_controls}")
        elif fallback not in (None, "unconstrained"):
            raise ValueError(f"fallback must be None, 'unconstrained' or a Problem, got {fallback!r}")
        if not isinstance(warm_start, bool) and not callable(warm_start):
            raise TypeError(f"warm_start must be a bool or a callable (problem, x, previous, params) -> [N], "
                            f"got {type(warm_start).__name__}")
        if warm_start is not False and solver != "sdfs":
            raise ValueError("warm_start applies to solver='sdfs' only")
        for name, fn in (("observe", observe), ("actuate", actuate)):
            if fn is not None and not callable(fn):
                raise TypeError(f"{name} must be callable or None, got {type(fn).__name__}")
        self.problem, self.solver, self.fallback = problem, solver, fallback
        self.warm_start = warm_start
        self.observe, self.actuate = observe, actuate
        self.solver_options = dict(solver_options)
        # Without the terminal set a bound's +inf ("terminal set out of reach") no longer holds: drop it too.
        if isinstance(fallback, Problem):
            self._relaxed = fallback
        else:
            self._relaxed = (problem.replace(terminal=None, lower_bound=None)
                             if fallback and problem.terminal is not None else None)
        # What a compiled closed loop depends on: equal keys share one executable.
        self._key = (problem.key, solver, fallback.key if isinstance(fallback, Problem) else fallback,
                     self.warm_start, observe, actuate,
                     tuple(sorted(self.solver_options.items())))

    def _search(self, problem, x, params, previous):
        opts = dict(self.solver_options)
        if callable(self.warm_start) and previous is not None:
            opts["warm_start"] = jnp.asarray(self.warm_start(problem, x, previous, params), jnp.int32)
        elif self.warm_start and previous is not None:
            shifted = jnp.concatenate([previous[1:], previous[-1:]])
            opts["warm_start"] = jnp.where(previous[0] >= 0, shifted, -1)  # -1: none
        return _SOLVERS[self.solver](problem, x, params=params, **opts)

    def _solve(self, x, params, previous):
        """``(deciding result, nodes of the constrained search, used_fallback)``."""
        result = self._search(self.problem, x, params, previous)
        if self._relaxed is None:
            return result, result.nodes, np.False_  # eager calls: NumPy scalars cost no dispatch (traced: constants)

        def fall_back(_):  # only searched when needed (both run under vmap)
            relaxed = self._search(self._relaxed, x, params, previous)
            return relaxed._replace(iterations=result.iterations + relaxed.iterations,
                                    negative_cost=result.negative_cost | relaxed.negative_cost,
                                    nan_encountered=result.nan_encountered | relaxed.nan_encountered,
                                    overflow=result.overflow | relaxed.overflow,
                                    complete=result.complete & relaxed.complete), np.True_

        if is_tracer(result.feasible):
            chosen, used = jax.lax.cond(result.feasible, lambda _: (result, np.False_), fall_back, None)
        else:
            chosen, used = (result, np.False_) if np.asarray(result.feasible) else fall_back(None)
        return chosen, result.nodes, used

    def solve(self, x, params=None, previous_sequence=None) -> tuple[SearchResult, jax.Array]:
        """Search at model state ``x``; returns ``(result, used_fallback)``.

        When the fallback decided, ``result`` is the fallback search's, with
        the first search's iterations added, its error flags kept, and
        ``complete`` only if both searches ran to the end (a constrained
        search stopped by ``max_nodes`` has not proven infeasibility).
        ``previous_sequence`` seeds the warm start (ignored unless
        ``warm_start``; an all ``-1`` sequence, i.e. infeasible, is no warm
        start and costs no nodes).
        """
        prev = None
        if self.warm_start and previous_sequence is not None:
            prev = jnp.asarray(previous_sequence, jnp.int32)
        result, _, used = self._solve(x, params, prev)
        return result, used

    def __call__(self, x, params=None, previous_sequence=None) -> tuple[jax.Array, SearchResult]:
        """The FIRHC law at model state ``x``: ``(u, result)`` with
        ``u = controls[sequence[0]]`` (eq. 4)."""
        result, _ = self.solve(x, params, previous_sequence)
        if self.fallback is None and not is_tracer(result.feasible) and not np.asarray(result.feasible):
            why = (" (the accumulated cost overflowed: scale the cost down or use float64)"
                   if np.asarray(result.overflow) else "")
            raise InfeasibleError(f"no input sequence of length {self.problem.horizon} meets the terminal "
                                  f"constraint with a finite cost from this state{why}; use "
                                  "fallback='unconstrained' or relax the constraint")
        return result.first_input, result

    # -- closed loop -------------------------------------------------------------
    def simulate(self, x0, steps: int, plant: Optional[Callable] = None, *, params=None, u0=None,
                 progress: bool = False, compiled: bool = True) -> ClosedLoop:
        """Run the closed loop for ``steps`` steps from plant state ``x0``.

        Args:
          plant: ``plant(x, u[, p]) -> x_next``, default the model's dynamics.
          params: optional pytree whose leaves have leading axis ``steps``:
            step k is solved (and simulated) with ``params[k]``.
          u0: the input applied before step 0 (seen by ``observe``); default
            zeros.
          compiled: ``True``: one ``lax.scan`` (everything traceable);
            ``False``: a Python loop over a jitted decision, for a plant that
            cannot be traced, and with each decision timed in ``solve_times``.
        """
        steps = positive_int("steps", steps)
        x0 = jnp.asarray(as_state(x0))
        params = check_params(params, leading=steps, axis="steps")
        m = self.problem.input_dim
        u0 = jnp.zeros((m,), input_dtype(self.problem)) if u0 is None else jnp.asarray(u0, input_dtype(self.problem))
        if u0.shape != (m,):
            raise ValueError(f"u0 must be one input of shape ({m},), got {tuple(u0.shape)}")
        default_plant = plant is None
        plant = plant or self.problem.model_plant
        if not callable(plant):
            raise TypeError(f"plant must be callable, got {type(plant).__name__}")
        p0 = None if params is None else jax.tree_util.tree_map(lambda a: a[0], params)
        pkey, _ = params_spec(p0)
        cached(("closed-loop check", self._key, plant if compiled else None, x0.shape, jnp.dtype(x0.dtype),
                jnp.dtype(u0.dtype), pkey),
               lambda: self._check_loop(plant if compiled else None, x0, u0, p0, params is not None,
                                        default_plant))
        with Progress(steps, f"FIRHC[{self.solver}]", enabled=progress):
            if compiled:
                key = ("closed loop", self._key, plant, steps, progress)
                run = cached(key, lambda: jax.jit(lambda x, u, p: self._scan(plant, x, u, p, steps, progress)))
                out = run(x0, u0, params)
            else:
                out = self._python_loop(plant, x0, u0, params, steps, progress)
        if self.fallback is None and not is_tracer(out.feasible) and not bool(jnp.all(out.feasible)):
            warnings.warn(f"closed loop: no feasible input sequence at step {out.first_infeasible_step}; "
                          "inputs are NaN from there (set fallback='unconstrained' to continue)",
                          RuntimeWarning, stacklevel=2)
        return out

    def _check_loop(self, plant, x0, u0, p0, with_params, default_plant=False):
        """Check observe, actuate and (when traced) plant abstractly, each blamed by name."""
        def shape(fn, name, *args):
            try:
                return jax.eval_shape(lambda p, *a: call(fn, p, *a), p0 if with_params else None, *args)
            except (TypeError, ValueError, KeyError, IndexError, AttributeError) as e:
                hint = ("; the default plant is the model's dynamics, which with observe set runs on model "
                        "states: pass plant= with the plant's own dynamics") if default_plant and "plant" in name \
                    else ""
                cls = ValueError if isinstance(e, ValueError) else TypeError
                raise cls(f"{name} failed on the closed loop's shapes: {type(e).__name__}: {e}{hint}") from e

        x = jax.ShapeDtypeStruct(x0.shape, x0.dtype)
        u = jax.ShapeDtypeStruct(u0.shape, u0.dtype)
        xm = shape(self.observe, "observe(x, u_prev[, p])", x, u) if self.observe else x
        if not isinstance(xm, jax.ShapeDtypeStruct):
            raise TypeError(f"observe must return one array (the model state), got {type(xm).__name__}")
        check_state(self.problem, jnp.zeros(xm.shape, xm.dtype), p0)
        up = shape(self.actuate, "actuate(x, u[, p])", x, u) if self.actuate else u
        if not isinstance(up, jax.ShapeDtypeStruct):
            raise TypeError(f"actuate must return one array (the plant input), got {type(up).__name__}")
        if plant is None:
            return
        out = shape(plant, "plant(x, u[, p])", x, up)
        if not isinstance(out, jax.ShapeDtypeStruct) or out.shape != x.shape or out.dtype != x.dtype:
            desc = f"shape {tuple(out.shape)} dtype {out.dtype}" if isinstance(out, jax.ShapeDtypeStruct) \
                else type(out).__name__
            raise TypeError(f"plant(x, u[, p]) must return the next plant state, shape {tuple(x.shape)} dtype "
                            f"{x.dtype} like x0; got {desc}"
                            + ("; the default plant is the model's dynamics: with observe set, pass plant="
                               if default_plant and self.observe is not None else ""))

    def _decide(self, x, u_prev, previous, p):
        """One decision from plant state ``x``: ``(u, u_plant, sequence, record)``
        where record lacks the next state."""
        xm = call(self.observe, p, x, u_prev) if self.observe else x
        result, nodes, used = self._solve(xm, p, previous if self.warm_start else None)
        u = result.first_input
        u_plant = call(self.actuate, p, x, u) if self.actuate else u
        idx = result.sequence[0]
        u_model = jnp.asarray(self.problem.controls)[jnp.maximum(idx, 0)]
        stage = self.problem.cost_of_step(self.problem.next_state(xm, u_model, 0, p), u_model, 0, p)
        record = (u_plant, idx, jnp.where(idx >= 0, stage, jnp.nan), result.cost, nodes,
                  jnp.where(used, result.nodes, 0), result.feasible & ~used, used, result.complete)
        return u, u_plant, result.sequence, record

    def _scan(self, plant, x0, u0, params, steps, progress):
        def body(carry, inp):
            x, u_prev, previous = carry
            k, p = inp
            u, u_plant, seq, record = self._decide(x, u_prev, previous, p)
            x_next = call(plant, p, x, u_plant)
            if progress:
                tick(k)
            return (x_next, u, seq), (x_next,) + record

        prev0 = jnp.full((self.problem.horizon,), -1, jnp.int32)
        _, rec = jax.lax.scan(body, (x0, u0, prev0), (jnp.arange(steps), params))
        return _closed_loop(x0, rec, jnp.full((steps,), jnp.nan))

    def _python_loop(self, plant, x0, u0, params, steps, progress):
        x, u, previous = x0, u0, jnp.full((self.problem.horizon,), -1, jnp.int32)
        rows = [None if params is None else jax.tree_util.tree_map(lambda a, k=k: a[k], params) for k in range(steps)]
        args = (x, u, previous, rows[0])
        spec = jax.tree_util.tree_map(lambda a: (a.shape, jnp.dtype(a.dtype)), args)
        # Compiled ahead of time (and cached), so that solve_times never include compilation.
        decide = cached(("closed-loop decision", self._key, jax.tree_util.tree_structure(args), str(spec)),
                        lambda: jax.jit(self._decide).lower(*args).compile())
        records, times = [], []
        for k in range(steps):
            t0 = time.perf_counter()
            u, u_plant, previous, record = jax.block_until_ready(decide(x, u, previous, rows[k]))
            times.append(time.perf_counter() - t0)
            x_next = call(plant, rows[k], x, u_plant)
            if not hasattr(x_next, "shape") or tuple(np.shape(x_next)) != x.shape:
                raise TypeError(f"plant(x, u[, p]) must return the next plant state of shape {tuple(x.shape)} "
                                f"like x0, got {type(x_next).__name__} of shape {np.shape(x_next)} at step {k}")
            x = jnp.asarray(x_next, x.dtype)
            records.append((x,) + record)
            if progress:
                tick_python(k)
        return _closed_loop(x0, jax.tree.map(lambda *a: jnp.stack(a), *records), jnp.asarray(times))


def _closed_loop(x0, rec, times) -> ClosedLoop:
    xs, us, idx, stage, pred, nodes, fb_nodes, feas, used, complete = rec
    return ClosedLoop(states=jnp.concatenate([x0[None], xs]), inputs=us, input_indices=idx, stage_costs=stage,
                      predicted_costs=pred, nodes=nodes, fallback_nodes=fb_nodes, feasible=feas, used_fallback=used,
                      complete=complete, solve_times=times)
