"""``python -m firhc_jax hopper``: the pneumatic hopping robot under FIRHC (Sec. IV.1, Figs. 4-8).

The robot is dropped from rest at the apex of the specified flight (foot at
``g T_air^2 / 8``) and controlled for ``--seconds`` by ``controller``
(``_hopper.py``; explained and measured in ``docs/applications/hopper.md``): side a by the paper's on/off
law, valve b by FIRHC over its three states, both valves sealed in flight, a 5 ms control period and a
plant integrated at 50 us.

The closed loop is ``FIRHC.simulate``, one step per control period:
``observe`` maps the plant state ``[6]`` to the model's ``[5]``, ``actuate``
adds side a's law and seals the valves in flight, and the plant integrates
one period. The CLI compiles the decision first (``compile_time_s``) and then
runs the loop from Python (``compiled=False``) so that every decision is
timed (``_timing.timed_closed_loop``); tests run it as one compiled
``lax.scan``, the same trajectory bit for bit.
The figures' plant-step trajectory is re-integrated from the recorded states
and commands.
"""
from __future__ import annotations

import dataclasses
import functools
import os
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import firhc_jax as fj
from firhc_jax.models import hopper as hm

from ..solvers import SOLVERS
from ._args import horizon_argument, number, solver_argument
from ._hopper import controller, warm_candidate  # noqa: F401  the closed loop's controller, importable here
from ._limits import exhaustive_run
from ._run import App
from ._status import stage
from ._timing import timed_closed_loop


@functools.lru_cache(maxsize=None)
def _fine_trajectory(params: hm.HopperParams):
    """``fn(X [S, 6], cmd [S, 2]) -> [S, SUBSTEPS, 6]``: every plant step of each recorded period, all periods
    at once (the loop's samples again, to round-off: vmap may fuse differently)."""
    return jax.jit(jax.vmap(lambda X, cmd: hm.control_period(X, cmd, params)[1]))


def _require_x64():
    if not jax.config.jax_enable_x64:
        raise RuntimeError("the hopper simulation needs float64: call "
                           "jax.config.update('jax_enable_x64', True) before running it")


def simulate(seconds: float = 2.0, horizon: int = 6, solver: str = "sdfs", params: hm.HopperParams | None = None,
             progress: bool = True, timed: bool = False, bound: bool = False, warm: bool = False,
             **options) -> tuple[fj.ClosedLoop, np.ndarray, float | None]:
    """Closed loop from the apex drop for ``seconds`` (rounded to whole control periods).

    Returns ``(loop, X, compile_s)``: the controller's record, one entry per
    control period (plant states at the samples, commands ``[S, 2]``, nodes,
    ..., with its time axis), the plant trajectory at every plant step
    ``[S * SUBSTEPS + 1, 6]``, re-run period by period (in parallel) from the
    recorded states and commands, and the seconds to trace and compile one
    decision. ``timed``: compile the decision first, then run the closed loop
    from Python so that ``loop.solve_times`` holds each decision's wall time
    (``_timing.timed_closed_loop``); else one compiled scan, the same
    trajectory bit for bit, and ``compile_s`` None. ``bound``, ``warm`` and
    ``options`` as in ``controller``.
    """
    _require_x64()
    params = params or hm.HopperParams()
    steps = max(1, int(round(seconds / hm.CONTROL_PERIOD)))
    X0 = jnp.asarray(hm.initial_state(params))
    ctrl = controller(horizon, params, solver, bound, warm, **options)
    plant = hm.make_plant(params)
    if timed:
        loop, compile_s = timed_closed_loop(ctrl, X0, steps, plant, dt=hm.CONTROL_PERIOD, progress=progress,
                                            settings=("hopper", horizon, params, solver, bound, warm, options))
    else:
        loop, compile_s = ctrl.simulate(X0, steps, plant, dt=hm.CONTROL_PERIOD, progress=progress), None
    with stage(f"re-integrating the plant at {hm.PLANT_DT * 1e6:g} us for the figures"):
        fine = jax.block_until_ready(_fine_trajectory(params)(loop.states[:-1], loop.inputs))  # [S, SUBSTEPS, 6]
    return loop, np.concatenate([np.asarray(X0)[None], np.asarray(fine).reshape(-1, 6)]), compile_s


# ---------------------------------------------------------------------------
# Figures of merit
# ---------------------------------------------------------------------------

def _times(X):
    """Plant sample times (s) of a fine trajectory ``[T, 6]``."""
    return np.arange(X.shape[0]) * hm.PLANT_DT


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
        t2.append(np.count_nonzero(stroke[sel] <= 0) * hm.PLANT_DT)
    return dict(liftoff=liftoff, touchdown=touchdown, t_air=t_air, t_hop=t_hop, t2=np.array(t2))


def last_compression(X):
    """Index range ``[i, j)`` of the last complete compression period (stroke <= 0 in contact)."""
    comp = (X[:, 0] - X[:, 2] <= 0) & hm.contact(X)
    starts = np.nonzero(comp[1:] & ~comp[:-1])[0] + 1
    ends = np.nonzero(~comp[1:] & comp[:-1])[0] + 1
    pairs = [(i, ends[ends > i][0]) for i in starts if np.any(ends > i)]
    return pairs[-1] if pairs else (0, len(comp))


def summarize(loop: fj.ClosedLoop, X, horizon: int, solver: str, seconds: float, params: hm.HopperParams,
              wall_s: float, loop_bound: bool = False, loop_warm: bool = False, pop_width: int = 1,
              compile_s: float | None = None) -> dict:
    """The ``summary.json`` contents. Search statistics are over the contact steps (the flight steps' searches
    are discarded by ``actuate``); solve times are null unless the loop was ``timed``."""
    gait, metrics = hm.desired_energy(hm.T_HOP, hm.T_AIR, params), hop_metrics(X)
    c = hm.contact(np.asarray(loop.states[:-1]))
    nodes, feasible = np.asarray(loop.nodes)[c], np.asarray(loop.feasible)[c]
    cmd, times = np.asarray(loop.inputs), np.asarray(loop.solve_times)[c]
    times = times[np.isfinite(times)]
    stroke = X[:, 0] - X[:, 2]

    def mean(a):  # None (JSON null) when there is nothing to average
        return float(np.mean(a)) if len(a) else None

    return dict(
        T2=gait.T2, E_d=gait.E_d, x_t1=gait.x_t1, xdot_t1=gait.xdot_t1,
        E_target_static=hm.static_target(params), v_liftoff_target=hm.liftoff_velocity(params),
        t_hop_mean=mean(metrics["t_hop"]), t_air_mean=mean(metrics["t_air"]), t2_mean=mean(metrics["t2"]),
        t_hop=metrics["t_hop"].tolist(), t_air=metrics["t_air"].tolist(), t2=metrics["t2"].tolist(),
        hops=int(len(metrics["t_air"])),
        infeasible_steps=int(np.count_nonzero(~feasible)),
        unsolved_steps=int(np.count_nonzero(np.asarray(loop.held)[c])),
        contact_steps=int(np.count_nonzero(c)), control_steps=int(len(c)),
        nodes_min=int(nodes.min()) if len(nodes) else 0, nodes_max=int(nodes.max()) if len(nodes) else 0,
        nodes_mean=mean(nodes), nodes_max_feasible=int(nodes[feasible].max(initial=0)),
        tree_size=hm.make_problem(horizon, params).tree_size(),
        fallback_nodes_mean=mean(np.asarray(loop.fallback_nodes)[c][~feasible]),
        solve_time_mean_s=mean(times), solve_time_median_s=float(np.median(times)) if len(times) else None,
        solve_time_max_s=float(times.max()) if len(times) else None, compile_time_s=compile_s,
        valve_a_charges=int(np.count_nonzero(cmd[:, 0] > 0)),
        valve_b_supply=int(np.count_nonzero(cmd[:, 1] > 0)),
        valve_b_exhaust=int(np.count_nonzero(cmd[:, 1] < 0)),
        stroke_min=float(stroke.min()), stroke_max=float(stroke.max()), stroke_limit=params.stroke / 2,
        horizon=horizon, solver=solver, bound=loop_bound, warm=loop_warm, pop_width=pop_width, seconds=seconds,
        control_period_s=hm.CONTROL_PERIOD, plant_dt_s=hm.PLANT_DT,
        weights=dict(lambda1=hm.LAMBDA1, lambda2=hm.LAMBDA2, beta=hm.BETA), energy_tol=hm.ENERGY_TOL,
        params=dataclasses.asdict(params), wall_time_s=wall_s,
    )


# ---------------------------------------------------------------------------
# Figures (equivalents of the paper's Figs. 4-8)
# ---------------------------------------------------------------------------

def figures(loop: fj.ClosedLoop, X, params: hm.HopperParams, out: str) -> list:
    """Write the PNG figures from the loop and its fine trajectory ``X``; returns their paths."""
    from ._plot import subplots

    p, gait = params, hm.desired_energy(hm.T_HOP, hm.T_AIR, params)
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
    ax.plot(100 * X[:, 0], X[:, 1], lw=0.8)  # the position in Fig. 4's unit
    ax.set(xlabel="body position x (cm)", ylabel="body velocity (m/s)", title="Fig. 5: velocity against position")
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
    E_d = np.asarray(hm.orbit_energy(z, hm.liftoff_velocity(p), p))
    fig, (a1, a2) = subplots(2, 1, figsize=(7, 5), sharex=True)
    a1.plot(tc, E, label="E, eq. (6)")
    a1.plot(tc, E_d, ":", label="desired: eq. (20) for the air in the chambers")
    a1.axhline(gait.E_d, color="gray", lw=0.8, ls="--", label=f"paper's constant E_d = {gait.E_d:.3f} J")
    a1.set(ylabel="energy (J)", title=f"Fig. 7: energy in a compression period ({1e3 * (tc[-1] - tc[0]):.0f} ms)")
    a1.legend(loc="best", fontsize=8)
    a2.plot(tc, 1e3 * (E - E_d), label="$E - E_d$ now (plant)")
    a2.axhspan(-1e3 * hm.ENERGY_TOL, 1e3 * hm.ENERGY_TOL, color="green", alpha=0.15,
               label=f"terminal constraint: |E(k+N) - E_d| <= {1e3 * hm.ENERGY_TOL:g} mJ,\n"
                     "on the prediction N periods ahead, not on E now")
    a2.set(xlabel="time (s)", ylabel="$E - E_d$ (mJ)")
    a2.legend(loc="best", fontsize=8)
    save(fig, "fig7_energy")

    cmd = np.asarray(loop.inputs)
    k = np.minimum(np.arange(i, j) // hm.SUBSTEPS, len(cmd) - 1)
    cmd_b = np.where(hm.contact(X[i:j]), cmd[k, 1], 0.0)  # the command in force at each plant step
    mdot = np.asarray(hm.valve_flow(cmd_b, X[i:j, 5], p))
    fig, ax = subplots(figsize=(7, 3.5))
    ax.plot(tc, 1e3 * mdot)
    ax.set(xlabel="time (s)", ylabel="mass flow into b (g/s)", title="Fig. 8: mass flow into chamber b")
    save(fig, "fig8_massflow")
    return paths


# ---------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------

# Exhaustive search costs about 2.3 us a node here (N = 8: 23 ms for 9,840 nodes, shared 2-core CPU).
EXHAUSTIVE_BUDGET = 1e8


class HopperRun(NamedTuple):
    """One run of the command."""

    loop: fj.ClosedLoop  # one entry per control period
    X: np.ndarray  # [S * SUBSTEPS + 1, 6] the plant at every plant step
    compile_s: float  # s tracing and compilation of one decision
    wall_s: float  # s the whole simulation took, compilation and figures' re-integration included


class Hopper(App):
    name = "hopper"
    help = "pneumatic hopping robot under FIRHC (paper Sec. IV.1, Figs. 4-8)"
    description = "Simulate the pneumatic hopping robot under FIRHC, write Figs. 4-8 and summary.json."

    def add_arguments(self, parser) -> None:
        horizon_argument(parser, 12, 6, short=False)
        solver_argument(parser)
        parser.add_argument("--bound", action="store_true",
                            help="sDFS with the admissible lower bound (docs/guide/bounds.md)")
        parser.add_argument("--warm", action="store_true",
                            help="sDFS seeded with the better of the previous solution shifted and unshifted "
                                 "(exact; with --bound: N = 10 in real time, docs/guide/bounds.md)")
        parser.add_argument("--pop-width", type=number(int, 1, 64), default=1, metavar="K",
                            help="nodes expanded per search iteration (default 1, the paper's sDFS; exact for every "
                                 "K; --bound --warm --pop-width 4: N = 10 within the 5 ms period, "
                                 "docs/guide/bounds.md)")
        parser.add_argument("--seconds", type=number(float, hm.CONTROL_PERIOD, 60), default=2.0,
                            help="simulated time in s (default 2)")

    def check(self, parser, args) -> None:
        """A run's exhaustive searches within ``EXHAUSTIVE_BUDGET`` nodes; ``--warm`` with sDFS only."""
        if args.warm and not SOLVERS[args.solver].warm_starts:
            parser.error(f"--warm needs --solver sdfs (or another solver that takes warm starts), got --solver "
                         f"{args.solver}")
        if not SOLVERS[args.solver].prunes:  # it visits the whole tree: bound the run
            steps = max(1, int(round(args.seconds / hm.CONTROL_PERIOD)))
            exhaustive_run(parser, steps, len(hm.VALVE_B), args.horizon, EXHAUSTIVE_BUDGET,
                           "about 4 minutes at 2.3 us a node", "lower --horizon or --seconds, or use --solver sdfs")

    def simulate(self, args) -> HopperRun:
        """Every decision timed (``simulate(..., timed=True)``)."""
        t0 = time.perf_counter()
        loop, X, compile_s = simulate(args.seconds, args.horizon, args.solver, hm.HopperParams(),
                                      progress=not args.no_progress, timed=True, bound=args.bound, warm=args.warm,
                                      pop_width=args.pop_width)
        return HopperRun(loop, X, compile_s, time.perf_counter() - t0)

    def summarize(self, args, run: HopperRun) -> dict:
        return summarize(run.loop, run.X, args.horizon, args.solver, args.seconds, hm.HopperParams(), run.wall_s,
                         args.bound, args.warm, args.pop_width, run.compile_s)

    def plot(self, args, run: HopperRun, summary: dict) -> list:
        return figures(run.loop, run.X, hm.HopperParams(), args.out)

    def report(self, args, summary: dict) -> str:
        def fmt(value, spec, scale=1.0):
            return "n/a" if value is None else format(scale * value, spec)

        return (f"hops {summary['hops']}  T_hop {fmt(summary['t_hop_mean'], '.4f')} s  "
                f"T_air {fmt(summary['t_air_mean'], '.4f')} s  (spec {hm.T_HOP} / {hm.T_AIR})  "
                f"infeasible {summary['infeasible_steps']}/{summary['contact_steps']}  "
                f"nodes {summary['nodes_min']}/{summary['nodes_max']}/{fmt(summary['nodes_mean'], '.0f')} "
                f"(min/max/mean)  solve {fmt(summary['solve_time_mean_s'], '.2f', 1e3)} ms/step")


APP = Hopper()
register = APP.register
run = APP.run
