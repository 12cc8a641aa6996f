"""Eager real-time decision against the same decision inside ``simulate`` (issue 22).

The two-level inverter of ``firhc_jax.models.inverter`` (N = 3, 8 switch
states, switching penalty through ``observe``, a new reference every step as
parameters), float64, one process. Three ways to take the decision at each
sample, timed per decision (the plant step is not timed):

* loop: ``simulate(..., params=..., compiled=False)``'s ``solve_times``.
* step: ``u, state, info = ctrl.step(state, x, p)`` from the user's Python
  loop (the real-time path; the row is absent before ``step`` existed).
* eager: ``ctrl(observe(x, u_prev, p), p)`` on a controller of the model
  problem, what a real-time loop had to write before ``step``.

The three rows are interleaved in rounds so that a noisy neighbour hits them
alike; the ratio of medians is the figure of merit (contract: step <= 1.3x
loop).

A second table times a compiled ``simulate`` of ``--progress-steps`` cheap
steps (N = 2, 3 inputs) with and without ``progress=True`` (issue 24: a host
callback per step made it 23x slower).

    python benchmarks/step_bench.py [--steps 300] [--rounds 3] [--horizon 3] [--progress-steps 100000]
"""
from __future__ import annotations

import argparse
import platform
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

import firhc_jax as fj
from firhc_jax.models import inverter


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=300, help="decisions per round and row")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--horizon", type=int, default=3)
    ap.add_argument("--progress-steps", type=int, default=100_000)
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    prm, N, T = inverter.InverterParams(), args.horizon, args.steps
    mem = inverter.make_problem(N, prm)
    refs = inverter.horizon_references(prm, T, N)  # [T, N, 2]
    params = {"ref": jnp.asarray(refs), "lambda_u": jnp.ones(T)}
    rows = [{"ref": jnp.asarray(refs[k]), "lambda_u": jnp.asarray(1.0, jnp.float64)} for k in range(T)]
    rl = jax.jit(inverter.make_plant(prm))
    plant = jax.jit(lambda i, u, p: rl(i, u))
    x0, u0 = jnp.asarray(inverter.initial_currents(prm)), jnp.zeros(3)
    ctrl = fj.FIRHC(mem.problem, observe=mem.observe)
    model_ctrl = fj.FIRHC(mem.problem)

    def loop():
        return list(np.asarray(ctrl.simulate(x0, T, plant, params=params, u0=u0, compiled=False).solve_times))

    def step():
        state, x, times = ctrl.init(x0, u0), x0, []
        for k in range(T):
            t0 = time.perf_counter()
            u, state, info = ctrl.step(state, x, rows[k])
            jax.block_until_ready(u)
            times.append(time.perf_counter() - t0)
            x = plant(x, u, rows[k])
        return times

    def eager():
        x, u_prev, times = x0, u0, []
        for k in range(T):
            t0 = time.perf_counter()
            out = model_ctrl(mem.observe(x, u_prev, rows[k]), rows[k])
            u = jax.block_until_ready(out[0])
            times.append(time.perf_counter() - t0)
            x, u_prev = plant(x, u, rows[k]), u
        return times

    ways = {"`simulate(..., compiled=False)` solve_times": loop}
    if hasattr(ctrl, "step"):
        ways["`ctrl.step(state, x, p)`, eager"] = step
    ways["`ctrl(observe(x, u, p), p)`, eager"] = eager
    for fn in ways.values():  # compile and warm up
        fn()
    times = {name: [] for name in ways}
    for _ in range(args.rounds):
        for name, fn in ways.items():
            times[name] += fn()

    print(f"# One decision per sample: inverter N = {N}, {platform.machine()}, {jax.devices()[0].platform}, "
          f"jax {jax.__version__}, {args.rounds} x {T} decisions per row\n")
    print("| how the decision is taken | decisions | median us | mean us | p90 us |")
    print("|---|---:|---:|---:|---:|")
    for name, ts in times.items():
        us = 1e6 * np.asarray(ts)
        print(f"| {name} | {len(us)} | {statistics.median(us):.1f} | {us.mean():.1f} | "
              f"{np.percentile(us, 90):.1f} |")
    base = statistics.median(times["`simulate(..., compiled=False)` solve_times"])
    for name, ts in times.items():
        print(f"\n{name} / loop (medians): {statistics.median(ts) / base:.2f}x", end="")
    print()
    progress_table(args.progress_steps, args.rounds)


def progress_table(steps: int, rounds: int):
    """Compiled closed loop of cheap steps with and without a progress bar (drawn on stderr), interleaved."""
    from firhc_jax import progress

    prob = fj.Problem(lambda x, u: 0.9 * x + 0.1 * u, jnp.array([-1.0, 0.0, 1.0]), fj.quadratic_cost(1.0, 0.0), 2)
    ctrl, x0 = fj.FIRHC(prob), jnp.ones(1)

    def run(on):
        t0 = time.perf_counter()
        jax.block_until_ready(ctrl.simulate(x0, steps, progress=on).states)
        return time.perf_counter() - t0

    run(False), run(True)  # compile both
    times = {False: [], True: []}
    for _ in range(rounds):
        for on in (False, True):
            times[on].append(run(on))
    off, on = statistics.median(times[False]), statistics.median(times[True])
    print(f"\n# Compiled simulate of {steps:,} cheap steps (N = 2, M = 3), median of {rounds}\n")
    print("| progress | s per run | us per step |")
    print("|---|---:|---:|")
    for name, t in (("off", off), ("on", on)):
        print(f"| {name} | {t:.3f} | {1e6 * t / steps:.2f} |")
    every = progress.interval(steps) if hasattr(progress, "interval") else 1  # 1: before issue 24
    print(f"\nprogress on / off: {on / off:.3f}x ({every} steps per bar update)")


if __name__ == "__main__":
    main()
