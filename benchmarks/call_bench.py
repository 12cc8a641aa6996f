"""Where the time of one eager decision goes: Python, the call and its outputs, the search.

Each public call is timed as users make it (new values every call, float64), and split into

* **Python**: the public call minus its compiled program (the checks, the signature look-up, reading the
  alarm; ``firhc_jax._src.runtime.lean``);
* **call**: a compiled program of the same arguments that only adds one to the state (what XLA:CPU and
  JAX's dispatch charge for these inputs and one output);
* **outputs**: reading the one output buffer back into the result's NumPy fields
  (``firhc_jax._src.runtime.packed``);
* **search**: the compiled program minus the call.

Rows: ``fj.sdfs`` on a 2-state 3-input pendulum at N = 1 and 5 (also with ``engine="c"``), ``ctrl.step`` and the
one-shot ``ctrl(x)`` on the two-level inverter (8 switch states, the reference as per-step parameters) at N = 1 and
3 (``ctrl.step`` also with ``engine="c"``: the generated C decision through ``ctypes``), ``lt.solve`` on the
three-level inverter at N = 5 (also with ``engine="c"``), and the step of ``simulate``'s compiled scan (inverter, N
= 3: the run's time per step, plant included). Every time is also a multiple of a trivial jitted call
(``jax.jit(lambda x: x + 1.0)`` on a JAX array), measured in the same rounds. Medians (p50) and 99th percentiles
(p99) of ``--calls`` calls a round, rounds interleaved; once pinned to one core (``os.sched_setaffinity``), once on
every core.

    python benchmarks/call_bench.py [--calls 2000] [--rounds 3] [--publish] [--small-loops]

``--small-loops``: the same, with ``fj.enable_small_loop_kernels()`` made first (its own process).
"""
from __future__ import annotations

import argparse
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
from _results import published
from step_bench import three_level_calls


def percentiles(ts) -> tuple[float, float]:
    return 1e6 * float(np.percentile(ts, 50)), 1e6 * float(np.percentile(ts, 99))


def cases(calls: int):
    """``{name: (public call, compiled program, trivial program of its arguments, unpack, argument sets)}``."""
    import firhc_jax as fj
    from firhc_jax._src.runtime import lean
    from firhc_jax.models import inverter

    rng = np.random.default_rng(0)
    out = {}
    budget, u0 = np.int32(2**31 - 1), np.zeros(3)  # no node budget; the one-shot call's input before

    def pendulum(x, u):
        omega = x[1] + 0.05 * (-9.81 * jnp.sin(x[0]) - 0.5 * x[1] + 2.0 * u[0])
        return jnp.stack([x[0] + 0.05 * omega, omega])

    for N in (1, 5):
        problem = fj.Problem(dynamics=pendulum, controls=np.array([-1.0, 0.0, 1.0]),
                             stage_cost=fj.quadratic_cost(lam=np.array([10.0, 1.0]), x_s=np.zeros(2), beta=0.1),
                             horizon=N)
        argsets = [(rng.uniform(-0.6, 0.6, 2),) for _ in range(calls)]
        fj.sdfs(problem, *argsets[0])
        entry = ("sdfs", problem, int, 1, False, int, fj.sdfs.__kwdefaults__["max_memory"], "xla")
        program = lean.recall(entry, (argsets[0][0], None, None))
        out[f"`fj.sdfs`, pendulum (2 states, 3 inputs), N = {N}"] = (
            lambda x, p=problem: fj.sdfs(p, x), lambda x, r=program: r(x, None, None, budget), (argsets[0][0],),
            argsets)
        fj.sdfs(problem, *argsets[0], engine="c")
        c_run = lean.recall(entry[:-1] + ("c",), (argsets[0][0], None, None))
        x_at, p_at, _, record_at = c_run._buffers()[-1]
        out[f"`fj.sdfs`, pendulum (2 states, 3 inputs), N = {N}, `engine=\"c\"`"] = (
            lambda x, p=problem: fj.sdfs(p, x, engine="c"),
            lambda x, f=c_run._fn, a=(x_at, p_at, None, 0, int(budget), record_at): f(*a), None, argsets)

    prm = inverter.InverterParams()
    for N in (1, 3):
        mem = inverter.make_problem(N, prm)
        refs = inverter.horizon_references(prm, calls, N)
        ctrl = fj.FIRHC(mem.problem, observe=mem.observe)
        xs = [np.asarray(inverter.initial_currents(prm)) + rng.normal(size=2) for _ in range(calls)]
        rows = [{"ref": refs[k], "lambda_u": np.float64(1.0)} for k in range(calls)]
        state = ctrl.init(xs[0], np.zeros(3))
        ctrl.step(state, xs[0], rows[0])
        program = lean.recall(("step", ctrl), (state, xs[0], rows[0]))
        out[f"`ctrl.step`, inverter (8 inputs), N = {N}"] = (
            lambda x, p, c=ctrl, s=state: c.step(s, x, p), lambda x, p, r=program, s=state: r(s, x, p),
            (state, xs[0], rows[0]), list(zip(xs, rows, strict=True)))
        c_ctrl = fj.FIRHC(mem.problem, observe=mem.observe, engine="c")
        c_state = c_ctrl.init(xs[0], np.zeros(3))
        c_ctrl.step(c_state, xs[0], rows[0])
        c_run = lean.recall(("step", c_ctrl), (c_state, xs[0], rows[0]))
        record, _, _, _, _, *addresses = c_run._buffers()
        out[f"`ctrl.step`, inverter (8 inputs), N = {N}, `engine=\"c\"`"] = (
            lambda x, p, c=c_ctrl, s=c_state: c.step(s, x, p), lambda x, p, f=c_run._fn, a=addresses: f(*a),
            None, list(zip(xs, rows, strict=True)))
        if N == 3:
            ctrl(xs[0], rows[0])
            program = lean.recall(("call", ctrl), (xs[0], rows[0], None))
            budget = state.budget  # the controller's (none: INT32_MAX), an argument of its decision
            out[f"`ctrl(x, p)`, inverter (8 inputs), N = {N}"] = (
                lambda x, p, c=ctrl: c(x, p), lambda x, p, r=program, b=budget: r(x, p, u0, b),
                (xs[0], rows[0], u0, budget), list(zip(xs, rows, strict=True)))

    lt, largs = three_level_calls(calls)
    program = lean.recall(("lt.solve", lt, True, "xla"), largs[0] + (None, None))
    out["`lt.solve`, three-level inverter, N = 5"] = (
        lambda x, u, y: lt.solve(x, u, y), lambda x, u, y: program(x, u, y, None, None, budget),
        lt._on_device(np.float64) + (lt._controls, lt._class_of) + largs[0] + (None, None, budget), largs)
    lt.solve(*largs[0], engine="c")
    c_run = lean.recall(("lt.solve", lt, True, "c"), largs[0] + (None, None))
    x_at, u_at, p_at, _, record_at = c_run._buffers()[-1]
    out["`lt.solve`, three-level inverter, N = 5, `engine=\"c\"`"] = (
        lambda x, u, y: lt.solve(x, u, y, engine="c"),
        lambda x, u, y, f=c_run._fn, a=(x_at, u_at, p_at, None, 0, int(budget), record_at): f(*a), None, largs)
    return out


def trivial_of(args):
    """A compiled program of these arguments that adds one to the first floating array: the call's cost."""
    leaves = jax.tree_util.tree_leaves(args)
    first = next(i for i, a in enumerate(leaves) if np.issubdtype(np.asarray(a).dtype, np.floating))
    fn = jax.jit(lambda *a: jax.tree_util.tree_leaves(a)[first] + 1.0)
    return fn.lower(*args).compile()


def scan_step(calls: int):
    import firhc_jax as fj
    from firhc_jax.models import inverter

    prm = inverter.InverterParams()
    mem = inverter.make_problem(3, prm)
    refs = inverter.horizon_references(prm, calls, 3)
    ctrl = fj.FIRHC(mem.problem, observe=mem.observe)
    rl = inverter.make_plant(prm)
    plant = jax.jit(lambda i, u, p: rl(i, u))
    params = {"ref": refs, "lambda_u": np.ones(calls)}
    x0 = np.asarray(inverter.initial_currents(prm))

    def run():
        return ctrl.simulate(x0, calls, plant, params=params, progress=False)
    run()
    return run


def measure(calls: int, rounds: int) -> list[tuple]:
    triv = jax.jit(lambda x: x + 1.0)
    xj = jnp.ones(2)
    triv(xj).block_until_ready()
    rows = []
    table = cases(calls)
    scan = scan_step(calls)
    t_triv, t_scan = [], []
    times = {name: {"public": [], "program": [], "call": []} for name in table}
    trivials = {name: trivial_of(c[2]) for name, c in table.items() if c[2] is not None}
    for _ in range(rounds):
        for _ in range(calls):
            t0 = time.perf_counter()
            triv(xj).block_until_ready()
            t_triv.append(time.perf_counter() - t0)
        for name, (public, program, args, argsets) in table.items():
            for which, fn in (("public", public), ("program", program)):
                for a in argsets:
                    t0 = time.perf_counter()
                    fn(*a)
                    times[name][which].append(time.perf_counter() - t0)
            triv_args = trivials.get(name)
            for _ in argsets if triv_args is not None else ():
                t0 = time.perf_counter()
                triv_args(*args).block_until_ready()
                times[name]["call"].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        scan()
        t_scan.append((time.perf_counter() - t0) / calls)
    unit = percentiles(t_triv)[0]
    rows.append(("trivial `jax.jit(lambda x: x + 1.0)`", *percentiles(t_triv), None, None, None, 1.0))
    for name, t in times.items():
        p50, p99 = percentiles(t["public"])
        prog = percentiles(t["program"])[0]
        if t["call"]:
            call = percentiles(t["call"])[0]
            rows.append((name, p50, p99, p50 - prog, call, prog - call, p50 / unit))
        else:  # the C engine: Python is everything but the C call, which the search column holds
            rows.append((name, p50, p99, p50 - prog, None, prog, p50 / unit))
    s = 1e6 * float(np.median(t_scan))
    rows.append(("`simulate`'s compiled scan, one step (inverter, N = 3, plant included)", s, None, None, None,
                 None, s / unit))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--calls", type=int, default=2000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--publish", action="store_true", help="also write the tables to benchmarks/results/call.md")
    ap.add_argument("--small-loops", action="store_true",
                    help="opt in to fj.enable_small_loop_kernels() first (results/call_small_loops.md)")
    args = ap.parse_args(argv)
    if args.small_loops:
        import firhc_jax as fj

        fj.enable_small_loop_kernels()
    jax.config.update("jax_enable_x64", True)
    name, flag = ("call_small_loops", " --small-loops") if args.small_loops else ("call", "")
    with published(name, args.publish, f"python benchmarks/call_bench.py --publish{flag}"):
        tables(args)


def tables(args) -> None:
    print("\nPython: the public call minus its compiled program; call: a program of the same arguments that only "
          "adds one; search + outputs: the program minus that call. us; p50 unless said. `engine=\"c\"` rows: "
          "search + outputs is the C decision called through ctypes on buffers already written; Python is the "
          "rest (writing the arguments, reading the outputs, the signature look-up).")
    every = os.sched_getaffinity(0)
    for label, cores in (("pinned to one core", {max(every)}), ("every core", every)):
        os.sched_setaffinity(0, cores)
        rows = measure(args.calls, args.rounds)
        print(f"\n## {label}\n")
        print("| call | p50 | p99 | Python | call | search + outputs | p50 / trivial call |")
        print("|---|---:|---:|---:|---:|---:|---:|")
        fmt = lambda v: "" if v is None else f"{v:.1f}"  # noqa: E731
        for name, p50, p99, py, call, search, ratio in rows:
            print(f"| {name} | {p50:.1f} | {fmt(p99)} | {fmt(py)} | {fmt(call)} | {fmt(search)} | {ratio:.1f}x |")
    os.sched_setaffinity(0, every)


if __name__ == "__main__":
    main()
