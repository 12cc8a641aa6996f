"""Three-tank system with 17 valve/pump modes (the paper's Sec. IV.2, eq. 25).

Layout (DTS200 arrangement, tanks standing side by side as T1 | T3 | T2)::

    reservoir --pump(off/low/high)--+--V_Fill1--> T1
                                    +--V_Fill2--> T2
    T1 <--V_trans1--> T3 <--V_trans2--> T2       (bottom pipes, flow both ways)
    T3 --V_trans3--> reservoir                   (drain)

The five valve names are the paper's input vector u = {V_Fill1, V_Fill2,
V_trans1, V_trans2, V_trans3, pump}; with the pump's on/off and low/high bits
that is 2^7 = 128 actuator patterns, of which ``MODES`` keeps 17.

Every open valve passes a Torricelli flow ``q = az * S_n * sqrt(2 g dh)``
(signed for the bottom pipes, dh the level difference). Written as eq. (25),
``dh/dt = dh_other / tau`` with the state-dependent time constant
``tau(k) = S_A sqrt(|dh|) / (az S_n sqrt(2 g))``. The paper's example mode
(``MODES[14]``, u = {0, 1, 1, 0, 1, low}) gives exactly eq. (25): T2 fills at
``Flow_low / A``, T1 and T3 exchange water, T3 drains.

One sample (t_s = 2 s) is integrated by ``TankParams.substeps`` classical RK4
sub-steps with levels clipped to ``[0, height]`` after each: a single Euler
step of 2 s would overshoot a draining tank below zero and two equalising tanks
past each other, because sqrt(dh) has unbounded slope at dh = 0.

Controller state (``x`` ``[5]``): ``[h1, h2, h3, mode, toggles]`` with levels
in m, ``mode`` the index of the mode that produced this state (float) and
``toggles`` how many actuators that step switched (valves opened or closed,
pump speed changed), so that ``stage_cost(x_next, u)`` can charge switching.
The control set is the column of mode indices ``[17, 1]``.
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import firhc_jax as fj

SET_POINT = (0.30, 0.25, 0.15)  # m, the paper's goal levels h1, h2, h3
INITIAL_LEVELS = (0.20, 0.18, 0.10)  # m, the paper's initial levels


@dataclasses.dataclass(frozen=True)
class TankParams:
    """Physical parameters (SI units).

    Values are the commonly quoted data of the Amira DTS200 laboratory
    three-tank system (the project's requirements list them; ref. [10] of the paper, which has
    the original rig's values, is not available). Where the DTS200 has no
    counterpart (pump speeds, which pipe drains) the choice is ours and noted.
    """

    area: float = 0.0154  # m^2, tank cross-section S_A (DTS200)
    pipe: float = 5e-5  # m^2, cross-section S_n of every pipe and valve (DTS200)
    az13: float = 0.5  # -, outflow coefficient of the T1-T3 pipe (DTS200 range 0.45-0.6)
    az32: float = 0.5  # -, outflow coefficient of the T3-T2 pipe (DTS200 range 0.45-0.6)
    az30: float = 0.6  # -, outflow coefficient of the T3 drain (DTS200's outflow valve value)
    q_high: float = 1.5e-4  # m^3/s, pump flow at high speed (DTS200 maximum pump flow)
    q_low: float = 0.5e-4  # m^3/s, pump flow at low speed: a third of q_high (our choice)
    height: float = 0.62  # m, tank height (DTS200 H_max); levels are clipped to [0, height]
    g: float = 9.81  # m/s^2
    ts: float = 2.0  # s, sample time t_s (paper)
    substeps: int = 4  # RK4 sub-steps per sample (0.5 s each; < 4 um from a tight-tolerance ODE solve)


class Mode(NamedTuple):
    """One actuator pattern: valve states (1 open) and pump speed (0 off, 1 low, 2 high)."""

    name: str
    fill1: int  # V_Fill1, pump -> T1
    fill2: int  # V_Fill2, pump -> T2
    trans1: int  # V_trans1, T1 <-> T3
    trans2: int  # V_trans2, T3 <-> T2
    trans3: int  # V_trans3, T3 -> reservoir
    pump: int  # 0 off, 1 low, 2 high
    why: str


# The 17 modes. Criteria: every pump-on mode has a fill valve open (no
# dead-heading); each level can be raised and lowered, alone or with the
# others, coarsely and finely; mode 0 holds every level (the equilibrium input
# u_e at any state, since nothing leaks).
MODES: tuple = (
    Mode("hold", 0, 0, 0, 0, 0, 0, "everything closed: every level stays, u_e at any set point"),
    Mode("drain3", 0, 0, 0, 0, 1, 0, "lower T3 alone"),
    Mode("t13", 0, 0, 1, 0, 0, 0, "move water T1 -> T3: lower T1, raise T3"),
    Mode("t23", 0, 0, 0, 1, 0, 0, "move water T2 -> T3: lower T2, raise T3"),
    Mode("t13+drain3", 0, 0, 1, 0, 1, 0, "lower T1 with T3 passing the water on"),
    Mode("t23+drain3", 0, 0, 0, 1, 1, 0, "lower T2 with T3 passing the water on"),
    Mode("all-drain", 0, 0, 1, 1, 1, 0, "lower T1 and T2 together, T3 draining: recover from overshoot"),
    Mode("fill1-low", 1, 0, 0, 0, 0, 1, "raise T1 alone, fine step"),
    Mode("fill2-low", 0, 1, 0, 0, 0, 1, "raise T2 alone, fine step"),
    Mode("fill1-high", 1, 0, 0, 0, 0, 2, "raise T1 alone, coarse step"),
    Mode("fill2-high", 0, 1, 0, 0, 0, 2, "raise T2 alone, coarse step"),
    Mode("fill12-low", 1, 1, 0, 0, 0, 1, "raise T1 and T2 together, finest step (flow split)"),
    Mode("fill12-high", 1, 1, 0, 0, 0, 2, "raise T1 and T2 together, start-up filling"),
    Mode("fill1-low+drain3", 1, 0, 0, 0, 1, 1, "raise T1 while lowering T3"),
    Mode("fill2-low+t13+drain3", 0, 1, 1, 0, 1, 1, "paper's eq. (25): T2 fills at low speed, T1 -> T3, T3 drains"),
    Mode("fill1-low+t23+drain3", 1, 0, 0, 1, 1, 1, "mirror of eq. (25): T1 fills at low speed, T2 -> T3, T3 drains"),
    Mode("fill12-high+t13+t23", 1, 1, 1, 1, 0, 2, "raise all three: pump feeds T1, T2, which feed T3"),
)
NUM_MODES = len(MODES)
PAPER_EXAMPLE_MODE = 14  # u = {V_Fill1=0, V_Fill2=1, V_trans1=1, V_trans2=0, V_trans3=1, pump=low}

_ACTUATORS = np.array([m[1:7] for m in MODES], dtype=np.int64)  # [17, 6] fill1..trans3, pump
# toggles between consecutive modes: valves that change plus a pump speed change, [17, 17]
_TOGGLES = (np.abs(_ACTUATORS[:, None, :5] - _ACTUATORS[None, :, :5]).sum(-1)
            + (_ACTUATORS[:, None, 5] != _ACTUATORS[None, :, 5])).astype(float)


def mode_coefficients(params: TankParams) -> np.ndarray:
    """Per-mode rate coefficients ``[17, 5]``: pump inflow to T1 and T2 (m/s)
    and the pipe constants ``k = az S_n sqrt(2 g) / S_A`` (m^0.5/s) of the
    T1-T3 pipe, the T3-T2 pipe and the T3 drain, zero where the valve is shut.

    With both fill valves open the pump's flow splits evenly (identical branches).
    """
    a = _ACTUATORS.astype(float)
    pump_flow = np.choose(_ACTUATORS[:, 5], [0.0, params.q_low, params.q_high])  # [17] m^3/s
    per_branch = pump_flow / np.maximum(a[:, 0] + a[:, 1], 1.0)
    root = params.pipe * np.sqrt(2.0 * params.g) / params.area
    return np.stack([a[:, 0] * per_branch / params.area, a[:, 1] * per_branch / params.area,
                     a[:, 2] * params.az13 * root, a[:, 3] * params.az32 * root,
                     a[:, 4] * params.az30 * root], axis=1)


def _signed_root(d):
    """sign(d) sqrt(|d|): Torricelli's law for a flow driven by a level difference d."""
    return jnp.sign(d) * jnp.sqrt(jnp.abs(d))


def _rates(h1, h2, h3, c):
    """Level rates (m/s) and drain outflow rate (m/s of T3 level) for mode coefficients ``c`` [5]."""
    in1, in2, k13, k32, k30 = c[0], c[1], c[2], c[3], c[4]
    f13 = k13 * _signed_root(h1 - h3)  # T1 -> T3
    f32 = k32 * _signed_root(h3 - h2)  # T3 -> T2
    f30 = k30 * jnp.sqrt(jnp.maximum(h3, 0.0))  # T3 -> reservoir
    return in1 - f13, in2 + f32, f13 - f32 - f30, f30


def make_plant(params: TankParams = TankParams()):
    """The sampled plant ``plant(h, mode) -> (h_next, drained)``.

    ``h`` ``[3]`` levels (m), ``mode`` integer index (scalar). ``drained`` is
    the volume (m^3) that left through the T3 drain during the sample,
    integrated with the same RK4 steps, so that over a sample without clipping
    ``S_A * sum(h_next - h) == pump volume - drained`` up to rounding.
    Elementwise scalar arithmetic only, so every search evaluates a given
    input sequence bit-identically.
    """
    coeffs = mode_coefficients(params)  # [17, 5]
    dt, top, steps = params.ts / params.substeps, params.height, params.substeps

    def substep(_, carry):  # classical RK4 over dt, then clip
        h1, h2, h3, out, c = carry
        a = _rates(h1, h2, h3, c)
        b = _rates(h1 + 0.5 * dt * a[0], h2 + 0.5 * dt * a[1], h3 + 0.5 * dt * a[2], c)
        d = _rates(h1 + 0.5 * dt * b[0], h2 + 0.5 * dt * b[1], h3 + 0.5 * dt * b[2], c)
        e = _rates(h1 + dt * d[0], h2 + dt * d[1], h3 + dt * d[2], c)
        rk = [(dt / 6.0) * (a[i] + 2.0 * b[i] + 2.0 * d[i] + e[i]) for i in range(4)]
        return (jnp.clip(h1 + rk[0], 0.0, top), jnp.clip(h2 + rk[1], 0.0, top),
                jnp.clip(h3 + rk[2], 0.0, top), out + rk[3], c)

    def plant(h, mode):
        c = jnp.asarray(coeffs, h.dtype)[mode]  # [5]
        # A loop, not unrolled: unrolled, XLA recomputes the chain for each output level (14x slower,
        # docs/applications/tanks.md).
        h1, h2, h3, out, _ = jax.lax.fori_loop(0, steps, substep, (h[0], h[1], h[2], jnp.zeros((), h.dtype), c))
        return jnp.stack([h1, h2, h3]), out * params.area

    return plant


def level_steps(params: TankParams = TankParams()) -> np.ndarray:
    """Largest rise and fall (m) of each level in one sample, ``[2, 3]`` (rows rise, fall; columns T1, T2, T3).

    Each rate is a pump inflow plus Torricelli flows ``k sqrt(dh)``, the
    largest coefficients of any mode, with ``dh`` at most the tank height plus
    the drift ``2 dt R`` of an RK4 stage point (``R``: the largest rate), so
    every stage rate, and their weighted mean, is bounded; clipping to
    ``[0, height]`` only shortens a move.
    """
    q1, q2, k13, k32, k30 = mode_coefficients(params).max(axis=0)
    dt = params.ts / params.substeps
    R = max(q1, q2) + 2 * (k13 + k32 + k30) * np.sqrt(params.height)
    root = np.sqrt(params.height + 4 * dt * R)  # twice the drift: covers R's own growth with the root
    return params.ts * root * np.array([[q1 / root + k13, q2 / root + k32, k13 + k32],
                                        [k13, k32, k32 + k30]])


def pump_volume(mode: int, params: TankParams = TankParams()) -> float:
    """Volume (m^3) the pump delivers during one sample in ``mode``."""
    return float(mode_coefficients(params)[mode, :2].sum() * params.area * params.ts)


def initial_state(levels=INITIAL_LEVELS, mode: int = 0) -> np.ndarray:
    """Controller state ``[5]`` for given levels, after ``mode`` (default hold), no toggles."""
    return np.array([*levels, float(mode), 0.0])


def make_problem(horizon: int, params: TankParams = TankParams(), set_point: np.ndarray = SET_POINT,
                 switch_penalty: float = 0.0, terminal_tol: float | None = None, bound: bool = False) -> fj.Problem:
    """The FIRHC problem: ``sum_i sum_tanks ((h - h_s) / 1 mm)^2 + switch_penalty * toggles``.

    Args:
      horizon: N (the paper uses 3-6).
      set_point: ``[3]`` goal levels in m.
      switch_penalty: cost per actuator toggle, in mm^2 of level error;
        0 disables it.
      terminal_tol: if given, the terminal set ``|h_i(k+N) - h_s,i| <= tol``
        (m) for all tanks, the paper's eq. (3) relaxed to a box.
      bound: add the admissible lower bound of ``docs/guide/bounds.md``: no level
        moves faster than ``level_steps`` towards its set point.

    Levels are scored in mm so that costs are O(1)-O(1e4) numbers. Each call
    makes new callables (a new compilation): build the problem once per run.
    """
    if switch_penalty < 0:
        raise ValueError(f"switch_penalty must be >= 0, got {switch_penalty}")
    if terminal_tol is not None and terminal_tol <= 0:
        raise ValueError(f"terminal_tol must be > 0 m, got {terminal_tol}")
    plant = make_plant(params)
    hs = np.asarray(set_point, dtype=float)  # [3]

    def dynamics(x, u):  # x [5], u [1] -> [5]
        mode = u[0].astype(jnp.int32)
        h_next, _ = plant(x[:3], mode)
        switched = jnp.asarray(_TOGGLES, x.dtype)[x[3].astype(jnp.int32), mode]
        return jnp.concatenate([h_next, jnp.stack([u[0].astype(x.dtype), switched])])

    def stage_cost(x_next, u):
        e = (x_next[:3] - jnp.asarray(hs, x_next.dtype)) * 1e3  # [3] mm
        return e[0] * e[0] + e[1] * e[1] + e[2] * e[2] + switch_penalty * x_next[4]

    terminal = None
    if terminal_tol is not None:
        def terminal(x):
            return jnp.all(jnp.abs(x[:3] - jnp.asarray(hs, x.dtype)) <= terminal_tol)

    steps = level_steps(params)  # [2, 3] rise, fall per sample

    def lower_bound(x, steps_left):
        """Level errors of the coming steps can shrink by at most ``level_steps`` a step: their squares summed;
        +inf where a level cannot enter the terminal box in time."""
        gap = jnp.asarray(hs, x.dtype) - x[:3]  # [3] m, > 0: the level must rise
        speed = jnp.where(gap > 0, jnp.asarray(steps[0], x.dtype), jnp.asarray(steps[1], x.dtype))
        j = jnp.arange(1, horizon + 1, dtype=x.dtype)[:, None]  # [N, 1]
        left = jnp.where(j <= steps_left, jnp.maximum(jnp.abs(gap) - j * speed, 0.0) * 1e3, 0.0)  # [N, 3] mm
        value = (1 - 1e-9) * jnp.sum(left * left)  # margin for the search's own rounding
        if terminal_tol is None:
            return value
        reach = jnp.all(jnp.abs(gap) - steps_left * speed <= terminal_tol)
        return jnp.where(reach, value, jnp.inf)

    controls = np.arange(NUM_MODES, dtype=float)[:, None]  # [17, 1] mode indices
    return fj.Problem(dynamics, controls, stage_cost, horizon, terminal, lower_bound if bound else None)
