"""``python -m firhc_jax inverter --levels 3``: the three-level inverter on ``fj.LinearTracking``, the
``inverter`` command's second variant (``ThreeLevel``; the command and its options are ``inverter.py``'s).

27 switch states, RL load (``firhc_jax.models.three_level``), the sinusoidal
current reference along the horizon, lambda_u per unit leg step and no leg
jumping from -1 to +1 in one sample (max_step = 1). The FIRHC closed loop
(warm-started with the shifted previous sequence, the decoder's initial
radius) runs for whole fundamental cycles from steady state, every decision
timed, and writes into ``--out`` (default ``out/inverter-3level``):

* ``summary.json``: THD, switching frequency per leg, nodes and solve times
  (keys listed in ``summarize``);
* ``inverter3_N<N>.png``: phase currents against their references and the
  spectrum of phase a with its THD;
* ``closed_loop.npz``: the whole run (``fj.ClosedLoop.load`` reads it).
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

import firhc_jax as fj
from firhc_jax.models import inverter as two_level
from firhc_jax.models import three_level

from ._inverter import InverterRun, figure, report, waveform_metrics
from ._run import App
from ._timing import timed_closed_loop

LAMBDA_U = 0.1  # A^2 per unit leg step (docs/applications/inverter.md)


def closed_loop(horizon: int, steps: int, lambda_u: float = LAMBDA_U, progress: bool = False) -> InverterRun:
    """Run the LinearTracking FIRHC law for ``steps`` samples from the reference at t = 0 (all legs at 0 before),
    every decision timed after one compilation (``_timing.timed_closed_loop``). Needs float64."""
    params = three_level.PARAMS
    lt = three_level.make_problem(horizon, params, lambda_u=lambda_u)
    ctrl = fj.FIRHC(lt.problem, observe=lt.observe, warm_start=True, pop_width=three_level.pop_width(horizon))
    p = lt.params(jnp.asarray(two_level.horizon_references(params, steps, horizon)))  # leading axis: steps
    i0 = jnp.asarray(two_level.initial_currents(params))
    loop, compile_time = timed_closed_loop(ctrl, i0, steps, _plant(), params=p, u0=jnp.zeros(3), dt=params.ts,
                                           progress=progress, settings=("three-level inverter", horizon, params,
                                                                        lambda_u))
    return InverterRun(loop, two_level.reference(params, loop.times), compile_time)


@functools.lru_cache(maxsize=None)
def _plant():
    """The RL load, ``plant(i, u, p)`` (the closed loop passes ``p`` to the plant too), jitted once."""
    rl = three_level.make_plant()
    return jax.jit(lambda i, u, p: rl(i, u))


def summarize(run: InverterRun, horizon: int, lambda_u: float) -> dict:
    """The ``summary.json`` record (currents in A, times in s, frequencies in Hz); the waveform figures as in
    the two-level variant (``waveform_metrics``: a leg's unit level steps, -1 -> 0 or 0 -> +1, counted as
    one commutation each; max_step = 1 forbids larger ones)."""
    w = waveform_metrics(run, three_level.PARAMS)
    return {
        "levels": 3,
        "horizon": horizon,
        "lambda_u": lambda_u,
        "pop_width": three_level.pop_width(horizon),
        "thd": w["thd"],
        "switching_frequency_hz": w["switching_frequency_hz"],
        "rms_tracking_error": w["rms_tracking_error"],
        "current_amplitude": w["current_amplitude"],
        "nodes_mean": float(run.nodes.mean()),
        "nodes_max": int(run.nodes.max()),
        "solve_time_median_s": float(np.median(run.solve_times)),
        "solve_time_max_s": float(run.solve_times.max()),
        "solve_time_mean_s": float(run.solve_times.mean()),
        "compile_time_s": run.compile_time,
        "thd_phases": w["thd_phases"],
        "leg_changes": w["leg_changes"],
        "predicted_cost_mean": float(run.predicted_costs.mean()),
        "steps": w["steps"],
        "seconds": w["seconds"],
        "parameters": w["parameters"],
    }


def _lambda_u(args) -> float:
    """``--lambda-u`` of a three-level run: ``LAMBDA_U`` unless given."""
    return LAMBDA_U if args.lambda_u is None else args.lambda_u


class ThreeLevel(App):
    """``inverter --levels 3``: uses ``horizon``, ``cycles``, ``lambda_u``, ``out`` and ``no_progress``."""

    name = "inverter"

    def default_out(self, args) -> str:
        """Its own folder: a three-level run never overwrites a two-level one."""
        return "out/inverter-3level"

    def check(self, parser, args) -> None:
        """The two-level options ``--solver``, ``--bound`` and ``--model`` do not apply and are refused."""
        if args.horizon > three_level.MAX_HORIZON:
            raise SystemExit(f"inverter --levels 3: --horizon must be at most {three_level.MAX_HORIZON}, "
                             f"got {args.horizon}")
        if args.solver != "sdfs" or args.bound or args.model != "exact":
            raise SystemExit("inverter --levels 3 runs fj.LinearTracking (sDFS with its own bound, exact model): "
                             "--solver, --bound and --model apply to --levels 2 only")

    def simulate(self, args) -> InverterRun:
        steps = int(args.cycles * three_level.PARAMS.steps_per_cycle)
        return closed_loop(args.horizon, steps, _lambda_u(args), progress=not args.no_progress)

    def summarize(self, args, run: InverterRun) -> dict:
        return summarize(run, args.horizon, _lambda_u(args))

    def report(self, args, summary: dict) -> str:
        return report(f"inverter --levels 3 N={args.horizon} lambda_u={_lambda_u(args):g}", summary)

    def plot(self, args, run: InverterRun, summary: dict) -> list:
        return figure(run, args.out, f"inverter3_N{args.horizon}.png", three_level.PARAMS,
                      f"Three-level inverter, LinearTracking, N = {args.horizon}, $\\lambda_u$ = {_lambda_u(args):g} "
                      f"A$^2$: {summary['switching_frequency_hz'] / 1e3:.2f} kHz per leg")

APP = ThreeLevel()
