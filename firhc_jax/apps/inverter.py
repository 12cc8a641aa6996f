"""``python -m firhc_jax inverter``: FCS-MPC current control of a two-level inverter feeding an RL load.

Runs the FIRHC closed loop (8 switch states, a sinusoidal reference passed as
per-step parameters, a switching penalty on the previous input) for whole
fundamental cycles from steady state, timing every decision, and writes into
``--out``:

* ``summary.json``: tracking error, fundamental amplitude, THD, switching
  frequency, nodes and solve times (keys listed in ``summarize``);
* ``inverter_N<N>_<solver>.png``: phase currents against their references
  (up to three cycles) and the spectrum of phase a with its THD;
* ``closed_loop.npz``: the whole run (``fj.ClosedLoop.load`` reads it).

The plant is the exact (zero-order hold) RL response; the prediction model is
exact too unless ``--model euler``.
"""
from __future__ import annotations

import functools
import json
import math
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import firhc_jax as fj
from firhc_jax.models import inverter as model
from firhc_jax.models.three_level import MAX_HORIZON as THREE_LEVEL_MAX_HORIZON

from ._args import number, output_dir
from ._limits import exhaustive_run
from ._status import stage
from ._timing import timed_closed_loop

MAX_HORIZON = 8  # 8^8 sequences; exhaustive search is already slow there
MAX_CYCLES = 100.0  # 80,000 decisions
# Exhaustive search costs about 26 ns a node here (N = 5: 0.98 ms for 37,448 nodes, shared 2-core CPU).
EXHAUSTIVE_BUDGET = 1e10


class InverterRun(NamedTuple):
    """One closed-loop run of T steps."""

    loop: fj.ClosedLoop  # the controller's record (states: alpha-beta load currents i(0) .. i(T), A)
    references: np.ndarray  # [T+1, 2] alpha-beta reference at the same instants, A
    compile_time: float  # s tracing and compilation of one decision (NaN: not timed)

    @property
    def currents(self) -> np.ndarray:
        """[T+1, 2] alpha-beta load currents, A."""
        return np.asarray(self.loop.states)

    @property
    def inputs(self) -> np.ndarray:
        """[T, 3] applied leg states (0/1)."""
        return np.asarray(self.loop.inputs)

    @property
    def predicted_costs(self) -> np.ndarray:
        """[T] optimal cost of each decision, A^2."""
        return np.asarray(self.loop.predicted_costs)

    @property
    def nodes(self) -> np.ndarray:
        """[T] nodes per decision."""
        return np.asarray(self.loop.nodes)

    @property
    def solve_times(self) -> np.ndarray:
        """[T] s wall time of each decision (compiled, compilation excluded)."""
        return np.asarray(self.loop.solve_times)


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
                                               progress=progress)
    else:
        loop, compile_time = ctrl.simulate(i0, steps, plant, params=p, u0=u0, dt=params.ts, progress=progress), math.nan
    return InverterRun(loop, model.reference(params, loop.times), compile_time)


@functools.lru_cache(maxsize=None)
def _plant(params: model.InverterParams):
    """The exact RL plant for the closed loop, ``plant(i, u, p)`` (it passes ``p`` to the plant too), jitted
    once per parameters."""
    rl = model.make_plant(params)
    return jax.jit(lambda i, u, p: rl(i, u))


def spectrum(signal: np.ndarray, ts: float) -> tuple[np.ndarray, np.ndarray]:
    """One-sided amplitude spectrum ``(f [Hz], |X| [A peak])``; free of leakage over whole fundamental cycles."""
    n = signal.shape[0]
    amp = np.abs(np.fft.rfft(signal)) * 2.0 / n
    amp[0] /= 2.0
    return np.fft.rfftfreq(n, ts), amp


def distortion(signal: np.ndarray, params: model.InverterParams) -> tuple[float, float]:
    """``(fundamental peak amplitude (A), THD)`` of a record sampled at ``params.ts``.

    The fundamental is the least-squares fit of dc + cos + sin at the reference
    frequency; THD is the rms of what the fit leaves over the rms of the
    fundamental. Over whole cycles this is the DFT definition with every
    non-fundamental bin up to the Nyquist frequency counted (harmonics and the
    inter-harmonics of the variable switching pattern), dc excluded; unlike
    the DFT it stays meaningful for records of part of a cycle.
    """
    w = 2.0 * np.pi * params.frequency * params.ts * np.arange(signal.shape[0])
    basis = np.stack([np.ones_like(w), np.cos(w), np.sin(w)], axis=1)  # [T, 3]
    coef, *_ = np.linalg.lstsq(basis, signal, rcond=None)
    amplitude = float(np.hypot(coef[1], coef[2]))
    residual = signal - basis @ coef
    return amplitude, float(np.sqrt(np.mean(residual**2)) / (amplitude / np.sqrt(2.0)))


def summarize(run: InverterRun, horizon: int, solver: str, lambda_u: float, params: model.InverterParams,
              method: str = "exact", levels: int = 2) -> dict:
    """The ``summary.json`` record of a run (currents in A, times in s, frequencies in Hz)."""
    steps = run.inputs.shape[0]
    seconds = steps * params.ts
    phases = model.to_phases(run.currents[:-1])  # [T, 3], one record of whole cycles
    errors = model.to_phases(run.references - run.currents)  # [T+1, 3]
    fundamentals, thds = zip(*(distortion(phases[:, x], params) for x in range(3)), strict=True)
    changes = np.abs(np.diff(run.inputs, axis=0)).sum(axis=0)  # [3] leg changes within the run
    return {
        "rms_tracking_error": float(np.sqrt(np.mean(errors**2))),
        "current_amplitude": float(np.mean(fundamentals)),
        "switching_frequency_hz": float(changes.mean() / (2.0 * seconds)),
        "solve_time_median_s": float(np.median(run.solve_times)),
        "nodes_mean": float(run.nodes.mean()),
        "nodes_max": int(run.nodes.max()),
        "horizon": horizon,
        "solver": solver,
        "thd": float(np.mean(thds)),
        "thd_phases": list(thds),
        "current_amplitudes": list(fundamentals),
        "reference_amplitude": params.amplitude,
        "leg_changes": changes.astype(int).tolist(),
        "lambda_u": lambda_u,
        "model": method,
        "levels": levels,
        "nodes_min": int(run.nodes.min()),
        "exhaustive_nodes_per_step": (8 ** (horizon + 1) - 8) // 7,
        "solve_time_mean_s": float(run.solve_times.mean()),
        "solve_time_max_s": float(run.solve_times.max()),
        "compile_time_s": run.compile_time,
        "predicted_cost_mean": float(run.predicted_costs.mean()),
        "steps": steps,
        "seconds": seconds,
        "parameters": {"vdc": params.vdc, "r": params.r, "l": params.l, "ts": params.ts,
                       "amplitude": params.amplitude, "frequency": params.frequency},
    }


def plot(run: InverterRun, path: Path, params: model.InverterParams, title: str = "") -> None:
    """Phase currents against references (at most three cycles) and the spectrum of phase a with its THD."""

    from ._plot import subplots

    shown = min(run.currents.shape[0], 3 * params.steps_per_cycle + 1)
    t = np.arange(shown) * params.ts * 1e3  # ms
    currents, refs = model.to_phases(run.currents[:shown]), model.to_phases(run.references[:shown])
    fig, (ax_i, ax_s) = subplots(2, 1, figsize=(9, 7), gridspec_kw={"height_ratios": [3, 2]})
    for x, (name, c) in enumerate(zip("abc", ("tab:blue", "tab:orange", "tab:green"), strict=True)):
        ax_i.plot(t, currents[:, x], color=c, lw=0.8, label=f"$i_{name}$")
        ax_i.plot(t, refs[:, x], color="k", ls="--", lw=0.6)
    ax_i.plot([], [], color="k", ls="--", lw=0.6, label="reference")
    ax_i.set_xlabel("time [ms]")
    ax_i.set_ylabel("phase current [A]")
    ax_i.legend(loc="upper right", ncol=4, fontsize=8)
    ax_i.set_title(title)
    phase_a = model.to_phases(run.currents[:-1])[:, 0]
    whole = phase_a.shape[0] // params.steps_per_cycle * params.steps_per_cycle  # spectrum over whole cycles
    f, amp = spectrum(phase_a[:whole or None], params.ts)
    fundamental, thd = distortion(phase_a, params)
    ax_s.semilogy(f[1:] * 1e-3, np.maximum(amp[1:] / fundamental * 100.0, 1e-4), color="tab:blue", lw=0.7)
    ax_s.set_ylim(1e-3, 200)
    ax_s.set_xlim(0, f[-1] * 1e-3)
    ax_s.set_xlabel("frequency [kHz]")
    ax_s.set_ylabel("$|I_a(f)|$ [% of fundamental]")
    ax_s.set_title(f"phase a: fundamental {fundamental:.3f} A, THD {thd * 100:.2f} %", fontsize=10)
    for ax in (ax_i, ax_s):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def register(subparsers) -> None:
    """Add the ``inverter`` subcommand."""
    p = subparsers.add_parser(
        "inverter", help="current control of a two-level three-phase inverter, 8 switch states (FCS-MPC)",
        description="FIRHC current control of a two-level voltage source inverter feeding an RL load "
                    "(520 V, 10 ohm, 10 mH, Ts = 25 us, 10 A at 50 Hz); writes summary.json and a figure.")
    p.add_argument("--horizon", "-N", type=number(int, 1, THREE_LEVEL_MAX_HORIZON), default=3,
                   help=f"prediction horizon N (1-{MAX_HORIZON} with --levels 2, 1-{THREE_LEVEL_MAX_HORIZON} "
                        "with 3; default 3)")
    p.add_argument("--solver", choices=("sdfs", "exhaustive"), default="sdfs",
                   help="search (default sdfs); exhaustive visits 8+...+8^N nodes per step")
    p.add_argument("--out", type=output_dir, default="out/inverter", help="output folder (default out/inverter)")
    p.add_argument("--cycles", type=number(float, 0, low_open=True, high=MAX_CYCLES), default=2.0,
                   help=f"simulated fundamental cycles of 20 ms, rounded down to whole samples (default 2, at "
                        f"most {MAX_CYCLES:g})")
    p.add_argument("--lambda-u", type=number(float, 0), default=None,
                   help="switching penalty in A^2 per leg change, charged against the previous input "
                        "(default 1; 0.1 per unit leg step with --levels 3)")
    p.add_argument("--bound", action="store_true", help="sDFS with the admissible lower bound (docs/bounds.md)")
    p.add_argument("--levels", type=int, choices=(2, 3), default=2,
                   help="inverter levels: 2, the two-level inverter (8 switch states, default); 3, the three-level "
                        "inverter (27 states) on fj.LinearTracking (docs/inverter.md)")
    p.add_argument("--model", choices=model.DISCRETISATIONS, default="exact",
                   help="prediction model: exact zero-order hold (default) or forward Euler; the plant is exact")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run, check=functools.partial(_check, p))


def _check(parser, args) -> None:
    """The horizon of the chosen inverter, two samples at least, and a two-level run's exhaustive searches
    within ``EXHAUSTIVE_BUDGET`` nodes."""
    params = model.InverterParams()  # the three-level inverter samples at the same rate
    steps = int(args.cycles * params.steps_per_cycle)
    if steps < 2:
        parser.error(f"--cycles must cover at least two samples, got {args.cycles:g}")
    if args.levels == 2 and args.horizon > MAX_HORIZON:
        parser.error(f"--horizon must be between 1 and {MAX_HORIZON} with --levels 2, got {args.horizon}")
    if args.levels == 2 and args.solver == "exhaustive":
        exhaustive_run(parser, steps, len(model.SWITCH_STATES), args.horizon, EXHAUSTIVE_BUDGET,
                       "about 4 minutes at 26 ns a node", "lower --horizon or --cycles, or use --solver sdfs")


def run(args) -> int:
    """Run the experiment described by the parsed ``args``; returns the exit status (0)."""
    if args.levels == 3:
        from .inverter_three_level import run as run_three_level

        return run_three_level(args)
    args.lambda_u = 1.0 if args.lambda_u is None else args.lambda_u
    jax.config.update("jax_enable_x64", True)
    params = model.InverterParams()
    steps = int(args.cycles * params.steps_per_cycle)
    args.out.mkdir(parents=True, exist_ok=True)
    result = closed_loop(args.horizon, args.solver, steps, args.lambda_u, params, args.model,
                         progress=not args.no_progress, bound=args.bound)
    summary = summarize(result, args.horizon, args.solver, args.lambda_u, params, args.model, args.levels)
    figure = args.out / f"inverter_N{args.horizon}_{args.solver}.png"
    with stage(f"writing summary.json, closed_loop.npz and {figure.name} to {args.out}"):
        (args.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        result.loop.save(args.out / "closed_loop.npz")
        plot(result, figure, params,
             title=f"Inverter FIRHC, N = {args.horizon}, {args.solver}, $\\lambda_u$ = {args.lambda_u:g} A$^2$: "
                   f"rms error {summary['rms_tracking_error']:.3f} A, "
                   f"{summary['switching_frequency_hz'] / 1e3:.2f} kHz per leg")
    print(f"inverter N={args.horizon} {args.solver} lambda_u={args.lambda_u:g}: rms tracking error "
          f"{summary['rms_tracking_error']:.4f} A, amplitude {summary['current_amplitude']:.4f} A, "
          f"THD {summary['thd'] * 100:.2f} %, switching {summary['switching_frequency_hz']:.0f} Hz per leg, "
          f"nodes/step {summary['nodes_mean']:.1f} mean / {summary['nodes_max']} max, "
          f"{summary['solve_time_median_s'] * 1e3:.3f} ms/step median")
    print(f"wrote {args.out / 'summary.json'}, {figure} and {args.out / 'closed_loop.npz'}")
    return 0
