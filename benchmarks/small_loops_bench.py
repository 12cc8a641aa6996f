"""What ``fj.enable_small_loop_kernels()`` changes: single decisions and compiled closed loops against batches.

The opt-in is process-wide, so each setting runs in its own process (this script again, ``--child``), the two
alternated ``--rounds`` times; each row gives the median of its rounds and the ratio on / off. Rows: one
``jax.jit(fj.sdfs)`` search of the pendulum (2 states, 3 inputs) at N = 5 and 8; ``ctrl.step`` on the
two-level inverter at N = 3 (per-step reference, warm start); the step of ``simulate``'s compiled scan (same
controller, 200 steps); ``fj.solve_batch`` on 4,096 synthetic states (17 inputs, N = 4, rows/s); and
``simulate_batch`` of 64 inverter loops of 200 steps (loops/s). float64, every core.

    python benchmarks/small_loops_bench.py [--rounds 2] [--quick] [--publish]
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time

import numpy as np
from _results import published


def child(quick: bool) -> dict:
    """The timings of one process (the opt-in already made or not by ``main``)."""
    import jax
    import jax.numpy as jnp

    import firhc_jax as fj
    from firhc_jax.models import inverter
    from firhc_jax.models.synthetic import SyntheticParams, make_problem

    jax.config.update("jax_enable_x64", True)
    out = {}

    def pendulum(x, u):
        omega = x[1] + 0.05 * (-9.81 * jnp.sin(x[0]) - 0.5 * x[1] + 2.0 * u[0])
        return jnp.stack([x[0] + 0.05 * omega, omega])

    def per_call(fn, calls):
        jax.block_until_ready(fn())
        t0 = time.perf_counter()
        for _ in range(calls):
            jax.block_until_ready(fn())
        return (time.perf_counter() - t0) / calls

    search = jax.jit(fj.sdfs)
    x0 = jnp.array([0.6, 0.0])
    for N in (5, 8):
        problem = fj.Problem(pendulum, jnp.array([-1.0, 0.0, 1.0]),
                             fj.quadratic_cost(jnp.array([10.0, 1.0]), jnp.zeros(2), 0.1), N)
        calls = 50 if quick else 300
        out[f"jit(fj.sdfs), pendulum N = {N} (us)"] = 1e6 * per_call(lambda p=problem: search(p, x0), calls)
    mem = inverter.make_problem(3)
    ctrl = fj.FIRHC(mem.problem, observe=mem.observe, warm_start=True)
    steps = 40 if quick else 200
    refs = inverter.horizon_references(inverter.InverterParams(), steps, 3)
    p = {"ref": jnp.asarray(refs), "lambda_u": jnp.full((steps,), 0.1)}
    state, x = ctrl.init(jnp.array([1.0, -2.0])), jnp.array([1.0, -2.0])
    p0 = jax.tree_util.tree_map(lambda a: a[0], p)
    out["ctrl.step, inverter N = 3 (us)"] = 1e6 * per_call(lambda: ctrl.step(state, x, p0)[0], 50 if quick else 500)
    rl = inverter.make_plant()
    plant = jax.jit(lambda i, u, p: rl(i, u))  # the closed loop passes the step's params to the plant too
    ctrl.simulate(jnp.array([1.0, -2.0]), steps, plant, params=p, progress=False)
    t0 = time.perf_counter()
    jax.block_until_ready(ctrl.simulate(jnp.array([1.0, -2.0]), steps, plant, params=p, progress=False).states)
    out["simulate's compiled step, inverter N = 3 (us)"] = 1e6 * (time.perf_counter() - t0) / steps
    syn = make_problem(4, SyntheticParams(17))
    B = 512 if quick else 4096
    X = np.random.default_rng(0).uniform(-1, 1, (B, 3))
    fj.solve_batch(syn, X, progress=False)
    t0 = time.perf_counter()
    jax.block_until_ready(fj.solve_batch(syn, X, progress=False).cost)
    out[f"solve_batch, {B} synthetic states (rows/s)"] = B / (time.perf_counter() - t0)
    loops = 16 if quick else 64
    X0 = np.tile(np.array([[1.0, -2.0]]), (loops, 1))
    P = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (loops,) + a.shape), p)
    ctrl.simulate_batch(X0, steps, plant, params=P, progress=False)
    t0 = time.perf_counter()
    jax.block_until_ready(ctrl.simulate_batch(X0, steps, plant, params=P, progress=False).states)
    out[f"simulate_batch, {loops} inverter loops (loops/s)"] = loops / (time.perf_counter() - t0)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="smaller runs, one round")
    ap.add_argument("--publish", action="store_true", help="also write benchmarks/results/small_loops.md")
    ap.add_argument("--child", choices=("on", "off"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        if args.child == "on":
            import firhc_jax as fj

            fj.enable_small_loop_kernels()
        print(json.dumps(child(args.quick)))
        return
    with published("small_loops", args.publish, "python benchmarks/small_loops_bench.py --publish"):
        runs = {"off": [], "on": []}
        for _ in range(1 if args.quick else args.rounds):
            for setting in ("off", "on"):
                cmd = [sys.executable, __file__, "--child", setting] + (["--quick"] if args.quick else [])
                done = subprocess.run(cmd, capture_output=True, text=True, check=True)
                runs[setting].append(json.loads(done.stdout.strip().splitlines()[-1]))
        print("fj.enable_small_loop_kernels(): each setting in its own process, alternated; medians of "
              f"{len(runs['off'])} round(s), float64, every core.\n")
        print("| what | default | small loop kernels | on / off |")
        print("|---|---:|---:|---:|")
        for key in runs["off"][0]:
            off = statistics.median(r[key] for r in runs["off"])
            on = statistics.median(r[key] for r in runs["on"])
            print(f"| {key} | {off:,.1f} | {on:,.1f} | {on / off:.2f} |")


if __name__ == "__main__":
    main()
