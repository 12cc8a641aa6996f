"""Per-step time of a closed loop whose reference changes every step.

The three-phase inverter of ``firhc_jax.models.inverter`` (N = 3, 8 switch
states, switching penalty), one process, two ways to give each decision its
new reference:

* rebuilt: a new ``Problem`` per step whose callables close over that step's
  reference (what the API forced before parameters): every step compiles.
* params: one ``FIRHC`` and ``params`` per step: nothing recompiles.

    python benchmarks/params_bench.py [--steps 200] [--rebuilt-steps 5] [--horizon 3]
"""
from __future__ import annotations

import argparse
import platform
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

import firhc_jax as fj
from firhc_jax.models import inverter


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=200, help="decisions timed with params")
    ap.add_argument("--rebuilt-steps", type=int, default=5, help="decisions timed with a rebuilt problem each")
    ap.add_argument("--horizon", type=int, default=3)
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    prm, N = inverter.InverterParams(), args.horizon
    mem = inverter.make_problem(N, prm)
    refs = inverter.horizon_references(prm, args.steps, N)  # [T, N, 2]
    x = jnp.asarray(inverter.initial_currents(prm))
    u_prev = jnp.zeros(3)

    def params(k):
        return {"ref": jnp.asarray(refs[k]), "lambda_u": jnp.asarray(1.0)}

    def timed(fn):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        return time.perf_counter() - t0

    rebuilt = []
    for k in range(args.rebuilt_steps):
        p = params(k)
        prob = fj.Problem(lambda z, u, p=p: mem.problem.dynamics(z, u, p), mem.problem.controls,
                          lambda z, u, p=p: mem.problem.stage_cost(z, u, p), N)
        rebuilt.append(timed(lambda prob=prob, p=p: fj.sdfs(prob, mem.observe(x, u_prev, p))))

    ctrl = fj.FIRHC(mem.problem)
    timed(lambda: ctrl(mem.observe(x, u_prev, params(0)), params(0)))  # compiles once
    with_params = [timed(lambda k=k: ctrl(mem.observe(x, u_prev, params(k)), params(k)))
                   for k in range(args.steps)]
    observed = [(mem.observe(x, u_prev, params(k)), params(k)) for k in range(args.steps)]
    ctrl_only = [timed(lambda z=z, p=p: ctrl(z, p)) for z, p in observed]
    loop = fj.FIRHC(mem.problem, observe=mem.observe).simulate(
        x, args.steps, plant=lambda i, u, p: inverter.make_plant(prm)(i, u), compiled=False,
        params={"ref": jnp.asarray(refs), "lambda_u": jnp.ones(args.steps)})
    in_loop = np.asarray(loop.solve_times)

    print(f"# Closed loop with a new reference every step: inverter N = {N}, {platform.machine()}, "
          f"{jax.devices()[0].platform}, jax {jax.__version__}\n")
    print("| how the reference reaches the decision | decisions | median ms | mean ms | max ms |")
    print("|---|---:|---:|---:|---:|")
    for name, ts in (("rebuilt Problem per step (compiles every step)", rebuilt),
                     ("`ctrl(observe(x, u, p), p)` per step, eager", with_params),
                     ("`ctrl(z, p)` alone (z observed beforehand)", ctrl_only),
                     ("`simulate(..., params=..., compiled=False)` solve_times", list(in_loop))):
        ms = 1e3 * np.asarray(ts)
        print(f"| {name} | {len(ms)} | {statistics.median(ms):.3f} | {ms.mean():.3f} | {ms.max():.3f} |")
    print(f"\nratio rebuilt / params (medians): {statistics.median(rebuilt) / statistics.median(with_params):,.0f}x")


if __name__ == "__main__":
    main()
