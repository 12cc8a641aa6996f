"""A real-time loop's decision times: p50, p99 and the maximum, collector on or paused, pinned or not,
quiet or loaded.

The loop is the real-time recipe (docs/guide/realtime.md): a Python loop of ``ctrl.step`` on the two-level
inverter (``firhc_jax.models.inverter``, switching penalty through ``observe``, a new reference every step)
and a jitted plant, each decision timed until its ``u`` is ready. The loop keeps every step's ``(u, info)``,
as a logging loop does: the objects that make Python's cyclic garbage collector run. Three ways, alternated
in rounds within one process:

* ``collector on``: the loop as Python runs it by default;
* ``gc.freeze(), collector on``: every object alive before the loop moved out of the collector's sight first
  (``gc.unfreeze()`` after);
* ``fj.collector_paused()``: the same loop inside it;
* ``simulate(compiled=False)``: the library's own Python loop (``solve_times``), which pauses the collector.

Every collection during a way's calls is timed (``gc.callbacks``): how many, how many of the oldest generation
(the ones that walk every object of the process), and the longest. For ``simulate`` they fall after its loop,
when the collector is on again, outside the decisions it times.

Each (pinning, load) setting is a fresh process: ``pinned`` restricts it to one core before JAX starts its
threads, so XLA's threads share that core with Python. ``loaded``: this script first starts one busy process
per core (pure Python loops) and stops them after. The machine's own load (other users) is printed with
each row: "quiet" only means no load of this script's.

    python benchmarks/realtime_bench.py [--horizon 1] [--steps 2000] [--rounds 3] [--repeats 2] [--publish]
"""
from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import subprocess
import sys
import time

import numpy as np

WAYS = ("collector on", "gc.freeze(), collector on", "fj.collector_paused()", "simulate(compiled=False)")
SPIN = "while True:\n    pass\n"


def worker(horizon: int, steps: int, rounds: int, pin: bool) -> dict:
    """Seconds of every decision of each way, in this process (pinned first if asked)."""
    if pin:
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})  # before JAX starts its threads
    import jax
    import jax.numpy as jnp

    import firhc_jax as fj
    from firhc_jax.models import inverter

    jax.config.update("jax_enable_x64", True)
    prm = inverter.InverterParams()
    mem = inverter.make_problem(horizon, prm)
    refs = inverter.horizon_references(prm, steps, horizon)
    params = {"ref": jnp.asarray(refs), "lambda_u": jnp.ones(steps)}
    rows = [{"ref": np.asarray(refs[k]), "lambda_u": np.float64(1.0)} for k in range(steps)]
    rl = inverter.make_plant(prm)
    plant = jax.jit(lambda i, u, p: rl(i, u))
    x0, u0 = np.asarray(inverter.initial_currents(prm)), np.zeros(3)
    ctrl = fj.FIRHC(mem.problem, observe=mem.observe)

    def loop():
        state, x, log, times = ctrl.init(x0, u0), x0, [], []
        for k in range(steps):
            t0 = time.perf_counter()
            u, state, info = ctrl.step(state, x, rows[k])
            jax.block_until_ready(u)
            times.append(time.perf_counter() - t0)
            log.append((u, info))
            x = plant(x, u, rows[k])
        return times

    def frozen():  # everything alive before the loop moved out of the collector's sight
        gc.freeze()
        try:
            return loop()
        finally:
            gc.unfreeze()

    def paused():
        with fj.collector_paused():
            return loop()

    def simulate():
        return np.asarray(ctrl.simulate(x0, steps, plant, params=params, u0=u0, compiled=False).solve_times).tolist()

    collections, began = [], []

    def collector(phase, info):  # every collection inside a loop: (generation, seconds)
        if phase == "start":
            began.append(time.perf_counter())
        elif began:
            collections.append((info["generation"], time.perf_counter() - began.pop()))

    ways = dict(zip(WAYS, (loop, frozen, paused, simulate), strict=True))
    for fn in ways.values():  # compile and warm up
        fn()
    times, pauses = {name: [] for name in WAYS}, {name: [] for name in WAYS}
    gc.callbacks.append(collector)
    for _ in range(rounds):
        for name, fn in ways.items():
            collections.clear()
            times[name] += fn()
            pauses[name] += collections
    gc.callbacks.remove(collector)
    t0 = time.perf_counter()
    gc.collect()
    full_s = time.perf_counter() - t0
    with fj.collector_paused():  # what a paused loop leaves for the collector: reference cycles
        loop()
        left = gc.collect()
    return {"times": times, "pauses": pauses, "full_collect_s": full_s, "left": left,
            "objects": len(gc.get_objects()), "cores": len(os.sched_getaffinity(0)), "load": os.getloadavg()[0]}


def run_setting(args, pin: bool) -> dict:
    """A fresh process's ``worker`` result."""
    cmd = [sys.executable, __file__, "--worker", "--horizon", str(args.horizon), "--steps", str(args.steps),
           "--rounds", str(args.rounds)] + (["--pin"] if pin else [])
    out = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def start_load() -> list:
    """One busy process per core of this machine, stopped by ``stop_load``."""
    return [subprocess.Popen([sys.executable, "-c", SPIN]) for _ in range(os.cpu_count() or 1)]


def stop_load(procs: list) -> None:
    for p in procs:
        p.kill()
        p.wait()


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--horizon", type=int, default=1)
    ap.add_argument("--steps", type=int, default=2000, help="decisions per way and round")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=2, help="fresh processes per setting")
    ap.add_argument("--publish", action="store_true", help="also write the table to benchmarks/results/realtime.md")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--pin", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(worker(args.horizon, args.steps, args.rounds, args.pin)))
        return
    from _results import published  # here: a worker pins itself before anything imports JAX

    with published("realtime", args.publish, "python benchmarks/realtime_bench.py --publish"):
        table(args)


def table(args):
    """Every setting's row, printed."""
    import jax

    print(f"# {platform.machine()}, {os.cpu_count()} cores, jax {jax.__version__}, float64; inverter N = "
          f"{args.horizon}, {args.repeats} processes x {args.rounds} rounds x {args.steps} decisions a way\n")
    print("| load | cores | way | p50 us | p99 us | max us | steps over 1 ms | collections during the calls (oldest "
          "generation) | longest collection ms | machine load (1 min) |")
    print("|---|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for loaded in (False, True):
        procs = start_load() if loaded else []
        try:
            if loaded:
                time.sleep(2.0)  # let the spinners start
            for pin in (False, True):
                results = [run_setting(args, pin) for _ in range(args.repeats)]
                loads = [r["load"] for r in results]
                for way in WAYS:
                    t = 1e6 * np.concatenate([r["times"][way] for r in results])
                    p50, p99 = np.percentile(t, [50, 99])
                    pauses = [p for r in results for p in r["pauses"][way]]
                    full = sum(g == 2 for g, _ in pauses)
                    longest = 1e3 * max((d for _, d in pauses), default=0.0)
                    print(f"| {'loaded' if loaded else 'quiet'} | {'1 (pinned)' if pin else results[0]['cores']} | "
                          f"{way} | {p50:.0f} | {p99:.0f} | {t.max():.0f} | {int(np.sum(t > 1000))} of {t.size} | "
                          f"{len(pauses)} ({full}) | {longest:.1f} | {min(loads):.1f}-{max(loads):.1f} |", flush=True)
                full_s = [r["full_collect_s"] for r in results]
                print(f"|  |  | (a full collection after the run: {1e3 * min(full_s):.0f}-{1e3 * max(full_s):.0f} ms, "
                      f"{results[0]['objects']:,} objects; unreachable objects left by {args.steps} paused steps: "
                      f"{max(r['left'] for r in results)}) |  |  |  |  |  |  |  |", flush=True)
        finally:
            stop_load(procs)


if __name__ == "__main__":
    main()
