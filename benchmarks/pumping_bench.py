"""Budgets on an economic problem with near-ties: the pumping station of
``firhc_jax.models.pumping`` (3 on/off pumps, 2 tanks, hourly prices and a
demand forecast along the horizon), plus the three-tank system and the hopper
at a tenth of their mean exact node counts.

Pumping table: one closed loop per setting, the plant is the model, float64;
closed-loop cost = the electricity paid plus the terminal value of the last
state (the water missing below target), EUR. ms per decision from
``simulate(..., compiled=False)``'s ``solve_times``. ``bound violations``:
predicted levels (every decision's plan rolled out on the model) outside
``[H_MIN, H_MAX]``, and the plant's lowest margin above ``H_MIN``.

Before the table, a brute-force check at N = 4: on closed-loop states the
exact and budgeted sDFS agree with ``fj.exhaustive`` (budgeted: never
cheaper, equal when ``complete``) and the lower bound passes
``check_lower_bound``.

The default 72-hour loop (the issue's) takes several minutes on a shared
2-core CPU, most of it the exact N = 8 row; ``--quick`` (12 hours, no exact
N = 8, no N = 24) well under one. ``--variant``: the same structure with other plant numbers
(``VARIANT``). Figures: docs/guide/budgets.md.

    python benchmarks/pumping_bench.py [--steps 72] [--quick] [--skip-others | --only-others] [--only 0,2]
                                       [--variant] [--bound demand|target|auto|none]
"""
from __future__ import annotations

import argparse
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

import firhc_jax as fj
from firhc_jax.models import pumping as pm

STATION = pm.PumpingParams()  # the model's numbers
# Other plant numbers, the same structure: a larger station (more power, higher lifts, other pump curves
# and tanks), its water valued at what refilling costs there.
VARIANT = pm.PumpingParams(area=(180.0, 140.0), lift=(25.0, 25.0, 34.0), a_coef=(15.0, 22.0, 19.0),
                           h_shut=(55.0, 52.0, 67.0), power=(45.0, 75.0, 65.0), parallel=0.85, water_value=0.11)


def pumping_setting(horizon: int, max_nodes, steps: int, station: pm.PumpingParams = STATION,
                    bound: str = "demand"):
    price, demand = pm.forecast(steps + horizon)
    params = pm.horizon_params(price, demand, steps, horizon)
    if bound == "auto":
        problem = pm.make_problem(horizon, station, bound=None).replace(lower_bound="auto")
    else:
        problem = pm.make_problem(horizon, station, bound=None if bound == "none" else bound)
    opts = {} if max_nodes is None else {"max_nodes": max_nodes}
    ctrl = fj.FIRHC(problem, **opts)
    x0 = jnp.asarray(pm.INITIAL_LEVELS)
    t0 = time.perf_counter()
    run = ctrl.simulate(x0, steps, params=params, compiled=False)
    wall = time.perf_counter() - t0
    X = np.asarray(run.states)
    final = float(station.water_value * np.sum(np.asarray(station.area) * np.maximum(np.asarray(station.target)
                                                                                     - X[-1], 0.0)))
    cost = float(np.sum(run.stage_costs)) + final
    plans = np.asarray(run.plans)
    controls = np.asarray(problem.controls)
    worst = 0
    for t in range(steps):  # predicted levels of every plan, rolled out on the model
        x = X[t]
        for k in range(horizon):
            if plans[t, k] < 0:
                break
            x = np.asarray(pm.step(x, controls[plans[t, k]], params["demand"][t, k], np, station))
            worst += int(np.any((x < station.h_min - 1e-12) | (x > station.h_max + 1e-12)))
    ms = 1e3 * np.asarray(run.solve_times)
    nodes = np.asarray(run.decision_nodes)
    return {"cost": cost, "ms_med": float(np.median(ms)), "ms_max": float(ms.max()), "nodes_mean": float(nodes.mean()),
            "nodes_max": int(nodes.max()), "complete": int(np.sum(run.complete)), "steps": steps,
            "violations": worst, "margin": float(X.min() - station.h_min), "held": int(np.sum(run.held)), "wall": wall}


def brute_force_check(states: np.ndarray, horizon: int = 4, budget: int = 300):
    problem = pm.make_problem(horizon)
    price, demand = pm.forecast(len(states) + horizon)
    params = pm.horizon_params(price, demand, len(states), horizon)
    worst = 0.0
    for i, x in enumerate(states):
        p = jax.tree_util.tree_map(lambda a, i=i: a[i], params)
        ref = fj.exhaustive(problem, x, params=p)
        exact = fj.sdfs(problem, x, params=p)
        cut = fj.sdfs(problem, x, params=p, max_nodes=budget)
        assert np.isclose(float(exact.cost), float(ref.cost), rtol=1e-12, atol=0), (i, exact.cost, ref.cost)
        assert float(cut.cost) >= float(ref.cost) * (1 - 1e-12) and int(cut.nodes) <= budget
        if bool(cut.complete):
            assert np.isclose(float(cut.cost), float(ref.cost), rtol=1e-12, atol=0)
        worst = max(worst, float(cut.cost) / float(ref.cost) - 1)
    for i in range(0, len(states), 2):
        p = jax.tree_util.tree_map(lambda a, i=i: a[i], params)
        bad = fj.diagnostics.check_lower_bound(problem, states[i:i + 1], p)
        assert not bad, bad[:3]
    print(f"brute force N={horizon}: {len(states)} states, sdfs == exhaustive; max_nodes={budget}: "
          f"at most {100 * worst:.2f}% dearer; lower bound admissible on every second state x 1..{horizon} steps")


def other_setting(name: str, max_nodes, steps: int):
    """A closed loop of the three-tank system (N = 5, bound, no terminal box) or the hopper
    (N = 10, bound, fallback); cost: the model's stage cost of every state reached with the input applied."""
    opts = {} if max_nodes is None else {"max_nodes": max_nodes}
    t0 = time.perf_counter()
    if name == "tanks":
        from firhc_jax.models import tanks
        problem = tanks.make_problem(5, bound=True)
        ctrl = fj.FIRHC(problem, **opts)
        run = ctrl.simulate(jnp.asarray(tanks.initial_state()), steps, compiled=False)
        costs = jax.vmap(problem.stage_cost)(run.states[1:], run.inputs)
    else:
        from firhc_jax.apps import hopper as ha
        from firhc_jax.models import hopper as hm
        run, _, _ = ha.simulate(steps * hm.CONTROL_PERIOD, 10, "sdfs", progress=False, timed=True, bound=True,
                                **opts)
        problem = hm.make_problem(10, hm.HopperParams(), bound=True)
        model = jax.vmap(hm.observe)(run.states[1:], run.inputs)
        costs = jax.vmap(problem.stage_cost)(model, run.inputs[:, 1:])
    ms = 1e3 * np.asarray(run.solve_times)
    nodes = np.asarray(run.decision_nodes)
    return {"cost": float(np.sum(costs)), "ms_med": float(np.median(ms)), "ms_max": float(ms.max()),
            "nodes_mean": float(nodes.mean()), "nodes_max": int(nodes.max()), "complete": int(np.sum(run.complete)),
            "steps": len(nodes), "held": int(np.sum(run.held)), "wall": time.perf_counter() - t0}


def row(label: str, r: dict) -> str:
    extra = f" | {r['violations']} / {1e3 * r['margin']:.1f} mm" if "violations" in r else f" | {r['held']}"
    return (f"| {label} | {r['cost']:.2f} | {r['ms_med']:.0f} / {r['ms_max']:.0f} | {r['nodes_mean']:,.0f} / "
            f"{r['nodes_max']:,} | {r['complete']}/{r['steps']}{extra} |")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=72, help="closed-loop length in hours (pumping)")
    ap.add_argument("--budget", type=int, default=200_000)
    ap.add_argument("--quick", action="store_true", help="12 hours, no exact N = 8, budgets at N = 8 and 12 only")
    ap.add_argument("--skip-others", action="store_true", help="pumping station only")
    ap.add_argument("--only-others", action="store_true", help="the three-tank system and the hopper only")
    ap.add_argument("--other-fraction", type=float, default=0.1,
                    help="their budget, as a fraction of their mean exact nodes")
    ap.add_argument("--only", default=None, help="comma-separated indices (0-4) of the pumping rows to run")
    ap.add_argument("--variant", action="store_true", help="the station with other plant numbers (VARIANT)")
    ap.add_argument("--bound", default="demand", choices=("demand", "target", "auto", "none"),
                    help="the pumping rows' lower bound: the model's two hand bounds, lower_bound=\"auto\" or none")
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    steps = 12 if args.quick else args.steps
    station = VARIANT if args.variant else STATION
    print(f"{platform.machine()}, jax {jax.__version__}, float64; pumping closed loop {steps} h, bound {args.bound}"
          + (", the variant station" if args.variant else ""))

    seed_run = fj.FIRHC(pm.make_problem(4)).simulate(jnp.asarray(pm.INITIAL_LEVELS), 12,
                                                     params=pm.horizon_params(*pm.forecast(16), 12, 4))
    brute_force_check(np.asarray(seed_run.states[:12]))
    settings = [("N = 6, exact", 6, None), ("N = 8, exact", 8, None), (f"N = 8, max_nodes={args.budget:,}", 8,
                args.budget), (f"N = 12, max_nodes={args.budget:,}", 12, args.budget),
                (f"N = 24, max_nodes={args.budget:,}", 24, args.budget)]
    if args.quick:
        settings = [settings[0], settings[2], settings[3]]
    if args.only_others:
        settings = []
    if args.only:
        chosen = args.only.split(",")
        settings = [s for i, s in enumerate(settings) if str(i) in chosen]
    print("| setting | closed-loop cost (EUR) | ms per decision, median / max | nodes mean / max | complete "
          "| predicted bound violations / lowest plant margin |")
    print("|---|---|---|---|---|---|")
    for label, horizon, budget in settings:
        print(row(label, pumping_setting(horizon, budget, steps, station, args.bound)), flush=True)
    if args.skip_others:
        return
    for name, steps_other in (("tanks", 40 if args.quick else 100), ("hopper", 200 if args.quick else 400)):
        exact = other_setting(name, None, steps_other)
        budget = max(1, int(exact["nodes_mean"] * args.other_fraction))
        cut = other_setting(name, budget, steps_other)
        print(f"\n{name}: stage-cost sum over the closed loop")
        print("| setting | closed-loop cost | ms per decision, median / max | nodes mean / max | complete | held |")
        print("|---|---|---|---|---|---|")
        print(row("exact", exact))
        print(row(f"max_nodes={budget:,}", cut), flush=True)


if __name__ == "__main__":
    main()
