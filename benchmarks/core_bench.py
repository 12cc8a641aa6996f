"""Single-solve speed of every search on the 17-input, 3-state, N = 5 synthetic problem.

Prints one table: nodes, loop iterations, median time, time per iteration, and
each time as a ratio to the vectorised exhaustive search measured in the same
process, plus a hand-written ``vmap`` exhaustive baseline (throughput yardstick).

    python benchmarks/core_bench.py [--f32] [--repeats 30] [--horizon 5] [--publish]
"""
from __future__ import annotations

import argparse
import statistics
import time

import jax
import jax.numpy as jnp
from _results import machine, published


def median_time(fn, repeats):
    jax.block_until_ready(fn())  # warm-up (compiles)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def handwritten_exhaustive(problem):
    """The yardstick: a plain vmap per level over the same callables, no chunking."""
    def solve(x0):
        x, cost = x0[None], jnp.zeros((1,), x0.dtype)
        for _ in range(problem.horizon):
            def children(xi, ci):
                xs = jax.vmap(lambda u: problem.dynamics(xi, u))(problem.controls)
                return xs, ci + jax.vmap(problem.stage_cost)(xs, problem.controls)
            x, cost = jax.vmap(children)(x, cost)
            x, cost = x.reshape(-1, x.shape[-1]), cost.reshape(-1)
        return jnp.min(cost)
    return jax.jit(solve)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--f32", action="store_true", help="float32 (default float64)")
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--horizon", type=int, default=5)
    ap.add_argument("--publish", action="store_true", help="also write the table to benchmarks/results/core.md")
    args = ap.parse_args(argv)
    with published("core", args.publish, "python benchmarks/core_bench.py --publish"):
        run(args)


def run(args):
    jax.config.update("jax_enable_x64", not args.f32)
    import firhc_jax as fj
    from firhc_jax.models.synthetic import SyntheticParams, benchmark_state, make_problem

    dtype = jnp.float32 if args.f32 else jnp.float64
    problem = make_problem(args.horizon, SyntheticParams(17), dtype=dtype)
    x0 = benchmark_state(dtype)
    rows = []

    def add(name, fn, repeats=args.repeats):
        r = fn()
        t = median_time(fn, repeats)
        rows.append((name, int(r.nodes) if hasattr(r, "nodes") else problem.tree_size(),
                     int(r.iterations) if hasattr(r, "iterations") else None, t))

    add("exhaustive (levels)", lambda: fj.exhaustive(problem, x0), max(3, args.repeats // 6))
    add("hand-written vmap exhaustive", lambda: handwritten_exhaustive(problem)(x0), max(3, args.repeats // 6))
    add("exhaustive dfs K=1", lambda: fj.exhaustive(problem, x0, method="dfs"), 3)
    for k in (1, 2, 4, 8):
        add(f"sdfs K={k}", lambda k=k: fj.sdfs(problem, x0, pop_width=k))
    jitted = jax.jit(lambda x: fj.sdfs(problem, x))
    add("sdfs K=1 inside jit", lambda: jitted(x0))

    base = rows[0][3]
    print(f"M=17, n=3, N={args.horizon}, {jnp.dtype(dtype).name}; tree {problem.tree_size():,} nodes; {machine()}\n")
    print("| search | nodes | % of tree | iterations | median time | us / iteration | time / exhaustive |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name, nodes, iters, t in rows:
        per_it = f"{1e6 * t / iters:.2f}" if iters and "sdfs" in name or (iters and "dfs" in name) else ""
        print(f"| {name} | {nodes:,} | {100 * nodes / problem.tree_size():.3f} | {iters if iters else ''} | "
              f"{1e3 * t:.3f} ms | {per_it} | {100 * t / base:.2f}% |")


if __name__ == "__main__":
    main()
