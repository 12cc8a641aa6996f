"""The type names of the public signatures."""
from typing import Any

from jax.typing import ArrayLike

PyTree = Any  # a pytree of arrays: the parameters (a dict, tuple or NamedTuple of arrays, nested)

__all__ = ["ArrayLike", "PyTree"]
