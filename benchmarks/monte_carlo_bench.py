"""Monte Carlo of closed loops: many spacecraft attitude loops, every way of batching them, in one process.

The plant is ``firhc_jax.models.spacecraft`` (27 thruster patterns, MRP
attitude and body rates): ``--loops`` closed loops (default 512) of
``--steps`` samples (60) at horizon ``--horizon`` (3), each from a random
attitude error (up to 20 deg) and rate (up to 0.5 deg/s per axis) with its own
inertia (each principal moment within 20 % of nominal), and the fuel weight
swept over the loops from 0 to ``--fuel-max`` deg^2 per firing. The params
leaves are ``[B, steps, ...]``. The controller is ``fj.FIRHC(problem)`` and the
plant the finer RK4 integration of the same equations (``make_plant``).

Ways of batching, each called once to compile it, then timed in
``--repeats`` rounds over all of them (``block_until_ready``; a noisy
neighbour hits every way alike), the best round of each:

(a) a Python loop of ``ctrl.simulate``, one loop at a time, timed on
    ``--python-loops`` loops spread over the fuel sweep and scaled to loops/s;
(b) ``jax.jit(jax.vmap(lax.scan over ctrl.step))``, what the README offers
    for many states (one execution: a vmapped while loop runs every lane until
    the slowest lane's search ends);
(c) ``jax.jit(lax.scan over fj.solve_batch)``: one execution (inside ``jit``
    ``solve_batch`` runs one part), at each of ``--lanes``; and each again
    with the loops split into one part per core, each part's jitted scan
    dispatched on its own execution stream without waiting (what
    ``solve_batch`` itself does outside ``jit``);
(d) ``ctrl.simulate_batch(X0, steps, plant, params=...)``, with the default
    options and at each of ``--lanes`` (``fj.FIRHC(problem, lanes=...)``).

Then the decisions are compared: the predicted cost of every loop and step of
(a), (b) and (c) against (d) (relative difference; a loop whose inputs differ
from (d)'s anywhere is counted, and its first such step is where a near-tie
was broken the other way), and ``--check`` decisions of (d) are solved again
by ``fj.exhaustive`` from the loop's state with its params.

    python benchmarks/monte_carlo_bench.py            # 512 loops (a few minutes on 2 cores)
    python benchmarks/monte_carlo_bench.py --quick    # 32 loops, under a minute
"""
from __future__ import annotations

import argparse
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np
from jaxlib import xla_client

import firhc_jax as fj
from firhc_jax._src.runtime.sharding import usable_cores
from firhc_jax.models import spacecraft as sc


def vmap_of_step(ctrl, plant, steps):
    """(b): ``jit(vmap(scan(step)))``: ``(X0 [B, n], params [B, T, ...]) -> (costs [B, T], inputs [B, T, m])``."""
    def one(x0, p):
        def body(carry, pk):
            state, x = carry
            u, state, info = ctrl.step(state, x, pk)
            return (state, plant(x, u, pk)), (info.result.cost, u)

        return jax.lax.scan(body, (ctrl.init(x0), x0), p, length=steps)[1]

    return jax.jit(jax.vmap(one))


def scan_of_solve_batch(problem, plant, lanes):
    """(c): ``jit(scan(solve_batch))``: ``(X0 [B, n], params [B, T, ...]) -> (costs [B, T], inputs [B, T, m])``."""
    def run(X0, P):
        def body(X, pk):
            r = fj.solve_batch(problem, X, params=pk, lanes=lanes)
            return jax.vmap(plant)(X, r.first_input, pk), (r.cost, r.first_input)

        costs, inputs = jax.lax.scan(body, X0, jax.tree.map(lambda a: jnp.swapaxes(a, 0, 1), P))[1]
        return costs.T, jnp.swapaxes(inputs, 0, 1)

    return jax.jit(run)


def on_every_core(run, X0, P, parts):
    """``run`` on ``parts`` interleaved shares of the loops at once, each dispatched on its own execution
    stream (the last share repeats the last loop where they do not divide evenly), back in loop order."""
    B = X0.shape[0]
    per = -(-B // parts)
    take = np.minimum(np.arange(per * parts).reshape(per, parts).T, B - 1)  # [parts, per]
    outs = []
    for i in range(parts):
        with xla_client.execution_stream_id(i + 1):
            outs.append(run(X0[take[i]], jax.tree.map(lambda a, i=i: a[take[i]], P)))
    order = np.argsort(take.ravel(), kind="stable")[:B]  # first copy of each loop
    return jax.tree.map(lambda *a: jnp.concatenate(a)[order], *outs)


def compare(name, costs, inputs, ref_costs, ref_inputs):
    """A line: the largest relative cost difference and the loops whose inputs differ from the reference."""
    costs, inputs = np.asarray(costs), np.asarray(inputs)
    differ = np.any(inputs != ref_inputs, axis=-1)  # [B, T]
    loops = np.flatnonzero(differ.any(axis=1))
    same = ~np.cumsum(differ, axis=1).astype(bool)  # steps before a loop's first differing input
    rel = np.abs(costs - ref_costs) / np.maximum(np.abs(ref_costs), 1e-300)
    where = "" if not loops.size else f" (first at loop {loops[0]}, step {np.argmax(differ[loops[0]])})"
    return (f"{name}: cost rel. diff. max {rel[same].max():.1e} over the steps before any input differs; "
            f"{loops.size} of {len(costs)} loops differ somewhere{where}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--loops", type=int, default=512)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--horizon", type=int, default=3)
    ap.add_argument("--python-loops", type=int, default=32, help="loops of (a), spread over the sweep")
    ap.add_argument("--lanes", type=int, nargs="+", default=[16, 32], help="pool slots tried in (c) and (d)")
    ap.add_argument("--fuel-max", type=float, default=20.0, help="deg^2 per firing, the last loop's weight")
    ap.add_argument("--repeats", type=int, default=3, help="timed rounds over every way, the best kept")
    ap.add_argument("--check", type=int, default=8, help="decisions of (d) solved again by fj.exhaustive")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="32 loops, 8 in (a), lanes 32, 2 repeats")
    args = ap.parse_args()
    if args.quick:
        args.loops, args.python_loops, args.lanes, args.repeats, args.check = 32, 8, [32], 2, 4
    jax.config.update("jax_enable_x64", True)

    B, T, N = args.loops, args.steps, args.horizon
    rng = np.random.default_rng(args.seed)
    X0, inertia = sc.random_loops(B, rng)
    fuel = np.linspace(0.0, args.fuel_max, B)
    P = jax.tree.map(jnp.asarray, sc.step_params(inertia, fuel, T))  # leaves [B, T, ...]
    X0 = jnp.asarray(X0)
    problem, plant = sc.make_problem(N), sc.make_plant()
    ctrl = fj.FIRHC(problem)
    parts = usable_cores()
    print(f"# spacecraft Monte Carlo: {B} loops x {T} steps, N = {N}, M = 27, fuel 0..{args.fuel_max:g} deg^2; "
          f"float64; jax {jax.__version__}; {platform.machine()}, {parts} usable cores; best of {args.repeats}")

    sub = np.unique(np.linspace(0, B - 1, min(args.python_loops, B)).round().astype(int))

    def python_loop():
        return [ctrl.simulate(X0[b], T, plant, params=jax.tree.map(lambda a, b=b: a[b], P)) for b in sub]

    step_vmapped = vmap_of_step(ctrl, plant, T)
    ways = {"(a) Python loop of ctrl.simulate": (python_loop, len(sub), f"{len(sub)} loops timed, scaled"),
            "(b) jit(vmap(scan(ctrl.step)))": (lambda: step_vmapped(X0, P), B, "one execution")}
    for lanes in args.lanes:
        run = scan_of_solve_batch(problem, plant, lanes)
        ways[f"(c) jit(scan(solve_batch)), lanes={lanes}"] = (lambda run=run: run(X0, P), B, "one execution")
        ways[f"(c) the same, lanes={lanes}, {parts} parts on their own streams"] = (
            lambda run=run: on_every_core(run, X0, P, parts), B, "one execution per core")
    ways["(d) ctrl.simulate_batch"] = (lambda: ctrl.simulate_batch(X0, T, plant, params=P), B, "default options")
    ways["(d) the same, progress=True"] = (lambda: ctrl.simulate_batch(X0, T, plant, params=P, progress=True), B,
                                           "a bar of loops x steps on stderr")
    for lanes in args.lanes:
        tuned = fj.FIRHC(problem, lanes=lanes)
        ways[f"(d) the same, lanes={lanes}"] = (lambda tuned=tuned: tuned.simulate_batch(X0, T, plant, params=P), B,
                                               f"fj.FIRHC(problem, lanes={lanes})")
    first, best, out = {}, dict.fromkeys(ways, np.inf), {}
    for name, (fn, _, _) in ways.items():  # the first call compiles
        t0 = time.perf_counter()
        out[name] = jax.block_until_ready(fn())
        first[name] = time.perf_counter() - t0
    for _ in range(args.repeats):  # rounds over every way, so that a noisy neighbour hits them alike
        for name, (fn, _, _) in ways.items():
            t0 = time.perf_counter()
            jax.block_until_ready(fn())
            best[name] = min(best[name], time.perf_counter() - t0)

    d_name = "(d) ctrl.simulate_batch"
    rate = {name: loops / best[name] for name, (_, loops, _) in ways.items()}
    print("\n| way | loops/s | ratio to (d) | first call (s) | note |\n|---|---|---|---|---|")
    for name, (_, _, note) in ways.items():
        print(f"| {name} | {rate[name]:,.1f} | {rate[name] / rate[d_name]:.2f} | {first[name]:.1f} | "
              f"{note} |")

    runs_a, run_d = out["(a) Python loop of ctrl.simulate"], out[d_name]
    costs_b, inputs_b = out["(b) jit(vmap(scan(ctrl.step)))"]
    lanes = max(args.lanes, key=lambda lanes: rate[f"(c) jit(scan(solve_batch)), lanes={lanes}"])
    costs_c, inputs_c = out[f"(c) jit(scan(solve_batch)), lanes={lanes}"]
    ref_costs, ref_inputs = np.asarray(run_d.predicted_costs), np.asarray(run_d.inputs)
    print()
    print(compare("(a) against (d)", np.stack([r.predicted_costs for r in runs_a]),
                  np.stack([r.inputs for r in runs_a]), ref_costs[sub], ref_inputs[sub]))
    print(compare("(b) against (d)", costs_b, inputs_b, ref_costs, ref_inputs))
    print(compare(f"(c) lanes={lanes} against (d)", costs_c, inputs_c, ref_costs, ref_inputs))
    picks = rng.choice(B * T, size=min(args.check, B * T), replace=False)
    worst = 0.0
    for b, k in zip(*np.unravel_index(picks, (B, T)), strict=True):
        ref = fj.exhaustive(problem, run_d.states[b, k], params=jax.tree.map(lambda a, b=b, k=k: a[b, k], P))
        worst = max(worst, abs(float(ref.cost) - ref_costs[b, k]) / float(ref.cost))
    print(f"fj.exhaustive on {len(picks)} decisions of (d): cost rel. diff. max {worst:.1e}")

    states = np.asarray(run_d.states)
    firings = np.abs(np.asarray(run_d.inputs)).sum(axis=(1, 2))  # [B] thruster-pair samples
    error = sc.pointing_error(states[:, -10:]).mean(axis=1)  # [B] deg, mean over the last 10 samples
    print("\n| fuel weight (deg^2) | loops | pointing error, last 10 samples (deg) | firings per loop | "
          "nodes per decision mean / max |\n|---|---|---|---|---|")
    nodes = np.asarray(run_d.decision_nodes)
    for q in np.array_split(np.arange(B), 4):
        print(f"| {fuel[q[0]]:.1f} - {fuel[q[-1]]:.1f} | {q.size} | {error[q].mean():.2f} | {firings[q].mean():.1f} | "
              f"{nodes[q].mean():,.0f} / {nodes[q].max():,} |")


if __name__ == "__main__":
    main()
