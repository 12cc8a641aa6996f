"""Finite-input predictive control problems (the paper's eqs. 1-3).

Notation used throughout the package:

* ``x`` ``[n]``   plant state.
* ``u`` ``[m]``   one control input, a row of the finite control set.
* ``controls`` ``[M, m]``  the finite control set S, ``M`` inputs.
* ``N``           prediction horizon (``Problem.horizon``).

Callable contracts (all must be traceable by ``jax.jit`` and ``jax.vmap``):

* ``dynamics(x, u) -> x_next``  ``[n] x [m] -> [n]``, same dtype as ``x``.
* ``stage_cost(x_next, u) -> c`` scalar, ``c >= 0``: the cost of the step
  that produced ``x_next`` with input ``u``. Non-negativity is what makes
  pruning in sDFS exact.
* ``terminal(x) -> bool`` scalar, tested on ``x(k+N)``: the terminal
  constraint (eq. 3), in practice a tolerance set. ``None``: unconstrained.
"""
from __future__ import annotations

import dataclasses
import operator
from typing import Any, Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np

Array = Any


def _is_tracer(x) -> bool:
    return isinstance(x, jax.core.Tracer)


@jax.tree_util.register_pytree_node_class
@dataclasses.dataclass(frozen=True, eq=False)
class Problem:
    """A finite-input receding horizon problem.

    Args:
      dynamics: ``dynamics(x, u) -> x_next`` (see module docstring).
      controls: ``[M, m]`` finite control set; a 1-D ``[M]`` array means m = 1.
      stage_cost: ``stage_cost(x_next, u) -> scalar >= 0``.
      horizon: prediction horizon N >= 1.
      terminal: optional ``terminal(x) -> bool`` tested on the last predicted
        state; ``None`` means no terminal constraint.

    A ``Problem`` is a static pytree (no array leaves): the callables, the
    horizon and the control set are compiled into the search as constants, so
    XLA can fold input-only arithmetic, and solving the same problem again
    (or a rebuilt one with the same callables and control values) reuses the
    compiled search. ``controls`` is kept as a read-only NumPy array.
    """

    dynamics: Callable
    controls: Array  # [M, m]
    stage_cost: Callable
    horizon: int
    terminal: Optional[Callable] = None

    def __post_init__(self):
        for name in ("dynamics", "stage_cost"):
            if not callable(getattr(self, name)):
                raise TypeError(f"Problem.{name} must be callable, got {type(getattr(self, name)).__name__}")
        if self.terminal is not None and not callable(self.terminal):
            raise TypeError(f"Problem.terminal must be callable or None, got {type(self.terminal).__name__}")
        object.__setattr__(self, "horizon", _check_horizon(self.horizon))
        object.__setattr__(self, "controls", _check_controls(self.controls))

    # -- sizes -------------------------------------------------------------
    @property
    def num_controls(self) -> int:
        """M, the number of inputs in the control set."""
        return self.controls.shape[0]

    @property
    def input_dim(self) -> int:
        """m, the dimension of one input."""
        return self.controls.shape[1]

    def tree_size(self) -> int:
        """Child nodes of the full search tree: sum_{i=1..N} M^i."""
        M = self.num_controls
        return sum(M**i for i in range(1, self.horizon + 1))

    def replace(self, **changes) -> "Problem":
        """A copy with some fields changed (e.g. ``terminal=None``)."""
        return dataclasses.replace(self, **changes)

    # -- pytree (static: everything is auxiliary data) -------------------------
    def tree_flatten(self):
        return (), (self.dynamics, self.stage_cost, self.horizon, self.terminal, _ControlsKey(self.controls))

    @classmethod
    def tree_unflatten(cls, aux, leaves):
        obj = object.__new__(cls)  # already validated
        dynamics, stage_cost, horizon, terminal, key = aux
        for name, value in (("dynamics", dynamics), ("controls", key.array), ("stage_cost", stage_cost),
                            ("horizon", horizon), ("terminal", terminal)):
            object.__setattr__(obj, name, value)
        return obj


class _ControlsKey:
    """Hashable view of the control set, so it can be static in ``jit``."""

    __slots__ = ("array", "_key")

    def __init__(self, array: np.ndarray):
        self.array = array
        self._key = (array.shape, array.dtype.str, array.tobytes())

    def __hash__(self):
        return hash(self._key)

    def __eq__(self, other):
        return isinstance(other, _ControlsKey) and self._key == other._key


def _check_horizon(horizon) -> int:
    if isinstance(horizon, bool):
        raise TypeError("horizon must be an int >= 1, got a bool")
    try:
        value = operator.index(horizon)
    except TypeError:
        raise TypeError(f"horizon must be an int >= 1, got {horizon!r} of type {type(horizon).__name__}") from None
    if value < 1:
        raise ValueError(f"horizon must be an int >= 1, got {value}")
    return value


def _check_controls(controls) -> np.ndarray:
    if _is_tracer(controls):
        raise TypeError("controls must be concrete values, not a traced array: the control set is compiled "
                        "into the search; build the Problem outside jit/vmap")
    try:
        arr = np.asarray(jnp.asarray(controls))  # jnp decides the dtype (float32 unless x64 is enabled)
    except TypeError as e:
        raise TypeError(f"controls must be a numeric array [M, m] or [M]: {e}") from None
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise ValueError(f"controls must be 1-D [M] or 2-D [M, m], got shape {tuple(arr.shape)}")
    if arr.shape[0] == 0:
        raise ValueError("controls is empty: the control set needs at least one input (M >= 1)")
    if arr.shape[1] == 0:
        raise ValueError(f"controls has inputs of dimension 0 (shape {tuple(arr.shape)}); need m >= 1")
    if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_):
        raise TypeError(f"controls must be numeric, got dtype {arr.dtype}")
    if np.issubdtype(arr.dtype, np.inexact) and not np.all(np.isfinite(arr)):
        raise ValueError("controls contains NaN or inf")
    arr = arr.copy()
    arr.flags.writeable = False
    return arr


def quadratic_cost(lam, x_s, beta=0.0, u_e=None) -> Callable:
    """Stage cost of eq. (2): ``sum(lam * (x - x_s)^2) + sum(beta * (u - u_e)^2)``.

    ``lam`` and ``beta`` are scalars or per-component weights (the paper's
    vectors of preferences); they must be non-negative. ``u_e`` defaults to 0.
    """
    lam_np, beta_np = np.asarray(lam, dtype=float), np.asarray(beta, dtype=float)
    if np.any(lam_np < 0) or np.any(beta_np < 0):
        raise ValueError("quadratic_cost weights lam and beta must be non-negative")

    def stage_cost(x_next, u):
        dx = x_next - jnp.asarray(x_s, dtype=x_next.dtype)
        du = u - (0.0 if u_e is None else jnp.asarray(u_e, dtype=u.dtype))
        lam_ = jnp.asarray(lam, dtype=x_next.dtype)
        beta_ = jnp.asarray(beta, dtype=x_next.dtype)
        return jnp.sum(lam_ * dx**2) + jnp.sum(beta_ * du.astype(x_next.dtype) ** 2)

    return stage_cost


# ---------------------------------------------------------------------------
# Checks of a problem against an initial state, done once per (shape, dtype).
# ---------------------------------------------------------------------------

def check_state(problem: Problem, x0) -> jax.Array:
    """Validate ``x0`` against ``problem`` and return it as an array.

    Raises ``ValueError``/``TypeError`` naming the mismatch before anything is
    compiled: ``x0`` not 1-D, ``dynamics`` changing shape or dtype,
    ``stage_cost`` not scalar, ``terminal`` not a boolean scalar, NaN in ``x0``.
    """
    if not _is_tracer(x0):
        x_np = np.asarray(x0)
        if x_np.dtype.kind in "fc" and not np.all(np.isfinite(x_np)):
            raise ValueError(f"x0 contains NaN or inf: {x_np}")
        x0 = jnp.asarray(x0)
    if x0.ndim != 1:
        raise ValueError(
            f"x0 must be a 1-D state vector [n], got shape {tuple(x0.shape)}; "
            "for a batch of states use jax.vmap or fj.solve_batch")
    if not jnp.issubdtype(x0.dtype, jnp.inexact):
        raise TypeError(f"x0 must have a floating dtype, got {x0.dtype}")
    key = (tuple(x0.shape), jnp.dtype(x0.dtype))
    cache = problem.__dict__.setdefault("_checked", set())
    if key not in cache:
        _check_callables(problem, jax.ShapeDtypeStruct(x0.shape, x0.dtype))
        cache.add(key)
    return x0


def _call_shape(fn, name, signature, *args):
    try:
        return jax.eval_shape(fn, *args)
    except (TypeError, ValueError) as e:  # re-raise with the callable named, keep the cause
        shapes = ", ".join(f"{tuple(a.shape)} {a.dtype}" for a in args)
        cls = TypeError if isinstance(e, TypeError) else ValueError
        raise cls(f"{name}{signature} failed on inputs of shape/dtype ({shapes}): {e}") from e


def _check_callables(problem: Problem, x: jax.ShapeDtypeStruct):
    u = jax.ShapeDtypeStruct(problem.controls.shape[1:], problem.controls.dtype)
    out = _call_shape(problem.dynamics, "dynamics", "(x, u)", x, u)
    if not isinstance(out, jax.ShapeDtypeStruct):
        raise TypeError(f"dynamics(x, u) must return one array [n], got {type(out).__name__}")
    if out.shape != x.shape:
        raise ValueError(
            f"dynamics(x, u) returned shape {tuple(out.shape)} but x0 has shape {tuple(x.shape)}; "
            "x0 must have the shape of the state that dynamics returns")
    if out.dtype != x.dtype:
        raise TypeError(
            f"dynamics(x, u) changed the state dtype from {x.dtype} to {out.dtype}; "
            "cast x0 (or the constants/controls inside dynamics) so that the dtypes agree")
    c = _call_shape(problem.stage_cost, "stage_cost", "(x_next, u)", x, u)
    if not isinstance(c, jax.ShapeDtypeStruct) or c.shape != ():
        shape = getattr(c, "shape", type(c).__name__)
        raise ValueError(f"stage_cost(x_next, u) must return a scalar, got shape {shape}")
    if not jnp.issubdtype(c.dtype, jnp.floating):
        raise TypeError(f"stage_cost(x_next, u) must return a floating scalar, got dtype {c.dtype}")
    if problem.terminal is not None:
        t = _call_shape(problem.terminal, "terminal", "(x)", x)
        if not isinstance(t, jax.ShapeDtypeStruct) or t.shape != () or t.dtype != jnp.bool_:
            is_array = isinstance(t, jax.ShapeDtypeStruct)
            desc = f"shape {tuple(t.shape)} dtype {t.dtype}" if is_array else type(t).__name__
            raise TypeError(f"terminal(x) must return a boolean scalar, got {desc}")


def cost_dtype(problem: Problem, x0) -> jnp.dtype:
    """dtype of accumulated costs: that of ``stage_cost``'s output."""
    u = jax.ShapeDtypeStruct(problem.controls.shape[1:], problem.controls.dtype)
    return jax.eval_shape(problem.stage_cost, jax.ShapeDtypeStruct(x0.shape, x0.dtype), u).dtype
