"""Where the rows of a batch run: devices, processes and CPU cores.

Devices. The rows are split over a 1-D mesh of every device of the job
(``jax.devices()``; over all processes after ``jax.distributed.initialize``)
with ``shard_map``; each device runs its own search on its share, with no
communication inside the search. Over several processes the rows enter as one
global array (laid out as a single process's jit would lay them out, checked
first to be the same on every process) and the result is all-gathered at the
end, so every process reads all of it.

Cores. A CPU device runs one execution of a program on one thread (the
pool's ``while`` loop is sequential), and executions dispatched on one
execution stream of a device run one after another: each waits for the one
enqueued before it. Executions on different streams run side by side on
XLA's CPU client thread pool. So on CPU a batch is split into parts, one per
core this process may use (``os.sched_getaffinity``) shared among the
devices, and the same compiled batch is dispatched once per part, each on its
own stream (``jaxlib.xla_client.execution_stream_id``: a setting of the
dispatching thread, restored at once; no global flag and no ``XLA_FLAGS``),
then the parts are put back in row order (``run_parts``).
"""
from __future__ import annotations

import contextlib
import functools
import hashlib
import os

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxlib import xla_client

AXIS = "rows"


def mesh_of(devices) -> Mesh:
    """1-D mesh over ``devices`` (default: every device of the job,
    ``jax.devices()``: the local devices in a single process). Meshes over the
    same devices compare equal, so the compiled batch is reused."""
    if devices is None:
        devices = jax.devices()
    elif isinstance(devices, (str, bytes, jax.Device)) or not isinstance(devices, (list, tuple, np.ndarray)):
        raise TypeError(f"devices must be a list of jax devices (e.g. jax.devices()[:2]) or None, got {devices!r}")
    devices = list(devices)
    if not devices:
        raise ValueError("devices is empty; pass None for all devices of the job (jax.devices())")
    for i, d in enumerate(devices):
        if not isinstance(d, jax.Device):
            raise TypeError(f"devices[{i}] must be a jax device (from jax.devices()), got {d!r}")
    if len(set(devices)) != len(devices):
        raise ValueError(f"devices lists a device more than once: {devices}")
    if len({d.platform for d in devices}) > 1:
        raise ValueError(f"devices mixes platforms: {sorted({d.platform for d in devices})}")
    return Mesh(np.array(devices), (AXIS,))


def global_rows(X, mesh: Mesh):
    """Multi-process mesh: every process's ``X`` (the same rows everywhere) as
    one global array over ``mesh``; a fingerprint of the rows is
    compared across processes first, so that differing ``X0`` fail loudly."""
    if isinstance(X, jax.Array) and not X.is_fully_addressable and not X.is_fully_replicated:
        raise ValueError("X0 is a jax.Array sharded over several processes; pass the same host (NumPy) array "
                         "[B, n] on every process")
    host = np.asarray(X)
    same_on_every_process(host, "X0")
    # The layout a single process's jit picks for the same call (rows split when they divide evenly, else
    # replicated and padded inside): the same partitioned program, hence bit-identical results.
    spec = PartitionSpec(AXIS) if host.shape[0] % mesh.devices.size == 0 else PartitionSpec()
    return jax.make_array_from_callback(host.shape, NamedSharding(mesh, spec), lambda i: host[i])


def same_on_every_process(tree, what: str) -> None:
    """A ``ValueError`` on every process of the job unless every process holds the same ``tree`` (its
    arrays' shapes and bytes, compared by a fingerprint gathered from each)."""
    digest = hashlib.sha256()
    for leaf in jax.tree_util.tree_leaves(tree):
        host = np.asarray(leaf)
        digest.update(np.array(host.shape, np.int64).tobytes() + host.tobytes())
    fingerprint = np.frombuffer(digest.digest(), np.uint8)
    every = np.asarray(multihost_utils.process_allgather(fingerprint))  # [processes, 32]
    if not np.all(every == every[0]):
        differ = np.flatnonzero(np.any(every != every[0], axis=1)).tolist()
        raise ValueError(f"{what} differs between processes (processes {differ} differ from process 0): every "
                         "process must pass the same batch (X0 and params)")


@functools.partial(jax.jit, static_argnames="mesh")
def replicated(tree, mesh: Mesh):
    """``tree`` replicated over every device of ``mesh`` (an all-gather across
    processes), so that each process can read the whole result."""
    return jax.lax.with_sharding_constraint(tree, NamedSharding(mesh, PartitionSpec()))


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has
    one, as under ``taskset`` or a container's CPU set; else all)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def default_parts(mesh: Mesh) -> int:
    """Parts of a batch to run at once on ``mesh``: on CPU devices, the usable
    cores shared among them (at least one each); 1 on other platforms."""
    if mesh.devices.flat[0].platform != "cpu":
        return 1
    return max(1, usable_cores() // mesh.devices.size)


def split_rows(trees, parts: int) -> list:
    """The rows of ``trees`` (leaves ``[B, ...]``, on the host) in ``parts`` shares: row i goes to part
    ``i % parts`` (interleaved, so that a run of hard rows is shared out; the last part's missing rows repeat
    row B - 1). ``join_rows`` puts results back in row order."""
    B = jax.tree_util.tree_leaves(trees)[0].shape[0]
    per_part = -(-B // parts)
    take = np.minimum(np.arange(per_part * parts).reshape(per_part, parts).T, B - 1)  # [parts, per_part] rows
    host = jax.tree_util.tree_map(np.asarray, trees)
    return [jax.tree_util.tree_map(lambda a, i=i: a[take[i]], host) for i in range(parts)]


def join_rows(outs, rows: int):
    """The parts' results (``split_rows``) back in row order, ``rows`` of them."""
    return _interleave(outs, rows)


@contextlib.contextmanager
def on_stream(part: int):
    """Dispatch on execution stream ``part + 1`` of the devices (a setting of this thread, restored after)."""
    with xla_client.execution_stream_id(part + 1):
        yield


def run_parts(run, X, params, budget, parts: int):
    """``run(X, params, budget)`` (a compiled batch, result with leading axis
    B) on ``parts`` shares of the rows at once (``split_rows``), each part
    dispatched on its own execution stream without waiting, and the results
    put back in row order. One compiled batch serves every part (equal
    shapes)."""
    outs = []
    for i, (Xi, pi) in enumerate(split_rows((X, params), parts)):
        with on_stream(i):
            outs.append(run(Xi, pi, budget))
    return join_rows(outs, X.shape[0])


@functools.partial(jax.jit, static_argnames="rows")
def _interleave(outs, rows: int):
    """The parts' results ``[per_part, ...]`` each, back in row order: row
    ``r * parts + i`` is row r of part i."""
    return jax.tree_util.tree_map(lambda *a: jnp.stack(a, axis=1).reshape((-1,) + a[0].shape[1:])[:rows], *outs)
