"""Two-level three-phase voltage source inverter feeding an RL load (FCS-MPC current control).

Each leg x in {a, b, c} connects its phase to the negative (S_x = 0) or the
positive (S_x = 1) dc rail, so the inverter has 2^3 = 8 switch states
``SWITCH_STATES`` ``[8, 3]`` (V0 .. V7; V0 and V7 both apply the zero vector).
In the alpha-beta frame (amplitude-invariant Clarke transform) a state applies

    v_alpha = Vdc/3 (2 S_a - S_b - S_c),   v_beta = Vdc/sqrt(3) (S_b - S_c)

to the load L di/dt = v - R i, decoupled and identical in alpha and beta.
Over one sample T_s with v held (zero-order hold) the exact solution is

    i(k+1) = a i(k) + b v(k),   a = exp(-R T_s / L),   b = (1 - a) / R,

and forward Euler (the discretisation of Rodriguez et al. 2007) gives
a = 1 - R T_s / L, b = T_s / L. ``make_plant`` and ``make_problem`` take either.

The problem is written with step indices (``Problem(step_index=True)``): the
reference moves within the horizon, so it is a parameter, and for the decision
at step k ``p["ref"]`` ``[N, 2]`` holds i_ref(k+1) .. i_ref(k+N); the stage cost
of the j-th input of a sequence (step index j = 0 .. N-1) is
|i_ref(k+j+1) - i(k+j+1)|^2 (A^2), ``fj.tracking_cost``'s ``p["ref"][j]``. The
model state is the currents ``[i_alpha, i_beta]`` (A) alone; a new reference
never recompiles. The switching penalty ``p["lambda_u"]`` (A^2 per leg change)
acts on the previous input through ``fj.with_input_memory`` and
``fj.input_change_cost``.

``distortion`` (fundamental and THD of a phase current), ``commutations`` and
``switching_frequency`` (of the applied leg levels) measure a run; they hold
for legs of any number of levels.
"""
from __future__ import annotations

import dataclasses
import functools
import math

import jax.numpy as jnp
import numpy as np

import firhc_jax as fj

DISCRETISATIONS = ("exact", "euler")

# Leg states (S_a, S_b, S_c) of V0 .. V7, ordered around the hexagon; V0 and V7 are the zero vector.
SWITCH_STATES = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 1, 1], [0, 0, 1], [1, 0, 1], [1, 1, 1]],
                         dtype=float)


@dataclasses.dataclass(frozen=True)
class InverterParams:
    """Circuit, sampling and reference (SI units).

    The values are the benchmark of Rodriguez et al., "Predictive current
    control of a voltage source inverter", IEEE Trans. Ind. Electron. 54(1),
    2007, as quoted in the project's requirements (the paper itself was not available
    here to check them; its load also has a back-EMF, which this RL load leaves out).
    """

    vdc: float = 520.0  # V, dc-link voltage
    r: float = 10.0  # ohm, load resistance per phase
    l: float = 10e-3  # noqa: E741  H, load inductance per phase
    ts: float = 25e-6  # s, sampling time T_s (40 kHz)
    amplitude: float = 10.0  # A, peak of the sinusoidal phase current reference
    frequency: float = 50.0  # Hz, reference frequency

    @property
    def steps_per_cycle(self) -> int:
        """Samples per fundamental period (800 with the defaults)."""
        return round(1.0 / (self.frequency * self.ts))


def voltage(u, vdc):
    """Alpha-beta voltage ``(v_alpha, v_beta)`` of leg states ``u`` ``[..., 3]`` (0/1), elementwise."""
    sa, sb, sc = u[..., 0], u[..., 1], u[..., 2]
    return vdc / 3.0 * (2.0 * sa - sb - sc), vdc / math.sqrt(3.0) * (sb - sc)


def discretise(params: InverterParams = InverterParams(), method: str = "exact") -> tuple[float, float]:
    """``(a, b)`` of i(k+1) = a i(k) + b v(k): exact zero-order hold or forward Euler."""
    if method not in DISCRETISATIONS:
        raise ValueError(f"method must be one of {DISCRETISATIONS}, got {method!r}")
    if method == "exact":
        a = math.exp(-params.r * params.ts / params.l)
        return a, -math.expm1(-params.r * params.ts / params.l) / params.r
    return 1.0 - params.r * params.ts / params.l, params.ts / params.l


def make_plant(params: InverterParams = InverterParams(), method: str = "exact"):
    """``plant(i, u) -> i_next``: currents ``[2]`` (alpha, beta, A) after one sample with leg states ``u`` ``[3]``."""
    a, b = discretise(params, method)

    def plant(i, u):
        v_alpha, v_beta = voltage(u.astype(i.dtype), params.vdc)
        return jnp.stack([a * i[0] + b * v_alpha, a * i[1] + b * v_beta])

    return plant


def reference(params: InverterParams, times) -> np.ndarray:
    """Alpha-beta current reference ``[..., 2]`` (A) at ``times`` (s): phase a peaks at t = 0."""
    w = 2.0 * np.pi * params.frequency * np.asarray(times, dtype=float)
    return params.amplitude * np.stack([np.cos(w), np.sin(w)], axis=-1)


def horizon_references(params: InverterParams, steps: int, horizon: int) -> np.ndarray:
    """``[steps, N, 2]``: for the decision at step k, the reference at steps k+1 .. k+N."""
    k = np.arange(steps)[:, None] + np.arange(1, horizon + 1)[None, :]
    return reference(params, k * params.ts)


def to_phases(i_ab) -> np.ndarray:
    """Phase quantities ``[..., 3]`` (a, b, c) from alpha-beta ``[..., 2]`` (inverse amplitude-invariant Clarke)."""
    i_ab = np.asarray(i_ab)
    al, be = i_ab[..., 0], i_ab[..., 1]
    return np.stack([al, -0.5 * al + 0.5 * math.sqrt(3.0) * be, -0.5 * al - 0.5 * math.sqrt(3.0) * be], axis=-1)


def distortion(signal, params: InverterParams = InverterParams()) -> tuple[float, float]:
    """``(fundamental peak amplitude, THD)`` of a phase current ``signal`` ``[T]`` (A) sampled at ``params.ts``.

    The fundamental is the least-squares fit of dc + cos + sin at ``params.frequency``; THD is the rms of what
    the fit leaves over the rms of the fundamental. Over whole cycles this is the DFT definition with every
    non-fundamental bin up to the Nyquist frequency counted (harmonics and the inter-harmonics of a variable
    switching pattern), dc excluded; unlike the DFT it stays meaningful for records of part of a cycle (of more
    than three samples: the fit has three unknowns).
    """
    signal = np.asarray(signal, dtype=float)
    if signal.ndim != 1 or signal.shape[0] == 0 or not np.all(np.isfinite(signal)):
        raise ValueError(f"signal must be a finite record [T] of one phase, got shape {signal.shape}")
    w = 2.0 * np.pi * params.frequency * params.ts * np.arange(signal.shape[0])
    basis = np.stack([np.ones_like(w), np.cos(w), np.sin(w)], axis=1)  # [T, 3]
    coef, *_ = np.linalg.lstsq(basis, signal, rcond=None)
    amplitude = float(np.hypot(coef[1], coef[2]))
    residual = signal - basis @ coef
    return amplitude, float(np.sqrt(np.mean(residual**2)) / (amplitude / np.sqrt(2.0)))


def commutations(inputs) -> np.ndarray:
    """``[legs]`` int: each leg's level changes within ``inputs`` ``[T, legs]`` (a run's applied leg levels),
    a change by l levels counted as l commutations (two-level 0 <-> 1: one; a multilevel leg's unit steps)."""
    inputs = np.asarray(inputs, dtype=float)
    if inputs.ndim != 2 or not np.all(np.isfinite(inputs)):
        raise ValueError(f"inputs must be finite leg levels [T, legs], got shape {inputs.shape}")
    return np.rint(np.abs(np.diff(inputs, axis=0)).sum(axis=0)).astype(int)


def switching_frequency(inputs, params: InverterParams = InverterParams()) -> float:
    """Switching frequency per leg (Hz) of ``inputs`` ``[T, legs]`` applied every ``params.ts``: the legs'
    mean ``commutations`` over the run's T samples, divided by two (a switching period has two)."""
    return float(commutations(inputs).mean() / (2.0 * np.shape(inputs)[0] * params.ts))


def current_bound(horizon: int, params: InverterParams = InverterParams(), method: str = "exact"):
    """Admissible ``lower_bound(x, steps_left, p)`` of the tracking cost (``docs/guide/bounds.md``).

    After l more steps from i, ``i(l) = a^l i + b sum_m a^(l-1-m) v_m`` with
    every v in the hexagon of the switch states (circumradius 2 Vdc / 3), so
    ``i(l)`` lies in ``a^l i`` plus that hexagon scaled by ``b (1 - a^l) / (1 - a)``:
    the current moves at most about ``Vdc / L`` per sample towards its
    reference. Each step's error is at least the distance from its
    reference to that set (bounded below by the circle and the three slabs
    of the hexagon); switching costs are left out (>= 0).
    """
    a, b = discretise(params, method)
    radius = 2.0 * params.vdc / 3.0
    normals = np.array([[math.cos(t), math.sin(t)] for t in (math.pi / 6, math.pi / 2, 5 * math.pi / 6)])  # [3, 2]

    def lower_bound(x, steps_left, p):
        l = jnp.arange(1, horizon + 1, dtype=x.dtype)  # noqa: E741  [N] steps ahead
        decay = a ** l
        scale = b * radius * (1.0 - decay) / (1.0 - a)  # [N] circumradius of the reachable hexagon
        # The step index of the input l steps ahead: the node's depth N - steps_left, plus l - 1.
        rows = jnp.clip(horizon - steps_left + jnp.arange(horizon), 0, horizon - 1)
        d = p["ref"][rows] - decay[:, None] * x[None, :]  # [N, 2] reference minus the free response
        circle = jnp.sqrt(jnp.sum(d * d, axis=1)) - scale
        slabs = jnp.max(jnp.abs(d @ jnp.asarray(normals.T, x.dtype)), axis=1) - scale * math.cos(math.pi / 6)
        gap = jnp.where(l <= steps_left, jnp.maximum(jnp.maximum(circle, slabs), 0.0), 0.0)
        return (1 - 1e-9) * jnp.sum(gap * gap)  # margin for the search's own rounding

    return lower_bound


@functools.lru_cache(maxsize=None)
def make_problem(horizon: int, params: InverterParams = InverterParams(), method: str = "exact",
                 bound: bool = False) -> fj.InputMemory:
    """The FIRHC problem with its switching penalty, as ``(problem, observe)``.

    ``problem`` tracks ``p["ref"]`` ``[N, 2]`` over the horizon (step indices)
    and charges ``p["lambda_u"]`` per leg change, the first step's against the
    input applied last; ``observe(i, u_prev, p)`` builds its state from the
    plant's currents ``[2]``. Use them as ``FIRHC(problem, observe=observe)``
    with per-step parameters ``{"ref": [T, N, 2], "lambda_u": [T]}``. Cached:
    equal arguments give the same problem, so closed loops of equal shapes
    share one compilation whatever the reference and ``lambda_u``.
    ``bound``: with ``current_bound``.
    """
    plant = make_plant(params, method)
    lower_bound = current_bound(horizon, params, method) if bound else None
    tracking = fj.Problem(lambda i, u, k, p: plant(i, u), SWITCH_STATES, fj.tracking_cost(), horizon,
                          lower_bound=lower_bound, step_index=True)
    return fj.with_input_memory(tracking, fj.input_change_cost("lambda_u", norm="abs"))


def initial_currents(params: InverterParams = InverterParams()) -> np.ndarray:
    """Load currents ``[2]`` at t = 0 on the reference: the run starts in steady state."""
    return reference(params, 0.0)

