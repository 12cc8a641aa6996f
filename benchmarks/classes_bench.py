"""When do LinearTracking's classes of inputs win? Three- and five-level inverters, closed-loop scans against the
plain problem of every switch state.

The plants: ``firhc_jax.models.three_level``'s RL load and circuit with legs of 3 levels ({-1, 0, 1}: 27 switch
states in 19 classes of up to 3 inputs of equal voltage) or 5 levels ({-2, ..., 2}, each Vdc / 4: 125 switch
states in 61 classes of up to 5). J: the current error plus lambda_u per unit leg step (``norm="abs"``, the
count of leg changes), no leg stepping by more than one level (max_step = 1). Per N: the closed loop as one
compiled ``FIRHC.simulate`` with ``LinearTracking.problem`` (a node per class, the cost-to-go bound) and with
the plain problem (a node per switch state, state [i, u, u - u_prev], no bound: ``sphere_bench.plain_problem``),
both warm-started with their previous plan, compiled first, then timed in alternating rounds (the fastest
round of each is kept). Columns: nodes a decision, microseconds a step, nanoseconds a node; the ratios of
nodes (plain / ours), of a node's cost (ours / plain) and of time (plain / ours: above 1, the classes win).

    python benchmarks/classes_bench.py [--levels 3 5] [--horizons 1 3 5 8] [--steps 800] [--rounds 3] [--publish]
"""
from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
from _results import machine, published
from sphere_bench import plain_problem

import firhc_jax as fj
from firhc_jax.models import inverter, three_level


def tracker(levels: int, N: int, lambda_u: float) -> fj.LinearTracking:
    """The inverter with legs of ``levels`` levels (odd): u_x in {-h .. h}, h = (levels - 1) / 2, applies
    Vdc / 2 * u_x / h."""
    h = (levels - 1) // 2
    A, B = three_level.model()
    controls = fj.product_controls(np.arange(-h, h + 1.0), repeat=3)
    return fj.LinearTracking(A, B / h, controls, N, lambda_u=lambda_u, max_step=1.0, norm="abs")


def loops(lt: fj.LinearTracking, steps: int):
    """``{name: run()}``: the two closed loops from the reference at t = 0, each a call of a compiled scan."""
    refs = jnp.asarray(inverter.horizon_references(three_level.PARAMS, steps, lt.horizon))
    x0, u0 = jnp.asarray(inverter.reference(three_level.PARAMS, 0.0)), jnp.zeros(3)
    A, B = jnp.asarray(lt.A), jnp.asarray(lt.B)

    def plant(x, u, p):
        return A @ x + B @ u

    ours = fj.FIRHC(lt.problem, observe=lt.observe, warm_start=True)
    plain, plain_observe = plain_problem(lt)
    theirs = fj.FIRHC(plain, observe=lambda x, u, p=None: plain_observe(x, u), warm_start=True)
    ours_params = lt.params(refs)
    plain_params = {"y_ref": refs, "d": jnp.zeros(refs.shape)}  # max_step = 1 makes L1 = squared for the plain one
    return {"LinearTracking": lambda: ours.simulate(x0, steps, plant, params=ours_params, u0=u0),
            "plain": lambda: theirs.simulate(x0, steps, plant, params=plain_params, u0=u0)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--levels", type=int, nargs="+", default=[3, 5])
    ap.add_argument("--horizons", type=int, nargs="+", default=[1, 3, 5, 8])
    ap.add_argument("--steps", type=int, default=800, help="decisions (one fundamental period = 800)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--lambda-u", type=float, default=0.1)
    ap.add_argument("--publish", action="store_true", help="also write the table to benchmarks/results/classes.md")
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    with published("classes", args.publish, "python benchmarks/classes_bench.py --publish"):
        run(args)


def run(args):
    print(f"classes_bench: {machine()}, float64, lambda_u = {args.lambda_u}, {args.steps} decisions, fastest of "
          f"{args.rounds} rounds\n")
    print(f"{'levels':>6} {'N':>3} {'classes':>9} {'nodes ours':>10} {'plain':>9} {'us/step ours':>12} {'plain':>8} "
          f"{'ns/node ours':>12} {'plain':>7} {'nodes p/o':>9} {'ns/node o/p':>11} {'time p/o':>8}")
    for levels in args.levels:
        for N in args.horizons:
            lt = tracker(levels, N, args.lambda_u)
            runs = loops(lt, args.steps)
            nodes, costs, best = {}, {}, {name: np.inf for name in runs}
            for name, run in runs.items():  # compile
                out = jax.block_until_ready(run())
                nodes[name], costs[name] = np.asarray(out.nodes).mean(), np.asarray(out.stage_costs).sum()
            for _ in range(args.rounds):
                for name, run in runs.items():
                    t0 = time.perf_counter()
                    jax.block_until_ready(run())
                    best[name] = min(best[name], time.perf_counter() - t0)
            us = {name: 1e6 * s / args.steps for name, s in best.items()}
            ns = {name: 1e3 * us[name] / nodes[name] for name in runs}
            a, b = "LinearTracking", "plain"
            print(f"{levels:>6} {N:>3} {f'{lt.num_classes} of {lt.class_size}':>9} {nodes[a]:>10,.0f} "
                  f"{nodes[b]:>9,.0f} {us[a]:>12.1f} {us[b]:>8.1f} {ns[a]:>12.0f} {ns[b]:>7.0f} "
                  f"{nodes[b] / nodes[a]:>8.2f}x {ns[a] / ns[b]:>10.1f}x {us[b] / us[a]:>7.2f}x", flush=True)


if __name__ == "__main__":
    main()
