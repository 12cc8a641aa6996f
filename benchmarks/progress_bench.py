"""What the automatic progress bar costs: every long call's default (``progress=None``) against no bar
(``progress=False``), on short calls and on a long one, interleaved in one process.

Short calls (well under the 2 s after which an automatic bar appears) must cost what they cost without a bar:
the ratio of medians None / False is the figure of merit. Each row alternates the two settings ``--rounds``
times after one warm-up call of each (compiled before timing). The long calls (``--long-steps`` steps of the
inverter's closed loop at N = 6, which runs in chunks under the automatic bar once its last run was timed
long; ``--long-rows`` rows of the three-level inverter at N = 10 through ``fj.solve_batch``, which runs as one
program under a bar of the time elapsed and expected) are compared with ``progress=False`` the same way, after
a first call each: the first ``None`` call after a long one is timed apart (it compiles the chunk's program
where the call runs in chunks). Bars go to a discarded stream.

    python benchmarks/progress_bench.py [--rounds 61] [--long-steps 40000] [--long-rows 8192] [--long-rounds 3]
        [--skip-long] [--publish]
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
from firhc_jax.models import inverter, three_level


def inverter_loop(N: int, T: int):
    """``(ctrl, plant, x0, u0, params)``: the two-level inverter's closed loop at horizon N for T steps."""
    prm = inverter.InverterParams()
    mem = inverter.make_problem(N, prm)
    params = {"ref": jnp.asarray(inverter.horizon_references(prm, T, N)), "lambda_u": jnp.ones(T)}
    rl = inverter.make_plant(prm)
    plant = jax.jit(lambda i, u, p: rl(i, u))
    return (fj.FIRHC(mem.problem, observe=mem.observe), plant, jnp.asarray(inverter.initial_currents(prm)),
            jnp.zeros(3), params)


def inverter_rows(B: int):
    """``call(progress)``: ``fj.solve_batch`` over ``B`` three-level inverter states at N = 10 (the work pool, 256
    lanes)."""
    N = 10
    lt = three_level.make_problem(N, lambda_u=0.1)
    rng = np.random.default_rng(0)
    phase = rng.uniform(0, 1 / three_level.PARAMS.frequency, B)
    X = inverter.reference(three_level.PARAMS, phase) + rng.uniform(-1.0, 1.0, (B, 2))
    U = three_level.SWITCH_STATES[rng.integers(0, 27, B)]
    t = phase[:, None] + np.arange(1, N + 1) * three_level.PARAMS.ts
    Z = jax.vmap(lt.observe)(jnp.asarray(X), jnp.asarray(U))
    P = lt.params(inverter.reference(three_level.PARAMS, t))
    return lambda p: fj.solve_batch(lt.problem, Z, params=P, lanes=256, progress=p).cost


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


def compare(fn, rounds: int, first=None) -> tuple[float, float]:
    """Median seconds of ``fn(False)`` and ``fn(None)``, alternated ``rounds`` times after a warm-up call each
    (``first``: a list that gets the warm-up ``None`` call's seconds)."""
    timed(fn, False)
    warm = timed(fn, None)
    if first is not None:
        first.append(warm)
    times = {False: [], None: []}
    for _ in range(rounds):
        for setting in (False, None):
            times[setting].append(timed(fn, setting))
    return statistics.median(times[False]), statistics.median(times[None])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=61)
    ap.add_argument("--long-steps", type=int, default=40_000)
    ap.add_argument("--long-rows", type=int, default=8192)
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
    long_calls = {
        f"`simulate`, inverter N = 6, {T:,} steps (None: in chunks)":
            lambda p: ctrl.simulate(x0, T, plant, params=params, u0=u0, progress=p).states,
        f"`solve_batch`, {args.long_rows:,} three-level inverter rows, N = 10 (None: one program)":
            inverter_rows(args.long_rows)}
    print(f"\n## Long calls ({args.long_rounds} rounds after a first call of each)\n")
    print("| call | False s | None s | None / False | the first None call after a long one (s) |")
    print("|---|---:|---:|---:|---:|")
    for name, run in long_calls.items():
        first = []
        with contextlib.redirect_stderr(io.StringIO()):
            off, auto = compare(run, args.long_rounds, first)
        print(f"| {name} | {off:.2f} | {auto:.2f} | {auto / off:.3f}x | {first[0]:.2f} |", flush=True)
    print(f"\nload at the end: {os.getloadavg()[0]:.1f}", file=sys.stdout)


if __name__ == "__main__":
    main()
