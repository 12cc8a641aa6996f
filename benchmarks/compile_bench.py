"""Where a decision's compile time goes: tracing, lowering and XLA compilation, per plant, in fresh processes.

    python benchmarks/compile_bench.py                 # 3 fresh processes per plant, no persistent cache
    python benchmarks/compile_bench.py --cache DIR     # the same with fj.enable_compilation_cache(DIR):
                                                       # the first process fills it, the others read it

Each process builds one controller and times its first ``ctrl.step`` (every
compilation a decision needs: the checks, the search, the fallback), split by
``jax.monitoring``'s events: ``trace`` (Python to jaxpr), ``lower`` (jaxpr to
MLIR) and ``xla`` (XLA's compilation, or reading it from the cache). ``other``
is the rest of the first call: the checks' Python and the decision itself.
Plants: the hopper (N = 6, float64), the three-tank system (N = 5), the
two-level inverter (N = 3, switching penalty) and a 5-state induction-motor-like
plant (N = 3, 8 inverter voltages, forward Euler).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

PLANTS = ("hopper", "tanks", "inverter", "motor")
EVENTS = {"/jax/core/compile/jaxpr_trace_duration": "trace",
          "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
          "/jax/core/compile/backend_compile_duration": "xla",
          "/jax/compilation_cache/cache_retrieval_time_sec": "xla"}


def _motor():
    """A 5-state induction-motor-like plant (stator currents, rotor fluxes, speed; per-unit), 8 voltages."""
    import jax.numpy as jnp
    import numpy as np

    import firhc_jax as fj

    rs, rr, ls, lr, lm, j, dt = 0.04, 0.03, 1.9, 1.9, 1.85, 50.0, 2e-2
    sigma = ls - lm * lm / lr
    volts = 0.6 * fj.product_controls([-1.0, 1.0], repeat=3) @ np.array([[1.0, -0.5, -0.5], [0.0, 0.866, -0.866]]).T

    def dynamics(x, u):
        i, psi, w = x[:2], x[2:4], x[4]
        rot = jnp.stack([-psi[1], psi[0]])
        dpsi = lm / lr * rr * i - rr / lr * psi + w * rot
        di = (u - rs * i - lm / lr * dpsi) / sigma
        torque = lm / lr * (psi[0] * i[1] - psi[1] * i[0])
        return jnp.concatenate([i + dt * di, psi + dt * dpsi, jnp.stack([w + dt * (torque - 0.1 * w) / j])])

    target = np.array([0.5, 0.3, 0.9, 0.0, 0.8])
    problem = fj.Problem(dynamics, volts, fj.quadratic_cost(lam=np.array([1.0, 1.0, 5.0, 5.0, 10.0]),
                                                            x_s=target, beta=0.01), 3)
    return fj.FIRHC(problem), np.array([0.0, 0.0, 0.5, 0.0, 0.7]), None, None


def _build(plant: str):
    """``(ctrl, x0, params0, u0)`` for one decision."""
    import numpy as np

    import firhc_jax as fj

    if plant == "hopper":
        from firhc_jax.apps.hopper import controller
        from firhc_jax.models import hopper as hm
        params = hm.HopperParams()
        return controller(6, params, "sdfs"), hm.initial_state(params), None, None
    if plant == "tanks":
        from firhc_jax.models import tanks
        return fj.FIRHC(tanks.make_problem(5), fallback="unconstrained"), tanks.initial_state(), None, None
    if plant == "inverter":
        from firhc_jax.models import inverter
        mem = inverter.make_problem(3)
        refs = inverter.horizon_references(inverter.InverterParams(), 1, 3)
        p0 = {"ref": refs[0], "lambda_u": np.float64(1.0)}
        return (fj.FIRHC(mem.problem, observe=mem.observe), inverter.initial_currents(), p0, np.zeros(3))
    return _motor()


def measure(plant: str, cache: str | None) -> dict:
    """One fresh process's split of the first decision (run in a subprocess by ``main``)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import firhc_jax as fj

    if cache:
        fj.enable_compilation_cache(cache)
    seen = {"trace": 0.0, "lower": 0.0, "xla": 0.0}

    def listener(event, duration, **kw):
        if event in EVENTS:
            seen[EVENTS[event]] += duration

    ctrl, x0, p0, u0 = _build(plant)
    jax.monitoring.register_event_duration_secs_listener(listener)
    t0 = time.perf_counter()
    jax.block_until_ready(ctrl.step(ctrl.init(x0, u0), x0, p0))
    total = time.perf_counter() - t0
    jax.monitoring.unregister_event_duration_listener(listener)
    return {"total": total, **seen, "other": total - sum(seen.values())}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3, help="fresh processes per plant (default 3)")
    ap.add_argument("--cache", default=None, help="persistent compilation cache folder (default: none)")
    ap.add_argument("--plants", nargs="+", choices=PLANTS, default=list(PLANTS))
    ap.add_argument("--one", choices=PLANTS, help=argparse.SUPPRESS)  # the subprocess's own entry
    args = ap.parse_args()
    if args.one:
        print(json.dumps(measure(args.one, args.cache)))
        return 0
    print(f"| plant | process | total s | trace s | lower s | xla s | other s |  (cache: {args.cache or 'off'})")
    print("|---|---|---|---|---|---|---|")
    for plant in args.plants:
        rows = []
        for run in range(args.runs):
            cmd = [sys.executable, __file__, "--one", plant] + (["--cache", args.cache] if args.cache else [])
            out = subprocess.run(cmd, capture_output=True, text=True, env=os.environ, check=True).stdout
            rows.append(json.loads(out.strip().splitlines()[-1]))
            r = rows[-1]
            print(f"| {plant} | {run + 1} | {r['total']:.2f} | {r['trace']:.2f} | {r['lower']:.2f} | {r['xla']:.2f} "
                  f"| {r['other']:.2f} |", flush=True)
        med = {k: statistics.median(r[k] for r in rows) for k in rows[0]}
        print(f"| {plant} | median | {med['total']:.2f} | {med['trace']:.2f} | {med['lower']:.2f} | {med['xla']:.2f} "
              f"| {med['other']:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
