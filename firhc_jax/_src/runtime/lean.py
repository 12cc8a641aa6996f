"""Eager calls that check their arguments once per signature.

A public call checks its arguments (types, shapes, dtypes, the callables against them) before it compiles.
Another call whose arguments have the same signature (the same pytree structure, array types, shapes and
dtypes, and the same x64 setting) would pass the same checks, so it skips them: ``remember`` keeps the
compiled program of a call under its signature, ``recall`` finds it (about 1 us for a few arrays). What depends
on the values (finite states and parameters, indices in range) the compiled program checks itself and returns
as one flag; where it is up, the caller runs its checks again on these values, which raise with their own
message. Only arrays (NumPy, JAX, NumPy scalars) and Python numbers make a signature: other leaves (lists,
nested sequences) take the checked path on every call.
"""
from __future__ import annotations

from typing import Any, Callable, Hashable

import jax
import jax.numpy as jnp
import numpy as np

from .memory_cache import peek, put

_ARRAY = jax.Array


def signature(args) -> tuple | None:
    """What the checks of ``args`` (a pytree; None leaves allowed) depend on, or None when a leaf is neither an
    array nor a Python number (then every call is checked)."""
    leaves, treedef = jax.tree_util.tree_flatten(args)
    out = [treedef, jax.config.jax_enable_x64]
    for a in leaves:
        if type(a) is np.ndarray or isinstance(a, np.generic):
            out.append((a.shape, a.dtype))
        elif type(a) in (float, int, bool):
            out.append(type(a))
        elif isinstance(a, _ARRAY) and not isinstance(a, jax.core.Tracer):
            out.append((a.shape, a.dtype, a.weak_type))
        else:
            return None
    return tuple(out)


def spec(args) -> tuple:
    """The shapes and dtypes a compiled program takes ``args`` (a checked pytree of arrays) as: its key. NumPy
    and JAX arrays, weakly typed or not, of one shape and (canonical) dtype share one program."""
    leaves, treedef = jax.tree_util.tree_flatten(args)
    return treedef, tuple((np.shape(a), jax.dtypes.canonicalize_dtype(a.dtype)) for a in leaves)


def recall(entry: Hashable, args) -> Any:
    """The program ``remember`` kept for a call ``entry`` with arguments of ``args``' signature, or None."""
    sig = signature(args)
    try:
        return None if sig is None else peek(("lean", entry, sig))
    except TypeError:  # an option given as an array, or of no use: the checked path takes it or names it
        return None


def remember(entry: Hashable, args, program: Any) -> None:
    """Keep ``program`` for calls ``entry`` with arguments of ``args``' signature (none kept without one)."""
    sig = signature(args)
    try:
        hash(entry)
    except TypeError:  # an option given as an array: every call takes the checked path
        return
    if sig is not None:
        put(("lean", entry, sig), program)


def non_finite(*trees) -> jax.Array:
    """[] bool: a floating leaf of ``trees`` holds NaN or inf (traced)."""
    bad = jnp.zeros((), bool)
    for a in jax.tree_util.tree_leaves(trees):
        if jnp.issubdtype(a.dtype, jnp.inexact):
            bad = bad | ~jnp.all(jnp.isfinite(a))
    return bad


def bad_sequence(sequence, num_controls: int) -> jax.Array:
    """[] bool (traced): ``sequence`` (None: none) is neither indices in ``[0, num_controls)`` nor all -1, the
    values ``checks.as_sequence`` refuses."""
    if sequence is None:
        return jnp.zeros((), bool)
    inside = jnp.all((sequence >= 0) & (sequence < num_controls))
    return ~(inside | jnp.all(sequence == -1))


def first_call(entry: Hashable, args, build: Callable[[], Any]) -> Any:
    """The program of a checked call: built once per signature of ``args`` and remembered for the next."""
    program = build()
    remember(entry, args, program)
    return program
