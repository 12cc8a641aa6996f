"""Checks of a problem's inputs, done before anything is compiled.

Each raises a ``ValueError`` or ``TypeError`` that names the argument. The
callables are checked abstractly (``jax.eval_shape``) once per problem, state
shape and dtype and parameter structure; the result is kept in the package's
bounded cache (``firhc_jax.cache``).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .cache import cached
from .problem import Problem, call, is_tracer

CALLABLE_FORMS = "dynamics(x, u, p), stage_cost(x_next, u, p), terminal(x, p), lower_bound(x, steps_left, p)"


def strong(a):
    """``a`` without weak type: a weakly typed array (from a Python scalar,
    ``jnp.full(n, 0.2)``) would compile a second search for the same shapes
    and dtypes. A strongly typed JAX array stays as it is; anything else
    becomes a NumPy array of JAX's canonical dtype, which a jitted search
    takes as it is (making a device array here would cost a dispatch per
    call; benchmarks/RESULTS.md, issue 9 section)."""
    if isinstance(a, jax.Array) and not a.weak_type:
        return a
    a = np.asarray(a)
    return a.astype(jax.dtypes.canonicalize_dtype(a.dtype), copy=False)


def check_params(params, leading: int | None = None, what: str = "params", axis: str = "B"):
    """``params`` with every leaf an array without weak type (``strong``; tracers stay), or a clear error.

    Leaves must be real numeric or boolean arrays; with ``leading`` each must
    have that leading axis (one entry per row or per step). Concrete leaves
    with NaN are refused (a NaN parameter would silently make states
    infeasible). Values and dtypes are kept (JAX's own canonicalisation aside:
    without x64, 64-bit arrays become 32-bit, as everywhere in JAX).
    """
    if params is None:
        return None
    leaves_with_path, treedef = jax.tree_util.tree_flatten_with_path(params)
    if not leaves_with_path:
        raise ValueError(f"{what} has no array leaves; pass {what}=None for callables without parameters")
    out = []
    for path, leaf in leaves_with_path:
        name = f"{what} leaf {jax.tree_util.keystr(path) or '(root)'}"
        if is_tracer(leaf):
            a = leaf
        else:
            arr = np.asarray(leaf) if not isinstance(leaf, jax.Array) else leaf
            kind = arr.dtype.kind if hasattr(arr, "dtype") else "O"
            if kind not in "biuf":
                raise TypeError(f"{name} must be a real numeric or boolean array, got {type(leaf).__name__} "
                                f"of dtype {getattr(arr, 'dtype', '?')}")
            if kind == "f" and not np.all(np.isfinite(np.asarray(arr))):
                raise ValueError(f"{name} contains NaN or inf")
            a = strong(arr)
        if leading is not None and (a.ndim == 0 or a.shape[0] != leading):
            raise ValueError(f"{name} must have leading axis {axis} = {leading}, got shape {tuple(a.shape)}")
        out.append(a)
    return jax.tree_util.tree_unflatten(treedef, out)


def params_spec(params, drop_leading: bool = False):
    """Abstract shapes of ``params`` (one row of it with ``drop_leading``): a
    hashable cache key and the argument for ``jax.eval_shape``."""
    if params is None:
        return None, None
    leaves, treedef = jax.tree_util.tree_flatten(params)
    specs = [jax.ShapeDtypeStruct(a.shape[1:] if drop_leading else a.shape, a.dtype) for a in leaves]
    key = (treedef, tuple((s.shape, jnp.dtype(s.dtype)) for s in specs))
    return key, jax.tree_util.tree_unflatten(treedef, specs)


def as_state(x0, name: str = "x0"):
    """``x0`` as a finite, real, floating 1-D array, or a clear error.

    A strongly typed JAX array (or a tracer) stays as it is; anything else
    comes back as a NumPy array (``strong``)."""
    if x0 is None:
        raise TypeError(f"{name} is None: pass the current state as an array [n]")
    if not is_tracer(x0):
        try:
            x_np = np.asarray(x0)
        except ValueError as e:
            raise ValueError(f"{name} must be a 1-D numeric array [n]: {e}") from None
        if x_np.dtype.kind == "c":
            raise TypeError(f"{name} must be real, got complex dtype {x_np.dtype}")
        if x_np.dtype.kind not in "biuf":
            raise TypeError(f"{name} must be a numeric array [n], got dtype {x_np.dtype}")
        if x_np.dtype.kind == "f" and not np.all(np.isfinite(x_np)):
            raise ValueError(f"{name} contains NaN or inf: {x_np}")
        x0 = strong(x0)
    if x0.ndim != 1:
        raise ValueError(
            f"{name} must be a 1-D state vector [n], got shape {tuple(x0.shape)}; "
            "for a batch of states use jax.vmap or fj.solve_batch")
    if not jnp.issubdtype(x0.dtype, jnp.floating):
        raise TypeError(f"{name} must have a real floating dtype, got {x0.dtype}")
    return x0


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


def _call_shape(fn, name, signature, with_params, pspec, *args):
    try:
        return jax.eval_shape(lambda p, *a: call(fn, p, *a), pspec if with_params else None, *args)
    except (TypeError, ValueError, KeyError, IndexError, AttributeError) as e:  # name the callable, keep the cause
        shapes = ", ".join(f"{tuple(a.shape)} {a.dtype}" for a in args)
        hint = (f" (with params the callables are called as {CALLABLE_FORMS})" if with_params else
                " (without params the callables take no p argument; pass params=... to give them one)")
        cls = TypeError if isinstance(e, TypeError) else ValueError
        raise cls(f"{name}{signature} failed on inputs of shape/dtype ({shapes}): {e}{hint}") from e


def _check_callables(problem: Problem, x: jax.ShapeDtypeStruct, pspec, with_params: bool):
    u = jax.ShapeDtypeStruct(problem.controls.shape[1:], problem.controls.dtype)
    p = ", p" if with_params else ""
    out = _call_shape(problem.dynamics, "dynamics", f"(x, u{p})", with_params, pspec, x, u)
    if not isinstance(out, jax.ShapeDtypeStruct):
        raise TypeError(f"dynamics(x, u{p}) must return one array [n], got {type(out).__name__}")
    if out.shape != x.shape:
        raise ValueError(
            f"dynamics(x, u{p}) returned shape {tuple(out.shape)} but x0 has shape {tuple(x.shape)}; "
            "x0 must have the shape of the state that dynamics returns")
    if out.dtype != x.dtype:
        raise TypeError(
            f"dynamics(x, u{p}) changed the state dtype from {x.dtype} to {out.dtype}; "
            "cast x0 (or the constants/controls inside dynamics) so that the dtypes agree")
    c = _call_shape(problem.stage_cost, "stage_cost", f"(x_next, u{p})", with_params, pspec, x, u)
    if not isinstance(c, jax.ShapeDtypeStruct) or c.shape != ():
        shape = getattr(c, "shape", type(c).__name__)
        raise ValueError(f"stage_cost(x_next, u{p}) must return a scalar, got shape {shape}")
    if not jnp.issubdtype(c.dtype, jnp.floating):
        raise TypeError(f"stage_cost(x_next, u{p}) must return a real floating scalar, got dtype {c.dtype}")
    if problem.terminal is not None:
        t = _call_shape(problem.terminal, "terminal", f"(x{p})", with_params, pspec, x)
        if not isinstance(t, jax.ShapeDtypeStruct) or t.shape != () or t.dtype != jnp.bool_:
            is_array = isinstance(t, jax.ShapeDtypeStruct)
            desc = f"shape {tuple(t.shape)} dtype {t.dtype}" if is_array else type(t).__name__
            raise TypeError(f"terminal(x{p}) must return a boolean scalar, got {desc}")
    if problem.lower_bound is not None:
        steps = jax.ShapeDtypeStruct((), jnp.int32)
        b = _call_shape(problem.lower_bound, "lower_bound", f"(x, steps_left{p})", with_params, pspec, x, steps)
        if not isinstance(b, jax.ShapeDtypeStruct) or b.shape != () or not jnp.issubdtype(b.dtype, jnp.floating):
            desc = f"shape {tuple(b.shape)} dtype {b.dtype}" if isinstance(b, jax.ShapeDtypeStruct) else type(b)
            raise TypeError(f"lower_bound(x, steps_left{p}) must return a floating scalar, got {desc}")


def cost_dtype(problem: Problem, x0, params=None, batched_params: bool = False):
    """dtype of accumulated costs: that of ``stage_cost``'s output."""
    u = jax.ShapeDtypeStruct(problem.controls.shape[1:], problem.controls.dtype)
    _, pspec = params_spec(params, drop_leading=batched_params)
    x = jax.ShapeDtypeStruct(x0.shape[-1:], x0.dtype)
    return jax.eval_shape(lambda p, a, b: call(problem.stage_cost, p, a, b), pspec, x, u).dtype
