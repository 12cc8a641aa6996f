"""``python -m firhc_jax inverter --levels 3``: the three-level inverter on ``fj.LinearTracking``.

27 switch states, RL load (``firhc_jax.models.three_level``), the sinusoidal
current reference along the horizon, lambda_u per unit leg step and no leg
jumping from -1 to +1 in one sample (max_step = 1). The FIRHC closed loop
(warm-started with the shifted previous sequence, the decoder's initial
radius) runs for whole fundamental cycles from steady state, every decision
timed, and writes into ``--out``:

* ``summary.json``: THD, switching frequency per leg, nodes and solve times
  (keys listed in ``summarize``);
* ``inverter3_N<N>.png``: phase currents against their references and the
  spectrum of phase a with its THD;
* ``closed_loop.npz``: the whole run (``fj.ClosedLoop.load`` reads it).
"""
from __future__ import annotations

import functools
import json

import jax
import jax.numpy as jnp
import numpy as np

import firhc_jax as fj
from firhc_jax.models import inverter as two_level
from firhc_jax.models import three_level

from ._status import stage
from ._timing import timed_closed_loop
from .inverter import InverterRun, distortion, plot

LAMBDA_U = 0.1  # A^2 per unit leg step (docs/inverter.md)


def closed_loop(horizon: int, steps: int, lambda_u: float = LAMBDA_U, progress: bool = False) -> InverterRun:
    """Run the LinearTracking FIRHC law for ``steps`` samples from the reference at t = 0 (all legs at 0 before),
    every decision timed after one compilation (``_timing.timed_closed_loop``). Needs float64."""
    params = three_level.PARAMS
    lt = three_level.tracking(horizon, lambda_u)
    ctrl = fj.FIRHC(lt.problem, observe=lt.observe, warm_start=True, pop_width=three_level.pop_width(horizon))
    p = lt.params(jnp.asarray(two_level.horizon_references(params, steps, horizon)))  # leading axis: steps
    i0 = jnp.asarray(two_level.initial_currents(params))
    loop, compile_time = timed_closed_loop(ctrl, i0, steps, _plant(), params=p, u0=jnp.zeros(3), dt=params.ts,
                                           progress=progress)
    return InverterRun(loop, two_level.reference(params, loop.times), compile_time)


@functools.lru_cache(maxsize=None)
def _plant():
    """The RL load, ``plant(i, u, p)`` (the closed loop passes ``p`` to the plant too), jitted once."""
    A, B = (jnp.asarray(a) for a in three_level.model())
    return jax.jit(lambda i, u, p: A @ i + B @ u)


def summarize(run: InverterRun, horizon: int, lambda_u: float) -> dict:
    """The ``summary.json`` record (currents in A, times in s, frequencies in Hz).

    Switching frequency per leg: unit level steps of the leg (0 -> +1 or
    -1 -> 0 and back, one commutation each; max_step = 1 forbids larger ones)
    over the run, divided by two (a switching period has two), averaged over
    the legs. THD as in the two-level app (``distortion``): every
    non-fundamental component of the phase current over whole cycles."""
    params = three_level.PARAMS
    steps = run.inputs.shape[0]
    seconds = steps * params.ts
    phases = two_level.to_phases(run.currents[:-1])
    errors = two_level.to_phases(run.references - run.currents)
    fundamentals, thds = zip(*(distortion(phases[:, x], params) for x in range(3)), strict=True)
    changes = np.abs(np.diff(run.inputs, axis=0)).sum(axis=0)  # [3] unit steps per leg within the run
    return {
        "levels": 3,
        "horizon": horizon,
        "lambda_u": lambda_u,
        "pop_width": three_level.pop_width(horizon),
        "thd": float(np.mean(thds)),
        "switching_frequency_hz": float(changes.mean() / (2.0 * seconds)),
        "rms_tracking_error": float(np.sqrt(np.mean(errors**2))),
        "current_amplitude": float(np.mean(fundamentals)),
        "nodes_mean": float(run.nodes.mean()),
        "nodes_max": int(run.nodes.max()),
        "solve_time_median_s": float(np.median(run.solve_times)),
        "solve_time_max_s": float(run.solve_times.max()),
        "solve_time_mean_s": float(run.solve_times.mean()),
        "compile_time_s": run.compile_time,
        "thd_phases": list(thds),
        "leg_changes": changes.astype(int).tolist(),
        "predicted_cost_mean": float(run.predicted_costs.mean()),
        "steps": steps,
        "seconds": seconds,
        "parameters": {"vdc": params.vdc, "r": params.r, "l": params.l, "ts": params.ts,
                       "amplitude": params.amplitude, "frequency": params.frequency},
    }


def run(args) -> int:
    """``inverter --levels 3``: uses ``horizon``, ``cycles``, ``lambda_u`` (None: ``LAMBDA_U``),
    ``out`` and ``no_progress`` of the parsed ``args``; returns the exit status (0). The two-level
    options ``--solver``, ``--bound`` and ``--model`` do not apply and are refused."""
    if args.horizon > three_level.MAX_HORIZON:
        raise SystemExit(f"inverter --levels 3: --horizon must be at most {three_level.MAX_HORIZON}, "
                         f"got {args.horizon}")
    if getattr(args, "solver", "sdfs") != "sdfs" or getattr(args, "bound", False) or \
            getattr(args, "model", "exact") != "exact":
        raise SystemExit("inverter --levels 3 runs fj.LinearTracking (sDFS with its own bound, exact model): "
                         "--solver, --bound and --model apply to --levels 2 only")
    jax.config.update("jax_enable_x64", True)
    lambda_u = LAMBDA_U if args.lambda_u is None else args.lambda_u
    steps = int(args.cycles * three_level.PARAMS.steps_per_cycle)
    if steps < 2:
        raise SystemExit(f"inverter: --cycles must cover at least two samples, got {args.cycles:g}")
    args.out.mkdir(parents=True, exist_ok=True)
    result = closed_loop(args.horizon, steps, lambda_u, progress=not args.no_progress)
    summary = summarize(result, args.horizon, lambda_u)
    figure = args.out / f"inverter3_N{args.horizon}.png"
    with stage(f"writing summary.json, closed_loop.npz and {figure.name} to {args.out}"):
        (args.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        result.loop.save(args.out / "closed_loop.npz")
        plot(result, figure, three_level.PARAMS,
             title=f"Three-level inverter, LinearTracking, N = {args.horizon}, $\\lambda_u$ = {lambda_u:g} A$^2$: "
                   f"{summary['switching_frequency_hz'] / 1e3:.2f} kHz per leg")
    print(f"inverter --levels 3 N={args.horizon} lambda_u={lambda_u:g}: THD {summary['thd'] * 100:.2f} %, "
          f"switching {summary['switching_frequency_hz']:.0f} Hz per leg, rms error "
          f"{summary['rms_tracking_error']:.3f} A, nodes/step {summary['nodes_mean']:,.0f} mean / "
          f"{summary['nodes_max']:,} max, {summary['solve_time_median_s'] * 1e3:.3f} ms median / "
          f"{summary['solve_time_max_s'] * 1e3:.2f} ms max")
    print(f"wrote {args.out / 'summary.json'}, {figure} and {args.out / 'closed_loop.npz'}")
    return 0
