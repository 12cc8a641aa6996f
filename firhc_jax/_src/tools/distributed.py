"""Multi-process batches: joining a JAX job, ``.npz`` I/O and a local launcher.

``fj.solve_batch`` needs nothing from this module: after
``jax.distributed.initialize(...)`` it splits the rows over every device of the
job (``jax.devices()``) and returns the whole result on every process. These
helpers serve ``python -m firhc_jax batch`` (``firhc_jax/apps/batch.py``), the
tests and the benchmarks:

* ``initialize``: join a job from arguments or the environment variables
  ``JAX_COORDINATOR_ADDRESS``, ``JAX_NUM_PROCESSES``, ``JAX_PROCESS_ID``
  (switching CPU collectives to gloo, which the final all-gather needs on CPU);
* ``load_states`` / ``load_params`` / ``save_result`` / ``load_result``: the
  ``.npy`` and ``.npz`` files of the command line;
* ``launch_local``: run one command as P processes of one job on 127.0.0.1
  (a free port), killing all of them if one fails or the time runs out;
* ``exit_on_failure``: make a failing process of a job exit at once (so the
  launcher sees the failure and stops the rest).

See docs/guide/batches.md, "Many devices and many hosts".
"""
from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

from ..search.result import SearchResult

ENV_COORDINATOR, ENV_NUM_PROCESSES, ENV_PROCESS_ID = "JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID"
STATES_KEY = "X0"
DEFAULT_TIMEOUT = 3600.0  # s: launch_local's safety net for a job that hangs


def _int_arg(value, name: str, low: int, high: int | None = None) -> int:
    if isinstance(value, str):
        try:
            value = int(value)
        except ValueError:
            raise ValueError(f"{name} must be an integer, got {value!r}") from None
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an int, got {value!r}")
    if value < low or (high is not None and value > high):
        raise ValueError(f"{name} must be an int in [{low}, {'inf' if high is None else high}], got {value}")
    return int(value)


def job_settings(coordinator: str | None = None, num_processes=None, process_id=None):
    """``(coordinator, num_processes, process_id)`` from the arguments, else the
    environment; ``None`` when no job is described (a single process).
    Checked: all three or none, ``0 <= process_id < num_processes``."""
    coordinator = coordinator if coordinator is not None else os.environ.get(ENV_COORDINATOR) or None
    num_processes = num_processes if num_processes is not None else os.environ.get(ENV_NUM_PROCESSES) or None
    process_id = process_id if process_id is not None else os.environ.get(ENV_PROCESS_ID) or None
    given = [v is not None for v in (coordinator, num_processes, process_id)]
    if not any(given):
        return None
    if not all(given):
        raise ValueError(f"a multi-process job needs the coordinator address, the number of processes and this "
                         f"process's id (arguments or {ENV_COORDINATOR}, {ENV_NUM_PROCESSES}, {ENV_PROCESS_ID}); "
                         f"got coordinator={coordinator!r}, num_processes={num_processes!r}, "
                         f"process_id={process_id!r}")
    if not isinstance(coordinator, str) or ":" not in coordinator:
        raise ValueError(f"coordinator must be 'host:port', got {coordinator!r}")
    num_processes = _int_arg(num_processes, "num_processes", 1)
    process_id = _int_arg(process_id, "process_id", 0, num_processes - 1)
    return coordinator, num_processes, process_id


def initialize(coordinator: str | None = None, num_processes=None, process_id=None, *,
               cpu_collectives: str | None = "gloo", timeout: int = 300) -> bool:
    """Join a multi-process JAX job; returns whether one was joined.

    Arguments default to ``JAX_COORDINATOR_ADDRESS`` ("host:port" of process
    0), ``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID``; with none of them set this
    does nothing and returns False (a single process). Call it before any other
    JAX work. ``cpu_collectives`` sets ``jax_cpu_collectives_implementation``
    (CPU processes need "gloo" for ``solve_batch``'s final all-gather; it does
    not affect GPU backends); None leaves it alone.
    """
    settings = job_settings(coordinator, num_processes, process_id)
    if settings is None:
        return False
    import jax

    if cpu_collectives is not None:
        jax.config.update("jax_cpu_collectives_implementation", cpu_collectives)
    address, count, index = settings
    jax.distributed.initialize(address, count, index, initialization_timeout=timeout)
    return True


# ---------------------------------------------------------------------------
# .npz files.
# ---------------------------------------------------------------------------

NPY_MAGIC, NPZ_MAGIC = b"\x93NUMPY", b"PK\x03\x04"


def read_arrays(path):
    """The array of an ``.npy`` file, or the ``{name: array}`` of an ``.npz``, read whole without pickles.

    A file that exists but cannot be parsed (not NumPy's, truncated,
    damaged, holding Python objects) raises a one-line ``ValueError``
    naming it; one that cannot be opened, the ``OSError`` (which names it).
    """
    path = Path(path)
    with open(path, "rb") as f:
        magic = f.read(len(NPY_MAGIC))
        if not (magic.startswith(NPZ_MAGIC) or magic == NPY_MAGIC):
            raise ValueError(f"{path} is neither an .npy nor an .npz file")
        f.seek(0)
        try:
            loaded = np.load(f, allow_pickle=False)
            if isinstance(loaded, np.ndarray):
                return loaded
            with loaded:
                return {key: loaded[key] for key in loaded.files}
        except Exception as e:  # noqa: BLE001  whatever NumPy, zipfile or zlib make of a damaged file
            reason = " ".join(str(e).split()) or "no reason given"
            raise ValueError(f"cannot read {path} ({type(e).__name__}: {reason})") from None


def load_states(path) -> np.ndarray:
    """The ``[B, n]`` states of an ``.npy`` file, or stored under key ``"X0"`` of an ``.npz`` file."""
    path = Path(path)
    data = read_arrays(path)
    if isinstance(data, dict):
        if STATES_KEY not in data:
            raise ValueError(f"{path} has no array {STATES_KEY!r} (the [B, n] states); it holds {list(data)}")
        data = data[STATES_KEY]
    X0 = np.asarray(data)
    if X0.ndim != 2:
        raise ValueError(f"{path}: {STATES_KEY} must be [B, n], got shape {X0.shape}")
    if X0.dtype == bool or not (np.issubdtype(X0.dtype, np.integer) or np.issubdtype(X0.dtype, np.floating)):
        raise ValueError(f"{path}: {STATES_KEY} must hold real numbers, got dtype {X0.dtype}")
    return X0


def load_params(path):
    """Per-row parameters: the array of an ``.npy`` file, or the arrays of an ``.npz`` file as a dict, a key
    ``a/b`` nested as ``p["a"]["b"]``."""
    path = Path(path)
    data = read_arrays(path)
    if not isinstance(data, dict):
        return data
    if not data:
        raise ValueError(f"{path} holds no arrays")
    params: dict = {}
    for key, array in data.items():
        *outer, leaf = key.split("/")
        node = params
        for part in outer:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ValueError(f"{path}: {key!r} nests under an array")
        if leaf in node:
            raise ValueError(f"{path}: {key!r} is both an array and a group")
        node[leaf] = array
    return params


def save_states(path, X0) -> None:
    """Write ``[B, n]`` states as the ``.npz`` that ``load_states`` reads."""
    np.savez(Path(path), **{STATES_KEY: np.asarray(X0)})


def save_result(path, result: SearchResult, **meta) -> None:
    """Write every field of a batched ``SearchResult`` (as NumPy arrays) and
    scalar or array ``meta`` entries (keys prefixed ``meta_``) to ``path``."""
    arrays = {field: np.asarray(getattr(result, field)) for field in SearchResult._fields}
    arrays.update({f"meta_{k}": np.asarray(v) for k, v in meta.items()})
    np.savez(Path(path), **arrays)


def load_result(path) -> tuple[SearchResult, dict]:
    """``(SearchResult of NumPy arrays, meta dict)`` from a ``save_result`` file."""
    with np.load(Path(path), allow_pickle=False) as data:
        missing = [f for f in SearchResult._fields if f not in data.files]
        if missing:
            raise ValueError(f"{path} is not a solve_batch result: missing {missing}")
        result = SearchResult(**{f: data[f] for f in SearchResult._fields})
        meta = {k[len("meta_"):]: data[k][()] if data[k].ndim == 0 else data[k]
                for k in data.files if k.startswith("meta_")}
    return result, meta


# ---------------------------------------------------------------------------
# A local launcher.
# ---------------------------------------------------------------------------

def free_port() -> int:
    """A TCP port on 127.0.0.1 that the OS reports free."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _dying_with(parent: int) -> list[str]:
    """Arguments before ``python``'s own that make a launched process die when
    the launcher dies, however it dies (``kill -9`` included), on Linux: a
    bootstrap sets the parent-death signal (kept across ``exec``) and execs
    ``python`` with the real arguments. Done in the child, not in a
    ``preexec_fn``: that would fork a multithreaded (JAX) process and run
    Python code between fork and exec."""
    if not sys.platform.startswith("linux"):
        return []
    boot = ("import ctypes, os, signal, sys\n"
            "ctypes.CDLL(None).prctl(1, signal.SIGKILL)\n"  # 1: PR_SET_DEATHSIG
            f"if os.getppid() != {parent}:\n    os._exit(1)\n"  # the launcher died before the line above
            "os.execv(sys.executable, [sys.executable, *sys.argv[1:]])")
    return ["-c", boot]


def _kill_group(proc: subprocess.Popen) -> None:
    """Kill a launched process still running and anything it started (its own
    process group)."""
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def launch_local(args, num_processes: int, *, timeout: float | None = DEFAULT_TIMEOUT, env: dict | None = None,
                 capture: bool = False, cwd=None) -> list[subprocess.CompletedProcess]:
    """Run ``python *args`` as ``num_processes`` processes of one job on 127.0.0.1.

    Each process gets ``JAX_COORDINATOR_ADDRESS`` (a free port),
    ``JAX_NUM_PROCESSES`` and its ``JAX_PROCESS_ID`` (read by ``initialize``).
    Polls all of them; as soon as one exits with an error (the others would
    wait for it in a collective) or ``timeout`` seconds pass (default
    ``DEFAULT_TIMEOUT``; None: no limit), kills every process still running,
    each with its process group. No process outlives the launcher: they are
    killed when it returns, raises or is interrupted, and on Linux when it is
    killed. Returns their ``CompletedProcess`` (stdout/stderr as text with
    ``capture``, else inherited; a killed process has a negative
    ``returncode``); raises ``subprocess.TimeoutExpired`` on timeout.
    """
    num_processes = _int_arg(num_processes, "num_processes", 1)
    base = dict(os.environ if env is None else env)
    base.update({ENV_COORDINATOR: f"127.0.0.1:{free_port()}", ENV_NUM_PROCESSES: str(num_processes)})
    command = [sys.executable, *map(str, args)]
    launch = [sys.executable, *_dying_with(os.getpid()), *map(str, args)]
    deadline = None if timeout is None else time.monotonic() + timeout
    procs, logs = [], []
    try:
        for i in range(num_processes):
            out = tempfile.TemporaryFile("w+") if capture else None
            err = tempfile.TemporaryFile("w+") if capture else None
            logs.append((out, err))
            procs.append(subprocess.Popen(launch, env={**base, ENV_PROCESS_ID: str(i)}, stdout=out, stderr=err,
                                          cwd=cwd, start_new_session=True))
        while True:
            codes = [p.poll() for p in procs]  # every process, not only up to the first still running
            if all(c is not None for c in codes):
                break
            if any(c not in (None, 0) for c in codes):
                break  # one failed: the others would block in a collective
            if deadline is not None and time.monotonic() > deadline:
                raise subprocess.TimeoutExpired(command, timeout)
            time.sleep(0.05)
    finally:
        for p in procs:
            _kill_group(p)
        for p in procs:
            p.wait()
    done = []
    for p, (out, err) in zip(procs, logs, strict=True):
        texts = []
        for f in (out, err):
            if f is None:
                texts.append(None)
            else:
                f.seek(0)
                texts.append(f.read())
                f.close()
        done.append(subprocess.CompletedProcess(command, p.returncode, *texts))
    return done


@contextlib.contextmanager
def exit_on_failure():
    """In a process of a multi-process job: on any exception (or a non-zero
    ``SystemExit``), print it and end the process at once (``os._exit``).

    A normal interpreter exit runs ``jax.distributed.shutdown``, which waits
    for every other process, while they wait in a collective for this one: the
    job would hang. Exiting at once lets a launcher (``launch_local``) see the
    failure and stop the others."""
    try:
        yield
    except SystemExit as e:
        if e.code in (None, 0):
            raise
        if not isinstance(e.code, int):
            print(e.code, file=sys.stderr)
        _exit_now(e.code if isinstance(e.code, int) else 1)
    except BaseException:  # noqa: B036 (KeyboardInterrupt too: the process must not hang on its way out)
        traceback.print_exc()
        _exit_now(1)


def _exit_now(code: int) -> None:
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
