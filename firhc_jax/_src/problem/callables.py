"""Checks of a problem's callables against the arguments of a search, done before anything is compiled.

The callables are checked abstractly (``jax.eval_shape``) once per problem, state shape and dtype and
parameter structure; the result is kept in the package's bounded cache. Each failure names the callable,
the shapes it was given and how this problem calls it.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from ..checks import as_batch, as_state, check_params
from ..runtime.memory_cache import cached
from .problem import Problem, call, refuse_differentiation


def callable_forms(problem: Problem, with_params: bool) -> str:
    """How this problem calls its callables, for error messages."""
    k = ", k" if problem.step_index else ""
    p = ", p" if with_params else ""
    x = "x, " if problem.previous_state else ""
    forms = [f"dynamics(x, u{k}{p})", f"stage_cost({x}x_next, u{k}{p})"]
    if problem.constraint is not None:
        forms.append(f"constraint({x}x_next, u{k}{p})")
    forms += [f"terminal(x{p})", f"terminal_cost(x{p})", f"lower_bound(x, steps_left{p})"]
    return ", ".join(forms)


def params_spec(params, drop_leading: bool | int = False):
    """Abstract shapes of ``params`` (one row of it with ``drop_leading``, or
    without that many leading axes): a
    hashable cache key and the argument for ``jax.eval_shape``."""
    if params is None:
        return None, None
    leaves, treedef = jax.tree_util.tree_flatten(params)
    specs = [jax.ShapeDtypeStruct(a.shape[int(drop_leading):], a.dtype) for a in leaves]
    key = (treedef, tuple((s.shape, jnp.dtype(s.dtype)) for s in specs))
    return key, jax.tree_util.tree_unflatten(treedef, specs)


def search_inputs(problem: Problem, states, params, batched: bool = False, name: str = "X0"):
    """The checks every public search starts with, in one order: the problem, no differentiation, the
    parameters, then the state ``x0`` ``[n]`` (or, ``batched``, the states ``[B, n]`` called ``name``, params
    with leading axis B) against the callables. Returns ``(states, params)`` as the search takes them."""
    if not isinstance(problem, Problem):
        raise TypeError(f"problem must be a firhc_jax.Problem, got {type(problem).__name__}")
    refuse_differentiation(states, params)
    if not batched:
        params = check_params(params)
        return check_state(problem, states, params), params
    X = as_batch(states, name)
    params = check_params(params, leading=X.shape[0])
    check_state(problem, X[0], params, batched_params=True)
    return X, params


def check_state(problem: Problem, x0, params=None, batched_params: bool = False) -> jax.Array:
    """Validate ``x0`` (and the callables against it and ``params``) and return
    it as an array. Raises ``ValueError``/``TypeError`` naming the mismatch:
    ``x0`` not 1-D or not finite, ``dynamics`` changing shape or dtype,
    ``stage_cost`` not a floating scalar, ``terminal`` not a boolean scalar,
    ``lower_bound`` not a scalar."""
    x0 = as_state(x0)
    pkey, pspec = params_spec(params, drop_leading=batched_params)
    x = jax.ShapeDtypeStruct(x0.shape, x0.dtype)
    cached(("checked", problem.key, x.shape, jnp.dtype(x.dtype), pkey),
           lambda: _check_callables(problem, x, pspec, params is not None))
    return x0


def shape_of(fn, pspec, *args, blame: str, hint: str = ""):
    """``jax.eval_shape`` of ``fn(*args[, p])``; a failure is raised again as a ``TypeError`` (a type or
    attribute error) or ``ValueError`` (any other) that starts with ``blame`` and ends with ``hint``."""
    try:
        return jax.eval_shape(lambda p, *a: call(fn, p, *a), pspec, *args)
    except (TypeError, ValueError, KeyError, IndexError, AttributeError) as e:  # name the callable, keep the cause
        cls = TypeError if isinstance(e, (TypeError, AttributeError)) else ValueError
        raise cls(f"{blame}: {type(e).__name__}: {e}{hint}") from e


def _call_shape(problem, fn, name, signature, with_params, pspec, *args):
    shapes = ", ".join(f"{tuple(a.shape)} {a.dtype}" for a in args)
    hint = f" (this problem calls {callable_forms(problem, with_params)}"
    hint += ("" if with_params else "; pass params=... to give the callables a p argument")
    hint += ("; set step_index=False if they take no step index k)" if problem.step_index else
             "; set Problem(..., step_index=True) if they take the step index k)")
    return shape_of(fn, pspec if with_params else None, *args,
                    blame=f"{name}{signature} failed on inputs of shape/dtype ({shapes})", hint=hint)


def _check_callables(problem: Problem, x: jax.ShapeDtypeStruct, pspec, with_params: bool):
    u = jax.ShapeDtypeStruct(problem.controls.shape[1:], problem.controls.dtype)
    p = ", p" if with_params else ""
    k = (jax.ShapeDtypeStruct((), jnp.int32),) if problem.step_index else ()
    ks = ", k" if problem.step_index else ""
    out = _call_shape(problem, problem.dynamics, "dynamics", f"(x, u{ks}{p})", with_params, pspec, x, u, *k)
    if not isinstance(out, jax.ShapeDtypeStruct):
        raise TypeError(f"dynamics(x, u{p}) must return one array [n], got {type(out).__name__}")
    if out.shape != x.shape:
        raise ValueError(
            f"dynamics(x, u{ks}{p}) returned shape {tuple(out.shape)} but x0 has shape {tuple(x.shape)}; "
            "x0 must have the shape of the state that dynamics returns")
    if out.dtype != x.dtype:
        raise TypeError(
            f"dynamics(x, u{ks}{p}) changed the state dtype from {x.dtype} to {out.dtype}; "
            "cast x0 (or the constants/controls inside dynamics) so that the dtypes agree")
    xs = (x,) if problem.previous_state else ()  # the state before the step
    before = "x, " if problem.previous_state else ""
    c = _call_shape(problem, problem.stage_cost, "stage_cost", f"({before}x_next, u{ks}{p})", with_params, pspec,
                    *xs, x, u, *k)
    _real_scalar(c, f"stage_cost({before}x_next, u{ks}{p})")
    if problem.terminal_cost is not None:
        g = _call_shape(problem, problem.terminal_cost, "terminal_cost", f"(x{p})", with_params, pspec, x)
        _real_scalar(g, f"terminal_cost(x{p})")
    if problem.constraint is not None:
        h = _call_shape(problem, problem.constraint, "constraint", f"({before}x_next, u{ks}{p})", with_params, pspec,
                        *xs, x, u,
                        *k)
        _bool_scalar(h, f"constraint({before}x_next, u{ks}{p})")
    if problem.terminal is not None:
        t = _call_shape(problem, problem.terminal, "terminal", f"(x{p})", with_params, pspec, x)
        _bool_scalar(t, f"terminal(x{p})")
    if problem.lower_bound is not None:
        steps = jax.ShapeDtypeStruct((), jnp.int32)
        b = _call_shape(problem, problem.lower_bound, "lower_bound", f"(x, steps_left{p})", with_params, pspec, x,
                        steps)
        _real_scalar(b, f"lower_bound(x, steps_left{p})")


def _real_scalar(c, what: str):
    if not isinstance(c, jax.ShapeDtypeStruct) or c.shape != ():
        shape = getattr(c, "shape", type(c).__name__)
        raise ValueError(f"{what} must return a scalar, got shape {shape}")
    if not jnp.issubdtype(c.dtype, jnp.floating):
        raise TypeError(f"{what} must return a real floating scalar, got dtype {c.dtype}")


def _bool_scalar(t, what: str):
    if not isinstance(t, jax.ShapeDtypeStruct) or t.shape != () or t.dtype != jnp.bool_:
        desc = f"shape {tuple(t.shape)} dtype {t.dtype}" if isinstance(t, jax.ShapeDtypeStruct) else type(t).__name__
        raise TypeError(f"{what} must return a boolean scalar, got {desc}")


def cost_dtype(problem: Problem, x0, params=None, batched_params: bool = False):
    """dtype of accumulated costs: that of ``stage_cost``'s output."""
    u = jax.ShapeDtypeStruct(problem.controls.shape[1:], problem.controls.dtype)
    _, pspec = params_spec(params, drop_leading=batched_params)
    x = jax.ShapeDtypeStruct(x0.shape[-1:], x0.dtype)
    return jax.eval_shape(lambda p, a, b: problem.cost_of_step(a, a, b, 0, p), pspec, x, u).dtype
