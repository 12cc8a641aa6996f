"""An application's decision kept on disk as a traced program, so that a second run neither traces nor lowers it.

JAX's persistent compilation cache (``enable_compilation_cache``, which the
command line turns on) keeps XLA's output, but every run still traces the
decision to a jaxpr and lowers it, only to find that output: on the hopper,
0.6 s of the 0.9 s a second run spends (docs/guide/caching.md). An application
builds its controller from this package's code and a few settings, so those
settings, the package's source and version, JAX's version and the platform
name the traced program exactly (``key``). ``decision`` stores it with
``jax.export`` (StableHLO bytecode, no pickle) under the SHA-256 of that key,
beside the compilation cache, and reads it back on the next run; XLA's
compiled form then comes from the persistent cache.

A kept program runs only when it is verifiably the one this run would trace:
its file starts with the full key it was written for and the SHA-256 of the
program's bytes (``read_header``), both checked before the program is read,
and the program's platform after. A damaged file, another setting's program
under this name or a program for another platform is traced and written
again, with a one-line warning; so is a kept program that fails when it runs.

Only applications use it: a user's controller holds callables whose code and
captured values no key here can see.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
import re
import stat
import tempfile
import warnings
from pathlib import Path
from typing import Callable

import jax
import jaxlib
import numpy as np

import firhc_jax as fj

from .. import ControllerState, SearchResult, StepInfo

FOLDER = "firhc_jax_exported"  # inside the compilation cache's folder
SUFFIX = ".jaxexport"
MAGIC = b"firhc_jax kept decision "  # how a kept file of any format starts
FORMAT = MAGIC + b"1\n"  # the first line of a kept file of this format; the header follows on one line
KEPT_NAME = re.compile(r"[0-9a-f]{64}" + re.escape(SUFFIX))  # kept_path's names
# The temporary file a decision is written to before it takes its name (``_write``), left where a run was killed
# in between; before it had the suffix, mkstemp's eight characters alone.
UNFINISHED_NAME = re.compile(r"\.tmp-\w+" + re.escape(SUFFIX) + r"|\.tmp-\w{8}")
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


def installation() -> dict:
    """The lines of every key that this installation and machine decide: a kept file whose key differs in one of
    them is never read here."""
    return {"format": FORMAT.decode().strip(), "firhc_jax": fj.__version__, "source": source_digest(),
            "jax": jax.__version__, "jaxlib": jaxlib.__version__, "platform": jax.export.default_export_platform()}


def key_lines(key_text: str) -> dict:
    """``{name: value}`` of a key's lines."""
    return dict(line.partition("=")[::2] for line in key_text.splitlines())


def key(settings, args) -> str:
    """The full key of the program built from ``settings`` and traced for ``args``: one ``name=value`` line for
    everything that decides what a trace produces and where it can run."""
    leaves, tree = jax.tree_util.tree_flatten(args)
    lines = {**installation(), "setting": canonical(settings), "arguments": str(tree),
             "shapes": " ".join(f"{np.shape(a)}{getattr(a, 'dtype', None) or np.asarray(a).dtype}" for a in leaves),
             "options": " ".join(f"{k}={getattr(jax.config, k)}" for k in TRACE_CONFIG)}
    return "\n".join(f"{name}={value}" for name, value in lines.items())


def kept_path(folder, key_text: str) -> Path:
    """Where the program of ``key_text`` is kept in the compilation cache's ``folder``."""
    return Path(folder) / FOLDER / f"{hashlib.sha256(key_text.encode()).hexdigest()}{SUFFIX}"


class Refused(Exception):
    """A kept file that must not run; its message says why, as the end of a sentence naming the file."""


def read_header(data: bytes) -> tuple[dict, bytes]:
    """``(header, program bytes)`` of a kept file's contents. The header holds ``key``, ``sha256`` and ``label``
    (the settings' first entry: the application's name). ``Refused`` when there is no header."""
    if not data.startswith(MAGIC):
        raise Refused("is not a kept decision")
    if not data.startswith(FORMAT):
        raise Refused("was written in another format")
    end = data.find(b"\n", len(FORMAT))
    try:
        header = json.loads(data[len(FORMAT):end])
        if not isinstance(header, dict) or not {"key", "sha256", "label"} <= header.keys():
            raise ValueError
    except (ValueError, RecursionError):  # RecursionError: JSON nested deeper than Python's parser goes
        raise Refused("has a damaged header") from None
    return header, data[end + 1:]


def read_regular(path: Path) -> bytes:
    """The contents of the regular file ``path``; ``Refused`` for anything else (a named pipe would wait for a
    writer for ever), ``OSError`` where it cannot be read."""
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0))
    with os.fdopen(fd, "rb") as f:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise Refused("is not a regular file")
        return f.read()


def _difference(kept: str, wanted: str) -> str:
    """The first line of two keys that differs, by name, with both values when they are short."""
    kept_lines = key_lines(kept)
    for name, value in key_lines(wanted).items():
        other = kept_lines.get(name)
        if other != value:
            return name + (f" ({other}, not {value})" if other is not None and len(other + value) <= 60 else "")
    return "key"


def _read(path: Path, key_text: str):
    """The kept program of ``key_text`` at ``path``, verified; ``None`` when there is none, ``Refused`` when the
    file must not run."""
    try:
        data = read_regular(path)
    except (FileNotFoundError, NotADirectoryError):  # none kept yet
        return None
    except OSError as e:
        raise Refused(f"cannot be read ({e.strerror or e})") from None
    header, blob = read_header(data)
    if header["key"] != key_text:
        raise Refused(f"was written for another {_difference(str(header['key']), key_text)}")
    if hashlib.sha256(blob).hexdigest() != header["sha256"]:
        raise Refused("is damaged (its program does not match the SHA-256 recorded with it)")
    try:
        program = jax.export.deserialize(bytearray(blob))
    except Exception as e:  # noqa: BLE001  whatever jax.export makes of bytes it cannot read
        raise Refused(f"cannot be read by jax.export ({type(e).__name__})") from None
    platform = jax.export.default_export_platform()
    if tuple(program.platforms) != (platform,):
        raise Refused(f"was exported for {'/'.join(program.platforms)}, not {platform}")
    return program


def _redo(path: Path, why: str) -> None:
    warnings.warn(f"the kept decision {str(path)!r} {why}: traced and written again", RuntimeWarning, stacklevel=3)


def _keep(ctrl, path: Path, key_text: str, label: str, args):
    """Trace ``ctrl.step`` for ``args``, write it to ``path`` with its header, and return the program."""
    program = jax.export.export(jax.jit(ctrl.step))(*args)
    blob = bytes(program.serialize())
    header = json.dumps({"key": key_text, "sha256": hashlib.sha256(blob).hexdigest(), "label": label})
    try:
        _write(path, FORMAT + header.encode() + b"\n" + blob)
    except OSError as e:
        warnings.warn(f"the decision could not be kept in {str(path.parent)!r} ({e.strerror or e}): the next "
                      "run traces it again", RuntimeWarning, stacklevel=3)
    return program


def _on_one_device(program) -> Callable:
    # Placed on one device: arguments whether committed there or not (an exported program's results are) share
    # one compilation.
    return jax.jit(program.call, in_shardings=jax.sharding.SingleDeviceSharding(jax.devices()[0]))


def decision(ctrl, settings, folder, state, x, params) -> Callable:
    """``ctrl.step`` for arguments shaped as ``(state, x, params)``, jitted: ``(state, x, params) -> (u, state,
    info)``, the same program, kept in ``folder`` (the compilation cache's) under ``FOLDER``.

    ``settings`` (numbers, strings, arrays, dataclasses and tuples, lists and
    dicts of them; ``canonical``) must be everything that built ``ctrl``
    besides the package's code: the package's source and version, JAX's
    version and the platform are added here (``key``). The traced program is
    read from the folder when an earlier run stored it there and it passes
    the checks (the module's docstring), and traced and stored otherwise; a
    file refused, or a kept program that fails when called, is traced and
    written again with a ``RuntimeWarning``, and a folder that cannot be
    written is warned about.
    """
    args = (state, x, params)
    _make_serializable(args)
    key_text = key(settings, args)
    path = kept_path(folder, key_text)
    label = settings if isinstance(settings, str) else str(settings[0]) if isinstance(settings, tuple) else ""
    try:
        program = _read(path, key_text)
    except Refused as e:
        _redo(path, str(e))
        program = None
    if program is None:
        return _on_one_device(_keep(ctrl, path, key_text, label, args))
    run = kept = _on_one_device(program)

    def decide(*call_args):
        nonlocal run
        try:
            return run(*call_args)
        except Exception as e:  # noqa: BLE001  a kept program that fails is replaced; a fresh one's error stands
            if run is not kept:
                raise
            _redo(path, f"failed when run ({type(e).__name__})")
            run = _on_one_device(_keep(ctrl, path, key_text, label, args))
            return run(*call_args)

    return decide


def _write(path: Path, blob: bytes) -> None:
    """Write ``blob`` to ``path`` whole or not at all (another process may be reading it), through a temporary
    file named as ``UNFINISHED_NAME`` says, so that ``python -m firhc_jax cache`` finds one a killed run left."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=SUFFIX)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(blob)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:  # cleared meanwhile (cache --clear)
            pass
        raise
