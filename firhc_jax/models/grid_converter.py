"""Medium-voltage three-level converter on an RL grid, per unit, as a ``LinearTracking`` problem.

The neutral-point-clamped converter of ``three_level`` (27 switch states, 19 alpha-beta voltages) feeds a
stiff 50 Hz grid through an RL filter. In per unit (base: the peak phase voltage and current, time in
seconds, omega_b = 2 pi 50) the filter current follows

    (X / omega_b) di/dt = V_dc / 2 * Clarke u - R i - v_g,

with the grid voltage v_g (1 pu, phase a at its peak at t = 0) a known disturbance: over sample k it is
held at v_g(k Ts), so x(k+1) = A x(k) + B u(k) + d(k) with d(k) = E v_g(k Ts) (``model``). The controller
tracks a current reference in phase with the grid (unity power factor) whose amplitude steps from 0.2 to
1 pu at ``GridParams.step_at``, weighs the current error with Q = I, charges lambda_u = 0.01 per unit leg
step and forbids a leg to jump from -1 to +1 (max_step = 1). Ts = 100 us.

This is the plant whose node counts watch ``LinearTracking``'s bound (``benchmarks/converter_bench.py``,
``tests/linear/test_converter_nodes.py``): a realistic per-unit model, small switching weight, and a large
reference step, where the continuous cost-to-go is far below J for several steps.
"""
from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from .. import LinearTracking, discretize, horizon_windows
from .three_level import CLARKE, SWITCH_STATES

LAMBDA_U = 0.01  # per unit current^2 per unit leg step


@dataclasses.dataclass(frozen=True)
class GridParams:
    """Filter, dc link, sampling and reference, per unit (time in seconds)."""

    x: float = 0.05  # filter reactance X at 50 Hz
    r: float = 0.0025  # filter resistance R (X / R = 20)
    vdc: float = 1.93  # dc-link voltage (5.2 kV over the 2.69 kV peak phase voltage of a 3.3 kV grid)
    ts: float = 100e-6  # s, sampling time
    frequency: float = 50.0  # Hz, grid frequency
    before: float = 0.2  # current amplitude before the step
    after: float = 1.0  # current amplitude from the step on
    step_at: int = 50  # the sample at which the reference steps


PARAMS = GridParams()


def model(params: GridParams = PARAMS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(A [2, 2], B [2, 3], E [2, 2])``: alpha-beta currents one sample later from leg levels u in {-1, 0, 1}^3
    and the grid voltage held over the sample: x(k+1) = A x(k) + B u(k) + E v_g(k)."""
    wb = 2.0 * np.pi * params.frequency
    gain = wb / params.x
    inputs = np.hstack([gain * params.vdc / 2.0 * CLARKE, -gain * np.eye(2)])  # [converter legs, grid voltage]
    A, BE = discretize(-gain * params.r * np.eye(2), inputs, params.ts)
    return A, BE[:, :3], BE[:, 3:]


def make_problem(horizon: int, params: GridParams = PARAMS, lambda_u: float = LAMBDA_U,
                 max_step: float | None = 1.0) -> LinearTracking:
    """The current controller: track i_ref along the horizon (Q = I), ``lambda_u`` per unit leg step."""
    A, B, _ = model(params)
    return LinearTracking(A, B, SWITCH_STATES, horizon, lambda_u=lambda_u, max_step=max_step)


def _signals(samples: int, params: GridParams) -> tuple[np.ndarray, np.ndarray]:
    """The current reference and the grid voltage ``[samples, 2]`` at t = k Ts."""
    k = np.arange(samples)
    angle = 2.0 * np.pi * params.frequency * params.ts * k
    unit = np.stack([np.cos(angle), np.sin(angle)], axis=-1)
    amplitude = np.where(k < params.step_at, params.before, params.after)
    return amplitude[:, None] * unit, unit


def decision_data(steps: int, horizon: int, params: GridParams = PARAMS) -> tuple[np.ndarray, np.ndarray]:
    """``(y_ref [steps, N, 2], d [steps, N, 2])``: for the decision at step t, the reference at t+1 .. t+N
    and the grid's effect over samples t .. t+N-1 (``lt.params(y_ref, d)``)."""
    reference, grid = _signals(steps + horizon + 1, params)
    _, _, E = model(params)
    return horizon_windows(reference, steps, horizon), horizon_windows(grid @ E.T, steps, horizon, start=0)


def initial_state(params: GridParams = PARAMS) -> np.ndarray:
    """``[2]`` the reference current at t = 0."""
    return _signals(1, params)[0][0]


def make_plant(params: GridParams = PARAMS):
    """``plant(x, u, p) -> x_next``, the model with the decision's disturbance ``d[0]``: ``fj.FIRHC.simulate``'s
    ``plant`` with the params of ``lt.problem`` (``lt.params(y_ref, d)``) or of ``lt.shared_problem``."""
    A, B, _ = model(params)

    def plant(x, u, p):
        d = p.data.d if hasattr(p, "data") else p.d
        return jnp.asarray(A, x.dtype) @ x + jnp.asarray(B, x.dtype) @ u.astype(x.dtype) + d[0]

    return plant
