"""Checks of a controller's decision and closed loop, and what it says when no input was found.

They run once per argument signature (shapes, dtypes, parameter structure),
before anything is compiled or while ``jax.jit`` traces, on abstract values
(``jax.eval_shape``); each failure names the callable or argument at fault.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..checks import as_inputs
from ..problem.callables import check_state, params_spec, shape_of
from ..problem.problem import Problem, input_dtype
from ..runtime.lean import non_finite
from ..runtime.memory_cache import cached
from ..search import solvers
from ..search.result import alarms
from ..search.sdfs import node_budget
from .decision import ControllerState, decide, solve

_DEFAULT_PLANT_HINT = ("; the default plant is the model's dynamics, which with observe set runs on model states: "
                       "pass plant= with the plant's own dynamics")


def controller_options(problem, solver, fallback, warm_start, observe, actuate, u_safe, solver_options) -> dict:
    """``FIRHC``'s arguments, checked: the fields of its ``Options``."""
    if not isinstance(problem, Problem):
        raise TypeError(f"problem must be a firhc_jax.Problem, got {type(problem).__name__}")
    table = solvers.get(solver)
    options = solvers.check_options(solver, solver_options)
    if options.get("max_nodes") is not None:  # what the int32 node counter can count, as fj.sdfs clamps it
        options["max_nodes"] = int(node_budget(options["max_nodes"]))
    if isinstance(fallback, Problem):
        if (fallback.horizon, fallback.num_controls) != (problem.horizon, problem.num_controls):
            raise ValueError(f"a fallback Problem needs the problem's horizon and inputs (N={problem.horizon}, "
                             f"M={problem.num_controls}), got N={fallback.horizon}, M={fallback.num_controls}")
    elif fallback not in (None, "unconstrained"):
        raise ValueError(f"fallback must be None, 'unconstrained' or a Problem, got {fallback!r}")
    if not isinstance(warm_start, bool) and not callable(warm_start):
        raise TypeError(f"warm_start must be a bool or a callable (problem, x, previous, params) -> [N], "
                        f"got {type(warm_start).__name__}")
    if warm_start is not False and not table.warm_starts:
        raise ValueError(f"warm_start applies to the sDFS solvers, not solver={solver!r}")
    for name, fn in (("observe", observe), ("actuate", actuate)):
        if fn is not None and not callable(fn):
            raise TypeError(f"{name} must be callable or None, got {type(fn).__name__}")
    if u_safe is not None:
        u_safe = as_inputs("u_safe", u_safe, problem.input_dim, input_dtype(problem), concrete=True)
    return dict(problem=problem, solver=solver, solver_options=options, fallback=fallback, warm_start=warm_start,
                observe=observe, actuate=actuate, u_safe=u_safe)


def check_search(opts, x, pspec) -> None:
    """The problems (main and fallback) on the model state ``x`` and the solver's memory."""
    for problem in (opts.problem, opts.fallback):
        if isinstance(problem, Problem):
            check_state(problem, np.zeros(x.shape, x.dtype), pspec)
    solvers.check_memory(opts.solver, opts.solver_options, opts.problem, x.shape[0], max(x.dtype.itemsize, 4))


_BUDGET = jax.ShapeDtypeStruct((), jnp.int32)  # a state's budget, as init makes it


def check_decision(opts, u, plan, x, pspec, budget=_BUDGET):
    """A decision's argument shapes, ``observe``, the problems on the model state, the solver's memory and
    ``actuate``; returns the plant input's shape and dtype."""
    N, m = opts.problem.horizon, opts.problem.input_dim
    if u.shape != (m,) or plan.shape != (N,) or not jnp.issubdtype(plan.dtype, jnp.integer) \
            or budget.shape != () or not jnp.issubdtype(budget.dtype, jnp.integer):
        raise ValueError(f"state does not belong to this controller: u {u.shape}, plan {plan.shape} "
                         f"{plan.dtype}, budget {budget.shape} {budget.dtype}, expected u ({m},), plan ({N},) "
                         "int32 and budget () int32; make it with ctrl.init")
    if len(x.shape) != 1 or not jnp.issubdtype(x.dtype, jnp.floating):
        raise TypeError(f"x must be a 1-D real floating state [n], got shape {x.shape} dtype {x.dtype}")
    if pspec is not None:
        for path, leaf in jax.tree_util.tree_flatten_with_path(pspec)[0]:
            if jnp.dtype(leaf.dtype).kind not in "biuf":
                raise TypeError(f"params leaf {jax.tree_util.keystr(path)} must be a real numeric or boolean "
                                f"array, got dtype {leaf.dtype}")
    xm = shape_of(opts.observe, pspec, x, u, blame="observe(x, u_prev[, p]) failed on the closed loop's shapes") \
        if opts.observe else x
    if not isinstance(xm, jax.ShapeDtypeStruct):
        raise TypeError(f"observe must return one array (the model state), got {type(xm).__name__}")
    check_search(opts, xm, pspec)
    up = shape_of(opts.actuate, pspec, x, u, blame="actuate(x, u[, p]) failed on the closed loop's shapes") \
        if opts.actuate else u
    if not isinstance(up, jax.ShapeDtypeStruct):
        raise TypeError(f"actuate must return one array (the plant input), got {type(up).__name__}")
    return up


def check_loop(opts, plant, u, plan, x, pspec, default_plant: bool) -> None:
    """The decision's checks, then (for a traced loop, ``plant`` not None) the plant's, each blamed by name."""
    try:
        up = check_decision(opts, u, plan, x, pspec)
    except (TypeError, ValueError) as e:
        if default_plant and opts.observe is not None and "x0" in str(e):
            raise type(e)(f"{e}{_DEFAULT_PLANT_HINT}") from e
        raise
    if plant is None:
        return
    hint = _DEFAULT_PLANT_HINT if default_plant else ""
    out = shape_of(plant, pspec, x, up, blame="plant(x, u[, p]) failed on the closed loop's shapes", hint=hint)
    if not isinstance(out, jax.ShapeDtypeStruct) or out.shape != x.shape or out.dtype != x.dtype:
        desc = f"shape {tuple(out.shape)} dtype {out.dtype}" if isinstance(out, jax.ShapeDtypeStruct) \
            else type(out).__name__
        raise TypeError(f"plant(x, u[, p]) must return the next plant state, shape {tuple(x.shape)} dtype "
                        f"{x.dtype} like x0; got {desc}"
                        + ("; the default plant is the model's dynamics: with observe set, pass plant="
                           if default_plant and opts.observe is not None else ""))


def no_input_message(opts, info) -> str:
    """Why a decision found no input, in the problem's own terms."""
    p, r, N = opts.problem, info.result, opts.problem.horizon
    if np.asarray(r.feasible):  # held although a sequence was found: its input is not finite
        return (f"first_input_of returned a non-finite input {np.asarray(r.first_input).tolist()} for the "
                f"optimal sequence {np.asarray(r.sequence).tolist()}; a controller never applies it")
    if not np.asarray(info.complete):
        return (f"no input found: the search stopped at max_nodes={opts.solver_options.get('max_nodes')} "
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
    if p.terminal is not None and opts.fallback is None:
        msg += "; use fallback='unconstrained' or relax the terminal constraint"
    return msg


def check_closed_loop(opts, plant_key, plant, u, x0, params, default: bool, drop: int) -> bool:
    """The closed loop's checks, once per signature and plant (``drop``: the leading axes of ``params``);
    whether they ran (a signature or plant not seen before: the loop compiles next)."""
    pkey, pspec = params_spec(params, drop_leading=drop)
    spec = lambda a: jax.ShapeDtypeStruct(np.shape(a), a.dtype)  # noqa: E731
    plan = jax.ShapeDtypeStruct((opts.problem.horizon,), np.int32)
    ran = []

    def check():
        check_loop(opts, plant, spec(u), plan, spec(x0), pspec, default)
        ran.append(True)

    cached(("closed-loop check", opts.key, plant_key, spec(x0), spec(u), pkey), check)
    return bool(ran)


def decide_checked(opts, state, x, p):
    """``decide`` after the abstract checks (run while jit traces: once per argument signature)."""
    pkey, pspec = params_spec(p)
    spec = lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype)  # noqa: E731
    cached(("step check", opts.key, spec(state.u), spec(state.plan), spec(state.budget), spec(x), pkey),
           lambda: check_decision(opts, spec(state.u), spec(state.plan), spec(x), pspec, spec(state.budget)))
    return decide(opts, state, x, p)


def one_shot(opts, x, p, u_prev, budget):
    """``FIRHC.__call__``'s decision after the checks: ``(u, info, alarm)``; ``alarm``: a value fails the
    checks (a non-finite state or parameter), the search raised an error flag, or no input was found."""
    plan = jnp.full((opts.problem.horizon,), -1, jnp.int32)
    u, _, info = decide_checked(opts, ControllerState(u=u_prev, plan=plan, budget=budget), x, p)
    return u, info, non_finite(x, p, u_prev) | alarms(info.result) | info.held


def solve_checked(opts, x, params, previous, max_nodes):
    """``solve`` after the checks of its searches (once per argument signature)."""
    pkey, pspec = params_spec(params)
    cached(("solve check", opts.key, x.shape, jnp.dtype(x.dtype), pkey),
           lambda: check_search(opts, jax.ShapeDtypeStruct(x.shape, x.dtype), pspec))
    result, _, used = solve(opts, x, params, previous, max_nodes)
    return result, used
