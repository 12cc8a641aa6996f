"""Four rooms, four on/off heaters, two zone temperatures: a ``LinearTracking`` problem.

Rooms 1-2 form zone 1 and rooms 3-4 zone 2, laid out in a square (1-2 and 3-4
share a wall inside a zone, 1-3 and 2-4 across the zones). Each room i has a
heat capacity ``capacity[i]``, a conductance ``loss[i]`` to the outside at
``ambient``, an on/off heater of ``power[i]``, and conducts ``wall`` through
every shared wall:

    capacity_i dT_i/dt = loss_i (T_amb - T_i) + sum_j wall_ij (T_j - T_i) + power_i u_i,   u_i in {0, 1}.

Sampled every ``ts`` = 60 s with the inputs held (exact zero-order hold; the
ambient term becomes the constant disturbance d). The outputs are the zone
means, y = C x with ``C`` ``[2, 4]``, weighted by the full ``WEIGHT`` (the
zones share a wall, so their errors are correlated). The rooms differ in size
and heater power, so no two heaters are interchangeable; near the set point
the heaters still run at partial duty, and many on/off sequences cost nearly
the same: the hard case for an exact search.
"""
from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from .. import LinearTracking, discretize, product_controls

HEATERS = product_controls([0.0, 1.0], repeat=4)  # [16, 4]
OUTPUTS = np.array([[0.5, 0.5, 0.0, 0.0], [0.0, 0.0, 0.5, 0.5]])  # [2, 4] zone means
WEIGHT = 100.0 * np.array([[1.0, 0.5], [0.5, 1.0]])  # [2, 2] per K^2: an error of 0.1 K in one zone costs 1
WALLS = ((0, 1), (2, 3), (0, 2), (1, 3))  # rooms sharing a wall
LAMBDA_U = 1e-3  # per heater switched: the cost of a 3 mK zone error held for one sample


@dataclasses.dataclass(frozen=True)
class ThermalParams:
    """Building data (SI units; our choice: four small offices of 1-2 kWh/K heavy construction)."""

    capacity: tuple = (4.0e6, 5.0e6, 3.5e6, 4.5e6)  # J/K per room
    loss: tuple = (90.0, 110.0, 80.0, 100.0)  # W/K to the outside per room
    power: tuple = (2500.0, 3000.0, 2000.0, 2800.0)  # W per heater
    wall: float = 60.0  # W/K through each shared wall
    ambient: float = 5.0  # degC
    set_point: tuple = (21.0, 20.0)  # degC, zone 1 and zone 2
    ts: float = 60.0  # s, sampling period


def model(params: ThermalParams = ThermalParams()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(A [4, 4], B [4, 4], d [4])``: room temperatures (degC) one sample later, x+ = A x + B u + d."""
    cap = np.asarray(params.capacity)
    k = np.diag(-np.asarray(params.loss))
    for i, j in WALLS:
        k[i, j] += params.wall
        k[j, i] += params.wall
        k[i, i] -= params.wall
        k[j, j] -= params.wall
    # The ambient term as a constant input held like the heaters: one exact discretisation.
    A, Bd = discretize(k / cap[:, None], np.column_stack([np.diag(np.asarray(params.power) / cap),
                                                          np.asarray(params.loss) * params.ambient / cap]), params.ts)
    return A, Bd[:, :-1], Bd[:, -1]


def make_problem(horizon: int, params: ThermalParams = ThermalParams(), lambda_u: float = LAMBDA_U) -> LinearTracking:
    """Track the zone set points (``WEIGHT``, per K^2) with ``lambda_u`` per heater switched."""
    A, B, _ = model(params)
    return LinearTracking(A, B, HEATERS, horizon, C=OUTPUTS, Q=WEIGHT, lambda_u=lambda_u)


def make_plant(params: ThermalParams = ThermalParams()):
    """``plant(x, u) -> x_next``: room temperatures ``[4]`` (degC) one sample later with heaters ``u`` ``[4]``
    (0/1), ambient included."""
    A, B, d = model(params)

    def plant(x, u):
        return jnp.asarray(A) @ x + jnp.asarray(B) @ u + jnp.asarray(d)

    return plant


def calm_states(count: int, rng: np.random.Generator, params: ThermalParams = ThermalParams(),
                spread: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """``(x [count, 4], u_prev [count, 4])``: room temperatures within ``spread`` K
    of the steady state that holds the set points at the least heater power,
    and a random previous heater pattern."""
    A, B, d = model(params)
    # Steady states x = A x + B v + d for a duty v in [0, 1]^4 with C x = set point: least-norm v.
    inv = np.linalg.inv(np.eye(4) - A)
    duty = np.linalg.lstsq(OUTPUTS @ inv @ B, np.asarray(params.set_point) - OUTPUTS @ inv @ d, rcond=None)[0]
    steady = inv @ (B @ duty + d)
    return steady + rng.uniform(-spread, spread, (count, 4)), HEATERS[rng.integers(0, 16, count)]
