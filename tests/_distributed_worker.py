"""Worker of tests/tools/test_distributed.py: solve a fixed set of batches with
fj.solve_batch and save every result field to an .npz.

    python tests/_distributed_worker.py OUT.npz [COORDINATOR NUM_PROCESSES PROCESS_ID]

With a coordinator it first joins that job (gloo CPU collectives); without,
it runs as a single process on whatever devices XLA_FLAGS gives it. Every
process of a job must get the same batches (fixed seeds here) and checks that
it can read the whole result, replicated on every device of the job.
"""
import sys

import jax
import jax.numpy as jnp
import numpy as np
from random_problems import make

import firhc_jax as fj

B = 10  # even: the rows are split as they are; the params case takes B - 1 (padded over 2 devices)


def param_problem():
    def dynamics(x, u, p):
        return jnp.stack([x[0] + 0.1 * x[1], x[1] + 0.1 * (u[0] - jnp.sin(x[0]))])

    def cost(x, u, p):
        return jnp.sum((x - p["r"]) ** 2) + p["w"] * u[0] ** 2

    return fj.Problem(dynamics, jnp.array([-1.0, 0.0, 1.0]), cost, 4)


def fails_on_process_1():
    """A ``--problem`` for ``python -m firhc_jax batch`` that raises on process 1 only, after the job is joined:
    process 0 then waits for it in the job's first collective."""
    import os
    if os.environ.get("JAX_PROCESS_ID") == "1":
        raise RuntimeError("process 1 fails on purpose")
    return make(7, 3, 1, 5, 4, "loose").problem()


def cases():
    rp = make(7, 3, 1, 5, 4, "loose")
    X0 = np.random.default_rng(B).uniform(-1, 1, (B, 3))
    for solver in ("sdfs", "sdfs-vmap", "exhaustive"):
        yield solver, lambda s=solver: fj.solve_batch(rp.problem(), X0, solver=s)
    rng = np.random.default_rng(3)
    params = {"r": rng.uniform(-0.5, 0.5, (B - 1, 2)), "w": rng.uniform(0.0, 0.2, B - 1)}
    Xp = rng.uniform(-1, 1, (B - 1, 2))
    yield "params", lambda: fj.solve_batch(param_problem(), Xp, params=params)


def closed_loops(ran: list | None = None) -> fj.ClosedLoop:
    """7 closed loops of the parameter problem in one simulate_batch (loops shared out over the processes);
    ``ran`` gets the number of loops this process ran itself."""
    from firhc_jax._src.control import runner as loop

    rng = np.random.default_rng(5)
    P = {"r": rng.uniform(-0.5, 0.5, (7, 6, 2)), "w": rng.uniform(0.0, 0.2, (7, 6))}
    ctrl = fj.FIRHC(param_problem(), warm_start=True)
    original = loop.run_compiled

    def counting(decide, plant, runs, steps, **options):
        if ran is not None:
            ran.append(sum(r[1].shape[0] for r in runs))
        return original(decide, plant, runs, steps, **options)

    loop.run_compiled = counting
    try:
        return ctrl.simulate_batch(rng.uniform(-1, 1, (7, 2)), 6, params=P)
    finally:
        loop.run_compiled = original


def main(path):
    out = {}
    for name, solve in cases():
        res = solve()
        assert res.cost.shape == (B - (name == "params"),), (name, res.cost.shape)
        if jax.process_count() > 1:  # a single process keeps the rows sharded over its devices
            assert res.cost.is_fully_replicated, (name, res.cost.sharding)
        assert len(res.cost.sharding.device_set) == jax.device_count(), (name, res.cost.sharding)
        for field in fj.SearchResult._fields:
            out[f"{name}.{field}"] = np.asarray(getattr(res, field))  # readable on every process
    ran = []
    for field, value in closed_loops(ran)._asdict().items():
        if value is not None:
            out[f"loops.{field}"] = np.asarray(value)
    out["loops_ran"] = np.array(ran)
    out["devices"] = np.array([jax.device_count(), jax.process_count()])
    if jax.process_count() > 1:  # a batch that differs between processes is refused on every process
        rp = make(7, 3, 1, 5, 4, "loose")
        try:
            fj.solve_batch(rp.problem(), np.full((4, 3), 0.1 * jax.process_index()))
        except ValueError as e:
            assert "X0 differs between processes" in str(e), e
            out["refused"] = np.array(True)
        try:  # the same for closed loops
            fj.FIRHC(rp.problem()).simulate_batch(np.full((4, 3), 0.1 * jax.process_index()), 2)
        except ValueError as e:
            assert "differs between processes" in str(e), e
            out["loops_refused"] = np.array(True)
    np.savez(path, **out)
    print("worker done", jax.process_index(), flush=True)


if __name__ == "__main__":
    if len(sys.argv) == 5:  # join the job before any other JAX work
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), initialization_timeout=60)
    jax.config.update("jax_enable_x64", True)
    main(sys.argv[1])
