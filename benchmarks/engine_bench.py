"""The JAX engine against compiled scalar code: every time as a ratio to the Numba peer (``numba_peer.py``).

One process, float64, medians after a warm-up. Rows: the fixed cost of one jitted call (N = 1, M = 1);
single sDFS solves (``jax.jit(fj.sdfs)``, K = 1) of the linear, synthetic and three-tank plants at N = 5;
the tanks' mean over a closed loop; batches on one core (``fj.solve_batch(cores=1)`` against the peer solving
row after row) and on every core (``fj.solve_batch``'s default against the peer's ``prange`` over the rows);
exhaustive search of the tanks. Each row checks that the peer found the library's sequences (and, for
single solves, its node counts). "per node" is the ratio of times per node (the pool's node counts differ
slightly from one sDFS per row). Needs ``pip install -e ".[bench]"``.

    python benchmarks/engine_bench.py [--quick] [--batches-only] [--repeats 7]
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import jax
import numpy as np

from firhc_jax._src.runtime.sharding import usable_cores

M = 17


def median_time(fn, repeats):
    """Median wall time of ``fn()`` after one warm-up call (which compiles); returns ``(seconds, result)``."""
    out = jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def check(name, ref_cost, ref_seq, cost, seq, ref_nodes=None, nodes=None):
    """Fail loudly if the peer and the library disagree: sequences (and node counts) exactly, costs to 1e-13
    (the last bits of a tank or synthetic state can differ, see ``numba_peer``)."""
    if not np.array_equal(np.asarray(ref_seq), np.asarray(seq)):
        raise AssertionError(f"{name}: sequences differ")
    np.testing.assert_allclose(np.asarray(cost), np.asarray(ref_cost), rtol=1e-13, atol=0, err_msg=name)
    if ref_nodes is not None and not np.array_equal(np.asarray(ref_nodes), np.asarray(nodes)):
        raise AssertionError(f"{name}: node counts differ")


def tank_states(problem, steps):
    """Controller states along the sDFS closed loop from the paper's initial levels."""
    from firhc_jax.apps.tanks import simulate

    return np.array(simulate(problem, "sdfs", steps)[0].states[:-1])  # a writable NumPy copy for Numba


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="smoke run: N = 3, small batches, few repeats")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--batches-only", action="store_true",
                    help="only the batch rows: one core each, then every core each (fj.solve_batch default "
                         "against the prange peer)")
    args = ap.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    import numba
    import numba_peer as peer
    from batch_bench import cpu_use

    import firhc_jax as fj
    from firhc_jax.models import tanks
    from firhc_jax.models.synthetic import SyntheticParams, benchmark_state, make_problem

    N = 3 if args.quick else 5
    reps = 2 if args.quick else args.repeats
    batches = (16, 64) if args.quick else (256, 4096)
    rng = np.random.default_rng(0)
    rows = []

    def add(name, t_numba, t_jax, nodes, jax_nodes=None, note=""):
        jax_nodes = nodes if jax_nodes is None else jax_nodes
        rows.append((name, t_numba, t_jax, nodes, jax_nodes, note))

    def single(name, problem, children, params, x, note=""):
        """One state; the peer's time is per solve over a compiled loop of solves (no Python dispatch)."""
        jitted = jax.jit(fj.sdfs)
        t_jax, ref = median_time(lambda: jitted(problem, x), reps)
        Mp, Np = problem.num_controls, problem.horizon
        cost, seq, nodes = peer.sdfs(children, params, x, Mp, Np)
        check(name, ref.cost, ref.sequence, cost, seq, ref.nodes, nodes)
        X = np.tile(x, (max(1, min(1000, 50_000 // nodes)), 1))
        t_nb, _ = median_time(lambda: peer.sdfs_batch(children, params, X, Mp, Np), reps)
        add(name, t_nb / len(X), t_jax, nodes, note=note + f"{int(ref.iterations)} iterations, "
            f"{1e6 * t_jax / int(ref.iterations):.2f} us/iteration (JAX)")

    lin, lin_p = peer.linear_problem(N), peer.linear_plant()
    tank, tank_p = tanks.make_problem(N), peer.tank_params()
    simd = peer.tank_children_simd  # the faster tank peer: every tanks row but one uses it
    states = tank_states(tank, 30 if args.quick else 100)
    T = len(states)
    hard = states[int(np.argmax(peer.sdfs_batch(simd, tank_p, states, M, N)[2]))]
    if not args.batches_only:
        # Fixed cost of a jitted call: one node, one input.
        single("fixed cost: N=1, M=1 (linear)", peer.linear_problem(1, 1), peer.linear_children, peer.linear_plant(1),
               np.ones(3))

        # The floor under it: a jitted call that returns a SearchResult (10 output buffers) without searching.
        one = peer.linear_problem(1, 1)
        empty = jax.jit(lambda x: fj.SearchResult(*(x[:1].sum() + i for i in range(10))))
        t_floor, _ = median_time(lambda: empty(np.ones(3)), reps)
        js = jax.jit(fj.sdfs)
        t_fixed = median_time(lambda: js(one, np.ones(3)), reps)[0]
        add("fixed cost: N=1, M=1 / a jitted call returning 10 outputs without searching", t_floor, t_fixed, 1,
            note="ratio to the floor (the Numba column holds the floor's time)")

        single(f"linear N={N}", lin, peer.linear_children, lin_p, np.array([1.5, -1.0, 0.8]))
        syn = make_problem(N, SyntheticParams(M), dtype=np.float64)
        single(f"synthetic N={N}", syn, peer.synthetic_children, peer.synthetic_params(syn),
               np.asarray(benchmark_state(np.float64)))

        single(f"tanks N={N}, hardest closed-loop state, peer one child at a time", tank, peer.tank_children, tank_p,
               hard)
        single(f"tanks N={N}, hardest closed-loop state", tank, simd, tank_p, hard)

        jitted = jax.jit(fj.sdfs)

        def jax_loop():
            return [jitted(tank, x) for x in states]

        t_jax, refs = median_time(jax_loop, max(1, reps // 2))
        t_nb, (costs, seqs, nodes) = median_time(lambda: peer.sdfs_batch(simd, tank_p, states, M, N),
                                                 max(1, reps // 2))
        check("tanks closed loop", [r.cost for r in refs], [r.sequence for r in refs], costs, seqs,
              [r.nodes for r in refs], nodes)
        add(f"tanks N={N}, mean over {T} closed-loop states", t_nb / T, t_jax / T, int(nodes.sum()) // T,
            note="one call per state")

    cores = usable_cores()
    for B in batches:
        X_lin = rng.uniform(-2, 2, (B, 3))
        X_tank = states[rng.integers(0, T, B)]  # closed-loop states with levels moved by up to 5 mm
        X_tank[:, :3] += rng.uniform(-0.005, 0.005, (B, 3))
        for name, problem, children, params, X in (("linear", lin, peer.linear_children, lin_p, X_lin),
                                                   ("tanks", tank, simd, tank_p, X_tank)):
            # One core each (the engine ratio), then every core each: solve_batch's default against prange.
            for label, cores_, peer_batch, note in (
                    ("one core, fj.solve_batch(cores=1)", 1, peer.sdfs_batch, "Numba: one core, row after row"),
                    (f"{cores} cores, fj.solve_batch default", None, peer.sdfs_batch_parallel,
                     f"Numba: prange over the rows, {numba.get_num_threads()} threads")):
                jax_call = lambda problem=problem, X=X, c=cores_: fj.solve_batch(problem, X, cores=c)  # noqa: E731
                peer_call = lambda children=children, params=params, X=X, f=peer_batch: f(  # noqa: E731
                    children, params, X, M, N)
                t_jax, ref = median_time(jax_call, max(1, reps // 2))
                t_nb, (costs, seqs, nodes) = median_time(peer_call, max(1, reps // 2))
                check(f"{name} batch {B} {label}", ref.cost, ref.sequence, costs, seqs)
                if cores_ is None:  # on a shared machine: what idle cores would take, from the threads' CPU time
                    calls = [min(1000, max(reps // 2, int(0.5 / t))) for t in (t_jax, t_nb)]  # >= 0.5 s: ticks
                    idle = [max(busiest, cpu / cores)
                            for _, busiest, cpu in (cpu_use(jax_call, calls[0]), cpu_use(peer_call, calls[1]))]
                    jax_nodes = int(np.asarray(ref.nodes).sum())
                    note += (f"; idle cores (threads' CPU time): JAX {_ms(idle[0])}, Numba {_ms(idle[1])}, per node "
                             f"{(idle[0] / jax_nodes) / (idle[1] / int(nodes.sum())):.1f}x")
                add(f"batch {name} N={N}, B={B}, {label}", t_nb, t_jax, int(nodes.sum()),
                    int(np.asarray(ref.nodes).sum()), note=note)

    if not args.batches_only:
        t_jax, ref = median_time(lambda: fj.exhaustive(tank, hard), max(1, reps // 3))
        t_nb, (cost, seq, nodes) = median_time(lambda: peer.exhaustive(simd, tank_p, hard, M, N),
                                               max(1, reps // 3))
        check("tanks exhaustive", ref.cost, ref.sequence, cost, seq, ref.nodes, nodes)
        add(f"exhaustive tanks N={N} (fj.exhaustive, levels)", t_nb, t_jax, nodes, note="hardest state")

        # The other peer for exhaustive search: a hand-written level-by-level vmap of the same callables.
        hand = jax.jit(lambda x: handwritten_levels(tank, x))
        t_hand, (h_cost, h_idx) = median_time(lambda: hand(hard), max(1, reps // 3))
        if not np.isclose(float(h_cost), float(ref.cost), rtol=1e-12):
            raise AssertionError("hand-written levels: cost differs from fj.exhaustive")
        add(f"exhaustive tanks N={N}: fj.exhaustive / hand-written vmap levels", t_hand, t_jax, nodes,
            note="ratio to the hand-written vmap, not to Numba (the Numba column holds the vmap)")

        # The pool over lanes: more lanes must never be slower (linear plant, largest batch).
        X_lin = rng.uniform(-2, 2, (batches[-1], 3))
        base = None
        for lanes in (16, 64, 256, 1024):
            t, r = median_time(lambda lanes=lanes: fj.solve_batch(lin, X_lin, lanes=lanes), max(1, reps // 2))
            base = base or t
            add(f"lanes sweep: linear N={N}, B={len(X_lin)}, lanes={lanes}", base, t, int(np.asarray(r.nodes).sum()),
                note="ratio to lanes=16 (the Numba column holds lanes=16's time)")

    print(f"# JAX engine vs Numba peer, float64, {'quick' if args.quick else 'full'} run; jax {jax.__version__}, "
          f"numba {numba.__version__}; {platform.machine()}, {cores} usable cores, {jax.local_device_count()} JAX "
          f"device(s); medians of {reps} after a warm-up; load average {os.getloadavg()[0]:.1f} at the end")
    print("| problem | Numba | JAX | nodes (Numba / JAX) | Numba ns/node | JAX ns/node | JAX / Numba | per node |"
          " note |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---|")
    for name, t_nb, t_jax, nodes, jax_nodes, note in rows:
        nodes_txt = f"{nodes:,}" if nodes == jax_nodes else f"{nodes:,} / {jax_nodes:,}"
        print(f"| {name} | {_ms(t_nb)} | {_ms(t_jax)} | {nodes_txt} | {1e9 * t_nb / nodes:.1f} | "
              f"{1e9 * t_jax / jax_nodes:.1f} | {t_jax / t_nb:.1f}x | {(t_jax / jax_nodes) / (t_nb / nodes):.1f}x | "
              f"{note} |")


def handwritten_levels(problem, x0):
    """Exhaustive search as a user would write it without the library: every level of the tree in one
    vmapped call of the problem's callables, then the cheapest leaf (unconstrained problems only)."""
    import jax.numpy as jnp

    U = jnp.asarray(problem.controls)
    x, cost = x0[None], jnp.zeros((1,), x0.dtype)

    def children(x):
        xs = jax.vmap(lambda u: problem.dynamics(x, u))(U)
        return xs, jax.vmap(problem.stage_cost)(xs, U)

    for _ in range(problem.horizon):
        xs, stage = jax.vmap(children)(x)
        x, cost = xs.reshape(-1, x.shape[-1]), (cost[:, None] + stage).reshape(-1)
    return jnp.min(cost), jnp.argmin(cost)


def _ms(t):
    return f"{1e3 * t:.3f} ms" if t < 1 else f"{t:.2f} s"


if __name__ == "__main__":
    main()
