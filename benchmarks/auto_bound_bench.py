"""``lower_bound="auto"`` against no bound and a hand-written bound, on two problems where pruning needs a bound.

* **Unit commitment.** Five on/off units (32 inputs); the state is the units' status, a step's cost is the
  start-up cost of each unit switched on (from the state before the step, ``previous_state``), the no-load
  cost of the units on and their merit-order dispatch against the hour's demand, read from the parameters
  with the step index; the units on must cover the demand plus a 10 % reserve (``constraint``). A closed
  loop over a day's demand. The hand bound is each remaining hour's cheapest feasible dispatch.
* **Comfort band.** A room (air and wall temperatures), a heater of four levels, the outside temperature
  and the price along the horizon, and a hard comfort band whose lower edge rises in the last two hours
  (the room is occupied). From half the sampled states the band cannot be met late in the horizon. The
  hand bound is ``+inf`` where full heating from the state cannot follow the band (the system is monotone,
  so full heating is the warmest completion), else 0.
* **A water heater** that must stay hot while water is drawn, paying the hour's price for each heating
  level: every completion pays along the whole horizon, and the derived bound is timed against none by
  ``fj.profile``, which says whether it pays for itself.

Every decision of every bound has the same cost as the one without a bound (exact). Times are per decision
(``FIRHC.simulate(compiled=False)``'s ``solve_times`` for the closed loop, each ``fj.sdfs`` call read back
for the sampled states), compiles excluded; float64.

    python benchmarks/auto_bound_bench.py [--uc-horizon 6] [--uc-steps 12] [--band-horizon 8] [--band-states 16]
                                          [--publish]
"""
from __future__ import annotations

import argparse
import statistics
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np
from _results import published

import firhc_jax as fj

# ---------------------------------------------------------------- unit commitment
CAPACITY = np.array([100.0, 80.0, 60.0, 40.0, 25.0])  # MW, in merit order (cheapest energy first)
ENERGY = np.array([20.0, 26.0, 33.0, 45.0, 70.0])  # EUR/MWh
NO_LOAD = np.array([400.0, 260.0, 160.0, 90.0, 30.0])  # EUR/h while on
START_UP = np.array([2500.0, 1500.0, 700.0, 300.0, 60.0])  # EUR per start
RESERVE = 1.1  # the units on cover the demand plus 10 %


def day_demand(hours: int) -> np.ndarray:
    """MW, hourly: a night low, a morning and an evening peak."""
    t = np.arange(hours) % 24
    return 110 + 90 * np.exp(-((t - 9) / 3.0) ** 2) + 120 * np.exp(-((t - 19) / 2.5) ** 2)


def dispatch_cost(u, demand):
    """EUR for the hour: no-load of the units on plus their energy, loaded in merit order."""
    on = jnp.asarray(CAPACITY) * u
    before = jnp.cumsum(on) - on
    output = jnp.clip(demand - before, 0.0, on)
    return jnp.sum(jnp.asarray(ENERGY) * output) + jnp.sum(jnp.asarray(NO_LOAD) * u)


def uc_problem(horizon: int, bound):
    def dynamics(x, u, k, p):
        return u.astype(x.dtype)

    def stage_cost(x, x_next, u, k, p):
        return jnp.sum(jnp.asarray(START_UP) * u * (1 - x)) + dispatch_cost(u, p["demand"][k])

    def constraint(x, x_next, u, k, p):
        return jnp.sum(jnp.asarray(CAPACITY) * u) >= RESERVE * p["demand"][k]

    controls = fj.product_controls([0.0, 1.0], repeat=5)  # [32, 5]

    def hand(x, steps_left, p):
        """Each remaining hour's cheapest feasible dispatch (start-ups left out)."""
        per_hour = jax.vmap(lambda d: jnp.min(jax.vmap(
            lambda u: jnp.where(jnp.sum(jnp.asarray(CAPACITY) * u) >= RESERVE * d, dispatch_cost(u, d), jnp.inf))(
                jnp.asarray(controls))))(p["demand"])
        rest = jnp.arange(horizon) >= horizon - steps_left
        return (1 - 1e-9) * jnp.sum(jnp.where(rest, per_hour, 0.0))

    lower = {"none": None, "hand": hand, "auto": "auto"}[bound]
    return fj.Problem(dynamics, controls, stage_cost, horizon, constraint=constraint, step_index=True,
                      previous_state=True, lower_bound=lower)


def unit_commitment(horizon: int, steps: int) -> list[dict]:
    demand = day_demand(steps + horizon)
    params = {"demand": fj.horizon_windows(demand, steps, horizon, start=0)}
    x0 = jnp.array([1.0, 1.0, 0.0, 0.0, 0.0])
    rows, reference = [], None
    for bound in ("none", "hand", "auto"):
        run = fj.FIRHC(uc_problem(horizon, bound)).simulate(x0, steps, params=params, compiled=False,
                                                                progress=False)
        costs = np.asarray(run.predicted_costs)
        if reference is None:
            reference = costs
        assert np.allclose(costs, reference, rtol=1e-9, atol=0), (bound, costs, reference)  # exact
        nodes = np.asarray(run.decision_nodes)
        rows.append({"bound": bound, "nodes_mean": float(nodes.mean()), "nodes_max": int(nodes.max()),
                     "ms": 1e3 * float(np.median(np.asarray(run.solve_times))),
                     "ms_max": 1e3 * float(np.max(np.asarray(run.solve_times))), "decisions": steps})
    return rows


# ---------------------------------------------------------------- comfort band
HEAT = np.array([0.0, 1.0, 2.0, 3.0])  # kW
HIGH = 26.0  # degC, the band's upper edge at every step


def band_step(x, u, outside):
    air = x[0] + 0.15 * (x[1] - x[0]) + 0.05 * (outside - x[0]) + 0.5 * u
    wall = x[1] + 0.04 * (x[0] - x[1]) + 0.01 * (outside - x[1])
    return jnp.stack([air, wall])


def band_problem(horizon: int, bound):
    def dynamics(x, u, k, p):
        return band_step(x, u[0], p["outside"][k])

    def stage_cost(x_next, u, k, p):
        return p["price"][k] * u[0] + 0.05 * (x_next[0] - 21.0) ** 2

    def constraint(x_next, u, k, p):
        return (x_next[0] >= p["low"][k]) & (x_next[0] <= HIGH)

    def hand(x, steps_left, p):
        """+inf where full heating, the warmest completion, leaves the band at some remaining step."""
        def warmest(carry, k):
            z, ok = carry
            z = band_step(z, HEAT[-1], p["outside"][k])
            return (z, ok & ((k < horizon - steps_left) | (z[0] >= p["low"][k]))), None
        start = horizon - steps_left

        def body(k, carry):
            return jax.lax.cond(k >= start, lambda c: warmest(c, k)[0], lambda c: c, carry)
        _, ok = jax.lax.fori_loop(0, horizon, body, (x, jnp.ones((), bool)))
        return jnp.where(ok, 0.0, jnp.inf).astype(x.dtype)

    lower = {"none": None, "hand": hand, "auto": "auto"}[bound]
    return fj.Problem(dynamics, HEAT, stage_cost, horizon, constraint=constraint, step_index=True, lower_bound=lower)


def band_params(horizon: int) -> dict:
    low = np.full(horizon, 17.0)
    low[-2:] = 22.0  # occupied in the last two hours
    return {"outside": jnp.asarray(np.linspace(8.0, 4.0, horizon)), "low": jnp.asarray(low),
            "price": jnp.asarray(0.2 + 0.1 * np.sin(np.arange(horizon) / 2.0))}


def band_states(count: int, horizon: int) -> np.ndarray:
    """``count`` states at 18.6-21.6 degC air: at N = 8 the colder half cannot be warmed into the band in time."""
    rng = np.random.default_rng(0)
    air = np.linspace(18.6, 21.6, count)
    return np.stack([air, air - rng.uniform(1.5, 2.5, count)], axis=1)


def decisions(problem, bound: str, X, params, reference):
    """One decision from each state of ``X`` timed (after one that compiles): ``(row, costs)``; the costs must
    be ``reference``'s (those of the first bound timed, when it is None): every bound is exact."""
    fj.sdfs(problem, X[0], params=params)  # compiles
    costs, nodes, times = [], [], []
    for x in X:
        t0 = time.perf_counter()
        r = jax.block_until_ready(fj.sdfs(problem, x, params=params))
        times.append(time.perf_counter() - t0)
        costs.append(float(r.cost))
        nodes.append(int(r.nodes))
    if reference is None:
        reference = np.asarray(costs)
    assert np.allclose(costs, reference, rtol=1e-9, atol=0), (bound, costs, reference)  # exact
    return {"bound": bound, "nodes_mean": float(np.mean(nodes)), "nodes_max": int(np.max(nodes)),
            "ms": 1e3 * statistics.median(times), "ms_max": 1e3 * max(times), "decisions": len(X)}, reference


def comfort_band(horizon: int, count: int) -> tuple[list[dict], int]:
    params = band_params(horizon)
    X = band_states(count, horizon)
    rows, reference = [], None
    for bound in ("none", "hand", "auto"):
        row, reference = decisions(band_problem(horizon, bound), bound, X, params, reference)
        rows.append(row)
    return rows, int(np.sum(np.isinf(reference)))


# ---------------------------------------------------------------- a water heater: what the bound costs
def heater_problem(horizon: int, bound):
    """A hot-water tank (off and three heating levels) that must stay at 45 degC or above while water is drawn,
    paying the hour's price for the energy: the cost of every completion is spread over the horizon."""
    def dynamics(x, u, k, p):
        return x + 4.0 * u - 0.05 * (x - 20.0) - p["draw"][k]

    def stage_cost(x_next, u, k, p):
        return p["price"][k] * jnp.sum(u)

    def constraint(x_next, u, k, p):
        return (x_next[0] >= 45.0) & (x_next[0] <= 80.0)

    return fj.Problem(dynamics, jnp.array([0.0, 1.0, 2.0, 3.0]), stage_cost, horizon, constraint=constraint,
                      step_index=True, lower_bound=bound)


def heater(horizon: int, count: int) -> tuple[list[dict], object]:
    rng = np.random.default_rng(1)
    params = {"draw": jnp.asarray(rng.uniform(1.0, 5.0, horizon)),
              "price": jnp.asarray(0.25 + 0.1 * np.cos(np.arange(horizon) / 3.0))}
    X = np.linspace(50.0, 70.0, count)[:, None]
    rows, reference = [], None
    for bound in ("none", "auto"):
        row, reference = decisions(heater_problem(horizon, None if bound == "none" else "auto"), bound, X, params,
                                   reference)
        rows.append(row)
    batch = {k: jnp.broadcast_to(v, (count,) + v.shape) for k, v in params.items()}
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        verdict = fj.profile(heater_problem(horizon, "auto"), X, batch, pop_widths=(1,), lanes=(), repeats=3,
                             max_exhaustive_nodes=1, progress=False)
    return rows, verdict


def table(rows: list[dict]) -> None:
    none = rows[0]
    hand = next((r for r in rows if r["bound"] == "hand"), None)
    print("| bound | nodes per decision, mean / max | of no bound's | of the hand bound's "
          "| ms per decision, median / max |")
    print("|---|---|---|---|---|")
    for r in rows:
        of_hand = f"{r['nodes_mean'] / hand['nodes_mean']:.2f}x" if hand else "-"
        print(f"| {r['bound']} | {r['nodes_mean']:,.0f} / {r['nodes_max']:,} | "
              f"{r['nodes_mean'] / none['nodes_mean']:.2%} | {of_hand} | {r['ms']:.2f} / {r['ms_max']:.2f} |")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--uc-horizon", type=int, default=6)
    ap.add_argument("--uc-steps", type=int, default=12, help="hours of the unit-commitment closed loop")
    ap.add_argument("--band-horizon", type=int, default=8)
    ap.add_argument("--band-states", type=int, default=16)
    ap.add_argument("--heater-horizon", type=int, default=8)
    ap.add_argument("--heater-states", type=int, default=8)
    ap.add_argument("--publish", action="store_true", help="also write benchmarks/results/auto_bound.md")
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    with published("auto_bound", args.publish, "python benchmarks/auto_bound_bench.py"):
        print(f"jax {jax.__version__}, float64; every bound's decisions cost what the unbounded search's do\n")
        print(f"## Unit commitment: 5 units, 32 inputs, N = {args.uc_horizon}, a closed loop of {args.uc_steps} h\n")
        table(unit_commitment(args.uc_horizon, args.uc_steps))
        rows, infeasible = comfort_band(args.band_horizon, args.band_states)
        print(f"\n## Comfort band: 4 heater levels, N = {args.band_horizon}, {args.band_states} states "
              f"({infeasible} of them infeasible late in the horizon)\n")
        table(rows)
        rows, verdict = heater(args.heater_horizon, args.heater_states)
        print(f"\n## A water heater: 4 levels, N = {args.heater_horizon}, {args.heater_states} states\n")
        table(rows)
        b = verdict.bound
        print(f"\nfj.profile (3 interleaved runs): sdfs {1e3 * b['seconds'] / args.heater_states:.2f} ms per decision "
              f"with the bound, {1e3 * b['seconds_without'] / args.heater_states:.2f} without: "
              f"{b['slowdown']:.2f}x; advice: {verdict.advice[0] if verdict.advice else 'none'}")


if __name__ == "__main__":
    main()
