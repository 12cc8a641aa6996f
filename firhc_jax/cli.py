"""Command line: ``python -m firhc_jax <subcommand>``.

Each application module registers its own subcommand through
``register(subparsers)`` and sets ``func`` on its parser, and optionally
``check(args)``, run before ``func``: limits on what the options size
together, refused with argparse's one-line error (``apps/_limits.py``).
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys

# Subcommand modules, in the order shown by --help.
_APPS = ("firhc_jax.apps.example", "firhc_jax.apps.hopper", "firhc_jax.apps.tanks", "firhc_jax.apps.inverter",
         "firhc_jax.apps.batch", "firhc_jax.apps.bench", "firhc_jax.apps.profile")


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
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    if getattr(args, "check", None):  # limits on what the options size together, before any work
        args.check(args)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
