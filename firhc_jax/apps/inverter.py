"""``python -m firhc_jax inverter``: FCS-MPC current control of a two-level inverter feeding an RL load.

Runs the FIRHC closed loop (8 switch states, a sinusoidal reference passed as
per-step parameters, a switching penalty on the previous input) for whole
fundamental cycles from steady state, timing every decision, and writes into
``--out`` (default ``out/inverter``; ``out/inverter-3level`` with ``--levels 3``):

* ``summary.json``: tracking error, fundamental amplitude, THD, switching
  frequency, nodes and solve times (keys listed in ``summarize``);
* ``inverter_N<N>_<solver>.png``: phase currents against their references
  (up to three cycles) and the spectrum of phase a with its THD;
* ``closed_loop.npz``: the whole run (``fj.ClosedLoop.load`` reads it).

The plant is the exact (zero-order hold) RL response; the prediction model is
exact too unless ``--model euler``. ``--levels 3`` runs the three-level
inverter instead (``inverter_three_level``, the command's other variant).
"""
from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

import firhc_jax as fj
from firhc_jax.models import inverter as model
from firhc_jax.models.three_level import MAX_HORIZON as THREE_LEVEL_MAX_HORIZON

from ..solvers import SOLVERS
from . import inverter_three_level
from ._args import horizon_argument, number, solver_argument
from ._inverter import InverterRun, figure, plot, report, spectrum, waveform_metrics  # noqa: F401
from ._limits import exhaustive_run
from ._run import App
from ._timing import timed_closed_loop

MAX_HORIZON = 8  # 8^8 sequences; exhaustive search is already slow there
MAX_CYCLES = 100.0  # 80,000 decisions
# Exhaustive search costs about 26 ns a node here (N = 5: 0.98 ms for 37,448 nodes, shared 2-core CPU).
EXHAUSTIVE_BUDGET = 1e10


def closed_loop(horizon: int, solver: str = "sdfs", steps: int = 1600, lambda_u: float = 0.0,
                params: model.InverterParams | None = None, method: str = "exact",
                progress: bool = False, bound: bool = False, timed: bool = True) -> InverterRun:
    """Run the FIRHC law for ``steps`` samples from the reference at t = 0 (V0 applied before).

    ``timed``: the decision is compiled first, then run from Python with
    every decision timed (``_timing.timed_closed_loop``); else one compiled
    scan (the same closed loop, ``compile_time`` NaN). Needs float64.
    ``params`` defaults to ``model.InverterParams()``; ``bound``: with
    ``model.current_bound``.
    """
    params = params or model.InverterParams()
    mem = model.make_problem(horizon, params, method, bound)
    ctrl = fj.FIRHC(mem.problem, solver, observe=mem.observe)
    refs = model.horizon_references(params, steps, horizon)  # [T, N, 2]
    p = {"ref": jnp.asarray(refs), "lambda_u": jnp.full((steps,), float(lambda_u))}
    i0, u0 = jnp.asarray(model.initial_currents(params)), jnp.zeros(3)
    plant = _plant(params)
    if timed:
        loop, compile_time = timed_closed_loop(ctrl, i0, steps, plant, params=p, u0=u0, dt=params.ts,
                                               progress=progress,
                                               settings=("inverter", horizon, params, method, bound, solver))
    else:
        loop, compile_time = ctrl.simulate(i0, steps, plant, params=p, u0=u0, dt=params.ts, progress=progress), math.nan
    return InverterRun(loop, model.reference(params, loop.times), compile_time)


@functools.lru_cache(maxsize=None)
def _plant(params: model.InverterParams):
    """The exact RL plant for the closed loop, ``plant(i, u, p)`` (it passes ``p`` to the plant too), jitted
    once per parameters."""
    rl = model.make_plant(params)
    return jax.jit(lambda i, u, p: rl(i, u))


def summarize(run: InverterRun, horizon: int, solver: str, lambda_u: float, params: model.InverterParams,
              method: str = "exact", levels: int = 2) -> dict:
    """The ``summary.json`` record of a run (currents in A, times in s, frequencies in Hz)."""
    w = waveform_metrics(run, params)
    return {
        "rms_tracking_error": w["rms_tracking_error"],
        "current_amplitude": w["current_amplitude"],
        "switching_frequency_hz": w["switching_frequency_hz"],
        "solve_time_median_s": float(np.median(run.solve_times)),
        "nodes_mean": float(run.nodes.mean()),
        "nodes_max": int(run.nodes.max()),
        "horizon": horizon,
        "solver": solver,
        "thd": w["thd"],
        "thd_phases": w["thd_phases"],
        "current_amplitudes": w["current_amplitudes"],
        "reference_amplitude": params.amplitude,
        "leg_changes": w["leg_changes"],
        "lambda_u": lambda_u,
        "model": method,
        "levels": levels,
        "nodes_min": int(run.nodes.min()),
        "exhaustive_nodes_per_step": (8 ** (horizon + 1) - 8) // 7,
        "solve_time_mean_s": float(run.solve_times.mean()),
        "solve_time_max_s": float(run.solve_times.max()),
        "compile_time_s": run.compile_time,
        "predicted_cost_mean": float(run.predicted_costs.mean()),
        "steps": w["steps"],
        "seconds": w["seconds"],
        "parameters": w["parameters"],
    }


def _lambda_u(args) -> float:
    """``--lambda-u`` of a two-level run: 1 A^2 per leg change unless given."""
    return 1.0 if args.lambda_u is None else args.lambda_u


class Inverter(App):
    """The two-level inverter; ``--levels 3`` is ``inverter_three_level.ThreeLevel``."""

    name = "inverter"
    help = "current control of a two-level three-phase inverter, 8 switch states (FCS-MPC)"
    description = ("FIRHC current control of a two-level voltage source inverter feeding an RL load "
                   "(520 V, 10 ohm, 10 mH, Ts = 25 us, 10 A at 50 Hz); writes summary.json and a figure.")

    def add_arguments(self, p) -> None:
        horizon_argument(p, THREE_LEVEL_MAX_HORIZON, 3, f"at most {MAX_HORIZON} with --levels 2")
        solver_argument(p, "exhaustive visits 8+...+8^N nodes per step")
        p.add_argument("--cycles", type=number(float, 0, low_open=True, high=MAX_CYCLES), default=2.0,
                       help=f"simulated fundamental cycles of 20 ms, rounded down to whole samples (default 2, at "
                            f"most {MAX_CYCLES:g})")
        p.add_argument("--lambda-u", type=number(float, 0), default=None,
                       help="switching penalty in A^2 per leg change, charged against the previous input "
                            "(default 1; 0.1 per unit leg step with --levels 3)")
        p.add_argument("--bound", action="store_true", help="sDFS with the admissible lower bound "
                       "(docs/guide/bounds.md)")
        p.add_argument("--levels", type=int, choices=(2, 3), default=2,
                       help="inverter levels: 2, the two-level inverter (8 switch states, default); 3, the "
                            "three-level inverter (27 states) on fj.LinearTracking (docs/applications/inverter.md)")
        p.add_argument("--model", choices=model.DISCRETISATIONS, default="exact",
                       help="prediction model: exact zero-order hold (default) or forward Euler; the plant is exact")

    out_help = "out/inverter; out/inverter-3level with --levels 3"

    def variant(self, args) -> App:
        return inverter_three_level.APP if args.levels == 3 else self

    def check(self, parser, args) -> None:
        """Two samples at least; the horizon of the chosen inverter, a two-level run's exhaustive searches
        within ``EXHAUSTIVE_BUDGET`` nodes, the three-level variant's own refusals."""
        params = model.InverterParams()  # the three-level inverter samples at the same rate
        steps = int(args.cycles * params.steps_per_cycle)
        if steps < 2:
            parser.error(f"--cycles must cover at least two samples, got {args.cycles:g}")
        if args.levels == 3:
            return inverter_three_level.APP.check(parser, args)
        if args.horizon > MAX_HORIZON:
            parser.error(f"--horizon must be between 1 and {MAX_HORIZON} with --levels 2, got {args.horizon}")
        if not SOLVERS[args.solver].prunes:  # it visits the whole tree: bound the run
            exhaustive_run(parser, steps, len(model.SWITCH_STATES), args.horizon, EXHAUSTIVE_BUDGET,
                           "about 4 minutes at 26 ns a node", "lower --horizon or --cycles, or use --solver sdfs")

    def simulate(self, args) -> InverterRun:
        params = model.InverterParams()
        return closed_loop(args.horizon, args.solver, int(args.cycles * params.steps_per_cycle), _lambda_u(args),
                           params, args.model, progress=not args.no_progress, bound=args.bound)

    def summarize(self, args, run: InverterRun) -> dict:
        return summarize(run, args.horizon, args.solver, _lambda_u(args), model.InverterParams(), args.model,
                         args.levels)

    def plot(self, args, run: InverterRun, summary: dict) -> list:
        return figure(run, args.out, f"inverter_N{args.horizon}_{args.solver}.png", model.InverterParams(),
                      f"Inverter FIRHC, N = {args.horizon}, {args.solver}, $\\lambda_u$ = {_lambda_u(args):g} A$^2$: "
                      f"rms error {summary['rms_tracking_error']:.3f} A, "
                      f"{summary['switching_frequency_hz'] / 1e3:.2f} kHz per leg")

    def report(self, args, summary: dict) -> str:
        return report(f"inverter N={args.horizon} {args.solver} lambda_u={_lambda_u(args):g}", summary)


APP = Inverter()
register = APP.register
run = APP.run
