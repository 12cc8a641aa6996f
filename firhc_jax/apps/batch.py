"""``python -m firhc_jax batch``: solve a batch of states from an ``.npz``, on
one process or as one process of a multi-process JAX job.

    python -m firhc_jax batch --plant tanks -N 4 --states X0.npz --out result.npz
    python -m firhc_jax batch ... --launch-local 2        # 2 processes on this machine
    JAX_COORDINATOR_ADDRESS=host0:1234 JAX_NUM_PROCESSES=4 JAX_PROCESS_ID=$i \\
        python -m firhc_jax batch ...                     # on each of 4 hosts

The states are the array ``X0`` ``[B, n]`` of ``--states`` (every process
reads the same file); process 0 writes every ``SearchResult`` field and the
timings (``meta_*`` keys) to ``--out`` (``firhc_jax.distributed.load_result``).
The problem is a built-in plant (``--plant``, ``--horizon``) or
``--problem MODULE:FUNCTION``, a function without arguments returning a
``Problem`` (importable on every host).
"""
from __future__ import annotations

import importlib
import statistics
import sys
import time
from pathlib import Path

from ._args import number

PLANTS = ("tanks", "synthetic")


def register(subparsers) -> None:
    """Add the ``batch`` subcommand."""
    p = subparsers.add_parser(
        "batch", help="solve a batch of states from an .npz (one process or a multi-process job)",
        description="fj.solve_batch on the states X0 [B, n] of an .npz file, over every device of the job; "
                    "process 0 writes the results as .npz. Multi-process: --launch-local P on one machine, "
                    "or --coordinator/--num-processes/--process-id (or the JAX_COORDINATOR_ADDRESS, "
                    "JAX_NUM_PROCESSES, JAX_PROCESS_ID environment variables) on each host.")
    p.add_argument("--states", type=Path, required=True, help=".npz holding X0 [B, n]")
    p.add_argument("--out", type=Path, required=True, help="result .npz, written by process 0")
    what = p.add_mutually_exclusive_group()
    what.add_argument("--plant", choices=PLANTS, default="tanks", help="built-in plant (default tanks)")
    what.add_argument("--problem", metavar="MODULE:FUNCTION", help="a function without arguments returning a Problem")
    p.add_argument("--horizon", "-N", type=number(int, 1, 10), default=4, help="horizon of --plant (default 4)")
    p.add_argument("--solver", choices=("sdfs", "sdfs-vmap", "exhaustive"), default="sdfs",
                   help="solve_batch's solver (default sdfs, the work pool)")
    p.add_argument("--lanes", type=number(int, 1), default=None, help="pool slots per device (default min(rows, 64))")
    p.add_argument("--pop-width", type=number(int, 1), default=1, help="K (default 1)")
    p.add_argument("--max-memory", type=number(int, 1), default=None, help="bytes per device (default 1 GiB)")
    p.add_argument("--float32", action="store_true", help="solve in float32 (default float64)")
    p.add_argument("--repeats", type=number(int, 0), default=0,
                   help="after the first (compiling) call, time this many more calls; their median is "
                        "meta_seconds (default 0: the first call's time)")
    job = p.add_argument_group("multi-process job (default: the environment, else a single process)")
    job.add_argument("--coordinator", metavar="HOST:PORT", help="address of process 0")
    job.add_argument("--num-processes", type=number(int, 1), help="processes in the job")
    job.add_argument("--process-id", type=number(int, 0), help="this process's index")
    job.add_argument("--launch-local", type=number(int, 1), metavar="P", default=None,
                     help="start P processes of one job on 127.0.0.1 running this command, and wait")
    job.add_argument("--timeout", type=number(float, 0, low_open=True), default=None,
                     help="with --launch-local: kill every process after this many seconds")
    p.set_defaults(func=run)


def _child_argv(args) -> list[str]:
    """This command's arguments without the launcher's."""
    argv = ["-m", "firhc_jax", "batch", "--states", str(args.states), "--out", str(args.out),
            "--solver", args.solver, "--pop-width", str(args.pop_width), "--repeats", str(args.repeats)]
    argv += ["--problem", args.problem] if args.problem else ["--plant", args.plant, "--horizon", str(args.horizon)]
    for flag, value in (("--lanes", args.lanes), ("--max-memory", args.max_memory)):
        if value is not None:
            argv += [flag, str(value)]
    return argv + (["--float32"] if args.float32 else [])


def make_problem(args):
    """The ``Problem`` named by ``--problem`` or ``--plant``/``--horizon``."""
    if args.problem:
        module, sep, name = args.problem.partition(":")
        if not sep or not module or not name:
            raise SystemExit(f"batch: --problem must be MODULE:FUNCTION, got {args.problem!r}")
        return getattr(importlib.import_module(module), name)()
    if args.plant == "tanks":
        from ..models import tanks

        return tanks.make_problem(args.horizon)
    from ..models.synthetic import synthetic_problem

    return synthetic_problem(17, args.horizon)


def run(args) -> int:
    """Solve (or, with ``--launch-local``, start the processes that solve); exit status."""
    from .. import distributed

    if args.launch_local is not None:
        if args.coordinator or args.num_processes is not None or args.process_id is not None:
            raise SystemExit("batch: --launch-local starts its own job; drop --coordinator/--num-processes/"
                             "--process-id")
        done = distributed.launch_local(_child_argv(args), args.launch_local, timeout=args.timeout)
        failed = [i for i, d in enumerate(done) if d.returncode != 0]
        if failed:
            print(f"batch: processes {failed} failed (exit {[done[i].returncode for i in failed]})", file=sys.stderr)
            return 1
        return 0
    try:
        distributed.initialize(args.coordinator, args.num_processes, args.process_id)
        X0 = distributed.load_states(args.states)
    except (OSError, ValueError) as e:
        raise SystemExit(f"batch: {e}") from None

    import jax
    import numpy as np
    from jax.experimental import multihost_utils

    from ..batch import DEFAULT_MAX_MEMORY, solve_batch

    jax.config.update("jax_enable_x64", not args.float32)
    X0 = X0.astype(np.float32 if args.float32 else np.float64)
    problem = make_problem(args)
    options = dict(solver=args.solver, lanes=args.lanes, pop_width=args.pop_width,
                   max_memory=args.max_memory or DEFAULT_MAX_MEMORY)
    many = jax.process_count() > 1

    def timed():
        if many:
            multihost_utils.sync_global_devices("firhc_jax batch")  # start the clocks together
        t0 = time.perf_counter()
        result = jax.block_until_ready(solve_batch(problem, X0, **options))
        return time.perf_counter() - t0, result

    try:
        first, result = timed()
    except ValueError as e:  # options the solver refuses (e.g. --lanes without the pool): a message, no traceback
        raise SystemExit(f"batch: {e}") from None
    times = [timed()[0] for _ in range(args.repeats)]
    seconds = statistics.median(times) if times else first
    if jax.process_index() == 0:
        nodes = int(np.asarray(result.nodes, np.int64).sum())
        args.out.parent.mkdir(parents=True, exist_ok=True)
        distributed.save_result(args.out, result, seconds=seconds, first_seconds=first, times=np.array(times),
                                processes=jax.process_count(), devices=jax.device_count(),
                                local_devices=jax.local_device_count(), nodes_per_second=nodes / seconds)
        print(f"batch: {len(X0)} rows on {jax.device_count()} devices ({jax.process_count()} processes): "
              f"{seconds * 1e3:.1f} ms{' (median)' if times else ''}, first call {first:.2f} s, "
              f"{nodes / seconds:.3g} nodes/s, {int(np.sum(result.feasible))} feasible -> {args.out}")
    if many:
        multihost_utils.sync_global_devices("firhc_jax batch done")  # process 0 has written --out
    return 0
