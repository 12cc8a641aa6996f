"""``python -m firhc_jax tanks``: the three-tank experiment of the paper's Sec. IV.2.

Runs the FIRHC closed loop on the 17-mode three-tank plant from the paper's
initial levels {0.2, 0.18, 0.1} m to the set point {0.3, 0.25, 0.15} m for
200 s (100 samples of 2 s) with ``FIRHC.simulate``, timing every decision,
and writes into ``--out``:

* ``summary.json``: final levels, errors, settling time, nodes per step and
  solve times (keys listed in ``summarize``);
* ``tanks_N<N>_<solver>.png``: the three levels against their set points,
  their errors in mm, and the applied mode sequence beneath;
* ``closed_loop.npz``: the whole run (``fj.ClosedLoop.load`` reads it).

The plant is the prediction model itself (no model error), as in the paper.
"""
from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import firhc_jax as fj
from firhc_jax.models import tanks as model

from ..solvers import SOLVERS
from ._args import horizon_argument, number, solver_argument
from ._limits import exhaustive_run
from ._run import App
from ._timing import timed_closed_loop

MAX_HORIZON = 10  # 17^10 sequences: beyond this even sDFS's worst steps become impractical
MAX_SECONDS = 3600.0  # 1,800 decisions, 18 times the paper's run
# Exhaustive search costs about 0.47 us a node here (N = 5: 715 ms for 1,508,597 nodes, shared 2-core CPU).
EXHAUSTIVE_BUDGET = 5e8


def simulate(problem: fj.Problem, solver: str = "sdfs", steps: int = 100, levels=model.INITIAL_LEVELS,
             progress: bool = False, timed: bool = False,
             dt: float | None = None, settings=None) -> tuple[fj.ClosedLoop, float | None]:
    """Run the FIRHC law for ``steps`` samples from ``levels`` (hold mode before t = 0).

    The plant is the prediction model itself. Needs float64
    (``jax_enable_x64``) for mm-accurate levels. With a terminal box, steps
    where it cannot be reached apply the unconstrained optimum
    (``loop.used_fallback``). Returns ``(loop, compile_s)``. ``timed``: the
    decision is compiled first, ``compile_s`` seconds of tracing and
    compilation (``_timing.timed_closed_loop``), then run from Python with
    each decision's wall time in ``loop.solve_times``. Otherwise one compiled
    scan (the same closed loop) and ``compile_s`` is None. ``dt``: the
    sample time, for the loop's time axis. ``settings``: all that built
    ``problem``, for a timed run to keep its decision on disk
    (``_timing.timed_closed_loop``).
    """
    fallback = "unconstrained" if problem.terminal is not None else None
    ctrl = fj.FIRHC(problem, solver, fallback=fallback)
    x0 = jnp.asarray(model.initial_state(levels))  # [5]
    if not timed:
        return ctrl.simulate(x0, steps, progress=progress, dt=dt), None
    return timed_closed_loop(ctrl, x0, steps, jax.jit(problem.dynamics), progress=progress, dt=dt,
                             settings=None if settings is None else ("tanks", settings, solver))


def settling_time(errors: np.ndarray, ts: float, tolerance: float) -> float | None:
    """First time (s) from which every ``|error|`` stays within ``tolerance``;
    ``None`` if the last sample is still outside. ``errors`` ``[T+1, 3]``."""
    outside = np.flatnonzero(np.max(np.abs(errors), axis=1) > tolerance)
    if outside.size == 0:
        return 0.0
    if outside[-1] == errors.shape[0] - 1:
        return None
    return float((outside[-1] + 1) * ts)


def summarize(loop: fj.ClosedLoop, compile_s: float | None, problem, solver: str, params: model.TankParams,
              set_point=model.SET_POINT, tolerance: float = 0.005, switch_penalty: float = 0.0,
              terminal_tol: float | None = None) -> dict:
    """The ``summary.json`` record of a run (lengths in m, times in s). Nodes per step count the fallback
    search too; solve times are null for an untimed run."""
    levels = np.asarray(loop.states)[:, :3]  # [T+1, 3]
    errors = levels - np.asarray(set_point)  # [T+1, 3]
    t = np.arange(levels.shape[0]) * params.ts  # [T+1]
    last = t >= t[-1] - 20.0 - 1e-9
    nodes = np.asarray(loop.nodes) + np.asarray(loop.fallback_nodes)  # [T]
    times = np.asarray(loop.solve_times)  # [T], NaN in a compiled scan
    modes = np.asarray(loop.input_indices)  # [T]

    def stat(fn):
        return float(fn(times)) if np.all(np.isfinite(times)) else None

    return {
        "final_levels": levels[-1].tolist(),
        "max_abs_error_last_20s": float(np.max(np.abs(errors[last]))),
        "settling_time_s": settling_time(errors, params.ts, tolerance),
        "nodes_min": int(nodes.min()),
        "nodes_max": int(nodes.max()),
        "nodes_mean": float(nodes.mean()),
        "solve_time_mean_s": stat(np.mean),
        "horizon": problem.horizon,
        "solver": solver,
        "solve_time_median_s": stat(np.median),
        "solve_time_max_s": stat(np.max),
        "compile_time_s": compile_s,
        "exhaustive_nodes_per_step": problem.tree_size(),
        "settling_tolerance_m": tolerance,
        "set_point": list(set_point),
        "initial_levels": levels[0].tolist(),
        "seconds": float(t[-1]),
        "sample_time_s": params.ts,
        "switch_penalty": switch_penalty,
        "terminal_tol": terminal_tol,
        "fallback_steps": int(np.count_nonzero(loop.used_fallback)),
        "mode_changes": int(np.count_nonzero(np.diff(modes))),
        "modes": modes.tolist(),
    }


def plot(loop: fj.ClosedLoop, path: Path, params: model.TankParams, set_point=model.SET_POINT,
         tolerance: float = 0.005, title: str = "") -> None:
    """Levels against set points, errors in mm (with the tolerance band) and the mode sequence beneath."""

    from ._plot import subplots

    levels = np.asarray(loop.states)[:, :3]  # [T+1, 3]
    t = np.arange(levels.shape[0]) * params.ts  # [T+1]
    colors = ("tab:blue", "tab:orange", "tab:green")
    fig, (ax_h, ax_e, ax_m) = subplots(3, 1, figsize=(9, 9), sharex=True,
                                           gridspec_kw={"height_ratios": [3, 2, 3]})
    for i, c in enumerate(colors):
        ax_h.plot(t, levels[:, i], color=c, label=f"$h_{i + 1}$")
        ax_h.axhline(set_point[i], color=c, ls="--", lw=0.8)
        ax_e.plot(t, (levels[:, i] - set_point[i]) * 1e3, color=c, label=f"$h_{i + 1} - h_{{s,{i + 1}}}$")
    ax_h.set_ylabel("level [m]")
    ax_h.legend(loc="lower right", ncol=3)
    ax_h.set_title(title)
    ax_e.axhspan(-tolerance * 1e3, tolerance * 1e3, color="0.85", label=f"$\\pm${tolerance * 1e3:g} mm")
    ax_e.set_ylim(-20, 20)
    ax_e.set_ylabel("error [mm]")
    ax_e.legend(loc="lower right", ncol=4, fontsize=8)
    ax_m.step(t[:-1], np.asarray(loop.input_indices), where="post", color="k", lw=1)
    ax_m.set_yticks(range(model.NUM_MODES))
    ax_m.set_yticklabels([f"{i} {m.name}" for i, m in enumerate(model.MODES)], fontsize=6)
    ax_m.set_ylim(-0.5, model.NUM_MODES - 0.5)
    ax_m.set_ylabel("mode")
    ax_m.set_xlabel("time [s]")
    for ax in (ax_h, ax_e, ax_m):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


class TanksRun(NamedTuple):
    """One run of the command."""

    loop: fj.ClosedLoop
    compile_s: float  # s tracing and compilation of one decision
    problem: fj.Problem


class Tanks(App):
    name = "tanks"
    help = "three-tank system, 17 valve/pump modes (paper Sec. IV.2)"
    description = "FIRHC closed loop of the three-tank system from levels {0.2, 0.18, 0.1} m to {0.3, 0.25, 0.15} m."

    def add_arguments(self, p) -> None:
        solver_argument(p, "exhaustive visits 17+...+17^N nodes per step")
        horizon_argument(p, MAX_HORIZON, 4, "paper: 3-6")
        p.add_argument("--seconds", type=number(float, 0, low_open=True, high=MAX_SECONDS), default=200.0,
                       help=f"simulated time in s, rounded down to whole 2 s samples (default 200, at most "
                            f"{MAX_SECONDS:g})")
        p.add_argument("--switch-penalty", type=number(float, 0), default=0.0,
                       help="cost per actuator toggle, in mm^2 of level error (default 0)")
        p.add_argument("--terminal-tol", type=number(float, 0, low_open=True), default=None,
                       help="terminal box half-width in m around the set point (default: none); steps where "
                            "it cannot be reached apply the unconstrained optimum")
        p.add_argument("--bound", action="store_true", help="sDFS with the admissible lower bound "
                       "(docs/guide/bounds.md)")
        p.add_argument("--tolerance", type=number(float, 0, low_open=True), default=0.005,
                       help="settling band half-width in m (default 0.005)")

    def check(self, parser, args) -> None:
        """At least one sample; a run's exhaustive searches within ``EXHAUSTIVE_BUDGET`` nodes."""
        ts = model.TankParams().ts
        steps = int(args.seconds // ts)
        if steps < 1:
            parser.error(f"--seconds must be at least one sample ({ts:g} s), got {args.seconds:g}")
        if not SOLVERS[args.solver].prunes:  # it visits the whole tree: bound the run
            exhaustive_run(parser, steps, model.NUM_MODES, args.horizon, EXHAUSTIVE_BUDGET,
                           "about 4 minutes at 0.47 us a node", "lower --horizon or --seconds, or use --solver sdfs")

    def simulate(self, args) -> TanksRun:
        params = model.TankParams()
        problem = model.make_problem(args.horizon, params, switch_penalty=args.switch_penalty,
                                     terminal_tol=args.terminal_tol, bound=args.bound)
        loop, compile_s = simulate(problem, args.solver, int(args.seconds // params.ts),
                                   progress=not args.no_progress, timed=True, dt=params.ts,
                                   settings=(args.horizon, params, args.switch_penalty, args.terminal_tol, args.bound))
        return TanksRun(loop, compile_s, problem)

    def summarize(self, args, run: TanksRun) -> dict:
        return summarize(run.loop, run.compile_s, run.problem, args.solver, model.TankParams(),
                         tolerance=args.tolerance, switch_penalty=args.switch_penalty, terminal_tol=args.terminal_tol)

    def plot(self, args, run: TanksRun, summary: dict) -> list:
        figure = Path(args.out) / f"tanks_N{args.horizon}_{args.solver}.png"
        plot(run.loop, figure, model.TankParams(), tolerance=args.tolerance,
             title=f"Three-tank FIRHC, N = {args.horizon}, {args.solver}: nodes/step min {summary['nodes_min']}, "
                   f"mean {summary['nodes_mean']:.0f}, max {summary['nodes_max']}")
        return [figure]

    def report(self, args, summary: dict) -> str:
        settled = summary["settling_time_s"]
        return (f"tanks N={args.horizon} {args.solver}: final levels "
                f"{', '.join(f'{h:.4f}' for h in summary['final_levels'])} m, "
                f"settled {'never' if settled is None else f'at {settled:g} s'}, "
                f"max |error| last 20 s {summary['max_abs_error_last_20s'] * 1e3:.2f} mm, "
                f"nodes/step {summary['nodes_min']}/{summary['nodes_mean']:.0f}/{summary['nodes_max']} "
                f"(min/mean/max), {summary['solve_time_mean_s'] * 1e3:.2f} ms/step")


APP = Tanks()
register = APP.register
run = APP.run
