"""Three-level three-phase inverter feeding an RL load, as a ``LinearTracking`` problem.

Each leg x in {a, b, c} connects its phase to the negative rail, the neutral
point or the positive rail of the dc link: u_x in {-1, 0, 1} applies
Vdc/2 * u_x. The 3^3 = 27 switch states ``SWITCH_STATES`` ``[27, 3]`` (in
``itertools.product`` order) give 19 distinct alpha-beta voltages: states
that differ by the same step on every leg apply the same voltage (common
mode), and only the switching term tells them apart. In the alpha-beta frame
(amplitude-invariant Clarke transform ``CLARKE``) the load is
L di/dt = v - R i, decoupled and identical in alpha and beta; over one sample
with v held the exact solution is i(k+1) = a i(k) + B u(k), a = exp(-R Ts / L).

The controller tracks a sinusoidal current reference i_ref along the
horizon, charges lambda_u ||u(k) - u(k-1)||^2 and forbids a leg to jump from
-1 to +1 in one sample (max_step = 1, so the squared and absolute switching
penalties coincide). The circuit is the benchmark's: R = 2 ohm, L = 2 mH,
Vdc = 400 V, Ts = 25 us, 20 A at 50 Hz (``ThreeLevelParams``).
"""
from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from .. import LinearTracking, discretize, product_controls
from .inverter import InverterParams

MAX_HORIZON = 30  # the command line's limit; N = 15 already takes about a second per decision at lambda_u = 0.1


@dataclasses.dataclass(frozen=True)
class ThreeLevelParams(InverterParams):
    """The two-level inverter's fields with the benchmark's circuit and reference (SI units; the same sampling
    time and frequency)."""

    vdc: float = 400.0  # V, dc-link voltage
    r: float = 2.0  # ohm, load resistance per phase
    l: float = 2e-3  # noqa: E741  H, load inductance per phase
    amplitude: float = 20.0  # A, peak of the sinusoidal phase current reference


PARAMS = ThreeLevelParams()
SWITCH_STATES = product_controls([-1.0, 0.0, 1.0], repeat=3)  # [27, 3]
CLARKE = np.array([[2.0, -1.0, -1.0], [0.0, math.sqrt(3.0), -math.sqrt(3.0)]]) / 3.0  # [2, 3] abc -> alpha-beta


def model(params: InverterParams = PARAMS) -> tuple[np.ndarray, np.ndarray]:
    """``(A [2, 2], B [2, 3])``: alpha-beta currents (A) one sample later, from leg levels u in {-1, 0, 1}^3."""
    return discretize(-params.r / params.l * np.eye(2), params.vdc / (2.0 * params.l) * CLARKE, params.ts)


def pop_width(horizon: int) -> int:
    """Nodes the sorted search pops per iteration at this horizon: 4 from N = 6 on, where it takes a third
    of the iterations for the same nodes (within 1 %), else 1 (docs/applications/inverter.md)."""
    return 4 if horizon > 5 else 1


def make_problem(horizon: int, params: InverterParams = PARAMS, lambda_u: float = 0.1,
                 max_step: float | None = 1.0) -> LinearTracking:
    """The current controller: track i_ref along the horizon (Q = I, A^2), lambda_u per unit leg step (A^2)."""
    A, B = model(params)
    return LinearTracking(A, B, SWITCH_STATES, horizon, lambda_u=lambda_u, max_step=max_step)


def make_plant(params: InverterParams = PARAMS):
    """``plant(i, u) -> i_next``: alpha-beta currents ``[2]`` (A) one sample later with leg levels ``u`` ``[3]``."""
    A, B = model(params)

    def plant(i, u):
        return jnp.asarray(A) @ i + jnp.asarray(B) @ u

    return plant
