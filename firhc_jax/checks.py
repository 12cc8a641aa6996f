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

def callable_forms(problem: Problem, with_params: bool) -> str:
    """How this problem calls its callables, for error messages."""
    k = ", k" if problem.step_index else ""
    p = ", p" if with_params else ""
    forms = [f"dynamics(x, u{k}{p})", f"stage_cost(x_next, u{k}{p})"]
    if problem.constraint is not None:
        forms.append(f"constraint(x_next, u{k}{p})")
    forms += [f"terminal(x{p})", f"terminal_cost(x{p})", f"lower_bound(x, steps_left{p})"]
    return ", ".join(forms)


def strong(a):
    """``a`` without weak type: a weakly typed array (from a Python scalar,
    ``jnp.full(n, 0.2)``) would compile a second search for the same shapes
    and dtypes. A strongly typed JAX array stays as it is; anything else
    becomes a NumPy array of JAX's canonical dtype, which a jitted search
    takes as it is (making a device array here would cost a dispatch per
    call; measured in benchmarks/RESULTS.md)."""
    if isinstance(a, jax.Array) and not a.weak_type:
        return a
    a = np.asarray(a)
    return a.astype(jax.dtypes.canonicalize_dtype(a.dtype), copy=False)


def check_params(params, leading: int | tuple | None = None, what: str = "params", axis: str = "B"):
    """``params`` with every leaf an array without weak type (``strong``; tracers stay), or a clear error.

    Leaves must be real numeric or boolean arrays; with ``leading`` (an int,
    or a tuple of them) each must have those leading axes (one entry per row,
    per step, or per loop and step). Concrete leaves
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
        if isinstance(leading, tuple) and tuple(a.shape[:len(leading)]) != leading:
            raise ValueError(f"{name} must have leading axes {axis} = {list(leading)}, got shape {tuple(a.shape)}")
        if isinstance(leading, int) and (a.ndim == 0 or a.shape[0] != leading):
            raise ValueError(f"{name} must have leading axis {axis} = {leading}, got shape {tuple(a.shape)}")
        out.append(a)
    return jax.tree_util.tree_unflatten(treedef, out)


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


def as_sequence(value, horizon: int, num_controls: int, name: str = "warm_start"):
    """``value`` as ``[N]`` int32 indices into the controls (all -1: none), or None when None; a traced value
    is checked for its shape and dtype only."""
    if value is None:
        return None
    try:
        seq = value if is_tracer(value) else np.asarray(value)
    except (TypeError, ValueError) as e:
        raise TypeError(f"{name} must be [N] = [{horizon}] integer indices into controls: {e}") from None
    if seq.shape != (horizon,) or not jnp.issubdtype(seq.dtype, jnp.integer):
        raise ValueError(f"{name} must be [N] = [{horizon}] integer indices into controls, "
                         f"got shape {tuple(seq.shape)} dtype {seq.dtype}")
    if not is_tracer(seq) and not (np.all((seq >= 0) & (seq < num_controls)) or np.all(seq == -1)):
        raise ValueError(f"{name} indices must lie in [0, {num_controls}) (or be all -1: none), got {seq.tolist()}")
    return seq.astype(jnp.int32 if is_tracer(seq) else np.int32)


def as_batch(X0, name: str = "X0"):
    """``X0`` ``[B, n]`` as a strongly typed floating array of finite states, or a clear error."""
    if isinstance(X0, jax.core.Tracer):
        X = X0
    else:
        try:
            X = jnp.asarray(strong(X0))
        except (TypeError, ValueError) as e:
            raise TypeError(f"{name} must be a numeric array [B, n]: {e}") from None
    if X.ndim != 2:
        raise ValueError(f"{name} must be a 2-D batch of states [B, n], got shape {tuple(X.shape)}; "
                         "for one state use fj.sdfs")
    if X.shape[0] == 0:
        raise ValueError(f"{name} is an empty batch (B = 0)")
    if not jnp.issubdtype(X.dtype, jnp.floating):
        raise TypeError(f"{name} must have a floating dtype, got {X.dtype}")
    if not isinstance(X, jax.core.Tracer):
        bad = np.flatnonzero(~np.all(np.isfinite(np.asarray(X)), axis=1))
        if bad.size:
            raise ValueError(f"{name} contains NaN or inf in rows {bad[:10].tolist()}{' ...' if bad.size > 10 else ''}")
    return X


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
    c = _call_shape(problem, problem.stage_cost, "stage_cost", f"(x_next, u{ks}{p})", with_params, pspec, x, u, *k)
    _real_scalar(c, f"stage_cost(x_next, u{ks}{p})")
    if problem.terminal_cost is not None:
        g = _call_shape(problem, problem.terminal_cost, "terminal_cost", f"(x{p})", with_params, pspec, x)
        _real_scalar(g, f"terminal_cost(x{p})")
    if problem.constraint is not None:
        h = _call_shape(problem, problem.constraint, "constraint", f"(x_next, u{ks}{p})", with_params, pspec, x, u,
                        *k)
        _bool_scalar(h, f"constraint(x_next, u{ks}{p})")
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
    return jax.eval_shape(lambda p, a, b: problem.cost_of_step(a, b, 0, p), pspec, x, u).dtype
