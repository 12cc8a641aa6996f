"""Three-level inverter: a lambda_u sweep of closed loops in one ``simulate_batch`` call, THD against switching.

``firhc_jax.models.three_level`` (27 switch states, RL load, 20 A at 50 Hz,
Ts = 25 us, max_step = 1) at horizon ``--horizon`` (5): ``--lambdas`` switching
weights (8, 0.1 to 100 A^2, log spaced) x ``--phases`` initial phases of the
reference (8, evenly over a period), ``--cycles`` fundamental periods each (2:
1,600 decisions), every loop from steady state (the currents on their
reference at t = 0, all legs at 0 before). The weights differ per loop, so the
model travels in the params (``lt.params(y_ref, with_model=True)`` of each
weight's tracker, stacked over the loops) and one controller on
``lt.shared_problem`` (warm-started, as ``python -m firhc_jax inverter
--levels 3``) runs them all: ``ctrl.simulate_batch(I0 [64, 2], T, plant,
params=[64, T, ...])``.

Each way called once to compile it, then timed in ``--repeats`` rounds over
both, the best round of each: that call against a Python loop of
``ctrl.simulate`` (the same controller, so one compilation) over
``--python-loops`` of the loops, scaled to loops/s, and the batch again at
each of ``--lanes`` (``fj.FIRHC(..., lanes=)``); the Python loop's
decisions are compared with the batch's, and the last loop's with its
weight's own controller (``FIRHC(lt.problem, ...)``). Per loop: THD (every
non-fundamental component of the three phase currents, averaged over them)
and switching frequency per leg (unit level steps over the run, halved,
averaged over the legs), as ``apps/inverter_three_level.summarize``. Writes a
table of the means per weight and the figure ``--figure``
(docs/img/inverter_sweep.png).

    python benchmarks/inverter_sweep.py            # 64 loops of 1,600 steps
    python benchmarks/inverter_sweep.py --quick    # 16 loops of 200 steps, no figure
"""
from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np
from matplotlib.figure import Figure

import firhc_jax as fj
from firhc_jax.models import inverter as two_level
from firhc_jax.models import three_level

PARAMS = three_level.PARAMS


def references(phase, steps: int, horizon: int):
    """``(y_ref [steps, N, 2], i0 [2])``: the reference shifted by ``phase`` (rad) along each decision's
    horizon, and the currents on it at t = 0 (A)."""
    t = (np.arange(steps)[:, None] + np.arange(1, horizon + 1)) * PARAMS.ts
    w = 2.0 * np.pi * PARAMS.frequency * t + phase
    return (PARAMS.amplitude * np.stack([np.cos(w), np.sin(w)], -1),
            PARAMS.amplitude * np.array([np.cos(phase), np.sin(phase)]))


def metrics(currents, inputs) -> tuple[float, float]:
    """``(THD, switching frequency per leg in Hz)`` of one loop: ``currents`` ``[T+1, 2]``, ``inputs`` ``[T, 3]``."""
    phases = two_level.to_phases(currents[:-1])
    thd = np.mean([two_level.distortion(phases[:, x], PARAMS)[1] for x in range(3)])
    return float(thd), two_level.switching_frequency(inputs, PARAMS)


def plot(lambdas, thd, fsw, N: int, path: Path) -> None:
    """THD (%) against switching frequency per leg (kHz): one marker per loop, coloured by lambda_u."""
    fig = Figure(figsize=(6.4, 4.4), layout="constrained")
    ax = fig.add_subplot()
    cmap = matplotlib.colormaps["viridis"]
    ax.plot(fsw.mean(axis=1) / 1e3, 100 * thd.mean(axis=1), "-", color="0.6", lw=1, zorder=0)
    for j, lam in enumerate(lambdas):
        c = cmap(j / max(1, len(lambdas) - 1))
        ax.scatter(fsw[j] / 1e3, 100 * thd[j], s=14, color=c, alpha=0.7)
        ax.plot(fsw[j].mean() / 1e3, 100 * thd[j].mean(), "o", ms=8, mfc="none", color=c,
                label=f"$\\lambda_u$ = {lam:.3g} A$^2$")
    ax.set_xlabel("switching frequency per leg (kHz)")
    ax.set_ylabel("current THD (%)")
    ax.grid(True, alpha=0.3)
    ax.set_title(f"Three-level inverter, N = {N}: {thd.size} closed loops in one simulate_batch\n"
                 f"(dots: {thd.shape[1]} initial phases per weight; circles: their mean)", fontsize=10)
    ax.legend(fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--horizon", type=int, default=5)
    ap.add_argument("--lambdas", type=float, nargs="+", default=np.geomspace(0.1, 100.0, 8).round(3).tolist())
    ap.add_argument("--phases", type=int, default=8)
    ap.add_argument("--cycles", type=float, default=2.0)
    ap.add_argument("--python-loops", type=int, default=16, help="loops of the Python loop, spread over the sweep")
    ap.add_argument("--lanes", type=int, nargs="*", default=[16], help="simulate_batch again at these lanes")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--figure", type=Path, default=Path("docs/img/inverter_sweep.png"))
    ap.add_argument("--quick", action="store_true", help="2 weights x 8 phases of 200 steps, no figure")
    args = ap.parse_args()
    if args.quick:
        args.lambdas, args.phases, args.cycles, args.python_loops, args.repeats, args.figure, args.lanes = \
            args.lambdas[::4], 8, 0.25, 4, 1, None, []
    jax.config.update("jax_enable_x64", True)

    N, L, F = args.horizon, len(args.lambdas), args.phases
    T = round(args.cycles * PARAMS.steps_per_cycle)
    phases = 2.0 * np.pi * np.arange(F) / F
    refs, i0 = zip(*(references(ph, T, N) for ph in phases), strict=True)
    trackers = [three_level.make_problem(N, lambda_u=lam) for lam in args.lambdas]
    # loop b = j * F + f: weight j, phase f; leaves [B, T, ...]
    params = jax.tree.map(lambda *a: jnp.concatenate(a), *(
        lt.params(jnp.asarray(np.stack(refs)), with_model=True) for lt in trackers))
    I0 = jnp.asarray(np.tile(np.stack(i0), (L, 1)))
    B = L * F
    lt = trackers[0]
    ctrl = fj.FIRHC(lt.shared_problem, observe=lt.observe, warm_start=True, pop_width=three_level.pop_width(N))
    A, Bm = (jnp.asarray(a) for a in three_level.model())

    def plant(i, u, p):
        return A @ i + Bm @ u

    size = sum(a.nbytes for a in jax.tree.leaves(params))
    print(f"# three-level inverter sweep: {L} weights x {F} phases = {B} loops x {T} steps, N = {N}; params "
          f"{size / 2**20:.0f} MiB; float64; jax {jax.__version__}; {platform.machine()}")

    u0 = jnp.zeros(3)
    sub = np.unique(np.linspace(0, B - 1, min(args.python_loops, B)).round().astype(int))

    def batch():
        return ctrl.simulate_batch(I0, T, plant, params=params, u0=u0, dt=PARAMS.ts)

    def python_loop():
        return [ctrl.simulate(I0[b], T, plant, params=jax.tree.map(lambda a, b=b: a[b], params), u0=u0)
                for b in sub]

    ways = {f"ctrl.simulate_batch, {B} loops": (batch, B),
            f"Python loop of ctrl.simulate ({len(sub)} loops timed, scaled)": (python_loop, len(sub))}
    for lanes in args.lanes:
        tuned = fj.FIRHC(lt.shared_problem, observe=lt.observe, warm_start=True, pop_width=three_level.pop_width(N),
                         lanes=lanes)
        ways[f"the same, lanes={lanes}"] = (lambda tuned=tuned: tuned.simulate_batch(
            I0, T, plant, params=params, u0=u0, dt=PARAMS.ts), B)
    first, best, out = {}, dict.fromkeys(ways, np.inf), {}
    for name, (fn, _) in ways.items():  # the first call compiles
        t0 = time.perf_counter()
        out[name] = jax.block_until_ready(fn())
        first[name] = time.perf_counter() - t0
    for _ in range(args.repeats):  # rounds over both, so that a noisy neighbour hits them alike
        for name, (fn, _) in ways.items():
            t0 = time.perf_counter()
            jax.block_until_ready(fn())
            best[name] = min(best[name], time.perf_counter() - t0)
    rate = {name: loops / best[name] for name, (_, loops) in ways.items()}
    run, runs = list(out.values())[:2]
    print("\n| way | loops/s | ratio to the Python loop | first call (s) |\n|---|---|---|---|")
    for name in ways:
        print(f"| {name} | {rate[name]:,.2f} | {rate[name] / list(rate.values())[1]:.2f} | {first[name]:.1f} |")
    inputs = np.asarray(run.inputs)
    differ = [b for b, r in zip(sub, runs, strict=True) if not np.array_equal(np.asarray(r.inputs), inputs[b])]
    rel = max(np.max(np.abs(np.asarray(r.predicted_costs) - np.asarray(run.predicted_costs)[b])
                     / np.asarray(run.predicted_costs)[b]) for b, r in zip(sub, runs, strict=True)
              if b not in differ) if len(differ) < len(sub) else np.nan
    print(f"\nPython loop against the batch: {len(sub) - len(differ)} of {len(sub)} loops with the same inputs at "
          f"every step (cost rel. diff. max {rel:.1e}); differing loops: {differ}")
    b, own = B - 1, trackers[-1]  # the last loop on its weight's own controller (the model held as constants)
    alone = fj.FIRHC(own.problem, observe=own.observe, warm_start=True, pop_width=three_level.pop_width(N)).simulate(
        I0[b], T, plant, params=own.params(jnp.asarray(refs[b % F])), u0=u0)
    same = np.array_equal(np.asarray(alone.inputs), inputs[b])
    gap = np.max(np.abs(np.asarray(alone.predicted_costs) / np.asarray(run.predicted_costs)[b] - 1))
    print(f"loop {b} on its own tracker's controller: inputs {'equal' if same else 'DIFFERENT'} at every step, "
          f"cost rel. diff. max {gap:.1e}")

    states = np.asarray(run.states)
    thd, fsw = (np.array(v).reshape(L, F) for v in zip(*(metrics(states[b], inputs[b]) for b in range(B)),
                                                         strict=True))
    nodes = np.asarray(run.decision_nodes).reshape(L, F, T)
    print("\n| λ_u (A²) | THD (%) mean / min / max | f_sw per leg (Hz) mean / min / max | nodes mean / max |\n"
          "|---|---|---|---|")
    for j, lam in enumerate(args.lambdas):
        print(f"| {lam:g} | {100 * thd[j].mean():.2f} / {100 * thd[j].min():.2f} / {100 * thd[j].max():.2f} | "
              f"{fsw[j].mean():,.0f} / {fsw[j].min():,.0f} / {fsw[j].max():,.0f} | "
              f"{nodes[j].mean():,.0f} / {nodes[j].max():,} |")
    if args.figure is not None:
        plot(args.lambdas, thd, fsw, N, args.figure)
        print(f"\nwrote {args.figure}")


if __name__ == "__main__":
    main()
