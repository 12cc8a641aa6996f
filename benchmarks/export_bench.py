"""The generated C decision (``fj.export_c``) against the Numba peer, the JAX search, and published FPGA times.

One process, float64, pinned or not as the caller runs it. Rows:

* the engine benchmark's problems at N = 5 (the 17-input linear plant, the synthetic plant, the three tanks at
  their hardest closed-loop state): the generated ``NAME_solve`` called through ``ctypes`` from Python, the
  same function in a C loop (no Python), the Numba peer (``numba_peer.sdfs``) called from Python and in a
  compiled loop, ``jax.jit(fj.sdfs)`` and the public ``fj.sdfs(..., engine="c")`` (the same C with the
  library's checks and result). The ratios the targets read are C through ctypes, and the public call with the
  C engine, over Numba called from Python: each pays one call from Python;
* the two-level and three-level inverters' decisions at N = 1, 2 and 3 (``NAME_step`` of the exported ``FIRHC``,
  warm start; the three-level one is ``LinearTracking``'s problem), through ``ctypes`` and replayed in a C loop,
  and ``ctrl.step`` with either engine, against the published FPGA times of a three-level drive (5.76 us at N = 1,
  17.27 us at N = 2: Stellato, Geyer, Goulart, IEEE TPEL 2017), with each generated controller's memory: its work
  arrays on the C stack, its state, and the code and tables of the compiled object (``size``).

Every row checks that the generated code found the library's cost and node count. The C code is compiled
with ``cc -O2`` (the default of ``Exported.compile``) and ``-O3 -march=native``.

    python benchmarks/export_bench.py [--quick] [--repeats 7] [--publish]
"""
from __future__ import annotations

import argparse
import ctypes
import shutil
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _results import published

FAST = ("-O3", "-march=native")
LOOP = r"""
#define _POSIX_C_SOURCE 199309L
#include <time.h>
#include "{name}.h"
double {name}_loop(int calls, const double *x0, const double *params) {{
    int sequence[{up}_N];
    double cost;
    long long nodes;
    struct timespec a, b;
    clock_gettime(CLOCK_MONOTONIC, &a);
    for (int i = 0; i < calls; i++) {name}_solve(x0, params, sequence, &cost, &nodes);
    clock_gettime(CLOCK_MONOTONIC, &b);
    return ((b.tv_sec - a.tv_sec) + 1e-9 * (b.tv_nsec - a.tv_nsec)) / calls;
}}
"""


def median_call(fn, calls: int, repeats: int) -> float:
    """Median over ``repeats`` of the mean seconds per call of ``calls`` calls (after a warm-up)."""
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(calls):
            fn()
        times.append((time.perf_counter() - t0) / calls)
    return statistics.median(times)


def c_loop(exported, flags, x0, params_flat, calls: int, repeats: int) -> float:
    """Seconds per ``NAME_solve`` in a C loop: the generated source and a timing loop in one library."""
    folder = Path(tempfile.mkdtemp())
    loop = folder / "loop.c"
    loop.write_text(LOOP.format(name=exported.name, up=exported.name.upper()))
    lib_path = folder / "loop.so"
    subprocess.run(["cc", "-std=c99", *flags, "-fPIC", "-shared", f"-I{exported.source.parent}", "-o", str(lib_path),
                    str(exported.source), str(loop), "-lm"], check=True)
    lib = ctypes.CDLL(str(lib_path))
    fn = getattr(lib, f"{exported.name}_loop")
    fn.restype = ctypes.c_double
    fn.argtypes = [ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p]
    x0 = np.ascontiguousarray(x0, np.float64)
    p = None if params_flat is None else params_flat.ctypes.data
    return statistics.median(fn(calls, x0.ctypes.data, p) for _ in range(repeats))


def footprint(exported, flags) -> tuple[int, int]:
    """``(text, data)`` bytes of the compiled object: code, and tables plus constants."""
    if shutil.which("size") is None:
        return -1, -1
    obj = exported.source.with_suffix(".o")
    subprocess.run(["cc", "-std=c99", *flags, "-c", "-o", str(obj), str(exported.source)], check=True)
    text, data, bss = subprocess.run(["size", str(obj)], capture_output=True, text=True,
                                     check=True).stdout.splitlines()[1].split()[:3]
    return int(text), int(data) + int(bss)


def engine_row(fj, peer, jitted, folder, label, problem, children, P, x0, *, quick, reps) -> str:
    """One row of the first table: the generated C, the Numba peer and the JAX search on one state."""
    ref = jitted(problem, x0)
    nodes = int(ref.nodes)
    calls = 20 if quick else max(10, min(2000, 200_000 // nodes))
    exported = fj.export_c(problem, folder / label.split(",")[0].replace(" ", "_"), name="plant", x0=x0)
    times = {}
    for tag, flags in (("O2", ("-O2",)), ("fast", FAST)):
        lib = exported.compile(flags=flags)
        code, seq, cost, c_nodes = lib.solve(x0)
        if c_nodes != nodes or not np.isclose(cost, float(ref.cost), rtol=1e-9):
            raise AssertionError(f"{label}: C found cost {cost}, {c_nodes} nodes; fj.sdfs {float(ref.cost)}, {nodes}")
        times[tag] = median_call(lambda lib=lib: lib.solve(x0), calls, reps)
    times["loop"] = c_loop(exported, FAST, x0, None, calls, reps)
    M, N = problem.num_controls, problem.horizon
    nodes_nb = peer.sdfs(children, P, x0, M, N)[2]
    assert nodes_nb == nodes, (label, nodes_nb, nodes)
    times["nb"] = median_call(lambda: peer.sdfs(children, P, x0, M, N), calls, reps)
    X = np.tile(x0, (calls, 1))
    peer.sdfs_batch(children, P, X, M, N)
    loops = []
    for _ in range(reps):
        t0 = time.perf_counter()
        peer.sdfs_batch(children, P, X, M, N)
        loops.append((time.perf_counter() - t0) / calls)
    times["nb_loop"] = statistics.median(loops)
    times["jit"] = median_call(lambda: jax.block_until_ready(jitted(problem, x0)), calls, reps)
    public = fj.sdfs(problem, x0, engine="c")
    if int(public.nodes) != nodes or not np.isclose(float(public.cost), float(ref.cost), rtol=1e-9):
        raise AssertionError(f"{label}: fj.sdfs(engine='c') found {float(public.cost)}, {int(public.nodes)} nodes")
    times["engine"] = median_call(lambda: fj.sdfs(problem, x0, engine="c"), calls, reps)
    us = {k: 1e6 * v for k, v in times.items()}
    return (f"| {label} | {nodes:,} | {us['O2']:.2f} | {us['fast']:.2f} | {us['loop']:.2f} | {us['nb']:.2f} "
            f"| {us['nb_loop']:.2f} | {us['jit']:.1f} | {us['engine']:.2f} | {us['O2'] / us['nb']:.2f} "
            f"| {us['engine'] / us['nb']:.2f} | {us['loop'] / us['nb_loop']:.2f} |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="smoke run: N = 3, few calls")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--publish", action="store_true", help="also write the tables to benchmarks/results/export.md")
    args = ap.parse_args(argv)
    with published("export", args.publish, "python benchmarks/export_bench.py --publish"):
        run(args)


def run(args):
    jax.config.update("jax_enable_x64", True)
    import numba_peer as peer
    from engine_bench import tank_states

    import firhc_jax as fj
    from firhc_jax.models import tanks
    from firhc_jax.models.synthetic import SyntheticParams, benchmark_state, make_problem

    N = 3 if args.quick else 5
    reps = 2 if args.quick else args.repeats
    folder = Path(tempfile.mkdtemp())
    print(f"Generated C against the Numba peer, N = {N}, float64; times per decision (us), medians of {reps}.")
    print("ctypes: NAME_solve called from Python; C loop: the same in a loop in C; Numba py: numba_peer.sdfs called "
          "from Python; Numba loop: per solve in a compiled loop; jit: jax.jit(fj.sdfs); engine c: the public "
          "fj.sdfs(problem, x0, engine=\"c\").\n")
    print("| problem | nodes | C ctypes -O2 | C ctypes -O3 native | C loop -O3 native | Numba py | Numba loop "
          "| jit(fj.sdfs) | fj.sdfs engine c | C ctypes -O2 / Numba py | engine c / Numba py | C loop / Numba loop |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    syn = make_problem(N, SyntheticParams(17), dtype=np.float64)
    cases = [("linear, 17 inputs", peer.linear_problem(N), peer.linear_children, peer.linear_plant(),
              np.array([1.5, -1.0, 0.8])),
             ("synthetic, 17 inputs", syn, peer.synthetic_children, peer.synthetic_params(syn),
              np.asarray(benchmark_state(np.float64)))]
    if not args.quick:  # finding the tanks' hardest state runs a closed loop first
        tank = tanks.make_problem(N)
        states = tank_states(tank, 100)
        tank_p = peer.tank_params()
        hard = states[int(np.argmax(peer.sdfs_batch(peer.tank_children_simd, tank_p, states, 17, N)[2]))]
        cases.append(("three tanks, hardest state", tank, peer.tank_children_simd, tank_p, hard))
    jitted = jax.jit(fj.sdfs)
    for case in cases:
        print(engine_row(fj, peer, jitted, folder, *case, quick=args.quick, reps=reps))

    print("\nThe inverters' exported controllers (warm start, the step's observe included), NAME_step per decision "
          "along a closed loop of 50 steps (10 with --quick): through ctypes, and replayed in a C loop (the decision "
          "alone; the three-level one maps its raw reference too), against published FPGA decisions of a "
          "three-level drive (27 switch states). Memory: the work arrays on the C "
          "stack (NAME_work_bytes()), the controller state, and the object's code and data (cc -O2, `size`).\n")
    print("| controller | N | nodes per decision (mean) | C ctypes -O2 (us) | C loop -O2 (us) | C loop -O3 native (us) "
          "| ctrl.step (us) | ctrl.step engine c (us) | FPGA (us) | stack bytes | state bytes | code bytes "
          "| data bytes |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for kind in ("two-level, 8 inputs", "three-level, 27 inputs (LinearTracking)"):
        for horizon in (1,) if args.quick else (1, 2, 3):
            print(inverter_row(fj, folder, kind, horizon, 10 if args.quick else 50))


def inverter_controller(fj, kind: str, horizon: int, steps: int):
    """``(what to export, ctrl, the exported code's params of 50 steps, ctrl.step's, plant)`` of the two-level
    inverter's controller or the three-level one's (``LinearTracking``: the generated code takes the raw
    reference and maps it as ``lt.params`` does)."""
    from firhc_jax.models import inverter, three_level

    refs = inverter.horizon_references(inverter.InverterParams(), steps, horizon)
    if kind.startswith("two"):
        mem = inverter.make_problem(horizon)
        ctrl = fj.FIRHC(mem.problem, observe=mem.observe, warm_start=True)
        params = [{"ref": jnp.asarray(r), "lambda_u": jnp.asarray(0.1)} for r in refs]
        return ctrl, ctrl, params, params, inverter.make_plant()
    lt = three_level.make_problem(horizon)
    ctrl = fj.FIRHC(lt.problem, observe=lt.observe, warm_start=True)
    raw = [(r, np.zeros((horizon, lt.n))) for r in refs]
    return lt, ctrl, raw, [lt.params(*r) for r in raw], three_level.make_plant()


def inverter_row(fj, folder, kind: str, horizon: int, steps: int) -> str:
    """One row of the second table: one closed loop through the generated step, timed three ways."""
    target, ctrl, c_params, params, plant = inverter_controller(fj, kind, horizon, steps)
    exported = fj.export_c(target, folder / f"{kind[:3]}{horizon}", name="inv", params=c_params[0], x0=np.zeros(2))
    text, data = footprint(exported, ("-O2",))
    lib = exported.compile()
    flat = np.stack([lib.flat_params(p) for p in c_params])
    x, state, spent, nodes, states = np.array([1.0, -2.0]), lib.init(np.zeros(2)), [], [], []
    for p_flat in flat:  # one closed loop, each decision timed over repeated calls from its state
        saved = lib.State.from_buffer_copy(state)
        states.append(x)
        t0 = time.perf_counter()
        for _ in range(20):
            ctypes.memmove(ctypes.addressof(state), ctypes.addressof(saved), ctypes.sizeof(state))
            code, u = lib.step(state, x, p_flat)
        spent.append((time.perf_counter() - t0) / 20)
        nodes.append(state.nodes)
        x = np.asarray(plant(jnp.asarray(x), jnp.asarray(u)))
    ctypes_us = 1e6 * statistics.median(spent)
    loops = {tag: 1e6 * step_loop(exported, flags, np.stack(states), flat) for tag, flags in
             (("O2", ("-O2",)), ("fast", FAST))}
    x, state, spent = np.array([1.0, -2.0]), ctrl.init(np.zeros(2)), []
    for p in params:
        t0 = time.perf_counter()
        u, state, _ = ctrl.step(state, x, p)
        spent.append(time.perf_counter() - t0)
        x = np.asarray(plant(jnp.asarray(x), jnp.asarray(u)))
    step_us = 1e6 * statistics.median(spent[1:])
    c_ctrl = fj.FIRHC(ctrl.problem, observe=ctrl.observe, warm_start=True, engine="c")
    x, state, spent = np.array([1.0, -2.0]), c_ctrl.init(np.zeros(2)), []
    for p in jax.tree_util.tree_map(np.asarray, params):  # NumPy in: a JAX array costs the C engine a copy out
        t0 = time.perf_counter()
        u, state, info = c_ctrl.step(state, x, p)
        spent.append(time.perf_counter() - t0)
        x = np.asarray(plant(jnp.asarray(x), jnp.asarray(u)))
    engine_us = 1e6 * statistics.median(spent[1:])
    fpga = {1: 5.76, 2: 17.27}.get(horizon)
    return (f"| {kind} | {horizon} | {np.mean(nodes):.1f} | {ctypes_us:.2f} | {loops['O2']:.2f} | {loops['fast']:.2f} "
            f"| {step_us:.0f} | {engine_us:.2f} | {'-' if fpga is None else fpga} | {exported.work_bytes:,} "
            f"| {exported.state_bytes} | {text:,} | {data:,} |")


STEPS = r"""
#define _POSIX_C_SOURCE 199309L
#include <time.h>
#include "{name}.h"
double {name}_steps(int steps, int rounds, const double *xs, const double *ps) {{
    {name}_state s;
    double u[{up}_PLANT_NU];
    struct timespec a, b;
    clock_gettime(CLOCK_MONOTONIC, &a);
    for (int r = 0; r < rounds; r++) {{
        {name}_init(&s, NULL, NULL);
        for (int t = 0; t < steps; t++) {name}_step(&s, xs + t * {up}_PLANT_NX, ps + t * {up}_NP, u);
    }}
    clock_gettime(CLOCK_MONOTONIC, &b);
    return ((b.tv_sec - a.tv_sec) + 1e-9 * (b.tv_nsec - a.tv_nsec)) / ((double)steps * rounds);
}}
"""


def step_loop(exported, flags, xs: np.ndarray, ps: np.ndarray, rounds: int = 200) -> float:
    """Seconds per ``NAME_step`` replaying a recorded closed loop (its plant states and params) in C."""
    folder = Path(tempfile.mkdtemp())
    (folder / "steps.c").write_text(STEPS.format(name=exported.name, up=exported.name.upper()))
    lib_path = folder / "steps.so"
    subprocess.run(["cc", "-std=c99", *flags, "-fPIC", "-shared", f"-I{exported.source.parent}", "-o", str(lib_path),
                    str(exported.source), str(folder / "steps.c"), "-lm"], check=True)
    fn = getattr(ctypes.CDLL(str(lib_path)), f"{exported.name}_steps")
    fn.restype = ctypes.c_double
    fn.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p]
    xs, ps = np.ascontiguousarray(xs, np.float64), np.ascontiguousarray(ps, np.float64)
    return statistics.median(fn(len(xs), rounds, xs.ctypes.data, ps.ctypes.data) for _ in range(5))

if __name__ == "__main__":
    main()
