"""Building blocks for the common case: linear plants, switch-level products and
tracking costs along the horizon.

* ``discretize(A, B, Ts)``: exact zero-order-hold discretisation of
  ``dx/dt = A x + B u``.
* ``linear_dynamics(A, B, d=None)``: ``dynamics(x, u, ...) = A x + B u (+ d)``.
* ``product_controls(*levels, repeat=1)``: every combination of per-component
  levels, the finite control set of m switches or legs.
* ``tracking_cost(C, Q, R, u_ref)``: ``||C x(k+1) - r(k)||_Q^2 + ||u(k) - u_ref||_R^2``
  with the reference ``r`` read from the parameters along the horizon.
* ``input_change_cost(lambda_u)``: the switching penalty
  ``lambda_u ||u(k) - u(k-1)||^2`` for ``fj.with_input_memory``.
* ``horizon_windows(signal, steps, horizon, start=1, axis=0)``: a sampled reference
  cut into the per-step parameters of a closed loop, ``[steps, N, ...]`` (of
  B scenarios with ``axis=1``: ``[B, steps, N, ...]``).

Each callable returned here ignores arguments it does not use, so it fits a
problem with or without ``step_index`` and ``params``. Matrices are checked and
kept as float64 NumPy arrays; they are cast to the state's dtype where they are
used, so float32 and float64 problems share one definition.
"""
from __future__ import annotations

import math
from typing import Callable

import jax.numpy as jnp
import numpy as np
import scipy.linalg

from ..annotations import ArrayLike
from ..checks import matrix, non_negative, positive_int, real_array
from .problem import check_target, weight, weighted_square

_MAX_CONTROLS = 2**31 - 1  # the searches index inputs with int32


def _state_input(A, B) -> tuple[np.ndarray, np.ndarray]:
    A = matrix("A", A)
    if A.shape[0] != A.shape[1]:
        raise ValueError(f"A must be square [n, n], got shape {A.shape}")
    B = matrix("B", np.reshape(B, (-1, 1)) if np.ndim(B) == 1 else B)
    if B.shape[0] != A.shape[0]:
        raise ValueError(f"B must have n = {A.shape[0]} rows like A, got shape {B.shape}")
    return A, B


def discretize(A: ArrayLike, B: ArrayLike, Ts: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation of ``dx/dt = A x + B u`` with
    sampling period ``Ts``: ``(Ad, Bd)`` with ``Ad = exp(A Ts)`` and
    ``Bd = int_0^Ts exp(A s) ds B``, both from one matrix exponential of
    ``[[A, B], [0, 0]] Ts`` (float64 NumPy arrays)."""
    A, B = _state_input(A, B)
    given = Ts
    Ts = real_array("Ts", Ts, "sampling period > 0")
    if Ts.ndim != 0 or Ts <= 0:
        raise ValueError(f"Ts must be a finite sampling period > 0, got {given!r}")
    Ts = float(Ts)
    n, m = B.shape
    block = np.zeros((n + m, n + m))
    block[:n, :n], block[:n, n:] = A, B
    with np.errstate(over="ignore", invalid="ignore"):
        E = scipy.linalg.expm(block * Ts)
    if not np.all(np.isfinite(E)):
        rate = float(np.max(np.real(np.linalg.eigvals(A))))
        raise ValueError(f"discretize: exp(A Ts) is not finite in float64 for Ts = {Ts!r} (the fastest growth "
                         f"rate of A is {rate:.3g} per unit time, exp({rate * Ts:.3g}) per sample); "
                         "shorten Ts or check A")
    return E[:n, :n], E[:n, n:]


def linear_dynamics(A: ArrayLike, B: ArrayLike, d: ArrayLike | None = None) -> Callable:
    """``dynamics(x, u, ...) -> A x + B u (+ d)`` for discrete-time ``A``
    ``[n, n]``, ``B`` ``[n, m]`` (a vector: m = 1) and an optional constant
    ``d`` ``[n]``. Inputs are promoted to the state's dtype. Disturbances that
    change along the horizon belong in the parameters: wrap it,
    ``lambda x, u, k, p: f(x, u) + p["d"][k]``."""
    A, B = _state_input(A, B)
    if d is not None:
        d = real_array("d", d, "vector")
        if d.shape != (A.shape[0],):
            raise ValueError(f"d must be a vector of shape ({A.shape[0]},), got {d!r}")

    def dynamics(x, u, *_):
        out = jnp.asarray(A, x.dtype) @ x + jnp.asarray(B, x.dtype) @ u.astype(x.dtype)
        return out if d is None else out + jnp.asarray(d, x.dtype)

    return dynamics


def product_controls(*levels: ArrayLike, repeat: int = 1) -> np.ndarray:
    """``[M, m]`` control set of every combination of the given per-component
    levels, in ``itertools.product`` order: ``product_controls([-1, 0, 1],
    repeat=3)`` is the 27 switch states of a three-level three-phase inverter,
    ``product_controls([0, 1], [0, 1, 2])`` an on/off valve and a three-speed
    pump."""
    if not levels:
        raise ValueError("product_controls needs at least one list of levels")
    repeat = positive_int("repeat", repeat)
    sets = []
    for i, lv in enumerate(levels):
        arr = np.asarray(lv)
        if arr.ndim != 1 or arr.size == 0:
            raise ValueError(f"levels[{i}] must be a non-empty 1-D list of values, got {lv!r}")
        sets.append(arr.tolist())
    M = math.prod(len(v) for v in sets) ** repeat
    if M > _MAX_CONTROLS:
        raise ValueError(f"product_controls would make {M:,} inputs (levels of sizes {[len(v) for v in sets]}, "
                         f"repeat={repeat}), more than the {_MAX_CONTROLS:,} that the searches index with int32")
    sets = sets * repeat
    dtype = np.array([value for v in sets for value in v]).dtype  # as for the rows written out
    out = np.empty((M, len(sets)), dtype)
    inner = M
    for j, v in enumerate(sets):  # itertools.product order: the last component changes fastest
        inner //= len(v)
        out[:, j] = np.tile(np.repeat(np.array(v, dtype), inner), M // (inner * len(v)))
    return out


def tracking_cost(C: ArrayLike | None = None, Q: ArrayLike | None = None, R: ArrayLike | None = None,
                  u_ref: ArrayLike | None = None, ref: str = "ref") -> Callable:
    """Stage cost ``||C x(k+1) - r(k)||_Q^2 + ||u(k) - u_ref||_R^2`` of tracking MPC.

    The reference is read from the parameters: with ``step_index`` it is
    ``p[ref]`` ``[N, p]``, the output reference at every predicted step
    (``r(k)`` is the target of ``x(k+1)``); without ``step_index``
    ``p[ref]`` ``[p]`` is a set point for the whole horizon. ``C`` defaults to
    the identity (``y = x``), ``Q`` to the identity, ``R`` to no input weight;
    ``Q`` and ``R`` are scalars, vectors or symmetric positive semidefinite
    matrices (``fj.quadratic_cost``'s rules). A step index beyond the
    reference's length reads NaN, so a reference shorter than the horizon is
    reported (``nan_encountered``) instead of silently clamped.

    Input changes are penalised with ``fj.with_input_memory(problem,
    fj.input_change_cost(lambda_u))``.
    """
    C = None if C is None else matrix("C", np.reshape(C, (1, -1)) if np.ndim(C) < 2 else C)
    Qw = weight("Q", 1.0 if Q is None else Q)
    Rw = None if R is None else weight("R", R)
    if u_ref is not None:
        real_array("u_ref", u_ref, "vector")

    def stage_cost(x_next, u, *rest):
        if not rest or not hasattr(rest[-1], "__getitem__") or isinstance(rest[-1], (jnp.ndarray, np.ndarray)):
            raise TypeError("tracking_cost reads the reference from the parameters: solve with "
                            f"params={{'{ref}': ...}} (a [N, p] array with step_index=True, else [p])")
        p = rest[-1]
        r = jnp.asarray(p[ref])
        dtype = x_next.dtype
        if C is not None and C.shape[1:] != x_next.shape:
            raise ValueError(f"tracking_cost: C has shape {C.shape}, which does not fit the state x_next of shape "
                             f"{tuple(x_next.shape)}: C must be [p, n] = [p, {x_next.shape[0]}]")
        y = x_next if C is None else jnp.asarray(C, dtype) @ x_next
        step = len(rest) == 2  # step_index: (k, p)
        if r.shape[step:] != y.shape or (step and r.ndim != 2):
            form = f"[N, {y.shape[0]}]" if step else f"[{y.shape[0]}]"
            raise ValueError(f"tracking_cost: params[{ref!r}] has shape {tuple(r.shape)}, but C x has shape "
                             f"{tuple(y.shape)}: the reference must be {form}")
        if step:
            r = r.at[rest[0]].get(mode="fill", fill_value=jnp.nan)
        check_target("tracking_cost", "Q", Qw, y, "the output C x")
        cost = weighted_square(Qw, y - r.astype(dtype))
        if Rw is not None:
            du = u.astype(dtype)
            check_target("tracking_cost", "R", Rw, du, "the input u")
            if u_ref is not None:
                check_target("tracking_cost", "u_ref", u_ref, du, "the input u", weight=False)
                du = du - jnp.asarray(u_ref, dtype)
            cost = cost + weighted_square(Rw, du)
        return cost

    return stage_cost


def input_change_cost(lambda_u: float | str, norm: str = "squared") -> Callable:
    """Switching penalty for ``fj.with_input_memory``:
    ``lambda_u * ||u - u_prev||_2^2`` (``norm="squared"``) or
    ``lambda_u * ||u - u_prev||_1`` (``norm="abs"``, the FCS-MPC count of leg
    changes for unit steps). ``lambda_u`` is a number >= 0, or the name of a
    parameter (``p[lambda_u]``) so that it can change between solves."""
    if norm not in ("squared", "abs"):
        raise ValueError(f"norm must be 'squared' or 'abs', got {norm!r}")
    if not isinstance(lambda_u, str):
        lam = non_negative("lambda_u (a number or a parameter name)", lambda_u)

    def switching_cost(u, u_prev, *rest):
        if isinstance(lambda_u, str):
            if not rest:
                raise TypeError(f"input_change_cost reads lambda_u from p[{lambda_u!r}]: solve with params")
            w = rest[-1][lambda_u]
        else:
            w = lam
        du = u - u_prev
        change = jnp.sum(du * du) if norm == "squared" else jnp.sum(jnp.abs(du))
        return jnp.asarray(w, du.dtype) * change

    return switching_cost


def band_penalty(lower: ArrayLike | str | None = None, upper: ArrayLike | str | None = None,
                 weight: ArrayLike | str = 1.0, *, index=None) -> Callable:
    """A soft constraint: ``penalty(x[, p])``, the L1 distance of ``x[index]`` outside the band
    ``[lower, upper]``, times ``weight`` (0 inside the band). Add it to a stage cost, where a hard
    ``constraint`` would leave no sequence (a comfort band, a tank level, a state of charge):
    ``stage_cost=lambda x, u: energy(u) + band(x)``.

    ``lower``, ``upper`` (either may be None: no bound on that side) and ``weight`` (>= 0) are numbers or
    arrays broadcast against ``x[index]``, or the name of a parameter (``p[name]``) so that they can change
    between solves and along the horizon. ``index``: what of the state the band applies to (an int, a slice
    or an index array; default the whole state). Non-negative, as sDFS needs."""
    if lower is None and upper is None:
        raise ValueError("band_penalty needs a lower or an upper bound (or both)")
    fixed = {}
    for name, value in (("lower", lower), ("upper", upper), ("weight", weight)):
        if value is not None and not isinstance(value, str):
            fixed[name] = real_array(f"band_penalty {name} (a number, an array or a parameter name)", value)
    if "weight" in fixed and np.any(fixed["weight"] < 0):
        raise ValueError(f"band_penalty weight must be >= 0, got {weight!r}")
    if "lower" in fixed and "upper" in fixed and np.any(fixed["lower"] > fixed["upper"]):
        raise ValueError(f"band_penalty lower must not exceed upper, got lower={lower!r}, upper={upper!r}")

    def read(name, value, rest, dtype):
        if isinstance(value, str):
            if not rest:
                raise TypeError(f"band_penalty reads {name} from p[{value!r}]: solve with params")
            return jnp.asarray(rest[-1][value], dtype)
        return jnp.asarray(fixed[name], dtype)

    def penalty(x, *rest):
        v = x if index is None else x[index]
        out = jnp.zeros_like(v)
        if lower is not None:
            out = out + jnp.maximum(read("lower", lower, rest, v.dtype) - v, 0)
        if upper is not None:
            out = out + jnp.maximum(v - read("upper", upper, rest, v.dtype), 0)
        return jnp.sum(read("weight", weight, rest, v.dtype) * out)

    return penalty


def horizon_windows(signal: ArrayLike, steps: int, horizon: int, start: int = 1, *, axis: int = 0) -> np.ndarray:
    """``[steps, N, ...]``: for the decision at step t, ``signal[t+start .. t+start+N-1]``.

    ``start=1`` (default): ``signal[t+1 .. t+N]``, the samples that the N
    predicted states ``x(t+1) .. x(t+N)`` should follow (references on
    states; with ``tracking_cost`` and ``step_index`` pass
    ``params={"ref": horizon_windows(r, T, N)}`` to ``FIRHC.simulate``).
    ``start=0``: ``signal[t .. t+N-1]``, the samples that go with the N inputs
    ``u(t) .. u(t+N-1)`` (prices, demands, disturbances on inputs).
    ``signal`` ``[steps + start + N - 1, ...]`` or longer, sampled at the
    control period, ``signal[0]`` at t = 0.

    ``axis``: the signal's time axis; the axes before it are kept in front.
    ``axis=1`` cuts B scenarios ``[B, steps + N, ...]`` into ``[B, steps, N, ...]``,
    the per-loop parameters of ``FIRHC.simulate_batch``."""
    steps, horizon = positive_int("steps", steps), positive_int("horizon", horizon)
    start = positive_int("start", start, minimum=0)
    axis = positive_int("axis", axis, minimum=0)
    signal = np.asarray(signal)
    if axis >= max(signal.ndim, 1):
        raise ValueError(f"axis {axis} is not an axis of signal, whose shape is {signal.shape}")
    need = steps + start + horizon - 1
    if signal.ndim == 0 or signal.shape[axis] < need:
        raise ValueError(f"signal needs at least steps + start + horizon - 1 = {need} samples along axis {axis}, "
                         f"got shape {signal.shape}")
    index = np.arange(steps)[:, None] + start + np.arange(horizon)[None, :]
    return np.take(signal, index, axis=axis)
