"""Engines that run eager searches and decisions outside XLA, by name (``fj.sdfs(..., engine=)``,
``lt.solve(..., engine=)``, ``FIRHC(..., engine=)``).

``"xla"`` (the default) is the compiled JAX program. Other engines live in the areas above the searches and the
controller (``"c"``: the generated C of ``fj.export_c``, ``firhc_jax._src.export.engine``) and register here
when the package is imported, so neither imports them.
"""
from __future__ import annotations

from typing import Any, Callable, Protocol


class Engine(Protocol):
    def check_search(self) -> None:
        """Raise where this engine cannot run an ``fj.sdfs``."""

    def build_search(self, problem, x0, params, budgeted: bool, pop_width: int) -> Callable[..., tuple]:
        """``run(x0, params, warm_start, max_nodes) -> (result, alarm)`` for arguments of these shapes and dtypes,
        as ``fj.sdfs``'s compiled search."""

    def check_tracking(self) -> None:
        """Raise where this engine cannot run ``LinearTracking.solve``."""

    def build_tracking(self, lt, x, u_prev, y_ref, d, budgeted: bool) -> Callable[..., tuple]:
        """``run(x, u_prev, y_ref, d, warm_start, max_nodes) -> (result, alarm)`` as ``lt.solve``'s compiled call."""

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
