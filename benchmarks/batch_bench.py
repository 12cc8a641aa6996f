"""Batched search throughput: ``fj.solve_batch``'s work pool against a plain
``vmap`` of ``fj.sdfs`` and a vmapped vectorised exhaustive search.

    python benchmarks/batch_bench.py --quick      # seconds: synthetic N=4, B = 1 and 64
    python benchmarks/batch_bench.py              # synthetic N=4, tanks N=4, hopper N=6; B = 1, 64, 1024, 4096;
                                                  # then 1 vs 4 forced host devices (minutes)
    python benchmarks/batch_bench.py --sweep      # also the pool's lanes x pop_width grid (long)
    python benchmarks/batch_bench.py --pinned --plants synthetic:4,tanks:4 --batches 4096
                                                  # default call pinned to one core (taskset -c 0) vs every core

Method. The states are drawn (with replacement, fixed seed) from closed-loop
runs: the tanks and hopper runs of ``firhc_jax.apps.bench`` where those
plants are present, and for the synthetic plant 16 closed loops of 32 steps
from random states, themselves run with ``solve_batch``. Every solver gets the
same ``[B, n]`` batch in the same process; a first call compiles (reported
separately), then the median of ``--repeats`` timed calls
(``block_until_ready``; fewer where they would take over a minute: the
exhaustive search of 4096 tank states takes two). "per-node cost" is time / nodes relative to the
exhaustive search's; "time" is relative to the exhaustive search's time.
Costs are checked against the exhaustive search (same optimum per row).
The device comparison runs this script again in subprocesses with
``XLA_FLAGS=--xla_force_host_platform_device_count=D``; ``--pinned`` runs it
in subprocesses under ``taskset -c 0`` and unpinned (one device: the default
call splits the rows over the usable cores), alternating. Each such run also
reads every thread's CPU time (``/proc``): on a machine shared with other
work the wall time measures the others too (Linux gives each session its
share of the cores, however many threads it runs), while the CPU times give
what idle cores would take, ``max(busiest thread, all threads / cores)``, and
the "idle-core speedup" from it.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from firhc_jax._src.runtime.sharding import usable_cores

SOLVERS = {"pool sDFS": "sdfs", "vmap sDFS": "sdfs-vmap", "vmap exhaustive": "exhaustive"}


def closed_loop_states(plant: str, horizon: int):
    """``(problem, states [S, n])``: the states a closed loop searched at."""
    if plant == "synthetic":
        from firhc_jax._src.search.batch import solve_batch
        from firhc_jax.models.synthetic import SyntheticParams, benchmark_state, make_problem

        problem = make_problem(horizon, SyntheticParams(17))
        rng = np.random.default_rng(0)
        X = jnp.asarray(np.asarray(benchmark_state()) + rng.normal(0.0, 0.3, (16, 3)))
        states = []
        for _ in range(32):
            states.append(np.asarray(X))
            X = jax.vmap(problem.dynamics)(X, solve_batch(problem, X).first_input)
        return problem, np.concatenate(states)
    from firhc_jax.apps import bench

    case = {"tanks": bench.tanks_case, "hopper": bench.hopper_case}[plant](horizon)
    return case.problem, np.asarray(case.states)


def timed(fn, repeats: int, budget: float = 60.0):
    """``(median seconds, first-call seconds, result)``: the first call compiles;
    then ``repeats`` timed calls, fewer (at least one) where the first call
    shows that they would take more than ``budget`` seconds."""
    t0 = time.perf_counter()
    result = jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    times = []
    for _ in range(max(1, min(repeats, int(budget // first)))):
        t0 = time.perf_counter()
        result = jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return statistics.median(times), first, result


def thread_cpu() -> dict[int, float]:
    """CPU seconds (user + system) each thread of this process has used so far (Linux ``/proc``)."""
    tick, out = os.sysconf("SC_CLK_TCK"), {}
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except FileNotFoundError:  # the thread ended meanwhile
            continue
        out[int(tid)] = (int(fields[11]) + int(fields[12])) / tick
    return out


def cpu_use(fn, calls: int) -> tuple[float, float, float]:
    """``(wall, busiest thread's CPU, every thread's CPU)`` seconds per call of ``fn`` (after a warm-up call).
    On a machine shared with other work the wall time measures the others too; the busiest thread's CPU time
    is what the call would take on idle cores (its critical path), whatever the others do."""
    jax.block_until_ready(fn())
    before, t0 = thread_cpu(), time.perf_counter()
    for _ in range(calls):
        jax.block_until_ready(fn())
    wall, after = time.perf_counter() - t0, thread_cpu()
    used = [after[t] - before.get(t, 0.0) for t in after]
    return wall / calls, max(used) / calls, sum(used) / calls


def measure(plant: str, horizon: int, batches, repeats: int, pool_options: dict, solvers=tuple(SOLVERS)) -> list[dict]:
    from firhc_jax._src.search.batch import solve_batch

    problem, states = closed_loop_states(plant, horizon)
    rng = np.random.default_rng(1)
    rows = []
    for B in batches:
        X = jnp.asarray(states[rng.integers(0, len(states), B)])
        out = {}
        for name, solver in SOLVERS.items():
            if name not in solvers and name != "vmap exhaustive":
                continue
            opts = pool_options if solver == "sdfs" else {}
            t, first, r = timed(lambda X=X, solver=solver, opts=opts: solve_batch(problem, X, solver=solver, **opts),
                                repeats)
            out[name] = (t, first, r)
        t_ex, _, ref = out["vmap exhaustive"]
        for name, (t, first, r) in out.items():
            np.testing.assert_allclose(r.cost, ref.cost, rtol=1e-9, err_msg=f"{plant} B={B} {name}")
            nodes = int(np.sum(r.nodes))
            rows.append({"plant": plant, "N": horizon, "M": problem.num_controls, "B": B, "solver": name,
                         "seconds": t, "compile_s": max(first - t, 0.0), "nodes": nodes,
                         "solves_per_s": B / t, "nodes_per_s": nodes / t,
                         "per_node_vs_exhaustive": (t / nodes) / (t_ex / int(np.sum(ref.nodes))),
                         "time_vs_exhaustive": t / t_ex})
        print(f"# {plant} N={horizon} B={B}: done", file=sys.stderr, flush=True)
    return rows


def sweep(plant: str, horizon: int, batches, repeats: int) -> list[dict]:
    """The pool alone over a lanes x pop_width grid."""
    from firhc_jax._src.search.batch import solve_batch

    problem, states = closed_loop_states(plant, horizon)
    rng = np.random.default_rng(1)
    rows = []
    for B in batches:
        X = jnp.asarray(states[rng.integers(0, len(states), B)])
        for lanes in (64, 256, 1024):
            for k in (1, 2, 4):
                t, _, r = timed(lambda X=X, lanes=lanes, k=k: solve_batch(problem, X, lanes=lanes, pop_width=k),
                                repeats)
                rows.append({"plant": plant, "N": horizon, "B": B, "lanes": lanes, "pop_width": k, "seconds": t,
                             "nodes": int(np.sum(r.nodes)), "solves_per_s": B / t})
    return rows


def device_child(plant: str, horizon: int, batch: int, repeats: int) -> None:
    """Runs in a subprocess with forced host devices: prints one JSON line."""
    from firhc_jax._src.search.batch import solve_batch

    problem, states = closed_loop_states(plant, horizon)
    X = jnp.asarray(states[np.random.default_rng(1).integers(0, len(states), batch)])
    t, first, r = timed(lambda: solve_batch(problem, X), repeats)
    _, busiest, cpu = cpu_use(lambda: solve_batch(problem, X), repeats)
    print(json.dumps({"devices": jax.local_device_count(), "cores": usable_cores(), "seconds": t,
                      "compile_s": max(first - t, 0.0), "busiest": busiest, "cpu": cpu,
                      "idle": max(busiest, cpu / usable_cores()), "cost": np.asarray(r.cost).tolist(),
                      "sequence": np.asarray(r.sequence).tolist(), "nodes": int(np.sum(r.nodes))}))


def child_runs(plant: str, horizon: int, batch: int, repeats: int, settings, rounds: int = 1) -> list[dict]:
    """This script's ``--child`` in a fresh process per ``(label, command prefix, XLA_FLAGS or None)``, the
    settings alternating for ``rounds`` rounds (so that a busy spell of a shared machine hits them alike); each
    setting's fastest round, compared with the first setting's."""
    best = {}
    for _ in range(rounds):
        for label, prefix, flags in settings:
            env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
            env.update(JAX_PLATFORMS="cpu", **({"XLA_FLAGS": flags} if flags else {}))
            cmd = [*prefix, sys.executable, __file__, "--child", f"{plant}:{horizon}:{batch}:{repeats}"]
            out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
            run = dict(json.loads(out.stdout.strip().splitlines()[-1]), label=label)
            if label not in best or run["seconds"] < best[label]["seconds"]:
                best[label] = run
    runs = [best[label] for label, _, _ in settings]
    base = runs[0]
    return [{"plant": plant, "N": horizon, "B": batch, "run": r["label"], "devices": r["devices"],
             "cores": r["cores"], "seconds": r["seconds"], "solves_per_s": batch / r["seconds"],
             "speedup": base["seconds"] / r["seconds"], "busiest": r["busiest"], "cpu": r["cpu"],
             "idle_speedup": base["idle"] / r["idle"], "same_sequences": r["sequence"] == base["sequence"],
             "max_cost_diff": float(np.max(np.abs(np.subtract(r["cost"], base["cost"]),
                                                  where=np.isfinite(base["cost"]), out=np.zeros(batch)))),
             "nodes": r["nodes"]} for r in runs]


def devices(plant: str, horizon: int, batch: int, repeats: int, counts=(1, 4)) -> list[dict]:
    """Default ``solve_batch`` with 1 and 4 forced host devices."""
    return child_runs(plant, horizon, batch, repeats,
                      [(f"{c} host devices", [], f"--xla_force_host_platform_device_count={c}") for c in counts])


def pinned(plant: str, horizon: int, batch: int, repeats: int, rounds: int) -> list[dict]:
    """Default ``solve_batch`` (one device) pinned to core 0 (``taskset -c 0``) and on every usable core."""
    return child_runs(plant, horizon, batch, repeats,
                      [("taskset -c 0", ["taskset", "-c", "0"], None), ("every core", [], None)], rounds)


def markdown(rows, devices_rows, sweep_rows) -> str:
    lines = [f"jax {jax.__version__}, {platform.machine()}, {os.cpu_count()} cores, "
             f"{'float64' if jax.config.jax_enable_x64 else 'float32'}, load average {os.getloadavg()[0]:.1f}"]
    if rows:
        lines += ["", "| plant | N | B | solver | time | solves/s | nodes/s | nodes/solve | per-node cost vs "
                  "exhaustive | time vs exhaustive | compile |",
                  "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['plant']} | {r['N']} | {r['B']} | {r['solver']} | {1e3 * r['seconds']:.1f} ms | "
                     f"{r['solves_per_s']:,.0f} | {r['nodes_per_s']:.3g} | {r['nodes'] / r['B']:,.0f} | "
                     f"{r['per_node_vs_exhaustive']:.2f}x | {r['time_vs_exhaustive']:.3f}x | {r['compile_s']:.1f} s |")
    if devices_rows:
        lines += ["", "| plant | N | B | run | devices | usable cores | time | solves/s | speedup | busiest thread "
                  "CPU | all threads CPU | idle-core speedup | same sequences | max cost diff | nodes |",
                  "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|"]
        for r in devices_rows:
            lines.append(f"| {r['plant']} | {r['N']} | {r['B']} | {r['run']} | {r['devices']} | {r['cores']} | "
                         f"{1e3 * r['seconds']:.1f} ms | {r['solves_per_s']:,.0f} | {r['speedup']:.2f}x | "
                         f"{1e3 * r['busiest']:.0f} ms | {1e3 * r['cpu']:.0f} ms | {r['idle_speedup']:.2f}x | "
                         f"{r['same_sequences']} | {r['max_cost_diff']:.1e} | {r['nodes']:,} |")
    if sweep_rows:
        lines += ["", "| plant | N | B | lanes | pop_width | time | solves/s | nodes |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|"]
        for r in sweep_rows:
            lines.append(f"| {r['plant']} | {r['N']} | {r['B']} | {r['lanes']} | {r['pop_width']} | "
                         f"{1e3 * r['seconds']:.1f} ms | {r['solves_per_s']:,.0f} | {r['nodes']:,} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="synthetic N=4, B = 1 and 64, one repeat")
    ap.add_argument("--plants", default="synthetic:4,tanks:4,hopper:6", help="plant:horizon list")
    ap.add_argument("--batches", default="1,64,1024,4096")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--solvers", default=",".join(SOLVERS), help="subset of: " + ", ".join(SOLVERS)
                    + " (the exhaustive search always runs: it is the reference)")
    ap.add_argument("--lanes", type=int, default=None, help="pool lanes (default: solve_batch's)")
    ap.add_argument("--pop-width", type=int, default=None, help="pool pop_width (default: solve_batch's)")
    ap.add_argument("--no-devices", action="store_true", help="skip the 1 vs 4 host devices comparison")
    ap.add_argument("--pinned", action="store_true",
                    help="only: the default call (largest batch) pinned to core 0 (taskset -c 0) against every "
                         "core, each plant in fresh processes")
    ap.add_argument("--rounds", type=int, default=3,
                    help="--pinned: alternate the two runs this many times, keep each one's fastest (default 3)")
    ap.add_argument("--sweep", action="store_true", help="also sweep the pool's lanes x pop_width (long)")
    ap.add_argument("--f32", action="store_true", help="float32 (default float64)")
    ap.add_argument("--json", help="also write the rows to this file")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    jax.config.update("jax_enable_x64", not args.f32)
    if args.child:
        plant, horizon, batch, repeats = args.child.split(":")
        return device_child(plant, int(horizon), int(batch), int(repeats))
    if args.quick:
        args.plants, args.batches, args.repeats, args.no_devices = "synthetic:4", "1,64", 1, True
    plants = [(p.split(":")[0], int(p.split(":")[1])) for p in args.plants.split(",")]
    batches = [int(b) for b in args.batches.split(",")]
    if args.pinned:
        device_rows = [r for plant, horizon in plants
                       for r in pinned(plant, horizon, max(batches), args.repeats, args.rounds)]
        print(markdown([], device_rows, []))
        return
    pool_options = {k: v for k, v in (("lanes", args.lanes), ("pop_width", args.pop_width)) if v is not None}
    rows, device_rows, sweep_rows = [], [], []
    for plant, horizon in plants:
        try:
            rows += measure(plant, horizon, batches, args.repeats, pool_options, args.solvers.split(","))
        except ImportError as e:  # a plant that is not (yet) in this checkout
            print(f"# skipping {plant}: {e}", file=sys.stderr)
            continue
        if args.sweep:
            sweep_rows += sweep(plant, horizon, batches, args.repeats)
    if not args.no_devices:
        plant, horizon = plants[0]
        device_rows = devices(plant, horizon, max(batches), args.repeats)
    print(markdown(rows, device_rows, sweep_rows))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"rows": rows, "devices": device_rows, "sweep": sweep_rows}, f, indent=1)


if __name__ == "__main__":
    main()
