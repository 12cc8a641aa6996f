"""A budget, a terminal set and a fallback: a cart-pole swing-up with a bang-bang force.

The terminal set (the pole near upright, slow, the cart near the middle) is out of reach while the pole
hangs, and without a bound the terminal-constrained search can prove that only by its whole tree
(``2^(N+1) - 2`` nodes). A decision's budget is split (docs/guide/budgets.md): while that search has found
no sequence it keeps half back for the fallback. The table: 8 closed loops of 100 steps from states near
hanging (``simulate_batch``), exact and at each budget: the mean closed-loop cost (the stage costs of the
states reached), held and fallback decisions, the first step upright and the loops' steps upright among
the last 20.

    python benchmarks/fallback_bench.py [--horizon 15] [--budgets 2000 20000 200000] [--loops 8] [--steps 100]
"""
from __future__ import annotations

import argparse
import platform
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np

import firhc_jax as fj

G, CART, POLE, HALF_LENGTH, DT, FORCE = 9.81, 1.0, 0.3, 0.5, 0.05, 8.0
UPRIGHT = np.cos(0.3)  # cos(theta) above this: upright


def dynamics(s, u):
    """Explicit Euler (velocities first) of the cart-pole; theta = 0 upright."""
    x, xd, th, thd = s
    sin, cos = jnp.sin(th), jnp.cos(th)
    total = CART + POLE
    push = (u[0] + POLE * HALF_LENGTH * thd ** 2 * sin) / total
    thdd = (G * sin - cos * push) / (HALF_LENGTH * (4.0 / 3.0 - POLE * cos ** 2 / total))
    xdd = push - POLE * HALF_LENGTH * thdd * cos / total
    xd2, thd2 = xd + DT * xdd, thd + DT * thdd
    return jnp.stack([x + DT * xd2, xd2, th + DT * thd2, thd2])


def stage_cost(s, u):
    x, xd, th, thd = s
    return 10.0 * (1 - jnp.cos(th)) + 0.05 * thd ** 2 + 0.5 * x ** 2 + 0.05 * xd ** 2


def make_problem(horizon: int) -> fj.Problem:
    return fj.Problem(dynamics, jnp.array([-FORCE, FORCE]), stage_cost, horizon,
                      terminal=lambda s: (jnp.cos(s[2]) >= UPRIGHT) & (jnp.abs(s[3]) <= 2.0) & (jnp.abs(s[0]) <= 2.0),
                      terminal_cost=lambda s: 5.0 * stage_cost(s, None))


def setting(horizon: int, max_nodes, X0: np.ndarray, steps: int) -> dict:
    opts = {} if max_nodes is None else {"max_nodes": max_nodes}
    ctrl = fj.FIRHC(make_problem(horizon), fallback="unconstrained", warm_start=True, **opts)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # held steps are counted in the table
        run = ctrl.simulate_batch(X0, steps)
    wall = time.perf_counter() - t0
    S = np.asarray(run.states)
    up = np.cos(S[:, :, 2]) >= UPRIGHT
    costs = np.asarray(jax.vmap(jax.vmap(stage_cost))(jnp.asarray(S[:, 1:]), jnp.asarray(run.inputs))).sum(1)
    first = [int(np.argmax(u)) if u.any() else steps for u in up]
    return {"cost": float(costs.mean()), "held": int(np.sum(run.held)), "fallback": int(np.sum(run.used_fallback)),
            "first": float(np.mean(first)), "last20": int(np.sum(up[:, -20:])),
            "nodes": float(np.mean(run.decision_nodes)), "wall": wall, "decisions": int(run.held.size)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--horizon", type=int, default=15)
    ap.add_argument("--budgets", type=int, nargs="+", default=[2000, 20000, 200000])
    ap.add_argument("--loops", type=int, default=8)
    ap.add_argument("--steps", type=int, default=100)
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    rng = np.random.default_rng(0)
    X0 = np.stack([[rng.uniform(-0.5, 0.5), 0.0, np.pi + rng.uniform(-0.3, 0.3), rng.uniform(-0.5, 0.5)]
                   for _ in range(args.loops)])
    print(f"{platform.machine()}, jax {jax.__version__}, float64; cart-pole N = {args.horizon}, "
          f"{args.loops} loops x {args.steps} steps")
    print("| budget | cost, mean of the loops | held | fallback decisions | first step upright, mean "
          "| loops x steps upright in the last 20 | nodes mean | wall s |")
    print("|---|---|---|---|---|---|---|---|")
    for budget in [None, *args.budgets]:
        r = setting(args.horizon, budget, X0, args.steps)
        name = "exact" if budget is None else f"{budget:,}"
        print(f"| {name} | {r['cost']:.1f} | {r['held']} of {r['decisions']} | {r['fallback']} | {r['first']:.1f} "
              f"| {r['last20']} | {r['nodes']:,.0f} | {r['wall']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
