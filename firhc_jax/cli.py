"""Command line: ``python -m firhc_jax <subcommand>``.

Each application module registers its own subcommand through
``register(subparsers)`` and sets ``func`` on its parser, and optionally
``check(args)``, run before ``func``: limits on what the options size
together, refused with argparse's one-line error (``apps/_limits.py``).
Every command keeps its compilations in JAX's persistent compilation cache
(``firhc_jax.enable_compilation_cache``), so a second run skips XLA's
compilation, and the applications keep their traced decisions beside it
(``apps/_exported.py``), so it skips tracing and lowering too; ``--no-cache``
turns both off for one run: nothing is read or written, whatever folder the
environment names (``JAX_COMPILATION_CACHE_DIR``). A command that sets
``uses_cache=False`` on its parser (``cache``, which lists and clears that
folder) takes no ``--no-cache``. Warnings are shown on one line each.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import sys
import warnings
from pathlib import Path

# Subcommand modules, in the order shown by --help.
_APPS = ("firhc_jax.apps.example", "firhc_jax.apps.hopper", "firhc_jax.apps.tanks", "firhc_jax.apps.inverter",
         "firhc_jax.apps.batch", "firhc_jax.apps.bench", "firhc_jax.apps.profile", "firhc_jax.apps.export",
         "firhc_jax.apps.cache")


def build_parser() -> argparse.ArgumentParser:
    invoked = os.path.basename(sys.argv[0])
    parser = argparse.ArgumentParser(
        prog="python -m firhc_jax" if invoked in ("__main__.py", "-c", "") else invoked,
        description="Finite-input receding horizon control with exact sorted depth-first search (JAX).")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _APPS:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as e:
            if e.name != name:  # a real missing dependency, not an app that is not there yet
                raise
            continue
        module.register(sub)
    for command in _leaves(parser):
        if command.get_default("uses_cache") is not False:
            command.add_argument("--no-cache", action="store_true",
                                 help="read and write nothing in the compilation cache and the kept decisions "
                                      "($JAX_COMPILATION_CACHE_DIR, else $XDG_CACHE_HOME/firhc_jax, else "
                                      "~/.cache/firhc_jax; 'python -m firhc_jax cache' lists them)")
    return parser


def _leaves(parser: argparse.ArgumentParser):
    """The parsers that run a command: ``parser`` itself, or the leaves below its subcommands."""
    groups = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not groups:
        yield parser
    for group in groups:
        for child in dict.fromkeys(group.choices.values()):  # aliases map to the same parser
            yield from _leaves(child)


def cache_folder() -> Path:
    """The folder the commands keep their compilations and decisions in, absolute and with ``~`` expanded: the one
    this process already set (``JAX_COMPILATION_CACHE_DIR``, a caller; empty counts as unset), else
    ``$XDG_CACHE_HOME/firhc_jax`` or ``~/.cache/firhc_jax``. The runs use it (``_use_compilation_cache``) and
    ``cache`` lists it."""
    import jax

    from ._src.runtime.disk_cache import cache_path

    return cache_path(jax.config.jax_compilation_cache_dir or None)


def _use_compilation_cache() -> None:
    """Turn on the compilation cache in ``cache_folder()``. A folder this process already set is kept, only
    written as that function names it: JAX would take a ``~`` in it for a folder of that name."""
    import jax
    from jax.experimental.compilation_cache import compilation_cache

    from ._src.runtime.disk_cache import enable_compilation_cache

    folder = cache_folder()
    if jax.config.jax_compilation_cache_dir:
        if jax.config.jax_compilation_cache_dir != str(folder):
            compilation_cache.reset_cache()  # a cache JAX already opened is closed, so the folder named is used
            jax.config.update("jax_compilation_cache_dir", str(folder))
        return
    try:
        enable_compilation_cache(folder)
    except OSError as e:  # a read-only home: the run goes on, compiling as if --no-cache were given
        warnings.warn(f"{e}; running without the persistent compilation cache", stacklevel=2)


def _one_line(message, category, filename, lineno, line=None) -> str:
    return f"warning: {message}\n"


@contextlib.contextmanager
def _warnings_on_one_line():
    """Python's warnings shown as ``warning: <message>``, without the file, line and source they come from."""
    shown = warnings.formatwarning
    warnings.formatwarning = _one_line
    try:
        yield
    finally:
        warnings.formatwarning = shown


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    if getattr(args, "check", None):  # limits on what the options size together, before any work
        args.check(args)
    with contextlib.ExitStack() as stack:
        stack.enter_context(_warnings_on_one_line())
        if getattr(args, "no_cache", False):
            from ._src.runtime.disk_cache import compilation_cache_off

            stack.enter_context(compilation_cache_off())
        elif getattr(args, "uses_cache", True):
            _use_compilation_cache()
        return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
