"""``python -m firhc_jax batch``: solve a batch of states from an ``.npy`` or
``.npz``, on one process or as one process of a multi-process JAX job.

    python -m firhc_jax batch --plant tanks -N 4 --states X0.npz --out result.npz
    python -m firhc_jax batch ... --launch-local 2        # 2 processes on this machine
    JAX_COORDINATOR_ADDRESS=host0:1234 JAX_NUM_PROCESSES=4 JAX_PROCESS_ID=$i \\
        python -m firhc_jax batch ...                     # on each of 4 hosts

The states are the array ``X0`` ``[B, n]`` of ``--states``, an ``.npy`` or an
``.npz`` holding it as ``X0`` (every process reads the same file); process 0 writes every ``SearchResult`` field and the
timings (``meta_*`` keys) to ``--out`` (``firhc_jax.distributed.load_result``).
The problem is a built-in plant (``--plant``, ``--horizon``) or
``--problem MODULE:FUNCTION``, a function without arguments returning a
``Problem`` (importable on every host). ``--params`` names an ``.npy`` (one
array) or ``.npz`` of per-row parameters (every array with leading axis B; a
key ``a/b`` is the leaf ``p["a"]["b"]``), e.g. ``np.savez("p.npz", **lt.params(Y))`` for a
``fj.LinearTracking``'s ``lt.problem``. The time reported is that of calls
after the first, which compiles.
"""
from __future__ import annotations

import inspect
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from ._args import number, solver_argument
from ._user_code import import_user_module, user_code

PLANTS = ("tanks", "synthetic")
MAX_LANES = 4096  # pool slots per device, each with a stack of sDFS nodes
MAX_REPEATS = 1000
MAX_PROCESSES = 1024
MAX_LOCAL_PROCESSES = 64  # each a Python process with JAX: about 0.3 GB of memory
# A pass over the rows is cut into at most this many calls, each of at least MIN_CHUNK_ROWS rows, so that a long
# batch shows its progress and the time left; a pool of 64 lanes per core stays full in calls of that size.
PROGRESS_CHUNKS = 20
MIN_CHUNK_ROWS = 256


def _physical_memory() -> int:
    """Bytes of memory of this machine (the most ``--max-memory`` may ask), 2^40 where it cannot be read."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 2 ** 40


HELP = "solve a batch of states from an .npy or .npz (one process or a multi-process job)"
DESCRIPTION = ("fj.solve_batch on the states X0 [B, n] of an .npy or .npz file, over every device of the job; "
               "process 0 writes the results as .npz. Multi-process: --launch-local P on one machine, "
               "or --coordinator/--num-processes/--process-id (or the JAX_COORDINATOR_ADDRESS, "
               "JAX_NUM_PROCESSES, JAX_PROCESS_ID environment variables) on each host.")


def register(subparsers) -> None:
    """Add the ``batch`` subcommand."""
    p = subparsers.add_parser("batch", help=HELP, description=DESCRIPTION)
    p.add_argument("--states", type=Path, required=True,
                   help=".npy of X0 [B, n], or .npz holding it as X0. --plant tanks: n = 5, the controller state "
                        "[h1, h2, h3 (the levels, m), mode (0-16, the mode that led to them), toggles (actuators "
                        "that mode switched)], e.g. a row 0.2 0.18 0.1 0 0; --plant synthetic: n = 3 (position, "
                        "velocity, heading), e.g. a row 0.2 0.03 0.33; --problem: the state of its dynamics")
    p.add_argument("--out", type=Path, required=True,
                   help="result .npz, written by process 0 (checked before any work)")
    what = p.add_mutually_exclusive_group()
    what.add_argument("--plant", choices=PLANTS, default="tanks",
                      help="built-in plant (default tanks): tanks, the three-tank system of 17 modes; synthetic, "
                           "the 17-input benchmark problem")
    what.add_argument("--problem", metavar="MODULE:FUNCTION", help="a function without arguments returning a Problem")
    p.add_argument("--params", type=Path, default=None,
                   help=".npy (one array) or .npz of per-row parameters, every array with leading axis B "
                        "(key 'a/b': leaf p['a']['b'])")
    p.add_argument("--horizon", "-N", type=number(int, 1, 10), default=4, help="horizon of --plant (default 4)")
    solver_argument(p, "in a batch sdfs and pool share a work pool")
    p.add_argument("--lanes", type=number(int, 1, MAX_LANES), default=None,
                   help=f"pool slots per device (default min(rows, 64), at most {MAX_LANES})")
    p.add_argument("--pop-width", type=number(int, 1, 64), default=1, help="K (default 1, at most 64)")
    p.add_argument("--max-memory", type=number(int, 1, _physical_memory()), default=None,
                   help="bytes per device (default 1 GiB, at most this machine's memory)")
    p.add_argument("--float32", action="store_true", help="solve in float32 (default float64)")
    p.add_argument("--repeats", type=number(int, 1, MAX_REPEATS), default=1,
                   help="after the first call, which compiles (its time is meta_first_seconds), time this many "
                        "more; their median is meta_seconds and gives nodes/s (default 1)")
    p.add_argument("--debug", action="store_true",
                   help="let an error in --problem's module through with its traceback (default: one line)")
    p.add_argument("--no-progress", action="store_true",
                   help=f"no progress bar (default: a bar of rows and the time left on stderr; a batch of "
                        f"{2 * MIN_CHUNK_ROWS} rows or more is solved in up to {PROGRESS_CHUNKS} calls for it)")
    job = p.add_argument_group("multi-process job (default: the environment, else a single process)")
    job.add_argument("--coordinator", metavar="HOST:PORT", help="address of process 0")
    job.add_argument("--num-processes", type=number(int, 1, MAX_PROCESSES), help="processes in the job")
    job.add_argument("--process-id", type=number(int, 0, MAX_PROCESSES - 1), help="this process's index")
    job.add_argument("--launch-local", type=number(int, 1, MAX_LOCAL_PROCESSES), metavar="P", default=None,
                     help=f"start P processes of one job on 127.0.0.1 running this command, and wait (at most "
                          f"{MAX_LOCAL_PROCESSES})")
    job.add_argument("--timeout", type=number(float, 0, low_open=True), default=None,
                     help="with --launch-local: stop the job (every process) after this many seconds "
                          "(default: firhc_jax.distributed.DEFAULT_TIMEOUT, 3600)")
    p.set_defaults(func=run)


def _child_argv(args) -> list[str]:
    """This command's arguments without the launcher's."""
    argv = ["-m", "firhc_jax", "batch", "--states", str(args.states), "--out", str(args.out),
            "--solver", args.solver, "--pop-width", str(args.pop_width), "--repeats", str(args.repeats)]
    argv += ["--problem", args.problem] if args.problem else ["--plant", args.plant, "--horizon", str(args.horizon)]
    for flag, value in (("--lanes", args.lanes), ("--max-memory", args.max_memory), ("--params", args.params)):
        if value is not None:
            argv += [flag, str(value)]
    return argv + [flag for flag, on in (("--float32", args.float32), ("--debug", args.debug),
                                         ("--no-progress", args.no_progress)) if on]


def check_out(path: Path) -> Path:
    """``--out`` before any work: an ``.npz`` file name (NumPy would append
    the suffix to any other) in a directory that can be created and written.
    Tried for real (root may write where ``os.access`` says no, and not
    where it says yes); an error is a ``SystemExit`` with the reason."""
    if path.is_dir():
        raise SystemExit(f"batch: --out {path} is a directory; give a file name such as {path / 'result.npz'}")
    if path.suffix != ".npz":
        raise SystemExit(f"batch: --out must name an .npz file (NumPy would write {path}.npz), got {str(path)!r}")
    for parent in path.parents:  # the nearest one that exists
        if parent.exists():
            if not parent.is_dir():
                raise SystemExit(f"batch: cannot write --out {path}: {parent} is not a directory")
            break
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        existed = path.exists()
        with open(path, "ab"):
            pass
        if not existed:
            path.unlink()
    except OSError as e:
        raise SystemExit(f"batch: cannot write --out {path}: {e.strerror or e}") from None
    return path


def make_problem(args):
    """The ``Problem`` named by ``--problem`` or ``--plant``/``--horizon``."""
    if args.problem:
        from .. import Problem

        spec = args.problem
        module, sep, name = spec.partition(":")
        if not sep or not module or not name:
            raise SystemExit(f"batch: --problem must be MODULE:FUNCTION, got {spec!r}")
        mod = import_user_module(module, f"batch: --problem {spec}: cannot import {module!r}:", args.debug)
        factory = getattr(mod, name, None)
        if factory is None:
            raise SystemExit(f"batch: --problem {spec}: module {module!r} has no {name!r}")
        try:
            inspect.signature(factory).bind()
        except TypeError:
            raise SystemExit(f"batch: --problem {spec} must be a function without arguments") from None
        except ValueError:  # no signature to inspect (some builtins): calling it tells
            pass
        with user_code(f"batch: --problem {spec}() raised", args.debug):
            problem = factory()
        if not isinstance(problem, Problem):
            raise SystemExit(f"batch: --problem {spec} must return a firhc_jax.Problem, got "
                             f"{type(problem).__name__}")
        return problem
    if args.plant == "tanks":
        from ..models import tanks

        return tanks.make_problem(args.horizon)
    from ..models.synthetic import SyntheticParams, make_problem

    return make_problem(args.horizon, SyntheticParams(17))


def _read(flag: str, load, path: Path):
    """``load(path)``, or a ``SystemExit`` naming ``flag`` and the file when it cannot be read."""
    try:
        return load(path)
    except OSError as e:
        raise SystemExit(f"batch: cannot read {flag} {path}: {e.strerror or e}") from None
    except ValueError as e:
        raise SystemExit(f"batch: {flag}: {e}") from None


def _check_rows(params, rows: int) -> None:
    """Every ``--params`` array has leading axis B (the rows of ``--states``), before the rows are cut."""
    import jax
    import numpy as np

    for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
        if np.shape(leaf)[:1] != (rows,):
            raise SystemExit(f"batch: --params: every array needs leading axis B = {rows} (the rows of --states); "
                             f"{jax.tree_util.keystr(path) or 'the array'} has shape {np.shape(leaf)}")


def chunks(rows: int) -> int:
    """Calls one pass over ``rows`` rows is cut into, so that progress shows between them: at most
    ``PROGRESS_CHUNKS``, each of at least ``MIN_CHUNK_ROWS`` rows (one call below twice that)."""
    return max(1, min(PROGRESS_CHUNKS, rows // MIN_CHUNK_ROWS))


def solve_in_chunks(problem, X0, params, options: dict, label: str | None):
    """``fj.solve_batch`` of every row, as NumPy arrays, in ``chunks(B)`` calls of equal size (one compilation:
    the last is filled up with copies of its last row, dropped after), with a bar of rows and an estimate of the
    time left on stderr (``label``; ``None``: no bar). Costs, sequences and flags are those of one call; the
    pool's node counts are not (they depend on which rows share it)."""
    import jax
    import numpy as np
    from tqdm.auto import tqdm

    from .. import SearchResult, solve_batch

    B = len(X0)
    size = -(-B // chunks(B))
    parts = []
    with tqdm(total=B, desc=label, unit="row", disable=label is None, file=sys.stderr, dynamic_ncols=True,
              mininterval=0) as bar:  # at most PROGRESS_CHUNKS updates: each is shown
        for start in range(0, B, size):
            rows = np.minimum(np.arange(start, start + size), B - 1)
            part = solve_batch(problem, X0[rows], params=jax.tree_util.tree_map(lambda a, r=rows: a[r], params),
                               progress=False, **options)  # this bar counts the rows
            parts.append([np.asarray(field)[:B - start] for field in part])
            bar.update(min(size, B - start))
    return SearchResult(*(np.concatenate(field) for field in zip(*parts, strict=True)))


def _job_failure(done) -> str:
    """One line on how a launched job ended badly."""
    parts = [f"process {i} " + (f"exit {d.returncode}" if d.returncode > 0 else f"killed (signal {-d.returncode})")
             for i, d in enumerate(done) if d.returncode != 0]
    return f"batch: the job failed ({', '.join(parts)}); the first process to fail stops the others"


def run(args) -> int:
    """Solve (or, with ``--launch-local``, start the processes that solve); exit status."""
    from .. import distributed

    if args.launch_local is not None:
        if args.coordinator or args.num_processes is not None or args.process_id is not None:
            raise SystemExit("batch: --launch-local starts its own job; drop --coordinator/--num-processes/"
                             "--process-id")
        check_out(args.out)
        timeout = distributed.DEFAULT_TIMEOUT if args.timeout is None else args.timeout
        try:
            done = distributed.launch_local(_child_argv(args), args.launch_local, timeout=timeout)
        except subprocess.TimeoutExpired:
            print(f"batch: the job did not finish within {timeout:g} s (--timeout); every process was stopped",
                  file=sys.stderr)
            return 1
        if any(d.returncode != 0 for d in done):
            print(_job_failure(done), file=sys.stderr)
            return 1
        return 0
    try:
        job = distributed.job_settings(args.coordinator, args.num_processes, args.process_id)
    except ValueError as e:
        raise SystemExit(f"batch: {e}") from None
    if job is None or job[2] == 0:  # process 0 writes --out
        check_out(args.out)
    if job is None:
        return _solve(args)
    with distributed.exit_on_failure():  # a failing process must not wait for the others on its way out
        return _solve(args)


def _solve(args) -> int:
    """Join the job (if any), solve and let process 0 write ``--out``."""
    from .. import distributed

    try:
        distributed.initialize(args.coordinator, args.num_processes, args.process_id)
    except (OSError, ValueError) as e:
        raise SystemExit(f"batch: {e}") from None
    X0 = _read("--states", distributed.load_states, args.states)
    params = None if args.params is None else _read("--params", distributed.load_params, args.params)

    import jax
    import numpy as np
    from jax.experimental import multihost_utils

    from ..solvers import DEFAULT_MAX_MEMORY

    jax.config.update("jax_enable_x64", not args.float32)
    X0 = X0.astype(np.float32 if args.float32 else np.float64)
    _check_rows(params, len(X0))
    problem = make_problem(args)
    options = dict(solver=args.solver, lanes=args.lanes, pop_width=args.pop_width,
                   max_memory=args.max_memory or DEFAULT_MAX_MEMORY)
    many = jax.process_count() > 1
    shown = not args.no_progress and jax.process_index() == 0

    def timed(label):
        if many:
            multihost_utils.sync_global_devices("firhc_jax batch")  # start the clocks together
        t0 = time.perf_counter()
        result = solve_in_chunks(problem, X0, params, options, label if shown else None)
        return time.perf_counter() - t0, result

    try:
        first, result = timed("first call (compiles)")
    except (ValueError, TypeError) as e:  # what the solver refuses (e.g. --lanes without the pool, NaN states)
        raise SystemExit(f"batch: {e}") from None
    # compiled by the first call: never in these
    times = [timed(f"timed call {i + 1}/{args.repeats}")[0] for i in range(args.repeats)]
    seconds = statistics.median(times)
    if jax.process_index() == 0:
        nodes = int(np.asarray(result.nodes, np.int64).sum())
        try:  # checked before the work, but a disk can fill up or a directory vanish since
            distributed.save_result(args.out, result, seconds=seconds, first_seconds=first, times=np.array(times),
                                    processes=jax.process_count(), devices=jax.device_count(),
                                    local_devices=jax.local_device_count(), nodes_per_second=nodes / seconds)
        except OSError as e:
            raise SystemExit(f"batch: cannot write --out {args.out}: {e.strerror or e}") from None
        print(f"batch: {len(X0)} rows on {jax.device_count()} devices ({jax.process_count()} processes): "
              f"{seconds * 1e3:.1f} ms{' (median)' if len(times) > 1 else ''} compiled, first call (compiling) "
              f"{first:.2f} s, {nodes / seconds:.3g} nodes/s, {int(np.sum(result.feasible))} feasible -> {args.out}")
    if many:
        multihost_utils.sync_global_devices("firhc_jax batch done")  # process 0 has written --out
    return 0
