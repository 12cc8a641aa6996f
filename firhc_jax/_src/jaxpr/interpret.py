"""One walk over a jaxpr for any value domain: generated C (``firhc_jax._src.export``) and interval bounds.

``interpret(closed, args, domain)`` evaluates a ``ClosedJaxpr`` equation by equation on values of the
domain's own kind. Calls that only wrap another jaxpr (``jit``, ``closed_call``, ``remat``, ``custom_jvp_call``,
``custom_vjp_call``) are inlined: the domain sees the primitives of the user's code, never the wrappers.
Everything else, loops and conditionals included, goes to ``domain.apply``, which may call ``interpret``
again on the bodies.
"""
from __future__ import annotations

from typing import Any, Protocol, Sequence

import numpy as np
from jax.extend import core

WRAPPERS = {"jit": "jaxpr", "pjit": "jaxpr", "closed_call": "call_jaxpr", "core_call": "call_jaxpr",
            "remat": "jaxpr", "remat2": "jaxpr", "checkpoint": "jaxpr", "custom_jvp_call": "call_jaxpr",
            "custom_vjp_call": "call_jaxpr", "custom_vjp_call_jaxpr": "fun_jaxpr", "custom_lin": None}


class Domain(Protocol):
    """What a value domain provides."""

    def constant(self, value: np.ndarray, aval) -> Any:
        """The domain's value of a constant (a literal or a closed-over array)."""

    def apply(self, eqn, invals: Sequence[Any]) -> Sequence[Any]:
        """The outputs of one equation, one per ``eqn.outvars``."""


class Unsupported(NotImplementedError):
    """A primitive the domain cannot evaluate; ``primitive`` names it."""

    def __init__(self, primitive: str, why: str = ""):
        self.primitive = primitive
        super().__init__(f"primitive {primitive!r} is not supported{': ' + why if why else ''}")


def subjaxpr(eqn) -> core.ClosedJaxpr | None:
    """The jaxpr a wrapper equation calls, closed (None: not a wrapper)."""
    name = WRAPPERS.get(eqn.primitive.name, "")
    if not name:
        return None
    inner = eqn.params[name]
    return inner if isinstance(inner, core.ClosedJaxpr) else core.ClosedJaxpr(inner, ())


def interpret(closed: core.ClosedJaxpr, args: Sequence[Any], domain: Domain) -> list:
    """The outputs of ``closed`` on ``args`` (domain values), in the domain."""
    jaxpr = closed.jaxpr
    env: dict = {}

    def read(v):
        if isinstance(v, core.Literal):
            return domain.constant(np.asarray(v.val, dtype=v.aval.dtype), v.aval)
        return env[v]

    for var, value in zip(jaxpr.constvars, closed.consts, strict=True):
        env[var] = domain.constant(np.asarray(value), var.aval)
    for var, value in zip(jaxpr.invars, args, strict=True):
        env[var] = value
    for eqn in jaxpr.eqns:
        invals = [read(v) for v in eqn.invars]
        inner = subjaxpr(eqn)
        if inner is not None:
            outs = interpret(inner, invals[len(invals) - len(inner.jaxpr.invars):], domain)
        else:
            outs = domain.apply(eqn, invals)
        for var, value in zip(eqn.outvars, outs, strict=True):
            if not isinstance(var, core.DropVar):
                env[var] = value
    return [read(v) for v in jaxpr.outvars]
