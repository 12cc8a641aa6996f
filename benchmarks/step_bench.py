"""What a decision costs outside a compiled loop: eager calls against their compiled forms.

Four tables, float64, one process; rows that are compared are interleaved in
rounds so that a noisy neighbour hits them alike, and the ratio of medians is
the figure of merit.

* step: the two-level inverter of ``firhc_jax.models.inverter`` (8 switch
  states, switching penalty through ``observe``, a new reference every step
  as parameters) at each ``--horizons`` N: an eager ``ctrl.step(state, x, p)``
  per decision (the real-time path, timed to its ``u``) against the same
  decision inside ``simulate``'s compiled scan (the run's wall time per step,
  plant included) and inside ``simulate(..., compiled=False)``
  (``solve_times``).
* one-shot: eager ``fj.sdfs``, ``ctrl(x, p)`` (inverter, N = 3) and
  ``lt.solve`` (three-level inverter, N = 5, ``firhc_jax.models.three_level``)
  against ``jax.jit`` of the same call; each call gets new values (states and
  references of a closed loop).
* python loop: ``simulate(..., compiled=False)`` of ``--loop-steps`` steps on a
  fresh controller, first call against second; the first call's compilation
  (tracing, lowering, XLA, from ``jax.monitoring``) is reported apart. Then
  the same loop with the plant not jitted (what each step pays for it).
* progress: a compiled ``simulate`` of ``--progress-steps`` cheap steps (N = 2,
  3 inputs) with and without ``progress=True``.
* runtime: what bounds a standalone call on XLA:CPU. A jitted function of k
  independent 800-byte results (``sin(x * i)``) for k = 4 .. 16, and the
  eager step of the inverter at N = 1 against it returning ``u`` only:
  microseconds a call and the process's context switches a call (every
  thread's, from ``/proc``; Linux only).

    python benchmarks/step_bench.py [--horizons 1 3] [--steps 300] [--rounds 3] [--loop-steps 1600]
                                    [--progress-steps 20000] [--sections step oneshot loop progress runtime]
"""
from __future__ import annotations

import argparse
import contextlib
import glob
import os
import platform
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

import firhc_jax as fj
from firhc_jax.apps._timing import BACKEND_COMPILE, LOWERED, TRACED
from firhc_jax.models import inverter, three_level

COMPILE_EVENTS = (TRACED, LOWERED, BACKEND_COMPILE)


def median_us(ts) -> float:
    return 1e6 * statistics.median(ts)


def inverter_case(N: int, T: int):
    """``(ctrl, plant, eager plant, x0, u0, params [T], rows)`` of the inverter at horizon N."""
    prm = inverter.InverterParams()
    mem = inverter.make_problem(N, prm)
    refs = inverter.horizon_references(prm, T, N)  # [T, N, 2]
    params = {"ref": jnp.asarray(refs), "lambda_u": jnp.ones(T)}
    rows = [{"ref": jnp.asarray(refs[k]), "lambda_u": jnp.asarray(1.0, jnp.float64)} for k in range(T)]
    rl = inverter.make_plant(prm)
    eager_plant = lambda i, u, p: rl(i, u)  # noqa: E731
    x0, u0 = jnp.asarray(inverter.initial_currents(prm)), jnp.zeros(3)
    return fj.FIRHC(mem.problem, observe=mem.observe), jax.jit(eager_plant), eager_plant, x0, u0, params, rows


def section_step(horizons, T: int, rounds: int):
    print(f"\n## Eager step against the compiled scan: inverter, {rounds} x {T} decisions per row\n")
    print("| N | eager `ctrl.step` us (median) | scan us per step | `compiled=False` solve_times us | "
          "eager / scan | eager / compiled=False |")
    print("|---:|---:|---:|---:|---:|---:|")
    for N in horizons:
        times = step_times(N, T, rounds)
        e, s, lp = (median_us(times[k]) for k in ("step", "scan", "loop"))
        print(f"| {N} | {e:.1f} | {s:.1f} | {lp:.1f} | {e / s:.2f}x | {e / lp:.2f}x |")


def step_times(N: int, T: int, rounds: int) -> dict:
    """Seconds per decision of the eager step, the scan and the Python loop, interleaved in rounds."""
    ctrl, plant, _, x0, u0, params, rows = inverter_case(N, T)

    def step():
        state, x, times = ctrl.init(x0, u0), x0, []
        for k in range(T):
            t0 = time.perf_counter()
            u, state, info = ctrl.step(state, x, rows[k])
            jax.block_until_ready(u)
            times.append(time.perf_counter() - t0)
            x = plant(x, u, rows[k])
        return times

    def scan():  # ten runs a round: one run is a few milliseconds
        times = []
        for _ in range(10):
            t0 = time.perf_counter()
            jax.block_until_ready(ctrl.simulate(x0, T, plant, params=params, u0=u0).states)
            times.append((time.perf_counter() - t0) / T)
        return times

    def loop():
        return list(np.asarray(ctrl.simulate(x0, T, plant, params=params, u0=u0, compiled=False).solve_times))

    ways = {"step": step, "scan": scan, "loop": loop}
    for fn in ways.values():  # compile and warm up
        fn()
    times = {name: [] for name in ways}
    for _ in range(rounds):
        for name, fn in ways.items():
            times[name] += fn()
    return times


def three_level_calls(calls: int):
    """``(lt, [(x, u_prev, y_ref)] * calls)``: the three-level inverter at N = 5 and the arguments of its
    ``lt.solve`` along a closed loop."""
    lt = three_level.make_problem(5)
    A, B = three_level.model()
    lrefs = inverter.horizon_references(three_level.PARAMS, calls, 5)
    x, u, largs = inverter.reference(three_level.PARAMS, 0.0), np.zeros(3), []
    for k in range(calls):  # the states of the closed loop
        largs.append((x, u, lrefs[k]))
        u = np.asarray(lt.controls[int(lt.solve(x, u, lrefs[k]).sequence[0])])
        x = A @ x + B @ u
    return lt, largs


def section_oneshot(calls: int, rounds: int):
    print(f"\n## One-shot calls, eager against `jax.jit` of the same call ({rounds} x {calls} calls, new values "
          "each)\n")
    print("| call | eager us (median) | jit us (median) | eager / jit |")
    print("|---|---:|---:|---:|")
    rng = np.random.default_rng(0)
    prm = inverter.InverterParams()
    mem = inverter.make_problem(3, prm)
    refs = inverter.horizon_references(prm, calls, 3)
    P, ctrl = mem.problem, fj.FIRHC(mem.problem)
    states = [np.asarray(mem.observe(rng.normal(size=2) * 5, inverter.SWITCH_STATES[rng.integers(8)]))
              for _ in range(calls)]
    rows = [{"ref": refs[k], "lambda_u": np.float64(1.0)} for k in range(calls)]
    lt, largs = three_level_calls(calls)
    cases = {
        "`fj.sdfs(problem, x, params=p)`, inverter N = 3": (lambda x, p: fj.sdfs(P, x, params=p),
                                                           list(zip(states, rows, strict=True))),
        "`ctrl(x, p)`, inverter N = 3": (lambda x, p: ctrl(x, p), list(zip(states, rows, strict=True))),
        "`lt.solve(x, u_prev, y_ref)`, three-level N = 5": (lambda x, u, y: lt.solve(x, u, y), largs),
    }
    for name, (fn, argsets) in cases.items():
        ways = {"eager": fn, "jit": jax.jit(fn)}
        times = {k: [] for k in ways}
        for f in ways.values():
            for a in argsets[:3]:
                jax.block_until_ready(f(*a))
        for _ in range(rounds):
            for k, f in ways.items():
                for a in argsets:
                    t0 = time.perf_counter()
                    jax.block_until_ready(f(*a))
                    times[k].append(time.perf_counter() - t0)
        e, j = median_us(times["eager"]), median_us(times["jit"])
        print(f"| {name} | {e:.1f} | {j:.1f} | {e / j:.2f}x |")


@contextlib.contextmanager
def compile_seconds():
    """The seconds of tracing, lowering and XLA compilation inside the block (``jax.monitoring``): ``[s]``."""
    total = [0.0]

    def listener(event, duration, **kw):
        if event in COMPILE_EVENTS:
            total[0] += duration

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield total
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


def section_loop(T: int):
    print(f"\n## `simulate(..., compiled=False)`: first call against second, inverter N = 3, {T} steps\n")
    fj.clear_cache()  # the first call compiles, as in a fresh process (the step section compiled this decision)
    jax.clear_caches()
    ctrl, plant, eager_plant, x0, u0, params, _ = inverter_case(3, T)
    walls, compiles = [], []
    for _ in range(2):
        with compile_seconds() as c:
            t0 = time.perf_counter()
            ctrl.simulate(x0, T, plant, params=params, u0=u0, compiled=False)
            walls.append(time.perf_counter() - t0)
        compiles.append(c[0])
    t0 = time.perf_counter()
    ctrl.simulate(x0, T, eager_plant, params=params, u0=u0, compiled=False)
    eager = time.perf_counter() - t0
    print("| call | wall s | compilation s | wall less compilation s | us per step |")
    print("|---|---:|---:|---:|---:|")
    for name, w, c in (("first", walls[0], compiles[0]), ("second", walls[1], compiles[1])):
        print(f"| {name} | {w:.2f} | {c:.2f} | {w - c:.2f} | {1e6 * (w - c) / T:.0f} |")
    print(f"| third, plant not jitted | {eager:.2f} | | | {1e6 * eager / T:.0f} |")
    print(f"\nfirst / second (compilation excluded): {(walls[0] - compiles[0]) / (walls[1] - compiles[1]):.2f}x; "
          f"an unjitted plant adds {1e6 * (eager - walls[1]) / T:.0f} us a step")


def section_progress(steps: int, rounds: int):
    """Compiled closed loop of cheap steps with and without a progress bar (drawn on stderr), interleaved."""
    from firhc_jax._src.runtime import progress

    prob = fj.Problem(lambda x, u: 0.9 * x + 0.1 * u, jnp.array([-1.0, 0.0, 1.0]), fj.quadratic_cost(1.0, 0.0), 2)
    ctrl, x0 = fj.FIRHC(prob), jnp.ones(1)

    def run(on):
        t0 = time.perf_counter()
        jax.block_until_ready(ctrl.simulate(x0, steps, progress=on).states)
        return time.perf_counter() - t0

    run(False), run(True)  # compile both
    times = {False: [], True: []}
    for _ in range(rounds):
        for on in (False, True):
            times[on].append(run(on))
    off, on = statistics.median(times[False]), statistics.median(times[True])
    print(f"\n## Compiled simulate of {steps:,} cheap steps (N = 2, M = 3), median of {rounds}\n")
    print("| progress | s per run | us per step |")
    print("|---|---:|---:|")
    for name, t in (("off", off), ("on", on)):
        print(f"| {name} | {t:.3f} | {1e6 * t / steps:.2f} |")
    print(f"\nprogress on / off: {on / off:.3f}x ({progress.interval(steps)} steps per bar update)")


def context_switches() -> int:
    """Voluntary and involuntary context switches of every thread of this process so far (Linux)."""
    total = 0
    for status in glob.glob(f"/proc/{os.getpid()}/task/*/status"):
        with contextlib.suppress(FileNotFoundError):
            with open(status) as f:
                total += sum(int(line.split()[1]) for line in f if "ctxt_switches" in line)
    return total


def per_call(fn, args_list, calls: int) -> tuple[float, float]:
    """Median microseconds of ``fn(*args)`` (cycling through ``args_list``) and context switches a call."""
    for a in args_list[:3]:
        jax.block_until_ready(fn(*a))
    times, before = [], context_switches()
    for k in range(calls):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args_list[k % len(args_list)]))
        times.append(time.perf_counter() - t0)
    return median_us(times), (context_switches() - before) / calls


def section_runtime(calls: int):
    print(f"\n## What bounds a standalone call: independent results against thread hand-offs ({calls} calls a row)\n")
    print("| program | us a call (median) | context switches a call |")
    print("|---|---:|---:|")
    x = jnp.ones(100)  # 800 bytes: above the size under which XLA:CPU runs a program's operations in order
    for k in (4, 8, 9, 10, 12, 16):
        fn = jax.jit(lambda x, k=k: tuple(jnp.sin(x * (i + 1)) for i in range(k)))
        us, switches = per_call(fn, [(x,)], calls)
        print(f"| {k} independent results | {us:.1f} | {switches:.2f} |")
    ctrl, _, _, x0, u0, _, rows = inverter_case(1, 50)
    state = ctrl.init(x0, u0)
    decide = ctrl._decide()
    for name, fn in (("inverter decision, N = 1: `ctrl.step`", ctrl.step),
                     ("the same decision returning `u` only", jax.jit(lambda s, x, p: decide(s, x, p)[0]))):
        us, switches = per_call(fn, [(state, x0, r) for r in rows], calls)
        print(f"| {name} | {us:.1f} | {switches:.2f} |")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--horizons", type=int, nargs="+", default=[1, 3])
    ap.add_argument("--steps", type=int, default=300, help="decisions per round and row (step, one-shot)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--loop-steps", type=int, default=1600)
    ap.add_argument("--progress-steps", type=int, default=20_000)
    ap.add_argument("--sections", nargs="+", default=["step", "oneshot", "loop", "progress", "runtime"],
                    choices=["step", "oneshot", "loop", "progress", "runtime"])
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    print(f"# {platform.machine()}, {jax.devices()[0].platform}, jax {jax.__version__}, float64")
    if "step" in args.sections:
        section_step(args.horizons, args.steps, args.rounds)
    if "oneshot" in args.sections:
        section_oneshot(args.steps, args.rounds)
    if "loop" in args.sections:
        section_loop(args.loop_steps)
    if "progress" in args.sections:
        section_progress(args.progress_steps, max(3 * args.rounds, 9))
    if "runtime" in args.sections:
        section_runtime(2000)


if __name__ == "__main__":
    main()
