"""One output buffer for a compiled call from Python.

A call of a compiled program from Python pays about 1 us for each output array it returns (and about
0.25 us for each JAX array it takes; a NumPy array costs a copy more): a ``SearchResult`` alone has ten
fields. ``compile_packed`` compiles a function whose outputs are packed into one byte buffer and reads them
back as NumPy views of one structured record, so a decision returns one array whatever it holds.
"""
from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np


def _as_bytes(leaf) -> jax.Array:
    leaf = jnp.asarray(leaf)
    if leaf.dtype == jnp.bool_:
        return leaf.astype(jnp.uint8).reshape(-1)
    return jax.lax.bitcast_convert_type(leaf, jnp.uint8).reshape(-1)


class Packed:
    """``fn``'s outputs as one byte buffer: ``traced(*args)`` is what to compile (a ``uint8`` vector),
    ``unpack(buffer)`` the output pytree again, as NumPy arrays (read-only views of the buffer). The layout is
    fixed by the trace; one ``Packed`` serves one output structure."""

    def __init__(self, fn: Callable):
        self._fn = fn
        self._treedef = None
        self._record = None

    def traced(self, *args) -> jax.Array:
        leaves, treedef = jax.tree_util.tree_flatten(self._fn(*args))
        leaves = [jnp.asarray(a) for a in leaves]
        self._treedef = treedef
        self._record = np.dtype([(f"f{i}", np.dtype(a.dtype), a.shape) for i, a in enumerate(leaves)])
        return jnp.concatenate([_as_bytes(a) for a in leaves])

    def unpack(self, buffer):
        record = np.asarray(buffer).view(self._record).reshape(())
        return self._treedef.unflatten([record[name] for name in self._record.names])


def compile_packed(fn: Callable, *args) -> Callable:
    """``fn(*args)`` compiled for these arguments' shapes and dtypes, its outputs packed (``Packed``): returns
    ``run(*args) -> outputs`` (NumPy arrays). Later arguments must have the same shapes and dtypes, or dtypes
    that JAX canonicalises to them (the callers key their programs by the arguments' signature)."""
    packed = Packed(fn)
    compiled = jax.jit(packed.traced).lower(*args).compile()

    def run(*a):
        return packed.unpack(compiled(*a))

    return run
