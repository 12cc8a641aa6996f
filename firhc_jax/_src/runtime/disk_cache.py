"""Compile once across runs: JAX's persistent compilation cache, opt in.

A decision compiles in seconds (XLA:CPU compiles the search's loop body once
per problem, horizon and solver option). In-process, ``firhc_jax._src.runtime.memory_cache``
keeps the executable; across processes, JAX's persistent compilation cache
stores XLA's output on disk, keyed by the lowered program, so a second run of
the same script finds it there and only traces and lowers again
(docs/guide/caching.md has the split measured per plant).

The library never turns it on by itself (that would change global JAX
config on import): call ``enable_compilation_cache()`` once at the start of
a script. The command line (``python -m firhc_jax``) calls it unless given
``--no-cache``, which runs inside ``compilation_cache_off``.
"""
from __future__ import annotations

import contextlib
import os
from pathlib import Path

import jax
from jax.experimental.compilation_cache import compilation_cache as _jax_cache

# Entries are written for compilations of at least this many seconds. JAX's default (1 s) would leave out the
# checks and small helpers a decision also compiles (0.1-0.5 s each here); below 0.05 s, reading the entry from
# disk costs about as much as compiling again.
MIN_COMPILE_SECONDS = 0.05


def default_cache_path() -> Path:
    """``$XDG_CACHE_HOME/firhc_jax``, or ``~/.cache/firhc_jax`` when ``XDG_CACHE_HOME`` is unset or empty."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "firhc_jax"


def cache_path(path: str | os.PathLike | None = None) -> Path:
    """The folder that ``path`` names, absolute, with ``~`` expanded (JAX itself would write into a folder named
    ``~``); ``default_cache_path()`` when ``path`` is None."""
    return (default_cache_path() if path is None else Path(os.fspath(path)).expanduser()).resolve()


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path:
    """Turn on JAX's persistent compilation cache in ``path`` (default: ``default_cache_path()``) and return it.

    Later compilations in this process are read from, and written to, that
    folder, so the next run of the same program skips XLA's compilation
    (tracing and lowering still run). The folder is created if needed; one
    that cannot be created or written raises ``OSError`` naming it.

    This sets global JAX options (``jax_compilation_cache_dir`` and
    ``jax_persistent_cache_min_compile_time_secs``) for the whole process;
    call it at most once, before the work whose compilation should be kept.
    The folder holds executable code: share it only with users you trust.
    """
    folder = cache_path(path)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".firhc_jax_write_test_{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise OSError(f"enable_compilation_cache: cannot use {str(folder)!r} as a cache folder: "
                      f"{e.strerror or e}") from None
    if jax.config.jax_compilation_cache_dir != str(folder):
        _jax_cache.reset_cache()  # a cache JAX already opened elsewhere is closed, so the new folder is used
        jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
    return folder


@contextlib.contextmanager
def compilation_cache_off():
    """No persistent compilation cache inside the block, even where ``JAX_COMPILATION_CACHE_DIR`` names a folder:
    JAX reads and writes nothing there (``jax_enable_compilation_cache``), and neither do the command line's kept
    decisions. As it was after the block."""
    was = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)
    _jax_cache.reset_cache()  # JAX decides once per process whether to use its cache: decided again
    try:
        yield
    finally:
        jax.config.update("jax_enable_compilation_cache", was)
        _jax_cache.reset_cache()
