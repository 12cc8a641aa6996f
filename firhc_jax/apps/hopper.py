"""``python -m firhc_jax hopper``: the pneumatic hopping robot under FIRHC (Sec. IV.1, Figs. 4-8).

The robot is dropped from rest at the apex of the specified flight (foot at
``g T_air^2 / 8``) and controlled for ``--seconds``:

* Control period 5 ms: longer than the 2-5 ms switching time of fast 3/2
  solenoid valves, so a commanded state is actually reached within a period,
  and short against the 0.2 s stance (about 40 decisions per stance).
* In contact (foot on the ground at the sample): side a by the paper's on/off
  law, side b by FIRHC over the three valve states. In flight both valves are
  sealed; the valve drivers are gated by the foot contact at every plant step,
  so they close at lift-off, not at the next sample.
* FIRHC, cost (24): ``(E - E_d)^2 + 0.1 (xdot - xdot_d)^2 + 10 u^2`` per
  step, ``u`` in {-0.01, 0, 0.01} (exhaust, closed, supply), terminal
  constraint ``|E(k+N) - E_d| <= 0.02 J``, prediction by the frictionless
  contact model (``firhc_jax.models.hopper.model_step``), which stops at a
  predicted lift-off. Two deviations from the paper, both measured and
  explained in ``docs/hopper.md``:

  - ``E_d`` is eq. (20) evaluated for the air now in the chambers
    (``orbit_energy``), not a constant: E is ~96% stored air energy, and a
    constant target lets the controller replace the friction losses with air,
    which parks the robot standing with E = E_d (one hop, then none).
  - eq. (19) is applied to the centre of mass: the foot leaves at rest, so the
    body must leave with ``(M + m) / M * g T_air / 2`` for a flight of T_air.

* Fallback: when no sequence meets the terminal constraint the same search
  runs without it (counted as an infeasible step). Should even that find
  nothing (NaN everywhere; it has not happened), valve b stays closed and the
  step is counted as unsolved.

The closed loop is ``FIRHC.simulate``, one step per control period:
``observe`` maps the plant state ``[6]`` to the model's ``[5]``, ``actuate``
adds side a's law and seals the valves in flight, and the plant integrates
one period. The CLI runs it from Python (``compiled=False``) so that every
decision is timed; tests and benchmarks run it as one compiled ``lax.scan``.
The figures' plant-step trajectory is re-integrated from the recorded states
and commands.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

import firhc_jax as fj
from firhc_jax.models import hopper as hm
from firhc_jax.nodes import rollout_cost

from ._args import number

T_HOP, T_AIR = 0.4, 0.2  # s, gait specification (paper)
CONTROL_PERIOD = 0.005  # s, see module docstring
PLANT_DT = 5e-5  # s, fixed RK4 step of the plant (ground contact eigenvalue ~ -1.9e4 1/s)
MODEL_SUBSTEPS = 5  # RK4 steps per control period in the prediction model (1 ms)
LAMBDA1, LAMBDA2, BETA = 1.0, 0.1, 10.0  # weights of cost (24)
VALVE_B = (-0.01, 0.0, 0.01)  # u: exhaust, closed, supply (the paper's scaling)
ENERGY_TOL = 0.02  # J, terminal constraint |E(k+N) - E_d| <= tol
A_DEADBAND = 0.01  # relative: side a charges below (1 - 1%) of the reference pressure
SUBSTEPS = int(round(CONTROL_PERIOD / PLANT_DT))  # plant steps per control period
IN_FLIGHT = 2.0  # model state's airborne flag for a decision taken in flight (see ``problem``)
OPEN_COST = BETA * min(u * u for u in VALVE_B if u != 0)  # cost of one period with valve b open (0.001)
PASSIVE_DRIFT = 1e-6  # J, allowance per closed period for the RK4 drift of the conserved E - E_d (seen: <= 1e-10)
A_IDLE_MARGIN = 1e-6  # relative margin on side a's threshold for "its law never fires below this node"


# ---------------------------------------------------------------------------
# Controller and closed loop
# ---------------------------------------------------------------------------

def side_a_law(s, Pa, p: hm.HopperParams):
    """Paper's on/off law for side a in contact: charge (1.0) if ``P_a < P_a0 (V_mida / V_a)^gamma``, else 0.0.

    ``s`` is the stroke (the paper's x in contact). A 1% dead band (sensor
    resolution) keeps round-off on the adiabat from firing a 5 ms charge; the
    plant has no leaks, so with it the law stays idle unless air is lost.
    """
    Pa_ref = hm.nominal_pressures(s, p)[0]
    return jnp.where(Pa < (1 - A_DEADBAND) * Pa_ref, 1.0, 0.0)


def liftoff_velocity(p: hm.HopperParams) -> float:
    """Body lift-off velocity targeted (m/s): eq. (19) for the centre of mass (module docstring)."""
    return (p.M + p.m) / p.M * hm.desired_energy(T_HOP, T_AIR, p).xdot_t1


def static_target(p: hm.HopperParams) -> float:
    """The controller's E_d (J) for the static charge of air."""
    return float(hm.orbit_energy(np.array([0.0, 0.0, p.P_a0, p.P_b0]), liftoff_velocity(p), p))


@functools.lru_cache(maxsize=None)
def problem(params: hm.HopperParams, horizon: int, bound: bool = False) -> fj.Problem:
    """The FIRHC problem for valve b (built once per parameters and horizon, so its search compiles once).

    Prediction state ``[5]``: ``[x, xdot, P_a, P_b, airborne]`` (see
    ``hm.model_step``; ``airborne`` 1 from a predicted lift-off on). Input
    ``u`` ``[1]``: one of ``VALVE_B``. The model applies side a's law itself,
    so the prediction sees what the plant gets. ``airborne = IN_FLIGHT``
    (set by ``observe``) marks a decision taken in flight: the valves are
    sealed, so the state stays put, only the valve term ``10 u^2`` is charged
    and the terminal constraint holds; the optimum is valve b closed, found in
    3N nodes. Contact decisions are unaffected (bit for bit).

    ``bound``: add the lower bound of ``docs/bounds.md`` (energy-band
    reachability and energy-error cost), exact results with fewer nodes.
    """
    return _problems(params, horizon)["bounded" if bound else "plain"]


def fallback_problem(params: hm.HopperParams, horizon: int) -> fj.Problem:
    """The bounded problem without its terminal set, for the fallback search: its bound is the same one without
    the ``+inf`` that only the terminal set justifies (the core drops a bound with the terminal set)."""
    return _problems(params, horizon)["relaxed"]


@functools.lru_cache(maxsize=None)
def _problems(params: hm.HopperParams, horizon: int) -> dict:
    p = params
    v_liftoff, E_target = liftoff_velocity(p), static_target(p)

    def dynamics(z, u):
        cmd = jnp.stack([side_a_law(z[0], z[2], p), jnp.sign(u[0])])
        return jnp.where(z[4] == IN_FLIGHT, z, hm.model_step(z, cmd, p, CONTROL_PERIOD, MODEL_SUBSTEPS))

    def energy_error(z):  # E_d re-evaluated for the air in the chambers of z (deviation 1)
        return hm.model_energy(z, p) - hm.orbit_energy(z, v_liftoff, p)

    def stage_cost(z, u):
        x, xd = z[0], z[1]
        # Desired velocity from the loss-free energy balance on the static charge's orbit.
        v2 = 2 * (E_target - hm.nominal_potential(x, p)) / p.M
        xd_d = jnp.sign(xd) * jnp.sqrt(jnp.maximum(v2, 0.0))
        gait = LAMBDA1 * energy_error(z) ** 2 + LAMBDA2 * (xd - xd_d) ** 2
        return jnp.where(z[4] == IN_FLIGHT, 0.0, gait) + BETA * u[0] ** 2

    def terminal(z):
        return (z[4] == IN_FLIGHT) | (jnp.abs(energy_error(z)) <= ENERGY_TOL)

    def bound(z, steps_left, band: bool):
        """docs/bounds.md. In flight 0. After a predicted lift-off (frozen state) the exact cost with valve b
        closed. In contact, with side a's law provably idle, e stays put while valve b is closed: either b stays
        closed (every stage costs at least LAMBDA1 e^2) or it opens at least once (BETA u^2 = OPEN_COST); with side
        a possibly charging, 0. ``band``: the terminal set applies, so a frozen or closed-valve future with e
        outside the band is infeasible (+inf)."""
        e, s = jnp.abs(energy_error(z)), steps_left.astype(z.dtype)
        frozen = s * stage_cost(z, jnp.zeros(1, z.dtype))
        j = jnp.arange(1, horizon + 1, dtype=z.dtype)
        drift = jnp.where(j <= s, jnp.maximum(e - j * PASSIVE_DRIFT, 0.0), 0.0)  # e after j closed periods
        closed = LAMBDA1 * jnp.sum(drift * drift)
        airborne = z[4] == 1.0
        if band:
            closed = jnp.where(e - s * PASSIVE_DRIFT <= ENERGY_TOL, closed, jnp.inf)
            frozen = jnp.where(e <= ENERGY_TOL, frozen, jnp.inf)
        Pa_ref = hm.nominal_pressures(z[0], p)[0]
        a_idle = z[2] >= (1 - A_DEADBAND) * (1 + A_IDLE_MARGIN) * Pa_ref  # side_a_law with a margin: never fires
        value = jnp.where(airborne, frozen, jnp.where(a_idle, jnp.minimum(closed, OPEN_COST), 0.0))
        return jnp.where(z[4] == IN_FLIGHT, 0.0, (1 - 1e-9) * value)  # margin for the search's own rounding

    def lower_bound(z, steps_left):
        return bound(z, steps_left, True)

    def relaxed_bound(z, steps_left):
        return bound(z, steps_left, False)

    plain = fj.Problem(dynamics, jnp.asarray(VALVE_B), stage_cost, horizon, terminal)
    return dict(plain=plain, bounded=plain.replace(lower_bound=lower_bound),
                relaxed=plain.replace(terminal=None, lower_bound=relaxed_bound))


def contact(X):
    """Foot on the ground (plant states ``[..., 6]``)."""
    return X[..., 2] <= 0


def observe(X, u_prev):
    """Prediction state ``[5]`` from a plant state ``[6]``: stroke, stroke rate, pressures, and ``IN_FLIGHT``
    when the foot is off the ground (0 on it)."""
    flag = jnp.where(contact(X), 0.0, IN_FLIGHT)
    return jnp.stack([X[0] - X[2], X[1] - X[3], X[4], X[5], flag])


def warm_candidate(problem: fj.Problem, x, previous, params=None):
    """The warm start for a search from ``x``: the cheaper of ``previous`` (the last decision's sequence ``[N]``)
    shifted by one step and ``previous`` unshifted, all -1 (none) when neither meets the terminal test or there
    is no previous sequence.

    Why two: the plant loses energy to friction that the model does not have, so the shifted plan often just
    misses the terminal band (no incumbent at all), while the same plan one period later meets it. Exact either
    way: a warm start only sets the search's first incumbent.
    """
    shifted = jnp.concatenate([previous[1:], previous[-1:]])
    candidates = jnp.stack([shifted, previous])  # [2, N]
    dtype = jnp.promote_types(x.dtype, jnp.float32)
    costs = jax.vmap(lambda w: rollout_cost(problem, x, w, dtype, params)[0])(jnp.maximum(candidates, 0))
    i = jnp.argmin(costs)
    return jnp.where((previous[0] >= 0) & jnp.isfinite(costs[i]), candidates[i], -1)


@functools.lru_cache(maxsize=None)
def controller(params: hm.HopperParams, horizon: int, solver: str, bound: bool = False, warm: bool = False,
               **options) -> fj.FIRHC:
    """FIRHC on valve b; valve a by ``side_a_law``; both sealed in flight.

    ``actuate`` turns the searched input into the plant's commands ``[2]``
    (a, b) in {-1, 0, 1}: in flight at the sample both are 0; should no
    sequence be found at all (NaN input; it has not happened) b stays closed.
    Cached so that repeated closed loops reuse one compiled executable.
    ``bound`` as in ``problem``, the fallback search with ``fallback_problem``'s bound; ``warm`` (sdfs only):
    seed each search with ``warm_candidate`` (the better of the previous solution shifted and unshifted);
    ``options`` go to the solver (e.g. ``max_nodes``).
    """
    p = params

    def actuate(X, u):
        b = jnp.where(jnp.isnan(u[0]), 0.0, jnp.sign(u[0]))
        return jnp.where(contact(X), jnp.stack([side_a_law(X[0] - X[2], X[4], p), b]), 0.0)

    return fj.FIRHC(problem(params, horizon, bound), solver,
                    fallback=fallback_problem(params, horizon) if bound else "unconstrained",
                    warm_start=warm_candidate if warm else False, observe=observe, actuate=actuate, **options)


def _period(X, cmd, p: hm.HopperParams):
    """One control period of the plant: ``(X_end, [SUBSTEPS, 6] states after each plant step)``.

    The valve drivers are gated by foot contact at every plant step, so the
    valves close at lift-off, not at the next sample.
    """
    def step(X, _):
        X = hm.plant_step(X, cmd * contact(X), p, PLANT_DT)
        return X, X

    return jax.lax.scan(step, X, None, length=SUBSTEPS)


@functools.lru_cache(maxsize=None)
def plant(params: hm.HopperParams):
    """``plant(X, cmd) -> X`` one control period later, for ``FIRHC.simulate`` (jitted, cached)."""
    return jax.jit(lambda X, cmd: _period(X, cmd, params)[0])


@functools.lru_cache(maxsize=None)
def _fine_trajectory(params: hm.HopperParams):
    """``fn(X [S, 6], cmd [S, 2]) -> [S, SUBSTEPS, 6]``: every plant step of each recorded period, all periods
    at once (the loop's samples again, to round-off: vmap may fuse differently)."""
    return jax.jit(jax.vmap(lambda X, cmd: _period(X, cmd, params)[1]))


def _require_x64():
    if not jax.config.jax_enable_x64:
        raise RuntimeError("the hopper simulation needs float64: call "
                           "jax.config.update('jax_enable_x64', True) before running it")


def simulate(seconds: float = 2.0, horizon: int = 6, solver: str = "sdfs", params: hm.HopperParams | None = None,
             progress: bool = True, timed: bool = False, bound: bool = False, warm: bool = False,
             **options) -> tuple[fj.ClosedLoop, np.ndarray]:
    """Closed loop from the apex drop for ``seconds`` (rounded to whole control periods).

    Returns ``(loop, X)``: the controller's record, one entry per control
    period (plant states at the samples, commands ``[S, 2]``, nodes, ...), and
    the plant trajectory at every plant step ``[S * SUBSTEPS + 1, 6]``, re-run
    period by period (in parallel) from the recorded states and commands.
    ``timed``: run the closed loop from Python so that ``loop.solve_times``
    holds each decision's wall time, compilation excluded (else one compiled
    scan, the same trajectory bit for bit). ``bound``, ``warm`` and ``options`` as in ``controller``.
    """
    _require_x64()
    params = params or hm.HopperParams()
    steps = max(1, int(round(seconds / CONTROL_PERIOD)))
    X0 = jnp.asarray(hm.apex_state(params, params.g * T_AIR**2 / 8))
    ctrl = controller(params, horizon, solver, bound, warm, **options)
    if timed:  # compile the decision first: FIRHC times it from its first call
        ctrl.simulate(X0, 1, plant(params), compiled=False)
    loop = ctrl.simulate(X0, steps, plant(params), progress=progress, compiled=not timed)
    fine = _fine_trajectory(params)(loop.states[:-1], loop.inputs)  # [S, SUBSTEPS, 6]
    return loop, np.concatenate([np.asarray(X0)[None], np.asarray(fine).reshape(-1, 6)])


# ---------------------------------------------------------------------------
# Figures of merit
# ---------------------------------------------------------------------------

def _times(X):
    """Plant sample times (s) of a fine trajectory ``[T, 6]``."""
    return np.arange(X.shape[0]) * PLANT_DT


def _crossings(t, y, rising: bool):
    """Times where ``y`` crosses 0 upwards (``rising``) or downwards, linearly interpolated."""
    above = y > 0
    idx = np.nonzero(above[1:] & ~above[:-1] if rising else ~above[1:] & above[:-1])[0]
    frac = (0 - y[idx]) / (y[idx + 1] - y[idx])
    return t[idx] + frac * (t[idx + 1] - t[idx])


def gait_events(X):
    """Lift-off and touch-down times (s) of the foot (``y`` crossing 0) in a fine trajectory ``[T, 6]``."""
    t, y = _times(X), X[:, 2]
    return _crossings(t, y, True), _crossings(t, y, False)


def hop_metrics(X) -> dict:
    """Flight times, hop periods (lift-off to lift-off) and compression periods (stroke <= 0) of complete hops."""
    liftoff, touchdown = gait_events(X)
    flights = [(lo, touchdown[touchdown > lo][0]) for lo in liftoff if np.any(touchdown > lo)]
    t_air = np.array([td - lo for lo, td in flights])
    t_hop = np.diff(liftoff)
    t, stroke = _times(X), X[:, 0] - X[:, 2]
    # Compression periods: stroke below mid-position while on the ground, between complete stances.
    t2 = []
    later = liftoff[np.searchsorted(liftoff, touchdown[0]):] if len(touchdown) else []
    for td, lo in zip(touchdown, later, strict=False):  # the last stance may be incomplete
        sel = (t >= td) & (t <= lo)
        t2.append(np.count_nonzero(stroke[sel] <= 0) * PLANT_DT)
    return dict(liftoff=liftoff, touchdown=touchdown, t_air=t_air, t_hop=t_hop, t2=np.array(t2))


def last_compression(X):
    """Index range ``[i, j)`` of the last complete compression period (stroke <= 0 in contact)."""
    comp = (X[:, 0] - X[:, 2] <= 0) & contact(X)
    starts = np.nonzero(comp[1:] & ~comp[:-1])[0] + 1
    ends = np.nonzero(~comp[1:] & comp[:-1])[0] + 1
    pairs = [(i, ends[ends > i][0]) for i in starts if np.any(ends > i)]
    return pairs[-1] if pairs else (0, len(comp))


def summarize(loop: fj.ClosedLoop, X, horizon: int, solver: str, seconds: float, params: hm.HopperParams,
              wall_s: float, loop_bound: bool = False, loop_warm: bool = False, pop_width: int = 1) -> dict:
    """The ``summary.json`` contents. Search statistics are over the contact steps (the flight steps' searches
    are discarded by ``actuate``); solve times are NaN unless the loop was ``timed``."""
    gait, metrics = hm.desired_energy(T_HOP, T_AIR, params), hop_metrics(X)
    c = contact(np.asarray(loop.states[:-1]))
    nodes, feasible = np.asarray(loop.nodes)[c], np.asarray(loop.feasible)[c]
    cmd, times = np.asarray(loop.inputs), np.asarray(loop.solve_times)[c]
    times = times[np.isfinite(times)]
    stroke = X[:, 0] - X[:, 2]

    def mean(a):  # None (JSON null) when there is nothing to average
        return float(np.mean(a)) if len(a) else None

    return dict(
        T2=gait.T2, E_d=gait.E_d, x_t1=gait.x_t1, xdot_t1=gait.xdot_t1,
        E_target_static=static_target(params), v_liftoff_target=liftoff_velocity(params),
        t_hop_mean=mean(metrics["t_hop"]), t_air_mean=mean(metrics["t_air"]), t2_mean=mean(metrics["t2"]),
        t_hop=metrics["t_hop"].tolist(), t_air=metrics["t_air"].tolist(), t2=metrics["t2"].tolist(),
        hops=int(len(metrics["t_air"])),
        infeasible_steps=int(np.count_nonzero(~feasible)),
        unsolved_steps=int(np.count_nonzero(np.asarray(loop.input_indices)[c] < 0)),
        contact_steps=int(np.count_nonzero(c)), control_steps=int(len(c)),
        nodes_min=int(nodes.min()) if len(nodes) else 0, nodes_max=int(nodes.max()) if len(nodes) else 0,
        nodes_mean=mean(nodes), nodes_max_feasible=int(nodes[feasible].max(initial=0)),
        tree_size=problem(params, horizon).tree_size(),
        fallback_nodes_mean=mean(np.asarray(loop.fallback_nodes)[c][~feasible]),
        solve_time_mean_s=mean(times), solve_time_median_s=float(np.median(times)) if len(times) else None,
        solve_time_max_s=float(times.max()) if len(times) else None,
        valve_a_charges=int(np.count_nonzero(cmd[:, 0] > 0)),
        valve_b_supply=int(np.count_nonzero(cmd[:, 1] > 0)),
        valve_b_exhaust=int(np.count_nonzero(cmd[:, 1] < 0)),
        stroke_min=float(stroke.min()), stroke_max=float(stroke.max()), stroke_limit=params.stroke / 2,
        horizon=horizon, solver=solver, bound=loop_bound, warm=loop_warm, pop_width=pop_width, seconds=seconds,
        control_period_s=CONTROL_PERIOD, plant_dt_s=PLANT_DT,
        weights=dict(lambda1=LAMBDA1, lambda2=LAMBDA2, beta=BETA), energy_tol=ENERGY_TOL,
        params=dataclasses.asdict(params), wall_time_s=wall_s,
    )


# ---------------------------------------------------------------------------
# Figures (equivalents of the paper's Figs. 4-8)
# ---------------------------------------------------------------------------

def figures(loop: fj.ClosedLoop, X, params: hm.HopperParams, out: str) -> list:
    """Write the PNG figures from the loop and its fine trajectory ``X``; returns their paths."""
    from ._plot import subplots

    p, gait = params, hm.desired_energy(T_HOP, T_AIR, params)
    t = _times(X)
    stroke, rate = X[:, 0] - X[:, 2], X[:, 1] - X[:, 3]
    paths = []

    def save(fig, name):
        path = os.path.join(out, f"hopper_{name}.png")
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        paths.append(path)

    fig, ax = subplots(figsize=(7, 3.5))
    ax.plot(t, 100 * X[:, 0], label="body x")
    ax.plot(t, 100 * X[:, 2], ":", label="foot y")
    ax.set(xlabel="time (s)", ylabel="displacement (cm)", title="Fig. 4: displacements")
    ax.legend(loc="upper right")
    save(fig, "fig4_displacements")

    fig, ax = subplots(figsize=(5, 4.5))
    ax.plot(X[:, 0], X[:, 1], lw=0.8)
    ax.set(xlabel="body position x (m)", ylabel="body velocity (m/s)", title="Fig. 5: velocity against position")
    save(fig, "fig5_phase")

    fig, ax = subplots(figsize=(7, 3.5))
    ax.plot(t, X[:, 4] / 1e3, label="$P_a$")
    ax.plot(t, X[:, 5] / 1e3, ":", label="$P_b$")
    ax.set(xlabel="time (s)", ylabel="pressure (kPa abs.)", title="Fig. 6: chamber pressures")
    ax.legend(loc="upper right")
    save(fig, "fig6_pressures")

    i, j = last_compression(X)
    tc = t[i:j]
    z = np.stack([stroke[i:j], rate[i:j], X[i:j, 4], X[i:j, 5]], axis=-1)  # [T, 4]
    E = np.asarray(hm.model_energy(z, p))
    E_d = np.asarray(hm.orbit_energy(z, liftoff_velocity(p), p))
    fig, (a1, a2) = subplots(2, 1, figsize=(7, 5), sharex=True)
    a1.plot(tc, E, label="E, eq. (6)")
    a1.plot(tc, E_d, ":", label="desired: eq. (20) for the air in the chambers")
    a1.axhline(gait.E_d, color="gray", lw=0.8, ls="--", label=f"paper's constant E_d = {gait.E_d:.3f} J")
    a1.set(ylabel="energy (J)", title=f"Fig. 7: energy in a compression period ({1e3 * (tc[-1] - tc[0]):.0f} ms)")
    a1.legend(loc="best", fontsize=8)
    a2.plot(tc, 1e3 * (E - E_d), label="$E - E_d$ now (plant)")
    a2.axhspan(-1e3 * ENERGY_TOL, 1e3 * ENERGY_TOL, color="green", alpha=0.15,
               label=f"terminal constraint: |E(k+N) - E_d| <= {1e3 * ENERGY_TOL:g} mJ,\n"
                     "on the prediction N periods ahead, not on E now")
    a2.set(xlabel="time (s)", ylabel="$E - E_d$ (mJ)")
    a2.legend(loc="best", fontsize=8)
    save(fig, "fig7_energy")

    cmd = np.asarray(loop.inputs)
    k = np.minimum(np.arange(i, j) // SUBSTEPS, len(cmd) - 1)
    cmd_b = np.where(contact(X[i:j]), cmd[k, 1], 0.0)  # the command in force at each plant step
    mdot = np.asarray(hm.valve_flow(cmd_b, X[i:j, 5], p))
    fig, ax = subplots(figsize=(7, 3.5))
    ax.plot(tc, 1e3 * mdot)
    ax.set(xlabel="time (s)", ylabel="mass flow into b (g/s)", title="Fig. 8: mass flow into chamber b")
    save(fig, "fig8_massflow")
    return paths


# ---------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------

def register(subparsers) -> None:
    """Add the ``hopper`` subcommand."""
    parser = subparsers.add_parser(
        "hopper", help="pneumatic hopping robot under FIRHC (paper Sec. IV.1, Figs. 4-8)",
        description="Simulate the pneumatic hopping robot under FIRHC, write Figs. 4-8 and summary.json.")
    parser.add_argument("--horizon", type=number(int, 1, 12), default=6, metavar="N",
                        help="prediction horizon (default 6)")
    parser.add_argument("--solver", choices=("sdfs", "exhaustive"), default="sdfs", help="search (default sdfs)")
    parser.add_argument("--bound", action="store_true", help="sDFS with the admissible lower bound (docs/bounds.md)")
    parser.add_argument("--warm", action="store_true",
                        help="sDFS seeded with the better of the previous solution shifted and unshifted (exact; "
                             "with --bound: N = 10 in real time, docs/bounds.md)")
    parser.add_argument("--pop-width", type=number(int, 1, 64), default=1, metavar="K",
                        help="nodes expanded per search iteration (default 1, the paper's sDFS; exact for every K; "
                             "--bound --warm --pop-width 4: N = 10 within the 5 ms period, docs/bounds.md)")
    parser.add_argument("--seconds", type=number(float, CONTROL_PERIOD, 60), default=2.0,
                        help="simulated time in s (default 2)")
    parser.add_argument("--out", default=os.path.join("out", "hopper"), metavar="DIR",
                        help="output directory (default out/hopper)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)


def run(args) -> int:
    """Simulate with every decision timed, write the figures and ``summary.json``."""
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        raise SystemExit(f"hopper: --out {args.out!r} exists and is not a directory")
    if args.warm and args.solver != "sdfs":
        raise SystemExit("hopper: --warm needs --solver sdfs")
    os.makedirs(args.out, exist_ok=True)
    jax.config.update("jax_enable_x64", True)
    params = hm.HopperParams()
    t0 = time.perf_counter()
    loop, X = simulate(args.seconds, args.horizon, args.solver, params, progress=not args.no_progress, timed=True,
                       bound=args.bound, warm=args.warm, pop_width=args.pop_width)
    wall = time.perf_counter() - t0
    summary = summarize(loop, X, args.horizon, args.solver, args.seconds, params, wall, args.bound, args.warm,
                        args.pop_width)
    figures(loop, X, params, args.out)
    with open(os.path.join(args.out, "summary.json"), "w") as f:
        json.dump(summary, f, indent=2)

    def fmt(value, spec, scale=1.0):
        return "n/a" if value is None else format(scale * value, spec)

    print(f"hops {summary['hops']}  T_hop {fmt(summary['t_hop_mean'], '.4f')} s  "
          f"T_air {fmt(summary['t_air_mean'], '.4f')} s  (spec {T_HOP} / {T_AIR})  "
          f"infeasible {summary['infeasible_steps']}/{summary['contact_steps']}  "
          f"nodes {summary['nodes_min']}/{summary['nodes_max']}/{fmt(summary['nodes_mean'], '.0f')} (min/max/mean)  "
          f"solve {fmt(summary['solve_time_mean_s'], '.2f', 1e3)} ms/step")
    print(f"wrote {args.out}/summary.json and hopper_fig4..8 PNGs")
    return 0
