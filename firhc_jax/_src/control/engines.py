"""Engines that run a controller's eager decisions outside XLA, by name (``FIRHC(..., engine=)``).

``"xla"`` (the default) is the compiled JAX decision. Other engines live in the areas above the controller
(``"c"``: the generated C of ``fj.export_c``, ``firhc_jax._src.export.engine``) and register here when the
package is imported, so the controller never imports them.
"""
from __future__ import annotations

from typing import Any, Callable, Protocol


class Engine(Protocol):
    def check(self, ctrl) -> None:
        """Raise where this engine cannot run ``ctrl``'s decisions (at construction)."""

    def build(self, ctrl, state, x, params) -> Callable[[Any, Any, Any], tuple]:
        """``run(state, x, params) -> (u, state, info)`` for arguments of these shapes and dtypes."""


ENGINES: dict[str, Engine] = {}


def engine(name: str) -> Engine | None:
    """The engine registered as ``name`` (None for ``"xla"``); a ``ValueError`` lists the names."""
    if name == "xla":
        return None
    if not isinstance(name, str) or name not in ENGINES:
        raise ValueError(f"engine must be one of {['xla', *ENGINES]}, got {name!r}")
    return ENGINES[name]
