"""The argument checks of every public entry point, run before anything is compiled.

Each refusal names the argument and says what was expected; each message is written here once. Arrays come
back as the searches take them: NumPy arrays of JAX's canonical dtype, or strongly typed JAX arrays (a weakly
typed one would compile a second search for the same shapes). Tracers are checked for shape and dtype only.
"""
from __future__ import annotations

import operator

import jax
import jax.numpy as jnp
import numpy as np


def is_tracer(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def positive_int(name: str, value, minimum: int = 1) -> int:
    """``value`` as a Python int >= ``minimum`` (NumPy integers accepted), or a
    ``TypeError``/``ValueError`` naming the argument. The one validator for
    every count and size argument of the package."""
    if isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be an int >= {minimum}, got a bool")
    try:
        out = operator.index(value)
    except TypeError:
        raise TypeError(f"{name} must be an int >= {minimum}, got {value!r} of type {type(value).__name__}") from None
    if out < minimum:
        raise ValueError(f"{name} must be an int >= {minimum}, got {out}")
    return out


def finite(name: str, array, detail: str = "") -> None:
    """A ``ValueError`` naming ``name`` where the concrete ``array`` holds NaN or inf (integers always pass)."""
    a = np.asarray(array)
    if a.dtype.kind in "fc" and not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or inf{detail}")


def numeric(name: str, value, what: str = "array") -> np.ndarray:
    """``value`` as a NumPy array of real numbers or booleans (its own dtype), or a ``TypeError`` naming ``name``:
    ragged, complex (NumPy would drop the imaginary part with only a warning) and non-numeric values refused."""
    try:
        a = np.asarray(value)
    except ValueError:  # ragged lists
        raise TypeError(f"{name} must be a real {what}, got {value!r}") from None
    if a.dtype.kind == "c":
        raise TypeError(f"{name} must be real, got complex dtype {a.dtype}")
    if a.dtype.kind not in "biuf":
        raise TypeError(f"{name} must be a real numeric {what}, got dtype {a.dtype}")
    return a


def real_array(name: str, value, what: str = "array") -> np.ndarray:
    """``value`` as a float64 NumPy array (``numeric``), finite, or an error naming ``name``. Traced values are
    refused: models and weights are built once, in NumPy, before any search."""
    if is_tracer(value):
        raise TypeError(f"{name} must be concrete values, not a traced array: the model is built once, in NumPy, "
                        "before any search (what changes between solves goes in the params)")
    a = numeric(name, value, what).astype(float)
    finite(name, a)
    return a


def matrix(name: str, value) -> np.ndarray:
    """``value`` as a read-only, finite, non-empty float64 matrix (``real_array``), or an error naming ``name``:
    the one rule for model matrices."""
    a = real_array(name, value, "matrix")
    if a.ndim != 2 or 0 in a.shape:
        raise ValueError(f"{name} must be a non-empty 2-D matrix, got shape {a.shape}")
    a.flags.writeable = False
    return a


def non_negative(name: str, value) -> float:
    """``value`` as a finite float >= 0, or an error naming ``name``."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a real number, got {value!r}") from None
    if not np.isfinite(v) or v < 0:
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    return v


def strong(a):
    """``a`` without weak type: a weakly typed array (from a Python scalar,
    ``jnp.full(n, 0.2)``) would compile a second search for the same shapes
    and dtypes. A strongly typed JAX array stays as it is; anything else
    becomes a NumPy array of JAX's canonical dtype, which a jitted search
    takes as it is (making a device array here would cost a dispatch per
    call; measured in docs/dev/benchmark-history.md)."""
    if isinstance(a, jax.Array) and not a.weak_type:
        return a
    a = np.asarray(a)
    with np.errstate(over="ignore"):  # a value beyond the canonical dtype is refused by ``kept_in_cast``
        return a.astype(jax.dtypes.canonicalize_dtype(a.dtype), copy=False)


def kept_in_cast(name: str, given, cast, detail: str = "") -> None:
    """A ``ValueError`` naming ``name`` where ``cast`` (the finite ``given`` as ``strong`` made it) lost values
    beyond the range of the narrower dtype JAX casts them to with x64 off (searched as inf, or wrapped
    around)."""
    a = np.asarray(cast)
    if a.dtype.kind == "f":
        if np.isfinite(a).all():
            return
        g = np.asarray(given)
        big, limit = float(np.max(np.abs(g))), float(np.finfo(a.dtype).max)
    elif a.dtype.kind in "iu" and np.asarray(given).dtype != a.dtype and not np.array_equal(given, a):
        g = np.asarray(given)
        big, limit = int(np.max(np.abs(g.astype(object)))), int(np.iinfo(a.dtype).max)
    else:
        return
    raise ValueError(f"{name} holds {big:.4g}, beyond the range of {a.dtype} (largest {limit:.4g}), which JAX "
                     f"casts {g.dtype} to with x64 off: scale it, or enable jax_enable_x64{detail}")


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
            arr = leaf if isinstance(leaf, jax.Array) else numeric(name, leaf)
            if arr.dtype.kind not in "biuf":
                raise TypeError(f"{name} must be a real numeric or boolean array, got dtype {arr.dtype}")
            finite(name, arr)
            a = strong(arr)
            kept_in_cast(name, arr, a)
        if isinstance(leading, tuple) and tuple(a.shape[:len(leading)]) != leading:
            raise ValueError(f"{name} must have leading axes {axis} = {list(leading)}, got shape {tuple(a.shape)}")
        if isinstance(leading, int) and (a.ndim == 0 or a.shape[0] != leading):
            raise ValueError(f"{name} must have leading axis {axis} = {leading}, got shape {tuple(a.shape)}")
        out.append(a)
    return jax.tree_util.tree_unflatten(treedef, out)


def as_state(x0, name: str = "x0"):
    """``x0`` as a finite, real, floating 1-D array, or a clear error.

    A strongly typed JAX array (or a tracer) stays as it is; anything else
    comes back as a NumPy array (``strong``)."""
    if x0 is None:
        raise TypeError(f"{name} is None: pass the current state as an array [n]")
    if not is_tracer(x0):
        x_np = numeric(name, x0, "state vector [n]")
        if x_np.dtype.kind in "fc" and not np.isfinite(x_np).all():  # the message is written only when raising
            finite(name, x_np, f": {x_np}")
        x0 = strong(x0)
        if x0.dtype != x_np.dtype:
            kept_in_cast(name, x_np, x0, f": {x_np}")
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
        X0 = X0 if isinstance(X0, jax.Array) else numeric(name, X0, "batch of states [B, n]")
        X = jnp.asarray(strong(X0))
    if X.ndim != 2:
        raise ValueError(f"{name} must be a 2-D batch of states [B, n], got shape {tuple(X.shape)}; "
                         "for one state use fj.sdfs")
    if X.shape[0] == 0:
        raise ValueError(f"{name} is an empty batch (B = 0)")
    if not jnp.issubdtype(X.dtype, jnp.floating):
        raise TypeError(f"{name} must have a floating dtype, got {X.dtype}")
    if not isinstance(X, jax.core.Tracer):
        bad = np.flatnonzero(~np.all(np.isfinite(np.asarray(X)), axis=1))
        rows = f" in rows {bad[:10].tolist()}{' ...' if bad.size > 10 else ''}"
        finite(name, X0, rows)
        kept_in_cast(name, X0, X, rows)
    return X


def as_inputs(name: str, value, m: int, dtype, leading: tuple = (), concrete: bool = False):
    """``value`` as searched inputs ``leading + [m]`` of ``dtype``, finite (default, None: zeros), or a clear
    error. One input ``[m]`` is repeated over ``leading``; a traced one is taken as it is unless ``concrete``
    (compiled in as a constant)."""
    if value is None:
        return np.zeros(leading + (m,), dtype)
    if is_tracer(value):
        if concrete:
            raise TypeError(f"{name} must be concrete, not a traced array (it is compiled in as a constant)")
        if value.shape != (m,):
            raise ValueError(f"{name} must be one input of shape ({m},), got {value.shape}")
        return value.astype(dtype)
    try:
        a = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError) as e:
        raise TypeError(f"{name} must be one input of shape ({m},): {e}") from None
    if a.shape != (m,) and a.shape != leading + (m,):
        also = f" (every loop) or {leading + (m,)} (one per loop)" if leading else ""
        raise ValueError(f"{name} must be one input of shape ({m},){also}, got {a.shape}")
    finite(name, a, f": {a}")
    return np.broadcast_to(a, leading + (m,)).copy() if a.shape != leading + (m,) else a


def input_rows(name: str, value, m: int) -> np.ndarray:
    """``value`` as concrete, finite inputs ``[..., m]`` (``numeric``; a scalar is one input when m = 1), or an
    error naming ``name``."""
    if is_tracer(value):
        raise TypeError(f"{name} must be concrete inputs, not a traced array")
    a = numeric(name, value, f"input [m] = [{m}] or inputs [..., {m}]")
    if a.ndim == 0 and m == 1:
        a = a[None]
    if a.ndim == 0 or a.shape[-1] != m:
        raise ValueError(f"{name} must be an input [m] = [{m}] or inputs [..., {m}], got shape {a.shape}")
    finite(name, a)
    return a


def sample_times(dt, steps: int):
    """``[T+1]`` seconds of each state (None without ``dt``)."""
    if dt is None:
        return None
    if isinstance(dt, (bool, np.bool_)) or not isinstance(dt, (int, float, np.integer, np.floating)) \
            or not np.isfinite(dt) or dt <= 0:
        raise ValueError(f"dt must be a finite positive number of seconds, got {dt!r}")
    return np.arange(steps + 1) * float(dt)
