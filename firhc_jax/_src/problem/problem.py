"""Finite-input predictive control problems (the paper's eqs. 1-3).

Notation used throughout the package:

* ``x`` ``[n]``   state of the prediction model.
* ``u`` ``[m]``   one control input, a row of the finite control set.
* ``controls`` ``[M, m]``  the finite control set S, ``M`` inputs.
* ``N``           prediction horizon (``Problem.horizon``).
* ``k``           with ``step_index=True``: the int32 index of ``u`` in the
  predicted sequence (0: the input applied now, ``N - 1``: the last). Traced,
  so it never recompiles; use it to read references and disturbances along
  the horizon from ``p`` (``p["ref"][k]``).
* ``p``           parameters: any pytree of arrays (a reference, weights, a
  set point), passed to the solvers as ``params=``. Values change without
  recompiling; only their shapes and dtypes are compiled in.

Callable contracts (all must be traceable by ``jax.jit`` and ``jax.vmap``).
Without ``params`` they are called without ``p``; with ``params`` (not None)
every callable takes ``p`` as its last argument. With ``step_index=True`` the
three per-step callables take ``k`` after their usual arguments:

* ``dynamics(x, u[, k][, p]) -> x_next``  ``[n] x [m] -> [n]``, same dtype as ``x``.
* ``stage_cost(x_next, u[, k][, p]) -> c`` scalar, ``c >= 0``: the cost of the
  step that produced ``x_next`` with input ``u``. Non-negativity is what makes
  pruning in sDFS exact. ``+inf`` makes a sequence infeasible (prefer
  ``constraint``, which also says so in the node count).
* ``constraint(x_next, u[, k][, p]) -> bool`` scalar: optional hard constraint
  on every step (current limits, forbidden transitions). A child where it is
  False is discarded: never expanded, never a solution, never counted as cheap.

With ``previous_state=True`` ``stage_cost`` and ``constraint`` also take the
state before the step, first: ``stage_cost(x, x_next, u[, k][, p])``,
``constraint(x, x_next, u[, k][, p])`` (a minimum up or down time, a ramp
limit, a cost of changing state, without carrying a flag in the state).
* ``terminal(x[, p]) -> bool`` scalar, tested on ``x(k+N)``: the terminal
  constraint (eq. 3), in practice a tolerance set. ``None``: unconstrained.
* ``terminal_cost(x[, p]) -> scalar >= 0``: optional cost of the last predicted
  state ``x(k+N)`` (do-mpc's ``mterm``), added to every complete sequence.
  Costs still only grow along a path, so pruning stays exact.
* ``first_input_of(x0, sequence[, p]) -> u`` ``[m]``: optional, for a problem
  whose controls stand for *classes* of plant inputs that the search merges
  (``fj.LinearTracking``: switch states of equal effect, the cheapest member
  chosen inside the node): the input to apply for the optimal ``sequence``
  ``[N]`` from ``x0``. Default: ``controls[sequence[0]]``.
* ``lower_bound(x, steps_left[, p]) -> scalar``: optional admissible bound on
  the cost still to come from ``x`` after ``steps_left`` (traced int32; N - 1
  down to 0: it is evaluated at the leaves too, where its value is unused)
  more inputs: their stage costs plus the terminal cost, ``+inf`` where the
  terminal set or the constraints cannot be met in that many steps. With it
  every search prunes a node when ``cost + bound`` is not below the incumbent.
  (The step index of the next input is ``N - steps_left``.) ``lower_bound="auto"``
  derives one from the model (``auto_bound``): per remaining step the least
  stage cost over the box of states reachable by then, ``+inf`` where no
  input's constraint or the terminal set can hold on that box.

Nothing in a search is differentiable (it is a discrete argmin); the cost of
a returned sequence can be re-evaluated differentiably with
``fj.rollout_cost``.
"""
from __future__ import annotations

import dataclasses
import weakref
from typing import Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np

from ..annotations import ArrayLike
from ..checks import finite, input_rows, is_tracer, positive_int, real_array
from .auto_bound import AutoBound


@jax.tree_util.register_pytree_node_class
@dataclasses.dataclass(frozen=True, eq=False)
class Problem:
    """A finite-input receding horizon problem.

    Args:
      dynamics: ``dynamics(x, u[, p]) -> x_next`` (see module docstring).
      controls: ``[M, m]`` finite control set; a 1-D ``[M]`` array means m = 1.
      stage_cost: ``stage_cost(x_next, u[, p]) -> scalar >= 0``.
      horizon: prediction horizon N >= 1.
      terminal: optional ``terminal(x[, p]) -> bool`` tested on the last
        predicted state; ``None`` means no terminal constraint.
      lower_bound: optional admissible ``lower_bound(x, steps_left[, p])``, or
        ``"auto"``: a bound derived from the model by interval arithmetic
        (``auto_bound``; afterwards ``problem.lower_bound`` is that callable,
        and a copy made with ``replace`` derives it again from its own model).
      terminal_cost: optional ``terminal_cost(x_N[, p]) -> scalar >= 0``.
      constraint: optional ``constraint(x_next, u[, k][, p]) -> bool``.
      step_index: pass ``k`` to ``dynamics``, ``stage_cost`` and ``constraint``.
      previous_state: pass the state before the step to ``stage_cost`` and
        ``constraint``, as their first argument (module docstring).
      first_input_of: optional ``first_input_of(x0, sequence[, p]) -> [m]``,
        the input to apply for an optimal sequence (module docstring).

    A ``Problem`` is a pytree with no array leaves: the callables, the horizon
    and the control set are static, compiled into the search as constants.
    Two problems with the same callables (the same function objects), horizon
    and control values share one compiled search; everything that changes
    between solves belongs in ``params``. ``controls`` is kept as a read-only
    NumPy array.
    """

    dynamics: Callable
    controls: ArrayLike  # [M, m]
    stage_cost: Callable
    horizon: int
    terminal: Optional[Callable] = None
    lower_bound: Optional[Callable] = None
    terminal_cost: Optional[Callable] = None
    constraint: Optional[Callable] = None
    step_index: bool = False
    first_input_of: Optional[Callable] = None
    previous_state: bool = False

    def __post_init__(self):
        derive = isinstance(self.lower_bound, AutoBound)  # a copy (replace) derives it again from its own model
        if isinstance(self.lower_bound, str):
            if self.lower_bound != "auto":
                raise ValueError(f'Problem.lower_bound must be a callable, "auto" or None, got {self.lower_bound!r}')
            derive = True
        if derive:
            object.__setattr__(self, "lower_bound", None)
        for name in ("dynamics", "stage_cost"):
            if not callable(getattr(self, name)):
                raise TypeError(f"Problem.{name} must be callable, got {type(getattr(self, name)).__name__}")
        for name in ("terminal", "lower_bound", "terminal_cost", "constraint", "first_input_of"):
            value = getattr(self, name)
            if value is not None and not callable(value):
                raise TypeError(f"Problem.{name} must be callable or None, got {type(value).__name__}")
        for name in ("step_index", "previous_state"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise TypeError(f"Problem.{name} must be True or False, got {getattr(self, name)!r}")
            object.__setattr__(self, name, bool(getattr(self, name)))
        horizon = positive_int("horizon", self.horizon)
        if horizon > _MAX_HORIZON:
            raise ValueError(f"horizon {horizon} is larger than {_MAX_HORIZON:,}: the search's node paths and "
                             "stack grow with N and N^2")
        object.__setattr__(self, "horizon", horizon)
        object.__setattr__(self, "controls", _check_controls(self.controls))
        if derive:
            object.__setattr__(self, "lower_bound", AutoBound(
                dynamics=self.dynamics, stage_cost=self.stage_cost, constraint=self.constraint, terminal=self.terminal,
                terminal_cost=self.terminal_cost, horizon=self.horizon, step_index=self.step_index,
                previous_state=self.previous_state, controls=self.controls, controls_key=_ControlsKey(self.controls)))
        object.__setattr__(self, "_key", tuple(getattr(self, f) for f in _CALLABLE_FIELDS)
                           + (self.horizon, self.step_index, self.previous_state, _ControlsKey(self.controls)))

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
        M, N = self.num_controls, self.horizon
        return N if M == 1 else (M ** (N + 1) - M) // (M - 1)

    def index_of(self, u: ArrayLike) -> int | np.ndarray:
        """The index of input ``u`` ``[m]`` in ``controls``, as ``warm_start``, ``SearchResult.sequence`` and
        ``ClosedLoop.input_indices`` hold it; of each input of ``[..., m]``, an int32 array ``[...]``.

        Values match exactly, compared in the controls' dtype (a float32 set finds the float32 value of
        ``0.1``); the first of equal rows is returned. An input that is not in the set is a ``ValueError``."""
        u = input_rows("u", u, self.input_dim)
        dtype = self.controls.dtype if np.issubdtype(self.controls.dtype, np.inexact) else np.float64
        hits = np.all(u.astype(dtype)[..., None, :] == self.controls.astype(dtype), axis=-1)  # [..., M]
        missing = ~hits.any(axis=-1)
        if missing.any():
            where = tuple(int(i) for i in np.argwhere(missing)[0])
            raise ValueError(f"u{list(where) if where else ''} = {u[where].tolist()} is not in the control set")
        index = np.argmax(hits, axis=-1).astype(np.int32)
        return int(index) if index.ndim == 0 else index

    def replace(self, **changes) -> "Problem":
        """A copy with some fields changed (e.g. ``terminal=None``)."""
        return dataclasses.replace(self, **changes)

    @property
    def key(self) -> tuple:
        """Hashable identity of what a compiled search depends on (fixed at
        construction, like every field; also the pytree's static data)."""
        return self._key

    # -- pytree (static: everything is auxiliary data) -------------------------
    def tree_flatten(self):
        return (), self.key

    @classmethod
    def tree_unflatten(cls, aux, leaves):
        obj = object.__new__(cls)  # already validated
        *fns, horizon, step_index, previous_state, controls = aux
        for name, value in zip(_CALLABLE_FIELDS, fns, strict=True):
            object.__setattr__(obj, name, value)
        for name, value in (("horizon", horizon), ("step_index", step_index), ("previous_state", previous_state),
                            ("controls", controls.array), ("_key", aux)):
            object.__setattr__(obj, name, value)
        return obj

    # -- the callables, with the step index and parameters as the problem takes them --
    def next_state(self, x, u, k, params=None):
        """``dynamics(x, u[, k][, p])``."""
        return call(self.dynamics, params, x, u, *self._k(k))

    def cost_of_step(self, x, x_next, u, k, params=None):
        """``stage_cost([x, ]x_next, u[, k][, p])`` of the step from ``x``."""
        return call(self.stage_cost, params, *self._x(x), x_next, u, *self._k(k))

    def allowed(self, x, x_next, u, k, params=None):
        """``constraint([x, ]x_next, u[, k][, p])`` of the step from ``x``, True without a constraint."""
        if self.constraint is None:
            return jnp.ones((), bool)
        return call(self.constraint, params, *self._x(x), x_next, u, *self._k(k))

    def first_input(self, x0, sequence, params=None):
        """The input to apply for the optimal ``sequence`` ``[N]`` from ``x0``
        (``first_input_of``, default ``controls[sequence[0]]``), in ``input_dtype``;
        a ``ValueError`` if ``first_input_of`` returns another shape than ``[m]``."""
        dtype = input_dtype(self)
        if self.first_input_of is None:
            return jnp.asarray(self.controls, dtype)[jnp.maximum(sequence[0], 0)]
        u = jnp.asarray(call(self.first_input_of, params, x0, sequence))
        if u.shape != (self.input_dim,):
            raise ValueError(f"first_input_of must return one input of shape [m] = [{self.input_dim}], "
                             f"got shape {tuple(u.shape)}")
        return u.astype(dtype)

    def model_plant(self, x, u, params=None):
        """The model as a plant of the closed loop: ``dynamics`` at step index 0."""
        return self.next_state(x, u, 0, params)

    def _k(self, k):
        return (jnp.asarray(k, jnp.int32),) if self.step_index else ()

    def _x(self, x):
        return (x,) if self.previous_state else ()


_CALLABLE_FIELDS = ("dynamics", "stage_cost", "terminal", "lower_bound", "terminal_cost", "constraint",
                    "first_input_of")
_MAX_HORIZON = 100_000


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


def _check_controls(controls) -> np.ndarray:
    if is_tracer(controls):
        raise TypeError("controls must be concrete values, not a traced array: the control set is compiled "
                        "into the search as a constant. Build the Problem outside jit/vmap, or pass the "
                        "changing values through params")
    if controls is None:
        raise TypeError("controls is None: pass the finite control set as an array [M, m] or [M]")
    try:
        given = np.asarray(controls)
    except ValueError as e:  # ragged nested lists
        raise ValueError(f"controls must be a rectangular array [M, m] or [M]: {e}") from None
    if given.dtype == object or not (np.issubdtype(given.dtype, np.number) or given.dtype == np.bool_):
        raise TypeError(f"controls must be a real numeric or boolean array [M, m] or [M], got dtype {given.dtype}")
    if np.issubdtype(given.dtype, np.complexfloating):
        raise TypeError("controls must be real, got a complex dtype")
    arr = given.astype(jax.dtypes.canonicalize_dtype(given.dtype))  # float32/int32 unless x64 is enabled
    if given.size and given.dtype.kind in "iu" and not np.array_equal(arr.astype(given.dtype), given):
        raise ValueError(f"controls of dtype {given.dtype} do not fit JAX's {arr.dtype} (values would wrap); "
                         "enable x64 or use smaller values")
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise ValueError(f"controls must be 1-D [M] or 2-D [M, m], got shape {tuple(arr.shape)}")
    if arr.shape[0] == 0:
        raise ValueError("controls is empty: the control set needs at least one input (M >= 1)")
    if arr.shape[1] == 0:
        raise ValueError(f"controls has inputs of dimension 0 (shape {tuple(arr.shape)}); need m >= 1")
    finite("controls", arr)
    if not np.issubdtype(arr.dtype, np.inexact) and not np.array_equal(arr.astype(np.float32), arr):
        raise ValueError("integer controls must be exactly representable in float32 (|u| <= 2^24): the input "
                         "a search returns is floating, so that an infeasible search can return NaN")
    arr = arr.copy()
    arr.flags.writeable = False
    return arr


def refuse_differentiation(*trees) -> None:
    """A clear ``TypeError`` when a search is differentiated: it is a discrete
    argmin (JAX's own message would be about while-loops)."""
    for leaf in jax.tree_util.tree_leaves(trees):
        if type(leaf).__name__ in ("JVPTracer", "LinearizeTracer"):  # jax.jvp, jax.grad
            raise TypeError("the searches are not differentiable (a discrete argmin over input sequences); "
                            "differentiate the cost of the returned sequence instead: "
                            "fj.rollout_cost(problem, x0, jax.lax.stop_gradient(result.sequence), params=params)")


def input_dtype(problem: Problem):
    """dtype of ``first_input``: the controls' own if floating, else the default
    float (float32, or float64 with x64), so that infeasible can be NaN."""
    if np.issubdtype(problem.controls.dtype, np.inexact):
        return problem.controls.dtype
    return jax.dtypes.canonicalize_dtype(np.float64)


def quadratic_cost(lam: ArrayLike, x_s: ArrayLike, beta: ArrayLike = 0.0, u_e: ArrayLike | None = None) -> Callable:
    """Stage cost of eq. (2): ``dx' Q dx + du' R du`` with ``dx = x_next - x_s``
    and ``du = u - u_e`` (``u_e`` defaults to 0).

    ``lam`` (Q) and ``beta`` (R) are each a scalar, a vector of per-component
    weights (the paper's vectors of preferences: ``sum(lam * dx**2)``) or a
    full matrix (``dx' Q dx``), which must be symmetric positive semidefinite.
    Weights must be finite and non-negative. Inputs are promoted to the
    state's floating dtype before ``u_e`` is subtracted, so integer or
    boolean controls keep real targets. The returned callable ignores any
    further arguments, so it serves problems with ``step_index`` and
    ``params`` alike.
    """
    Q, R = weight("lam", lam), weight("beta", beta)
    targets = {}
    for name, v in (("x_s", x_s), ("u_e", u_e)):
        if v is None:
            continue
        targets[name] = real_array(f"quadratic_cost target {name}", v, "vector")
    if Q.ndim and "x_s" in targets and targets["x_s"].ndim and targets["x_s"].shape != Q.shape[:1]:
        raise ValueError(f"quadratic_cost: x_s has shape {targets['x_s'].shape} but lam has shape {Q.shape}: "
                         "both must have the state's length n")

    def stage_cost(x_next, u, *_):
        dtype = x_next.dtype
        du = u.astype(dtype)
        for name, v, against, what in (("x_s", x_s, x_next, "the state x_next"), ("lam", Q, x_next, "the state x_next"),
                                       ("u_e", u_e, du, "the input u"), ("beta", R, du, "the input u")):
            if v is not None:
                check_target("quadratic_cost", name, v, against, what, weight=name in ("lam", "beta"))
        dx = x_next - jnp.asarray(x_s, dtype=dtype)
        du = du - (0.0 if u_e is None else jnp.asarray(u_e, dtype=dtype))
        return weighted_square(Q, dx) + weighted_square(R, du)

    return stage_cost


def check_target(fn: str, name: str, value, v, what: str, weight: bool = True) -> None:
    """A ``ValueError`` naming ``name`` and both shapes where ``value`` (a target, or with ``weight`` a weight:
    also a matrix ``[len, len]``) does not fit the vector ``v`` it applies to. Checked where ``v``'s length is
    known, when the callable is traced (``fj.Problem``'s checks, before anything is compiled): broadcast, a
    target of the wrong length would silently multiply the cost."""
    shape = tuple(np.shape(value))
    if shape not in ((), tuple(v.shape)) and not (weight and shape == tuple(v.shape) * 2):
        raise ValueError(f"{fn}: {name} has shape {shape}, which does not fit {what} of shape {tuple(v.shape)}")


def weight(name: str, w) -> np.ndarray:
    """A quadratic weight checked: finite, and a non-negative scalar or vector,
    or a symmetric positive semidefinite matrix; else a ``ValueError`` naming
    ``name``. Returned as a read-only float64 NumPy array (cast to the state's
    dtype where it is used)."""
    w_np = real_array(f"weight {name}", w, "scalar, vector or matrix")
    if w_np.ndim > 2:
        raise ValueError(f"weight {name} must be a scalar, a vector or a matrix, got shape {w_np.shape}")
    if w_np.ndim < 2 and np.any(w_np < 0):
        raise ValueError(f"weight {name} must be non-negative, got {w!r}")
    if w_np.ndim == 2:
        if w_np.shape[0] != w_np.shape[1]:
            raise ValueError(f"weight {name} must be a square matrix, got shape {w_np.shape}")
        scale = max(1.0, float(np.max(np.abs(w_np)))) if w_np.size else 1.0
        if not np.allclose(w_np, w_np.T, rtol=0, atol=1e-12 * scale):
            raise ValueError(f"weight {name} must be a symmetric matrix, got {w_np.tolist()}")
        low = float(np.min(np.linalg.eigvalsh(w_np))) if w_np.size else 0.0
        if low < -1e-10 * scale:
            raise ValueError(f"weight {name} must be positive semidefinite; its smallest eigenvalue is {low:.3g}")
    w_np.flags.writeable = False
    return w_np


def weighted_square(w: np.ndarray, v):
    """``v' W v`` for a matrix weight (clamped at 0: rounding can take a
    semidefinite form a few ulps below it, which the searches would report as
    a negative cost), ``sum(w * v**2)`` for a scalar or vector."""
    W = jnp.asarray(w, dtype=v.dtype)
    return jnp.maximum(v @ (W @ v), 0) if w.ndim == 2 else jnp.sum(W * v**2)


def call(fn: Callable, params, *args):
    """``fn(*args)`` without parameters, ``fn(*args, params)`` with them.

    Inside a trace the call goes through ``jax.jit(fn, inline=True)``: JAX
    keeps ``fn``'s jaxpr per argument signature (and its ``vmap`` per batch
    axis), so a decision's checks, search and fallback trace a user's
    callable once instead of once each; the program is the same, inlined.
    Outside a trace (a plant in a Python loop) ``fn`` runs as it is."""
    args = args if params is None else (*args, params)
    if any(map(is_tracer, jax.tree_util.tree_leaves(args))) and _traceable(fn):
        return jax.jit(fn, inline=True)(*args)
    return fn(*args)


def _traceable(fn) -> bool:
    """Whether JAX can keep ``fn``'s traces (its cache holds functions by weak reference)."""
    try:
        weakref.ref(fn)
    except TypeError:
        return False
    return True
