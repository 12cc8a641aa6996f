"""A pumping station: three on/off pumps fill two storage tanks that supply a
town, priced by the hour (an economic finite-input problem with near-ties).

Pumps 0 and 1 lift water into tank A, pump 2 into tank B. A pump's flow falls
with the head it works against (the static lift plus the tank's level):
``q = a sqrt(H_shut - H)``; two pumps on the same main deliver ``PARALLEL``
of their sum (pipe friction). The plant steps one hour (explicit Euler, the
level at the start of the hour sets the flows). Inputs: the 8 on/off
combinations (``fj.product_controls([0, 1], repeat=3)``).

Stage cost: the electricity of the hour, ``price[k] * sum P_i`` (EUR). Hard
level bounds ``[H_MIN, H_MAX]`` per tank (``constraint=``). Terminal cost:
the water missing below ``TARGET`` at the end of the horizon, priced at
``WATER_VALUE`` EUR/m^3 (the stored water is worth what refilling costs).
Parameters (``step_index=True``): ``price [N]`` EUR/kWh and ``demand [N, 2]``
m^3/h drawn from each tank, the forecast along the horizon.

Lower bound (admissible): over the remaining steps a tank must receive at
least its demand minus what its level can give up down to ``H_MIN``, and no
cubic metre can be pumped cheaper than at the lowest price left in the
horizon by the tank's most efficient combination at its lowest level (flow
only falls as the level rises). The stronger ``"target"`` bound adds each
further cubic metre that the end level lacks below ``TARGET``, at that price
or ``WATER_VALUE`` (the terminal cost), whichever is lower. Tank capacities
are left out.
"""
from __future__ import annotations

import dataclasses
import itertools

import jax.numpy as jnp
import numpy as np

import firhc_jax as fj

AREA = np.array([220.0, 160.0])  # m^2 per tank
H_MIN, H_MAX = 0.5, 4.5  # m, hard bounds on both levels
TARGET = np.array([2.5, 2.5])  # m, levels the stored water is valued against
TANK_OF = np.array([0, 0, 1])  # the tank each pump fills
LIFT = np.array([22.0, 22.0, 31.0])  # m, static head of each pump's main
A_COEF = np.array([17.0, 24.0, 21.0])  # m^3/h per sqrt(m) of head margin
H_SHUT = np.array([52.0, 50.0, 64.0])  # m, shut-off head
POWER = np.array([18.0, 30.0, 26.0])  # kW per pump when on
PARALLEL = 0.88  # share of their summed flow that two pumps on one main deliver
WATER_VALUE = 0.045  # EUR per m^3 missing below TARGET at the end of the horizon


@dataclasses.dataclass(frozen=True)
class PumpingParams:
    """The station's data (the module's constants by default; arrays as tuples, so the record is hashable)."""

    area: tuple = tuple(AREA)  # m^2 per tank
    h_min: float = H_MIN  # m, hard lower bound on both levels
    h_max: float = H_MAX  # m, hard upper bound on both levels
    target: tuple = tuple(TARGET)  # m, levels the stored water is valued against
    tank_of: tuple = tuple(TANK_OF)  # the tank each pump fills
    lift: tuple = tuple(LIFT)  # m, static head of each pump's main
    a_coef: tuple = tuple(A_COEF)  # m^3/h per sqrt(m) of head margin
    h_shut: tuple = tuple(H_SHUT)  # m, shut-off head
    power: tuple = tuple(POWER)  # kW per pump when on
    parallel: float = PARALLEL  # share of their summed flow that two pumps on one main deliver
    water_value: float = WATER_VALUE  # EUR per m^3 missing below target at the end of the horizon


def pump_flows(levels, on, xp=jnp, params: PumpingParams = PumpingParams()):
    """``[3]`` m^3/h of each pump at tank ``levels`` ``[2]`` with pumps ``on`` ``[3]`` (0/1)."""
    p = params
    head = xp.asarray(p.lift) + levels[xp.asarray(p.tank_of)]
    q = xp.asarray(p.a_coef) * xp.sqrt(xp.maximum(xp.asarray(p.h_shut) - head, 0.0)) * on
    shared = 1.0 - (1.0 - p.parallel) * on[0] * on[1]  # the two pumps of tank A share its main
    return q * xp.stack([shared, shared, xp.ones_like(shared)])


def inflow(levels, on, xp=jnp, params: PumpingParams = PumpingParams()):
    """``[2]`` m^3/h into each tank."""
    q = pump_flows(levels, on, xp, params)
    return xp.stack([q[0] + q[1], q[2]])


def step(levels, on, demand, xp=jnp, params: PumpingParams = PumpingParams()):
    """Levels one hour later (explicit Euler)."""
    return levels + (inflow(levels, on, xp, params) - demand) / xp.asarray(params.area)


def make_plant(params: PumpingParams = PumpingParams()):
    """``plant(levels, on, demand) -> levels`` one hour later (``step``)."""
    return lambda levels, on, demand: step(levels, on, demand, jnp, params)


def energy_per_volume(params: PumpingParams = PumpingParams()) -> np.ndarray:
    """``[2]`` the least kWh per m^3 any combination spends on each tank, at ``h_min``
    (the cheapest level to pump into)."""
    best = np.full(2, np.inf)
    for on in itertools.product([0.0, 1.0], repeat=3):
        on = np.array(on)
        q = inflow(np.full(2, params.h_min), on, np, params)
        for j in range(2):
            serving = on * (np.asarray(params.tank_of) == j)
            if q[j] > 0:
                best[j] = min(best[j], float(np.sum(np.asarray(params.power) * serving)) / q[j])
    return best


def forecast(steps: int, seed: int = 0):
    """``(price [steps], demand [steps, 2])`` hourly: a day-night price with a
    morning and an evening peak, flat stretches (near-ties), and a town demand
    with the same rhythm plus noise."""
    rng = np.random.default_rng(seed)
    hour = np.arange(steps) % 24
    price = np.where(hour < 6, 0.10, np.where(hour < 9, 0.24, np.where(hour < 17, 0.16,
                                                                         np.where(hour < 21, 0.28, 0.12))))
    base = 1.0 + 0.45 * np.sin(2 * np.pi * (hour - 7) / 24)
    demand = np.stack([52.0 * base, 24.0 * base], 1) * rng.uniform(0.9, 1.1, (steps, 2))
    return price, demand


def horizon_params(price, demand, steps: int, horizon: int) -> dict:
    """Per-decision parameters ``{"price": [steps, N], "demand": [steps, N, 2]}``:
    decision t sees hours ``t .. t + N - 1`` (``price``, ``demand`` need
    ``steps + N`` hours)."""
    index = np.arange(steps)[:, None] + np.arange(horizon)[None, :]
    return {"price": np.asarray(price)[index], "demand": np.asarray(demand)[index]}


def make_problem(horizon: int, params: PumpingParams = PumpingParams(), bound: str | None = "demand") -> fj.Problem:
    """The FIRHC problem of horizon ``horizon`` (its per-decision parameters: ``horizon_params``).
    ``bound``: ``"demand"`` (the water that must be pumped to stay above
    ``h_min``; weak where the tanks are full, as a first bound tends to be),
    ``"target"`` (also the water missing below ``target`` at the end; several
    times fewer nodes) or None."""
    if not isinstance(params, PumpingParams):
        raise TypeError(f"params must be a PumpingParams, got {type(params).__name__}")
    if bound not in (None, "demand", "target"):
        raise ValueError(f"bound must be None, 'demand' or 'target', got {bound!r}")
    st = params
    controls = fj.product_controls([0.0, 1.0], repeat=3)  # [8, 3]
    e_min = energy_per_volume(st)

    def dynamics(x, u, k, p):
        return step(x, u.astype(x.dtype), p["demand"][k].astype(x.dtype), jnp, st)

    def stage_cost(x_next, u, k, p):
        return p["price"][k] * jnp.sum(jnp.asarray(st.power, x_next.dtype) * u)

    def constraint(x_next, u, k, p):
        return jnp.all((x_next >= st.h_min) & (x_next <= st.h_max))

    def terminal_cost(x, p):
        return st.water_value * jnp.sum(jnp.asarray(st.area, x.dtype)
                                        * jnp.maximum(jnp.asarray(st.target, x.dtype) - x, 0.0))

    def lower_bound(x, steps_left, p):
        """The water each tank must still receive (and with ``"target"`` the water that makes its level up to
        ``target`` at the end, worth ``water_value`` a m^3 if not pumped), at the cheapest energy price left."""
        rest = jnp.arange(horizon) >= horizon - steps_left  # [N] the remaining hours
        price = jnp.min(jnp.where(rest, p["price"], jnp.inf))
        area = jnp.asarray(st.area, x.dtype)
        demand = jnp.sum(jnp.where(rest[:, None], p["demand"], 0.0), axis=0)
        must = jnp.maximum(demand - (x - st.h_min) * area, 0.0)  # [2] m^3 to pump to stay above h_min
        per_m3 = price * jnp.asarray(e_min, x.dtype)
        value = per_m3 * must
        if bound == "target":
            makeup = jnp.maximum(demand + (jnp.asarray(st.target, x.dtype) - x) * area - must, 0.0)
            value = value + jnp.minimum(per_m3, st.water_value) * makeup
        return (1 - 1e-9) * jnp.sum(value)

    return fj.Problem(dynamics, controls, stage_cost, horizon, step_index=True, constraint=constraint,
                      terminal_cost=terminal_cost, lower_bound=None if bound is None else lower_bound)


INITIAL_LEVELS = np.array([2.2, 2.0])
