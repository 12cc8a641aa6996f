"""What the automatic progress bar costs: every long call's default (``progress=None``) against no bar
(``progress=False``), on short calls and on a long one, interleaved in one process.

Short calls (well under the 2 s after which an automatic bar appears) must cost what they cost without a bar:
the ratio of medians None / False is the figure of merit. Each row alternates the two settings ``--rounds``
times after one warm-up call of each (compiled before timing). The long call (``--long-steps`` steps of the
inverter at N = 6, a few seconds) runs in chunks under the automatic bar once its first run was timed long, and
is compared with the one-program run; its bar goes to a discarded stream.

    python benchmarks/progress_bench.py [--rounds 61] [--long-steps 40000] [--long-rounds 3] [--skip-long] [--publish]
"""
from __future__ import annotations

import argparse
import contextlib
import io
import os
import platform
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from _results import published

import firhc_jax as fj
from firhc_jax.models import inverter


def inverter_loop(N: int, T: int):
    """``(ctrl, plant, x0, u0, params)``: the two-level inverter's closed loop at horizon N for T steps."""
    prm = inverter.InverterParams()
    mem = inverter.make_problem(N, prm)
    params = {"ref": jnp.asarray(inverter.horizon_references(prm, T, N)), "lambda_u": jnp.ones(T)}
    rl = inverter.make_plant(prm)
    plant = jax.jit(lambda i, u, p: rl(i, u))
    return (fj.FIRHC(mem.problem, observe=mem.observe), plant, jnp.asarray(inverter.initial_currents(prm)),
            jnp.zeros(3), params)


def cases():
    """``{name: call(progress)}`` of short calls."""
    cheap = fj.Problem(lambda x, u: 0.9 * x + 0.1 * u, jnp.array([-1.0, 0.0, 1.0]), fj.quadratic_cost(1.0, 0.0), 2)
    ctrl, x1 = fj.FIRHC(cheap), jnp.ones(1)
    inv, plant, x0, u0, params = inverter_loop(3, 200)
    X = np.random.default_rng(0).uniform(-2, 2, (64, 1))
    wide = fj.Problem(lambda x, u: 0.9 * x + 0.1 * u, jnp.array([-1.0, 0.0, 1.0]), fj.quadratic_cost(1.0, 0.0), 6)
    return {
        "`simulate`, 40 cheap steps (N = 2, M = 3)": lambda p: ctrl.simulate(x1, 40, progress=p).states,
        "`simulate`, 2,000 cheap steps": lambda p: ctrl.simulate(x1, 2000, progress=p).states,
        "`simulate`, inverter N = 3, 200 steps": lambda p: inv.simulate(x0, 200, plant, params=params, u0=u0,
                                                                         progress=p).states,
        "`simulate(compiled=False)`, 40 cheap steps": lambda p: ctrl.simulate(x1, 40, progress=p,
                                                                              compiled=False).states,
        "`simulate_batch`, 8 loops x 20 cheap steps": lambda p: ctrl.simulate_batch(
            np.linspace(-1, 1, 8)[:, None], 20, progress=p).states,
        "`solve_batch`, 64 rows, N = 6": lambda p: fj.solve_batch(wide, X, progress=p).cost,
        "`fj.profile`, 4 states, N = 6, 3 settings": lambda p: fj.profile(wide, X[:4], pop_widths=(1,), lanes=(4,),
                                                                         repeats=1, progress=p),
    }


def timed(fn, setting) -> float:
    t0 = time.perf_counter()
    jax.block_until_ready(fn(setting))
    return time.perf_counter() - t0


def compare(fn, rounds: int) -> tuple[float, float]:
    """Median seconds of ``fn(False)`` and ``fn(None)``, alternated ``rounds`` times after a warm-up call each."""
    timed(fn, False), timed(fn, None)
    times = {False: [], None: []}
    for _ in range(rounds):
        for setting in (False, None):
            times[setting].append(timed(fn, setting))
    return statistics.median(times[False]), statistics.median(times[None])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=61)
    ap.add_argument("--long-steps", type=int, default=40_000)
    ap.add_argument("--long-rounds", type=int, default=3)
    ap.add_argument("--skip-long", action="store_true")
    ap.add_argument("--publish", action="store_true", help="also write the tables to benchmarks/results/progress.md")
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    with published("progress", args.publish, "python benchmarks/progress_bench.py --publish"):
        tables(args)


def tables(args):
    """Both tables, printed."""
    print(f"# {platform.machine()}, {os.cpu_count()} cores, jax {jax.__version__}, float64, load "
          f"{os.getloadavg()[0]:.1f}\n")
    print(f"## Short calls: `progress=False` against the default `progress=None` ({args.rounds} rounds)\n")
    print("| call | False ms | None ms | None / False |")
    print("|---|---:|---:|---:|")
    with contextlib.redirect_stderr(io.StringIO()):  # a bar, if one appeared, is not this table
        for name, fn in cases().items():
            off, auto = compare(fn, args.rounds)
            print(f"| {name} | {1e3 * off:.3f} | {1e3 * auto:.3f} | {auto / off:.3f}x |", flush=True)
    if args.skip_long:
        return
    T = args.long_steps
    ctrl, plant, x0, u0, params = inverter_loop(6, T)
    run = lambda p: ctrl.simulate(x0, T, plant, params=params, u0=u0, progress=p).states  # noqa: E731
    with contextlib.redirect_stderr(io.StringIO()):
        off, auto = compare(run, args.long_rounds)
    print(f"\n## A long call: inverter N = 6, {T:,} steps ({args.long_rounds} rounds; None runs in chunks "
          "under the bar)\n")
    print("| False s | None s | None / False |")
    print("|---:|---:|---:|")
    print(f"| {off:.2f} | {auto:.2f} | {auto / off:.3f}x |")
    print(f"\nload at the end: {os.getloadavg()[0]:.1f}", file=sys.stdout)


if __name__ == "__main__":
    main()
