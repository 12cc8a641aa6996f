"""One decision on several lanes: ``FIRHC(solver="pool", lanes=L)`` against ``solver="sdfs"``, each decided by
XLA and by the C engine (``engine="c"``).

The work pool as a controller's solver: the root on one slot, the other
slots steal nodes of the same search, so each iteration expands up to
``L * K * M`` children in one call. Timed as a controller runs: the closed
loop of ``simulate(..., compiled=False)``, every decision its own compiled
call (or, with ``engine="c"``, its own call of the generated C), timed in
``solve_times`` (compilation never counted). Every variant runs the same
closed loop (the decisions' costs are checked equal, the C engine's node
counts equal XLA's), in rounds that alternate the variants, in one process;
the table gives the median over rounds of each variant's mean time per
decision.

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
    solvers = {"sdfs": ("sdfs", {})}
    for L in lanes:
        solvers[f"pool lanes={L}"] = ("pool", {"lanes": L})
    variants = {(v, engine): fj.FIRHC(problem, solver, engine=engine, **extra, **options)
                for v, (solver, extra) in solvers.items() for engine in ("xla", "c")}
    times = {v: [] for v in variants}
    loops = {}
    for _ in range(rounds + 1):  # the first round compiles
        for v, ctrl in variants.items():
            loop = ctrl.simulate(run["x0"], run["steps"], run["plant"], params=run.get("params"), u0=run.get("u0"),
                                 compiled=False)
            times[v].append(float(np.mean(np.asarray(loop.solve_times))))
            loops[v] = loop
    ref = loops["sdfs", "xla"]
    rows = []
    for v in solvers:
        xla, c = loops[v, "xla"], loops[v, "c"]
        for loop in (xla, c):
            np.testing.assert_allclose(np.asarray(loop.predicted_costs), np.asarray(ref.predicted_costs), rtol=1e-9)
        np.testing.assert_array_equal(np.asarray(c.nodes), np.asarray(xla.nodes))
        t_xla, t_c = (statistics.median(times[v, e][1:]) for e in ("xla", "c"))
        rows.append({"case": name, "solver": v, "xla": 1e3 * t_xla, "c": 1e3 * t_c,
                     "nodes": float(np.mean(np.asarray(xla.nodes))),
                     "ratio": t_xla / statistics.median(times["sdfs", "xla"][1:]), "c_ratio": t_c / t_xla})
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
    print("| case | solver | nodes / decision | XLA ms / decision | XLA vs sdfs | C engine ms / decision "
          "| C / XLA |")
    print("|---|---|---|---|---|---|---|")
    for case in (inverter_case(10, args.steps), tanks_case(5, args.steps)):
        for r in measure(case, lanes, args.rounds):
            print(f"| {r['case']} | {r['solver']} | {r['nodes']:.0f} | {r['xla']:.3f} | {r['ratio']:.2f}x "
                  f"| {r['c']:.3f} | {r['c_ratio']:.3f}x |")


if __name__ == "__main__":
    main()
