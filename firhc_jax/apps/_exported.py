"""An application's decision kept on disk as a traced program, so that a second run neither traces nor lowers it.

JAX's persistent compilation cache (``enable_compilation_cache``, which the
command line turns on) keeps XLA's output, but every run still traces the
decision to a jaxpr and lowers it, only to find that output: on the hopper,
0.6 s of the 0.9 s a second run spends (docs/guide/caching.md). An application
builds its controller from this package's code and a few settings, so those
settings, the package's source and JAX's version name the traced program
exactly. ``decision`` stores it with ``jax.export`` (StableHLO bytecode, no
pickle) under a digest of all of them, beside the compilation cache, and
reads it back on the next run; XLA's compiled form then comes from the
persistent cache.

Only applications use it: a user's controller holds callables whose code and
captured values no digest here can see.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import os
import tempfile
import warnings
from pathlib import Path
from typing import Callable

import jax
import jaxlib
import numpy as np

from .. import ControllerState, SearchResult, StepInfo

FOLDER = "firhc_jax_exported"  # inside the compilation cache's folder
# The JAX options that change what a trace produces.
TRACE_CONFIG = ("jax_enable_x64", "jax_numpy_dtype_promotion", "jax_numpy_rank_promotion",
                "jax_default_matmul_precision")


_serializable: set = set()  # the NamedTuple classes jax.export can write and read in this process


def _namedtuples(tree):
    """The NamedTuple classes in a ``PyTreeDef``, outermost first."""
    data = tree.node_data()
    if data is not None and issubclass(data[0], tuple) and hasattr(data[0], "_fields"):
        yield data[0]
    for child in tree.children():
        yield from _namedtuples(child)


def _make_serializable(args) -> None:
    """Let ``jax.export`` write and read the decision's arguments (``ControllerState``, a model's parameter
    NamedTuples) and results (``StepInfo``, ``SearchResult``)."""
    found = _namedtuples(jax.tree_util.tree_structure(args))
    for cls in (*found, ControllerState, StepInfo, SearchResult):
        if cls not in _serializable:
            jax.export.register_namedtuple_serialization(
                cls, serialized_name=f"{cls.__module__}.{cls.__qualname__}")
            _serializable.add(cls)


@functools.cache
def source_digest() -> str:
    """SHA-256 of every Python file of the package, by relative path: a changed line gives another digest."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def canonical(value) -> str:
    """An exact text of an application's settings: floats by their bits, arrays by their bytes, dataclasses by
    their fields. Anything else is refused (``TypeError``): its text could hide a difference."""
    if value is None or isinstance(value, (bool, int, str)) and not isinstance(value, np.generic):
        return repr(value)
    if isinstance(value, (float, np.ndarray, np.generic)):
        a = np.asarray(value)
        return f"{a.dtype}{a.shape}:{a.tobytes().hex()}"
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        fields = ",".join(f"{f.name}={canonical(getattr(value, f.name))}" for f in dataclasses.fields(value))
        return f"{type(value).__module__}.{type(value).__qualname__}({fields})"
    if isinstance(value, (tuple, list)):
        return f"{type(value).__name__}({','.join(map(canonical, value))})"
    if isinstance(value, dict):
        items = sorted((canonical(k), canonical(v)) for k, v in value.items())
        return f"dict({','.join(f'{k}:{v}' for k, v in items)})"
    raise TypeError(f"cannot name a setting of type {type(value).__name__} exactly")


def digest(settings, args) -> str:
    """The file name of the program built from ``settings`` and traced for ``args``."""
    leaves, tree = jax.tree_util.tree_flatten(args)
    parts = [canonical(settings), source_digest(), jax.__version__, jaxlib.__version__, str(tree),
             *(f"{np.shape(a)} {getattr(a, 'dtype', None) or np.asarray(a).dtype}" for a in leaves),
             *(f"{k}={getattr(jax.config, k)}" for k in TRACE_CONFIG)]
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


def decision(ctrl, settings, folder, state, x, params) -> Callable:
    """``ctrl.step`` for arguments shaped as ``(state, x, params)``, jitted: ``(state, x, params) -> (u, state,
    info)``, the same program, kept in ``folder`` (the compilation cache's) under ``FOLDER``.

    ``settings`` (numbers, strings, arrays, dataclasses and tuples, lists and
    dicts of them; ``canonical``) must be everything that built ``ctrl``
    besides the package's code: the package's source and JAX's version are
    added here. The traced program is read from the folder when an earlier run
    stored it there, and traced and stored otherwise; a file that cannot be
    read is traced and written again, and one that cannot be written is
    warned about (``RuntimeWarning``).
    """
    _make_serializable((state, x, params))
    path = Path(folder) / FOLDER / f"{digest(settings, (state, x, params))}.jaxexport"
    try:
        program = jax.export.deserialize(bytearray(path.read_bytes()))
    except Exception:  # noqa: BLE001  none yet, or a damaged or foreign file: traced and written again
        program = jax.export.export(jax.jit(ctrl.step))(state, x, params)
        try:
            _write(path, program.serialize())
        except OSError as e:
            warnings.warn(f"the decision could not be kept in {str(path.parent)!r} ({e.strerror or e}): the next "
                          "run traces it again", RuntimeWarning, stacklevel=2)
    # Placed on one device: arguments whether committed there or not (an exported program's results are) share
    # one compilation.
    return jax.jit(program.call, in_shardings=jax.sharding.SingleDeviceSharding(jax.devices()[0]))


def _write(path: Path, blob: bytes) -> None:
    """Write ``blob`` to ``path`` whole or not at all (another process may be reading it)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(blob)
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise
