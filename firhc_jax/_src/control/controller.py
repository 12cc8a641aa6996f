"""The receding horizon law (eq. 4): the controller's options, its entry points, its closed loops.

``FIRHC(problem)`` solves the finite-horizon problem at the current state and
applies the first input of the optimal sequence. One decision is a pure
function, ``u, state, info = ctrl.step(state, x, params)`` from
``state = ctrl.init(x0, u0)``: observe, search (warm start from the state,
fallback), actuate. A real-time loop calls it once per sampling period;
``simulate`` runs the same function for T steps, as one compiled ``lax.scan``
(``compiled=True``) or as a Python loop timing each decision
(``compiled=False``); a Python loop of ``step`` reproduces either.
``simulate_batch`` runs B closed loops at once, their searches shared out
by the solver's batch (``firhc_jax.solvers``). The decision itself is
``firhc_jax._src.control.decision``; the loop runner ``firhc_jax._src.control.runner``.

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
(``info.held``, ``ClosedLoop.held``); ``simulate`` and ``simulate_batch``
warn at the first held step (a Python loop: as it happens; a compiled run
in chunks, under a progress bar: at the end of its chunk; a compiled run in
one piece: after it, naming the step) and count the held steps after the
run; the one-shot
``ctrl(x)`` raises ``InfeasibleError``.

With ``params`` (leaves with leading axis ``steps``) step k calls every
callable, the problem's and these, with ``params[k]``: a reference trajectory,
time-varying weights. New values of the same shapes never recompile.
"""
from __future__ import annotations

import dataclasses
import functools
import inspect
import warnings
from typing import Any, Callable, Mapping, Optional

import jax
import numpy as np

from ..annotations import ArrayLike, PyTree
from ..checks import as_batch, as_inputs, as_sequence, as_state, check_params, is_tracer, positive_int, sample_times
from ..problem.auto_bound import AutoBound
from ..problem.problem import Problem, input_dtype
from ..runtime import engines, lean
from ..runtime.memory_cache import cached
from ..runtime.packed import compile_packed
from ..search.result import SearchResult, raise_on_errors
from .closed_loop import ClosedLoop
from .decision import ControllerState, StepInfo, budget_of, decide, decide_rows
from .decision_checks import (
    check_closed_loop,
    controller_options,
    decide_checked,
    no_input_message,
    one_shot,
    solve_checked,
)
from .runner import first_held_warning, ready, run_compiled, run_loops, run_python, user_plant, warn_held


class InfeasibleError(RuntimeError):
    """A one-shot decision (``FIRHC.__call__``) found no input to apply."""


def code_of(fn):
    """The code object behind a callable (a function, a bound method, a ``functools.partial``, a jitted or
    wrapped function), or None."""
    fn = inspect.unwrap(fn)
    while isinstance(fn, functools.partial):
        fn = inspect.unwrap(fn.func)
    return getattr(getattr(fn, "__func__", fn), "__code__", None)


def _hashable(value):
    """A field's part of a key: problems by their key, arrays by their bytes, mappings item by item."""
    if isinstance(value, Problem):
        return ("problem", value.key)
    if isinstance(value, np.ndarray):
        return ("array", value.dtype.str, value.shape, value.tobytes())
    if isinstance(value, Mapping):
        return tuple(sorted((k, _hashable(v)) for k, v in value.items()))
    return value


@dataclasses.dataclass(frozen=True, eq=False)
class Options:
    """Everything a controller decides with, checked (``FIRHC``'s arguments). Its ``key`` is derived from
    every field: controllers with equal keys share their compiled steps and loops."""

    problem: Problem
    solver: str  # a name in firhc_jax.solvers.SOLVERS
    solver_options: Mapping[str, Any]  # every option of the solver, defaults filled in
    fallback: Any  # None, "unconstrained" or a Problem
    warm_start: Any  # bool, or warm_start(problem, x, previous, params) -> [N]
    observe: Optional[Callable]
    actuate: Optional[Callable]
    u_safe: Optional[np.ndarray]  # [m] or None

    @functools.cached_property
    def key(self) -> tuple:
        """Every field, ``max_nodes`` only as whether there is a budget: its value travels with the state
        (``ControllerState.budget``), so controllers of other budgets share their compiled functions."""
        def field(name):
            value = getattr(self, name)
            if name == "solver_options":
                value = {**value, "max_nodes": value.get("max_nodes") is not None}
            return name, _hashable(value)
        return tuple(field(f.name) for f in dataclasses.fields(self))

    @functools.cached_property
    def relaxed(self) -> Optional[Problem]:
        """The fallback's problem (None: no fallback). Without the terminal set a bound's +inf ("terminal set
        out of reach") no longer holds: ``"unconstrained"`` drops both."""
        if isinstance(self.fallback, Problem):
            return self.fallback
        if self.fallback and self.problem.terminal is not None:
            derived = isinstance(self.problem.lower_bound, AutoBound)  # derived again without the terminal set
            return self.problem.replace(terminal=None, lower_bound=self.problem.lower_bound if derived else None)
        return None

    @property
    def budgeted(self) -> bool:
        return self.solver_options.get("max_nodes") is not None

    @property
    def search_options(self) -> dict:
        """The options a traced search takes (the budget travels apart; memory is checked before)."""
        return {k: v for k, v in self.solver_options.items() if k not in ("max_nodes", "max_memory")}


class FIRHC:
    """Finite-input receding horizon controller.

    Args:
      problem: the ``Problem`` solved at every step.
      solver: a name in ``firhc_jax.solvers.SOLVERS``: ``"sdfs"`` (default),
        ``"pool"`` (one decision on ``lanes`` slots of the work pool, by
        stealing), ``"sdfs-vmap"``, ``"exhaustive"``. In ``simulate_batch``
        each solver runs its batch: ``"sdfs"`` and ``"pool"`` share a work
        pool among the loops.
      fallback: what to do when no sequence meets the terminal constraint.
        ``None`` (default): no input is found (see ``u_safe``).
        ``"unconstrained"``: apply the optimum of the same problem without the
        terminal set and without its lower bound (whose ``+inf`` no longer
        holds), ``problem.replace(terminal=None, lower_bound=None)``: every
        other field, stage and terminal costs and hard constraints included,
        is kept (a ``lower_bound="auto"`` is derived again for that problem).
        Flagged in ``used_fallback``. A ``Problem`` (same horizon and
        inputs): apply its optimum instead, e.g. the relaxed problem with a
        bound of its own.
      warm_start: (sDFS solvers) ``True``: seed each search with the previous
        solution shifted by one step (the last input repeated). A callable
        ``warm_start(problem, x, previous, params) -> [N]`` int sequence (all
        -1: none) picks the seed itself (``previous``: the last decision's
        sequence; ``problem``: the one being searched, main or fallback).
        Exactness unchanged: a seed only sets the first incumbent.
      observe: ``observe(x, u_prev[, p]) -> x_model``: what the controller sees
        of the plant state (module docstring); default the plant state.
      actuate: ``actuate(x, u[, p]) -> u_plant``: the input the plant receives
        for the searched input (module docstring); default ``u``.
      u_safe: ``[m]`` the searched input applied (through ``actuate``) when a
        decision finds no input; default: hold the input applied last.
      engine: what runs the eager decisions (``step`` and ``ctrl(x)``
        called from Python): ``"xla"`` (default), the compiled JAX decision;
        ``"c"``, the decision exported as C (``fj.export_c``), compiled with
        the system's C compiler (``$CC``, else ``cc``; checked here) on the
        first call for each argument signature and called through
        ``ctypes``, every solver node for node as in XLA
        (docs/guide/realtime.md). Traced calls and ``simulate``'s compiled
        loop run in XLA either way.
      **solver_options: the solver's options (``SOLVERS[solver].options``):
        ``pop_width``, ``max_nodes``, ``max_memory``, ``lanes`` for the sDFS
        solvers; ``method``, ``chunk_nodes``, ``pop_width``, ``max_memory``
        for exhaustive. Unknown options are refused here. ``max_nodes`` is
        the budget of a whole decision: the fallback search gets what the
        first one left. Budgets beyond ``2**31 - 1`` (what the int32 node
        counter counts) count as ``2**31 - 1``, as in ``fj.sdfs``.
    """

    def __init__(self, problem: Problem, solver: str = "sdfs", *, fallback: str | Problem | None = None,
                 warm_start: bool | Callable = False, observe: Optional[Callable] = None,
                 actuate: Optional[Callable] = None, u_safe: ArrayLike | None = None, engine: str = "xla",
                 **solver_options: Any):
        self.options = Options(**controller_options(problem, solver, fallback, warm_start, observe, actuate,
                                                    u_safe, solver_options))
        self._engine = engines.engine(engine)
        if self._engine is not None:
            self._engine.check(self)
        self.engine = engine
        self._last_plant = None  # the plant of the last compiled closed loop (_note_plant)

    problem = property(lambda self: self.options.problem)
    solver = property(lambda self: self.options.solver)
    solver_options = property(lambda self: dict(self.options.solver_options))
    fallback = property(lambda self: self.options.fallback)
    warm_start = property(lambda self: self.options.warm_start)
    observe = property(lambda self: self.options.observe)
    actuate = property(lambda self: self.options.actuate)
    u_safe = property(lambda self: self.options.u_safe)

    # -- one decision --------------------------------------------------------------
    def init(self, x0: ArrayLike, u0: ArrayLike | None = None) -> ControllerState:
        """The state before the first decision at plant state ``x0``.

        ``u0``: the input applied before it (``observe``'s first ``u_prev``,
        and the input held if the first decision finds none); default zeros.
        ``x0`` is checked here (finite, real, 1-D floating); the callables are
        checked by the first ``step`` (they need the parameters' shapes).
        """
        as_state(x0)
        u0 = as_inputs("u0", u0, *self._input_form)
        return ControllerState(u=u0, plan=np.full((self.problem.horizon,), -1, np.int32),
                               budget=budget_of(self.options))

    def step(self, state: ControllerState, x: ArrayLike,
             params: PyTree = None) -> tuple[jax.Array, ControllerState, StepInfo]:
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
        if state.budget is None:  # made by hand: this controller's budget
            state = state._replace(budget=budget_of(self.options))
        run = lean.recall(("step", self), (state, x, params))
        if run is None:
            raw = (state, x, params)
            if not ready(x):
                x = as_state(x, "x")
            if params is not None and not all(map(ready, jax.tree_util.tree_leaves(params))):
                params = check_params(params)
            if any(map(is_tracer, jax.tree_util.tree_leaves((state, x, params)))):
                return self._decide()(state, x, params)
            if self._engine is None:
                run = self._eager("step", decide_checked, (state, x, params))
            else:
                args = (state, x, params)
                run = cached(("step", self.engine, self.options.key, lean.spec(args)),
                             lambda: self._engine.build(self, *args))
            lean.remember(("step", self), raw, run)
        return run(state, x, params)

    def _decide(self) -> Callable:
        """The jitted decision of this controller's key (checked while traced: once per signature)."""
        return cached(("step", self.options.key), lambda: jax.jit(functools.partial(decide_checked, self.options)))

    def _eager(self, name: str, fn: Callable, args: tuple) -> Callable:
        """``fn(self.options, *args)`` compiled for these checked arguments' shapes and dtypes (one output
        buffer: ``compile_packed``), shared by controllers of equal options and remembered for this controller's
        calls whose arguments, unchecked, have the signature of ``args`` (``lean``)."""
        program = cached((name, "eager", self.options.key, lean.spec(args)),
                         lambda: compile_packed(functools.partial(fn, self.options), *args))
        lean.remember((name, self), args, program)
        return program

    def __call__(self, x: ArrayLike, params: PyTree = None, *,
                 u_prev: ArrayLike | None = None) -> tuple[jax.Array, StepInfo]:
        """One-shot decision at plant state ``x``: ``(u, info)``.

        The first decision from scratch, ``step(init(x, u_prev), x, params)``
        (no warm start; ``info.used_fallback`` says which search decided),
        with the checks of a one-shot call: states and parameters are scanned
        for NaN, a negative stage cost raises ``ValueError``, and when no
        input is found it raises ``InfeasibleError`` (whatever the fallback)
        instead of holding. Inside ``jit``/``vmap`` it holds and flags like
        ``step``. In a loop over time use ``init``/``step``.
        """
        if self._engine is not None:
            return self._call_engine(x, params, u_prev)
        run = lean.recall(("call", self), (x, params, u_prev))
        if run is None:
            x = as_state(x)
            state, params = self.init(x, u_prev), check_params(params)
            if any(map(is_tracer, jax.tree_util.tree_leaves((x, params)))):
                u, _, info = self.step(state, x, params)
                return u, info
            run = self._eager("call", one_shot, (x, params, state.u, state.budget))
            lean.remember(("call", self), (x, params, u_prev), run)
            u_prev = state.u
        else:
            u_prev = np.zeros(*self._input_form) if u_prev is None else np.asarray(u_prev, self._input_form[1])
        u, info, alarm = run(x, params, u_prev, budget_of(self.options))
        if alarm:
            self._raise_one_shot(x, params, u_prev, info)
        return u, info

    def _raise_one_shot(self, x, params, u_prev, info: StepInfo) -> None:
        """A one-shot decision's alarm: the checks of a first call on these values, then the search's error
        flags, then no input found (each raises with its own message)."""
        self.init(x, u_prev)
        check_params(params)
        raise_on_errors(info.result)
        if info.held:
            raise InfeasibleError(no_input_message(self.options, info))

    def _call_engine(self, x, params, u_prev):
        """``__call__`` through the step of an engine other than XLA: one decision from scratch, then the
        one-shot checks when the report raises an alarm (a non-finite value, an error flag, no input)."""
        if u_prev is None:
            u_prev = np.zeros(*self._input_form)
        start = ControllerState(u=u_prev, plan=np.full((self.problem.horizon,), -1, np.int32),
                                budget=budget_of(self.options))
        u, _, info = self.step(start, x, params)
        if info.held or info.result.nan_encountered or info.result.negative_cost or info.result.overflow:
            self._raise_one_shot(x, params, u_prev, info)
        return u, info

    def solve(self, x: ArrayLike, params: PyTree = None,
              previous_sequence: ArrayLike | None = None) -> tuple[SearchResult, jax.Array]:
        """The searches of one decision at *model* state ``x`` (no ``observe``,
        ``actuate`` or safe input): ``(result, used_fallback)``.

        When the fallback decided, ``result`` is the fallback search's, with
        the first search's iterations added, its error flags kept, and
        ``complete`` only if both searches ran to the end (a constrained
        search stopped by ``max_nodes`` has not proven infeasibility).
        ``previous_sequence``: the last decision's plan, the candidates'
        source (ignored unless ``warm_start`` or ``max_nodes``; an all ``-1``
        sequence, i.e. infeasible, is none and costs no nodes). No input found: ``result.feasible`` is
        False and ``result.first_input`` NaN.
        """
        x, params = as_state(x, "x"), check_params(params)
        prev = as_sequence(previous_sequence, self.problem.horizon, self.problem.num_controls,
                           "previous_sequence") if self.warm_start or self.options.budgeted else None
        fn = cached(("solve", self.options.key), lambda: jax.jit(functools.partial(solve_checked, self.options)))
        result, used = fn(x, params, prev, budget_of(self.options))
        return raise_on_errors(result), used

    # -- closed loops ------------------------------------------------------------
    def simulate(self, x0: ArrayLike, steps: int, plant: Optional[Callable] = None, *, params: PyTree = None,
                 u0: ArrayLike | None = None, dt: float | None = None,
                 progress: bool | None = None, compiled: bool = True) -> ClosedLoop:
        """Run the closed loop for ``steps`` steps from plant state ``x0``: ``step`` then ``plant``.

        Args:
          plant: ``plant(x, u[, p]) -> x_next``, default the model's dynamics.
          params: optional pytree whose leaves have leading axis ``steps``:
            step k is solved (and simulated) with ``params[k]``.
          u0: the input applied before step 0 (seen by ``observe``, held if
            the first decision finds none); default zeros.
          dt: the sampling period in seconds: the run gets ``times`` ``[T+1]``
            (``k * dt``) and plots against time.
          progress: a progress bar with an estimate, on stderr or in the
            notebook. ``None`` (default): once the run has taken 2 s.
            ``True``: at once; ``False``: never. A compiled run reports its
            steps when it runs as chunks of steps dispatched again and again
            (the same results to the last bit): with ``True``, and by default
            when the last run of this loop says this one takes 2 s or more;
            otherwise it is one compiled program, whose bar shows the time
            elapsed (docs/guide/realtime.md).
          compiled: ``True``: one ``lax.scan`` (everything traceable);
            ``False``: a Python loop over the compiled ``step``, for a plant
            that cannot be traced, and with each decision timed in
            ``solve_times`` (compiled before the loop, so never counted).
            The plant is called as it is: jit it, or each of its
            operations is one eager dispatch a step.

        Steps where no input was found hold the safe input (``held``): a
        ``RuntimeWarning`` names the first one as it happens (``compiled=False``),
        at the end of its chunk (a run under a progress bar) or after the run, and
        another counts them after the run.
        """
        steps = positive_int("steps", steps)
        x0 = as_state(x0)
        params = check_params(params, leading=steps, axis="steps")
        state = self.init(x0, u0)
        sample_times(dt, steps)
        plant, plant_key, default = self._plant(plant)
        fresh = check_closed_loop(self.options, plant_key if compiled else False, plant if compiled else None,
                                  state.u, x0, params, default, drop=1)
        if compiled:
            self._note_plant(plant, default, fresh)
        return self._run(state, x0, steps, plant, plant_key, params, progress, None if compiled else self.step,
                         dt)

    def _run(self, state, x0, steps: int, plant, plant_key, params, progress: Optional[bool], decision, dt
             ) -> ClosedLoop:
        """A checked closed loop (``simulate``'s), under its progress bar and followed by the held-input warning:
        one compiled scan where ``decision`` is None, else a Python loop of ``decision``, a compiled decision of
        this controller (``step``'s contract); ``dt`` (checked) gives its time axis."""
        label = f"FIRHC[{self.solver}]"
        # the warning points at the caller of simulate: through _report, _in_chunks and run_compiled, or run_python
        on_held = first_held_warning(self.u_safe is not None, stacklevel=7 if decision is None else 5)
        if decision is None:
            out, = run_compiled(functools.partial(decide, self.options), user_plant(plant), [(state, x0, params)],
                                steps, key=(self.options.key, plant_key), progress=progress, label=label,
                                on_held=on_held)
        else:
            out = run_python(decision, user_plant(plant), state, x0, params, steps, progress=progress, label=label,
                             on_held=on_held)
        warn_held(out.held, steps, self.u_safe is not None)
        return out._replace(times=sample_times(dt, steps))

    def simulate_batch(self, X0: ArrayLike, steps: int, plant: Optional[Callable] = None, *, params: PyTree = None,
                       u0: ArrayLike | None = None, dt: float | None = None,
                       progress: bool | None = None) -> ClosedLoop:
        """Run B closed loops at once, loop b from plant state ``X0[b]``: one compiled run.

        Loop b makes the decisions of ``simulate(X0[b], steps, plant, params=params[b], u0=u0[b])``: at
        every step the B searches run as the solver's batch (``"sdfs"``, ``"pool"``: one work pool whose
        lanes take the next loop's root or steal nodes, so a long search never holds the other loops; with
        ``max_nodes`` no loop's nodes are shared, so each is searched node for node as ``simulate`` does:
        ``"sdfs"`` on one slot, ``"pool"`` on a pool of ``lanes`` slots of its own).
        The loops are split into parts, one per CPU core and per local device, run side by side; in a job of
        several processes (``jax.distributed``) each runs its share and every process gets every loop.
        Costs are equal (to the last bits: XLA vectorises the batch its own way); inputs too, except at exact
        ties, which a stolen node or a last-bit difference may tip to another optimal sequence (README).

        Args:
          X0: ``[B, n]`` initial plant states.
          plant: ``plant(x, u[, p]) -> x_next`` for one loop (vmapped here); default the model's dynamics.
          params: optional pytree whose leaves are ``[B, steps, ...]``: loop b, step k uses ``params[b, k]``.
          u0: ``[m]`` (every loop) or ``[B, m]``: the input applied before step 0; default zeros.
          dt: the sampling period in seconds (``times`` ``[T+1]``).
          progress: a bar counting loops x steps (compiled chunks of steps; ``None``, ``True``, ``False`` as in
            ``simulate``).

        Returns a ``ClosedLoop`` with a leading axis B on every field but ``times``; ``solve_times`` NaN.
        """
        steps = positive_int("steps", steps)
        X0 = as_batch(X0)
        B = X0.shape[0]
        params = check_params(params, leading=(B, steps), axis="[B (loops), steps]")
        u0 = as_inputs("u0", u0, *self._input_form, (B,))
        state = ControllerState(u=u0, plan=np.full((B, self.problem.horizon), -1, np.int32),
                                budget=np.full((B,), budget_of(self.options), np.int32))
        times = sample_times(dt, steps)
        plant, plant_key, default = self._plant(plant)
        self._note_plant(plant, default, check_closed_loop(self.options, plant_key, plant, state.u[0], X0[0], params,
                                                           default, drop=2))
        out = run_loops(functools.partial(decide_rows, self.options), jax.vmap(user_plant(plant)), state, X0, params,
                        steps, key=("batch", self.options.key, plant_key), progress=progress,
                        label=f"FIRHC[{self.solver}] x {B} loops",
                        on_held=first_held_warning(self.u_safe is not None, stacklevel=7))
        warn_held(out.held, steps * B, self.u_safe is not None)
        return out._replace(times=times)

    @property
    def _input_form(self) -> tuple:
        """``(m, dtype)`` of the searched inputs (``u0``, ``u_safe``)."""
        return self.problem.input_dim, input_dtype(self.problem)

    def _note_plant(self, plant, default: bool, compiling: bool) -> None:
        """A compiled closed loop's ``plant`` (``compiling``: the loop compiles for it): a one-line warning when
        it compiles for a new object with the code of the last plant (a plant defined anew for each call
        compiles the whole loop each time)."""
        last, self._last_plant = self._last_plant, None if default else plant
        code = None if default or not compiling or last is None or last is plant else code_of(plant)
        if code is None or code != code_of(last):
            return
        warnings.warn(f"FIRHC compiles its closed loop again for a new plant object with the code of the last one "
                      f"({code.co_name} at {code.co_filename}:{code.co_firstlineno}): the plant is part of the "
                      "compiled loop, keyed by the object; define it once and pass that same object to every call "
                      "(values that change belong in params)", UserWarning, stacklevel=3)

    def _plant(self, plant):
        """``(plant, its cache key, whether it is the default)``: the default plant (the model's dynamics)
        is keyed as None, since the model_plant of an equal problem is another bound method."""
        if plant is None:
            return self.problem.model_plant, None, True
        if not callable(plant):
            raise TypeError(f"plant must be callable, got {type(plant).__name__}")
        return plant, plant, False
