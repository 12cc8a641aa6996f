"""The receding horizon law (eq. 4): one decision, ``step``, and the closed loop built on it.

``FIRHC(problem)`` solves the finite-horizon problem at the current state and
applies the first input of the optimal sequence. One decision is a pure
function, ``u, state, info = ctrl.step(state, x, params)`` from
``state = ctrl.init(x0, u0)``: observe, search (warm start from the state,
fallback), actuate. A real-time loop calls it once per sampling period;
``simulate`` runs the same function for T steps, as one compiled ``lax.scan``
(``compiled=True``) or as a Python loop timing each decision
(``compiled=False``); a Python loop of ``step`` reproduces either.

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

No input found: when every search of a decision comes back empty (no sequence
with a finite cost meets the constraints, or ``max_nodes`` stopped the search
before any complete sequence), or the input found is not finite (a
``first_input_of`` returning NaN), a controller never hands a NaN to the plant.
``step`` and ``simulate`` apply a safe input instead: ``u_safe`` if given,
else the input applied last (``u0`` at the start), and flag the decision
(``info.held``, ``ClosedLoop.held``); ``simulate`` warns after a run with
held steps; the one-shot ``ctrl(x)`` raises ``InfeasibleError``.

With ``params`` (leaves with leading axis ``steps``) step k calls every
callable, the problem's and these, with ``params[k]``: a reference trajectory,
time-varying weights. New values of the same shapes never recompile.
"""
from __future__ import annotations

import functools
import time
import warnings
from typing import Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .cache import cached
from .checks import as_state, check_params, check_state, params_spec
from .closed_loop import ClosedLoop
from .exhaustive import exhaustive
from .problem import Problem, call, input_dtype, is_tracer, positive_int
from .progress import Progress, due, interval, tick_python
from .result import SearchResult, raise_on_errors
from .sdfs import sdfs

_SOLVERS = {"sdfs": sdfs, "exhaustive": exhaustive}
_OPTIONS = {"sdfs": {"pop_width", "max_nodes", "max_memory"}, "exhaustive": {"method", "chunk_nodes", "pop_width"}}
_COUNTS = ("pop_width", "max_nodes", "max_memory", "chunk_nodes")


class InfeasibleError(RuntimeError):
    """A one-shot decision (``FIRHC.__call__``) found no input to apply."""


class ControllerState(NamedTuple):
    """What the next decision needs (a pytree: ``lax.scan`` carries it, ``vmap`` batches it)."""

    u: jax.Array  # [m] the searched input applied last, before actuate: observe's u_prev, the input held
    plan: jax.Array  # [N] int32 the last decision's sequence (all -1: none), the warm start's seed


class StepInfo(NamedTuple):
    """What one decision did (``FIRHC.step``); ``ClosedLoop`` holds these stacked over the steps."""

    result: SearchResult  # the deciding search: the fallback's when used_fallback
    used_fallback: jax.Array  # [] bool the input came from the fallback search
    complete: jax.Array  # [] bool every search behind the decision ran to the end (not stopped by max_nodes)
    nodes: jax.Array  # [] int32 nodes of the terminal-constrained search
    fallback_nodes: jax.Array  # [] int32 nodes of the fallback search (0 when not used)
    feasible: jax.Array  # [] bool the terminal-constrained search found a sequence
    held: jax.Array  # [] bool no input found: the safe input (u_safe, else the last input) was applied
    stage_cost: jax.Array  # [] model stage cost of the applied step (NaN when held)

    @property
    def decision_nodes(self) -> jax.Array:
        """[] int32 nodes of the whole decision, both searches: at most ``max_nodes``."""
        return self.nodes + self.fallback_nodes


def _ready(a) -> bool:
    """An argument the compiled step takes as it is: a real NumPy array, or a JAX array (or tracer)
    without weak type (a weakly typed one would compile a second step for the same shapes)."""
    if type(a) is np.ndarray:
        return a.dtype.kind in "biuf"
    return isinstance(a, jax.Array) and not a.weak_type


def _spec(a) -> jax.ShapeDtypeStruct:
    return jax.ShapeDtypeStruct(np.shape(a), a.dtype)


class FIRHC:
    """Finite-input receding horizon controller.

    Args:
      problem: the ``Problem`` solved at every step.
      solver: ``"sdfs"`` (default) or ``"exhaustive"``.
      fallback: what to do when no sequence meets the terminal constraint.
        ``None`` (default): no input is found (see ``u_safe``).
        ``"unconstrained"``: apply the optimum of the same problem without the
        terminal set and without its lower bound (whose ``+inf`` no longer
        holds), ``problem.replace(terminal=None, lower_bound=None)``: every
        other field, stage and terminal costs and hard constraints included,
        is kept. Flagged in ``used_fallback``. A ``Problem`` (same horizon and
        inputs): apply its optimum instead, e.g. the relaxed problem with a
        bound of its own.
      warm_start: (sdfs only) ``True``: seed each search with the previous
        solution shifted by one step (the last input repeated). A callable
        ``warm_start(problem, x, previous, params) -> [N]`` int sequence (all
        -1: none) picks the seed itself (``previous``: the last decision's
        sequence; ``problem``: the one being searched, main or fallback).
        Exactness unchanged: a seed only sets the first incumbent.
      observe, actuate: plant/model maps of the closed loop (module docstring).
      u_safe: ``[m]`` the searched input applied (through ``actuate``) when a
        decision finds no input; default: hold the input applied last.
      **solver_options: passed to the solver: ``pop_width``, ``max_nodes``,
        ``max_memory`` for sdfs; ``method``, ``chunk_nodes``, ``pop_width``
        for exhaustive. Unknown options are refused here. ``max_nodes`` is
        the budget of a whole decision: the fallback search gets what the
        first one left.
    """

    def __init__(self, problem: Problem, solver: str = "sdfs", *, fallback=None,
                 warm_start=False, observe: Optional[Callable] = None, actuate: Optional[Callable] = None,
                 u_safe=None, **solver_options):
        if not isinstance(problem, Problem):
            raise TypeError(f"problem must be a firhc_jax.Problem, got {type(problem).__name__}")
        if solver not in _SOLVERS:
            raise ValueError(f"solver must be one of {sorted(_SOLVERS)}, got {solver!r}")
        unknown = set(solver_options) - _OPTIONS[solver]
        if unknown:
            raise TypeError(f"unknown option(s) {sorted(unknown)} for solver={solver!r}; "
                            f"it accepts {sorted(_OPTIONS[solver])}")
        for name in _COUNTS:
            if solver_options.get(name) is not None:
                solver_options[name] = positive_int(name, solver_options[name])
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
        self.u_safe = None if u_safe is None else self._input("u_safe", u_safe)
        # Without the terminal set a bound's +inf ("terminal set out of reach") no longer holds: drop it too.
        if isinstance(fallback, Problem):
            self._relaxed = fallback
        else:
            self._relaxed = (problem.replace(terminal=None, lower_bound=None)
                             if fallback and problem.terminal is not None else None)
        # What a compiled step or closed loop depends on: equal keys share one executable.
        safe = None if self.u_safe is None else (self.u_safe.dtype.str, self.u_safe.tobytes())
        self._key = (problem.key, solver, fallback.key if isinstance(fallback, Problem) else fallback,
                     self.warm_start, observe, actuate, safe, tuple(sorted(self.solver_options.items())))
        self._step_fn = None

    def _input(self, name: str, value) -> np.ndarray:
        """One searched input ``[m]`` of the problem's input dtype, finite, or a clear error."""
        m, dtype = self.problem.input_dim, input_dtype(self.problem)
        if is_tracer(value):
            raise TypeError(f"{name} must be concrete, not a traced array (it is compiled in as a constant)")
        try:
            a = np.asarray(value, dtype=dtype)
        except (TypeError, ValueError) as e:
            raise TypeError(f"{name} must be one input of shape ({m},): {e}") from None
        if a.shape != (m,):
            raise ValueError(f"{name} must be one input of shape ({m},), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} contains NaN or inf: {a}")
        return a

    # -- one decision --------------------------------------------------------------
    def init(self, x0, u0=None) -> ControllerState:
        """The state before the first decision at plant state ``x0``.

        ``u0``: the input applied before it (``observe``'s first ``u_prev``,
        and the input held if the first decision finds none); default zeros.
        ``x0`` is checked here (finite, real, 1-D floating); the callables are
        checked by the first ``step`` (they need the parameters' shapes).
        """
        as_state(x0)
        N, m, dtype = self.problem.horizon, self.problem.input_dim, input_dtype(self.problem)
        if u0 is None:
            u0 = np.zeros(m, dtype)
        elif is_tracer(u0):  # init under jit/vmap: a state like any other
            if u0.shape != (m,):
                raise ValueError(f"u0 must be one input of shape ({m},), got {u0.shape}")
            u0 = u0.astype(dtype)
        else:
            u0 = self._input("u0", u0)
        return ControllerState(u=u0, plan=np.full((N,), -1, np.int32))

    def step(self, state: ControllerState, x, params=None):
        """One decision at plant state ``x``: ``(u, state, info)``.

        Observe (``observe(x, state.u, params)``), search (warm start from
        ``state.plan``; the fallback if the first search finds nothing; the
        whole decision within ``max_nodes``), actuate. ``u`` is the input to
        apply to the plant (after ``actuate``); ``state`` the next decision's;
        ``info`` a ``StepInfo``. When no input is found ``u`` is the safe input
        (``u_safe``, else ``state.u`` held) and ``info.held`` is set; a
        non-finite state or parameter is met that way too (its nodes are
        discarded), flagged in ``info.result.nan_encountered``.

        Pure: works under ``jax.jit``, ``jax.vmap`` and ``lax.scan``.
        Eagerly it is one call of a compiled decision (compiled on the first
        call for each argument shape and dtype, which also checks the
        callables); nothing is checked or scanned per call, and error flags
        (``info.result.negative_cost``, ...) are reported, not raised.
        ``simulate`` is this function in a loop: a Python loop of ``step``
        with the same plant (jitted, as ``simulate`` compiles it) and
        per-step ``params`` gives the same states, to the last bit.
        """
        if type(state) is not ControllerState:
            raise TypeError(f"state must be the ControllerState from ctrl.init or ctrl.step, got "
                            f"{type(state).__name__}")
        if not _ready(x):
            x = as_state(x, "x")
        if params is not None and not all(map(_ready, jax.tree_util.tree_leaves(params))):
            params = check_params(params)
        fn = self._step_fn
        if fn is None:  # one jitted step per controller key, shared by equal controllers
            fn = self._step_fn = cached(("step", self._key), lambda: jax.jit(self._checked_step))
        return fn(state, x, params)

    def __call__(self, x, params=None, *, u_prev=None):
        """One-shot decision at plant state ``x``: ``(u, info)``.

        The first decision from scratch, ``step(init(x, u_prev), x, params)``
        (no warm start; ``info.used_fallback`` says which search decided),
        with the checks of a one-shot call: states and parameters are scanned
        for NaN, a negative stage cost raises ``ValueError``, and when no
        input is found it raises ``InfeasibleError`` (whatever the fallback)
        instead of holding. Inside ``jit``/``vmap`` it holds and flags like
        ``step``. In a loop over time use ``init``/``step``.
        """
        x = as_state(x)
        u, _, info = self.step(self.init(x, u_prev), x, check_params(params))
        if not is_tracer(info.held):
            raise_on_errors(info.result)
            if np.asarray(info.held):
                raise InfeasibleError(self._no_input_message(info))
        return u, info

    def solve(self, x, params=None, previous_sequence=None) -> tuple[SearchResult, jax.Array]:
        """The searches of one decision at *model* state ``x`` (no ``observe``,
        ``actuate`` or safe input): ``(result, used_fallback)``.

        When the fallback decided, ``result`` is the fallback search's, with
        the first search's iterations added, its error flags kept, and
        ``complete`` only if both searches ran to the end (a constrained
        search stopped by ``max_nodes`` has not proven infeasibility).
        ``previous_sequence`` seeds the warm start (ignored unless
        ``warm_start``; an all ``-1`` sequence, i.e. infeasible, is no warm
        start and costs no nodes). No input found: ``result.feasible`` is
        False and ``result.first_input`` NaN.
        """
        x, params = as_state(x, "x"), check_params(params)
        prev = None
        if self.warm_start and previous_sequence is not None:
            prev = np.asarray(previous_sequence)
            N, M = self.problem.horizon, self.problem.num_controls
            if prev.shape != (N,) or prev.dtype.kind not in "iu" or not (
                    np.all((prev >= 0) & (prev < M)) or np.all(prev == -1)):
                raise ValueError(f"previous_sequence must be [N] = [{N}] indices in [0, {M}) (or all -1), "
                                 f"got {prev.tolist()}")
            prev = prev.astype(np.int32)
        fn = cached(("solve", self._key), lambda: jax.jit(self._checked_solve))
        result, used = fn(x, params, prev)
        return raise_on_errors(result), used

    # -- the decision, traced --------------------------------------------------------
    def _search(self, problem, x, params, previous, budget=None):
        opts = dict(self.solver_options)
        if budget is not None:
            opts["max_nodes"] = budget
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
            return result, result.nodes, jnp.zeros((), bool)
        max_nodes = self.solver_options.get("max_nodes")

        def fall_back(_):  # only searched when needed (both run under vmap), within what the first search left
            left = None if max_nodes is None else jnp.maximum(max_nodes - result.nodes, 0)
            relaxed = self._search(self._relaxed, x, params, previous, left)
            return relaxed._replace(iterations=result.iterations + relaxed.iterations,
                                    negative_cost=result.negative_cost | relaxed.negative_cost,
                                    nan_encountered=result.nan_encountered | relaxed.nan_encountered,
                                    overflow=result.overflow | relaxed.overflow,
                                    complete=result.complete & relaxed.complete), jnp.ones((), bool)

        chosen, used = jax.lax.cond(result.feasible, lambda _: (result, jnp.zeros((), bool)), fall_back, None)
        return chosen, result.nodes, used

    def _checked_solve(self, x, params, previous):
        check_state(self.problem, x, params)
        result, _, used = self._solve(x, params, previous)
        return result, used

    def _decide(self, state: ControllerState, x, p):
        """One decision (``step`` without its argument handling)."""
        xm = call(self.observe, p, x, state.u) if self.observe else x
        result, nodes, used = self._solve(xm, p, state.plan if self.warm_start else None)
        # A non-finite input (a first_input_of returning NaN or inf) is no input: the safe input replaces it.
        held = ~result.feasible | ~jnp.all(jnp.isfinite(result.first_input))
        u = jnp.where(held, state.u if self.u_safe is None else self.u_safe, result.first_input)
        u_plant = call(self.actuate, p, x, u) if self.actuate else u
        idx = result.sequence[0]
        u_model = jnp.asarray(self.problem.controls)[jnp.maximum(idx, 0)]
        stage = self.problem.cost_of_step(self.problem.next_state(xm, u_model, 0, p), u_model, 0, p)
        info = StepInfo(result=result, used_fallback=used, complete=result.complete, nodes=nodes,
                        fallback_nodes=jnp.where(used, result.nodes, 0), feasible=result.feasible & ~used,
                        held=held, stage_cost=jnp.where(held, jnp.nan, stage))
        return u_plant, ControllerState(u=u, plan=jnp.where(held, -1, result.sequence)), info

    def _checked_step(self, state: ControllerState, x, p):
        """``_decide`` after the abstract checks (run while jit traces: once per argument signature)."""
        pkey, pspec = params_spec(p)
        key = ("step check", self._key, _spec(state.u), _spec(state.plan), _spec(x), pkey)
        cached(key, lambda: self._check_step(_spec(state.u), _spec(state.plan), _spec(x), pspec))
        return self._decide(state, x, p)

    def _check_step(self, u, plan, x, pspec, default_plant=False):
        """Check a decision's argument shapes, ``observe``, the problem on the model state and
        ``actuate``, each blamed by name; returns the plant input's shape and dtype."""
        N, m = self.problem.horizon, self.problem.input_dim
        if u.shape != (m,) or plan.shape != (N,) or not jnp.issubdtype(plan.dtype, jnp.integer):
            raise ValueError(f"state does not belong to this controller: u {u.shape}, plan {plan.shape} "
                             f"{plan.dtype}, expected u ({m},) and plan ({N},) int32; make it with ctrl.init")
        if len(x.shape) != 1 or not jnp.issubdtype(x.dtype, jnp.floating):
            raise TypeError(f"x must be a 1-D real floating state [n], got shape {x.shape} dtype {x.dtype}")
        if pspec is not None:
            for path, leaf in jax.tree_util.tree_flatten_with_path(pspec)[0]:
                if jnp.dtype(leaf.dtype).kind not in "biuf":
                    raise TypeError(f"params leaf {jax.tree_util.keystr(path)} must be a real numeric or boolean "
                                    f"array, got dtype {leaf.dtype}")

        def shape(fn, name, *args):
            try:
                return jax.eval_shape(lambda p, *a: call(fn, p, *a), pspec, *args)
            except (TypeError, ValueError, KeyError, IndexError, AttributeError) as e:
                cls = ValueError if isinstance(e, ValueError) else TypeError
                raise cls(f"{name} failed on the closed loop's shapes: {type(e).__name__}: {e}") from e

        xm = shape(self.observe, "observe(x, u_prev[, p])", x, u) if self.observe else x
        if not isinstance(xm, jax.ShapeDtypeStruct):
            raise TypeError(f"observe must return one array (the model state), got {type(xm).__name__}")
        check_state(self.problem, np.zeros(xm.shape, xm.dtype), pspec)
        up = shape(self.actuate, "actuate(x, u[, p])", x, u) if self.actuate else u
        if not isinstance(up, jax.ShapeDtypeStruct):
            raise TypeError(f"actuate must return one array (the plant input), got {type(up).__name__}")
        return up

    def _no_input_message(self, info: StepInfo) -> str:
        """Why a decision found no input, in the problem's own terms."""
        p, r, N = self.problem, info.result, self.problem.horizon
        if np.asarray(r.feasible):  # held although a sequence was found: its input is not finite
            return (f"first_input_of returned a non-finite input {np.asarray(r.first_input).tolist()} for the "
                    f"optimal sequence {np.asarray(r.sequence).tolist()}; a controller never applies it")
        if not np.asarray(info.complete):
            return (f"no input found: the search stopped at max_nodes={self.solver_options.get('max_nodes')} "
                    f"(the whole decision's budget) before it reached a complete input sequence of length {N}; "
                    "raise max_nodes")
        needs = ["a finite cost"]
        if p.terminal is not None:
            needs.append("the terminal constraint met")
        if getattr(p, "constraint", None) is not None:
            needs.append("every constraint satisfied")
        msg = f"no input sequence of length {N} with {' and '.join(needs)} was found from this state"
        if np.asarray(info.used_fallback):
            msg += "; the fallback search found none either"
        if np.asarray(r.overflow):
            msg += " (the accumulated cost overflowed: scale the cost down or use float64)"
        if np.asarray(r.nan_encountered):
            msg += " (non-finite states or NaN costs were met and discarded: check the state and the parameters)"
        if p.terminal is not None and self.fallback is None:
            msg += "; use fallback='unconstrained' or relax the terminal constraint"
        return msg

    # -- closed loop -------------------------------------------------------------
    def simulate(self, x0, steps: int, plant: Optional[Callable] = None, *, params=None, u0=None, dt=None,
                 progress: bool = False, compiled: bool = True) -> ClosedLoop:
        """Run the closed loop for ``steps`` steps from plant state ``x0``: ``step`` then ``plant``.

        Args:
          plant: ``plant(x, u[, p]) -> x_next``, default the model's dynamics.
          params: optional pytree whose leaves have leading axis ``steps``:
            step k is solved (and simulated) with ``params[k]``.
          u0: the input applied before step 0 (seen by ``observe``, held if
            the first decision finds none); default zeros.
          dt: the sampling period in seconds: the run gets ``times`` ``[T+1]``
            (``k * dt``) and plots against time.
          progress: a progress bar (at most ``progress.TICKS`` updates; a
            compiled run is then one compiled chunk of steps dispatched
            again and again, with the same results to the last bit).
          compiled: ``True``: one ``lax.scan`` (everything traceable);
            ``False``: a Python loop over the compiled ``step``, for a plant
            that cannot be traced, and with each decision timed in
            ``solve_times`` (compiled before the loop, so never counted).
            The plant is called as it is: jit it, or each of its
            operations is one eager dispatch a step.

        Steps where no input was found hold the safe input (``held``); a
        ``RuntimeWarning`` follows such a run.
        """
        steps = positive_int("steps", steps)
        x0 = as_state(x0)
        params = check_params(params, leading=steps, axis="steps")
        state = self.init(x0, u0)
        times = None
        if dt is not None:
            if isinstance(dt, (bool, np.bool_)) or not isinstance(dt, (int, float, np.integer, np.floating)) \
                    or not np.isfinite(dt) or dt <= 0:
                raise ValueError(f"dt must be a finite positive number of seconds, got {dt!r}")
            times = np.arange(steps + 1) * float(dt)
        default_plant = plant is None
        if not default_plant and not callable(plant):
            raise TypeError(f"plant must be callable, got {type(plant).__name__}")
        # The default plant is keyed as None: the model_plant of an equal problem is another bound method.
        plant_key, plant = (None, self.problem.model_plant) if default_plant else (plant, plant)
        pkey, pspec = params_spec(params, drop_leading=True)
        cached(("closed-loop check", self._key, plant_key if compiled else False, _spec(x0), _spec(state.u), pkey),
               lambda: self._check_loop(plant if compiled else None, _spec(state.u), _spec(state.plan),
                                        _spec(x0), pspec, default_plant))
        with Progress(steps, f"FIRHC[{self.solver}]", enabled=progress):
            if compiled:
                out = self._compiled_loop(plant, plant_key, state, x0, params, steps, progress)
            else:
                out = self._python_loop(plant, state, x0, params, steps, progress)
        if not is_tracer(out.held):
            held = np.flatnonzero(np.asarray(out.held))
            if held.size:
                what = "u_safe" if self.u_safe is not None else "the input applied last"
                warnings.warn(f"closed loop: no feasible input sequence found (or its first input was not finite) "
                              f"at {held.size} of {steps} steps "
                              f"(first: step {held[0]}); {what} was held there, flagged in ClosedLoop.held",
                              RuntimeWarning, stacklevel=2)
        return out._replace(times=times)

    def _check_loop(self, plant, u, plan, x, pspec, default_plant):
        """The step's checks, then (when traced) the plant's, each blamed by name."""
        try:
            up = self._check_step(u, plan, x, pspec)
        except (TypeError, ValueError) as e:
            if default_plant and self.observe is not None and "x0" in str(e):
                raise type(e)(f"{e}; the default plant is the model's dynamics, which with observe set runs on "
                              "model states: pass plant= with the plant's own dynamics") from e
            raise
        if plant is None:
            return
        try:
            out = jax.eval_shape(lambda p, *a: call(plant, p, *a), pspec, x, up)
        except (TypeError, ValueError, KeyError, IndexError, AttributeError) as e:
            hint = ("; the default plant is the model's dynamics, which with observe set runs on model "
                    "states: pass plant= with the plant's own dynamics") if default_plant else ""
            cls = ValueError if isinstance(e, ValueError) else TypeError
            raise cls(f"plant(x, u[, p]) failed on the closed loop's shapes: {type(e).__name__}: {e}{hint}") from e
        if not isinstance(out, jax.ShapeDtypeStruct) or out.shape != x.shape or out.dtype != x.dtype:
            desc = f"shape {tuple(out.shape)} dtype {out.dtype}" if isinstance(out, jax.ShapeDtypeStruct) \
                else type(out).__name__
            raise TypeError(f"plant(x, u[, p]) must return the next plant state, shape {tuple(x.shape)} dtype "
                            f"{x.dtype} like x0; got {desc}"
                            + ("; the default plant is the model's dynamics: with observe set, pass plant="
                               if default_plant and self.observe is not None else ""))

    def _compiled_loop(self, plant, plant_key, state, x0, params, steps, progress):
        """The closed loop as compiled scans: one of ``steps`` steps, or with ``progress`` the same compiled
        chunk of ``interval(steps)`` steps dispatched again and again, the carry passed on and the bar moved
        between chunks (a host callback inside the scan costs more than cheap steps; docs/xla_notes.md).
        The parameters of the last chunk's steps past ``steps`` repeat the last row; those steps are dropped."""
        if not progress:
            key = ("closed loop", self._key, plant_key, steps)
            run = cached(key, lambda: jax.jit(lambda s, x, p: _with_x0(
                x, self._scan(plant, (s, x), p, 0, steps)[1], jnp.full((steps,), jnp.nan))))
            return run(state, x0, params)
        length = interval(steps)
        chunks = -(-steps // length)
        if params is not None and chunks * length > steps:
            pad = chunks * length - steps
            params = jax.tree.map(lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], pad, 0)]), params)
        key = ("closed loop chunk", self._key, plant_key, length)
        run = cached(key, lambda: jax.jit(lambda c, p, start: self._scan(plant, c, p, start, length)))
        carry, recs, last = (state, x0), [], None
        for start in range(0, steps, length):
            carry, rec = run(carry, params, np.int32(start))
            recs.append(rec)
            if last is not None:  # the chunk before this one is done (or nearly): move the bar
                _report(*last)
            last = min(start + length, steps) - 1, carry[1]
        _report(*last)
        join = cached(("closed loop join", steps, length), lambda: jax.jit(functools.partial(_join, steps=steps)))
        return join(x0, recs)

    def _scan(self, plant, carry, params, start, length):
        """Steps ``start`` .. ``start + length - 1`` of the closed loop (parameter rows ``start`` ..):
        ``(carry, ClosedLoop)`` whose ``states`` are the states after each step (only what a ``ClosedLoop``
        keeps is stacked: each stacked output costs time per step)."""
        def body(carry, p):
            # Barriers keep the step and the plant apart, as in a user's loop of the compiled step and a
            # jitted plant: XLA fuses (and rounds) each the same way there and here.
            state, x = jax.lax.optimization_barrier(carry)
            u, state, info = self._checked_step(state, x, p)
            x_next = call(plant, p, *jax.lax.optimization_barrier((x, u)))
            return (state, x_next), (x_next, u, info)

        rows = None if params is None else jax.tree.map(lambda a: jax.lax.dynamic_slice_in_dim(a, start, length),
                                                         params)
        carry, (xs, us, info) = jax.lax.scan(body, carry, rows, length=length)
        return carry, _closed_loop(xs, us, info, None)

    def _python_loop(self, plant, state, x0, params, steps, progress):
        x = x0
        host = None if params is None else jax.tree.map(np.asarray, params)  # rows as views: no dispatch each
        rows = [None if host is None else jax.tree.map(lambda a, k=k: a[k, ...], host) for k in range(steps)]
        self.step(state, x, rows[0])  # compiles the step for these shapes, so that solve_times never count it
        decide = self._step_fn
        records, times = [], []
        for k in range(steps):
            t0 = time.perf_counter()
            u, state, info = jax.block_until_ready(decide(state, x, rows[k]))
            times.append(time.perf_counter() - t0)
            x_next = call(plant, rows[k], x, u)
            if not hasattr(x_next, "shape") or tuple(np.shape(x_next)) != x.shape:
                raise TypeError(f"plant(x, u[, p]) must return the next plant state of shape {tuple(x.shape)} "
                                f"like x0, got {type(x_next).__name__} of shape {np.shape(x_next)} at step {k}")
            x = x_next if _ready(x_next) and x_next.dtype == x.dtype else np.asarray(x_next, x.dtype)
            # what a ClosedLoop keeps (each field is read back to the host once)
            records.append((x, u, info._replace(result=info.result._replace(
                first_input=None, nodes=None, feasible=None, iterations=None, negative_cost=None,
                nan_encountered=None, overflow=None, complete=None))))
            if progress and due(k, steps):
                tick_python(k)
        # Stacked on the host, one device array per field: an eager jnp.stack of T arrays compiles a
        # T-operand concatenation per field on a run's first call.
        stacked = jax.tree.map(lambda *a: jnp.asarray(np.stack(a)), *records)
        return _with_x0(x0, _closed_loop(*stacked, None), jnp.asarray(times))


def _report(step: int, x) -> None:
    """Move the bar to ``step`` once the chunk that computed ``x`` is done."""
    if not is_tracer(x):
        jax.block_until_ready(x)
    tick_python(step)


def _join(x0, chunks, steps: int) -> ClosedLoop:
    """The run of ``steps`` steps from the ``ClosedLoop`` of each chunk (one compiled call: eager
    concatenations of many arrays cost more than the chunks' own dispatch)."""
    loop = jax.tree.map(lambda *a: jnp.concatenate(a)[:steps], *chunks)
    return _with_x0(x0, loop, jnp.full((steps,), jnp.nan))


def _with_x0(x0, loop: ClosedLoop, times) -> ClosedLoop:
    """``loop`` with ``x0`` before its states and these ``solve_times``."""
    return loop._replace(states=jnp.concatenate([jnp.asarray(x0)[None], loop.states]), solve_times=times)


def _closed_loop(xs, us, info: StepInfo, times) -> ClosedLoop:
    """The ``ClosedLoop`` of stacked steps, ``states`` the states after each step (``x0`` not included)."""
    plans = jnp.where(info.held[:, None], -1, info.result.sequence)  # -1 where held, found or not
    return ClosedLoop(states=xs, inputs=us, input_indices=plans[:, 0], stage_costs=info.stage_cost,
                      predicted_costs=info.result.cost, nodes=info.nodes, fallback_nodes=info.fallback_nodes,
                      feasible=info.feasible, used_fallback=info.used_fallback, complete=info.complete,
                      held=info.held, plans=plans, solve_times=times)
