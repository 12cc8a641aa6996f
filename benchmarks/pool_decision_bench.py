"""One decision on several lanes: ``FIRHC(solver="pool", lanes=L)`` against ``solver="sdfs"``.

The work pool as a controller's solver: the root on one slot, the other
slots steal nodes of the same search, so each iteration expands up to
``L * K * M`` children in one call. Timed as a controller runs: the closed
loop of ``simulate(..., compiled=False)``, every decision its own compiled
call, timed in ``solve_times`` (compilation never counted). Every variant
runs the same closed loop (the decisions' costs are checked equal), in
rounds that alternate the variants, in one process; the table gives the
median over rounds of each variant's mean time per decision.

    python benchmarks/pool_decision_bench.py [--rounds 3] [--lanes 1,2,4,8]
"""
from __future__ import annotations

import argparse
import statistics

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import firhc_jax as fj  # noqa: E402
from firhc_jax.models import inverter as two_level  # noqa: E402
from firhc_jax.models import tanks, three_level  # noqa: E402


def inverter_case(horizon: int = 10, steps: int = 100):
    """The three-level inverter's current control (LinearTracking, 27 inputs in 19 classes)."""
    lt = three_level.make_problem(horizon)
    params = lt.params(jnp.asarray(two_level.horizon_references(three_level.PARAMS, steps, horizon)))
    A, B = (jnp.asarray(a) for a in three_level.model())
    plant = jax.jit(lambda i, u, p: A @ i + B @ u)
    x0 = jnp.asarray(two_level.initial_currents(three_level.PARAMS))
    options = dict(observe=lt.observe, warm_start=True, pop_width=three_level.pop_width(horizon))
    return "three-level inverter N=%d" % horizon, lt.problem, options, dict(x0=x0, steps=steps, plant=plant,
                                                                              params=params, u0=jnp.zeros(3))


def tanks_case(horizon: int = 5, steps: int = 100):
    """The three tanks, 17 valve/pump modes."""
    problem = tanks.make_problem(horizon)
    x0 = jnp.asarray(tanks.initial_state())
    return "three tanks N=%d" % horizon, problem, {}, dict(x0=x0, steps=steps, plant=jax.jit(problem.dynamics))


def measure(case, lanes, rounds: int) -> list[dict]:
    name, problem, options, run = case
    variants = {"sdfs": fj.FIRHC(problem, **options)}
    for L in lanes:
        variants[f"pool lanes={L}"] = fj.FIRHC(problem, "pool", lanes=L, **options)
    times = {v: [] for v in variants}
    loops = {}
    for _ in range(rounds + 1):  # the first round compiles
        for v, ctrl in variants.items():
            loop = ctrl.simulate(run["x0"], run["steps"], run["plant"], params=run.get("params"), u0=run.get("u0"),
                                 compiled=False)
            times[v].append(float(np.mean(np.asarray(loop.solve_times))))
            loops[v] = loop
    ref = loops["sdfs"]
    rows = []
    for v, loop in loops.items():
        np.testing.assert_allclose(np.asarray(loop.predicted_costs), np.asarray(ref.predicted_costs), rtol=1e-9)
        t = statistics.median(times[v][1:])
        rows.append({"case": name, "solver": v, "ms": 1e3 * t, "nodes": float(np.mean(np.asarray(loop.nodes))),
                     "ratio": t / statistics.median(times["sdfs"][1:])})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--lanes", default="1,2,4,8")
    ap.add_argument("--steps", type=int, default=100)
    args = ap.parse_args()
    lanes = [int(v) for v in args.lanes.split(",")]
    print(f"jax {jax.__version__}, {jax.devices()[0].platform}; mean time per decision, median of "
          f"{args.rounds} rounds (same closed loop, costs checked equal)")
    print("| case | solver | ms / decision | nodes / decision | time vs sdfs |")
    print("|---|---|---|---|---|")
    for case in (inverter_case(10, args.steps), tanks_case(5, args.steps)):
        for r in measure(case, lanes, args.rounds):
            print(f"| {r['case']} | {r['solver']} | {r['ms']:.3f} | {r['nodes']:.0f} | {r['ratio']:.2f}x |")


if __name__ == "__main__":
    main()
