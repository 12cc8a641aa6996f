"""Argument types shared by the command-line applications: numbers with bounds
and output folders, each refused by argparse with a one-line message before
any work starts."""
from __future__ import annotations

import argparse
import math
import os
import tempfile
from pathlib import Path


def number(kind=float, low=None, high=None, low_open=False):
    """An argparse ``type``: ``kind`` (int or float) within ``[low, high]``
    (``(low, high]`` with ``low_open``); ``None`` leaves a side unbounded."""
    name = "an integer" if kind is int else "a number"

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {name}, got {text!r}") from None
        too_low = low is not None and (value <= low if low_open else value < low)
        if not math.isfinite(value) or too_low or (high is not None and value > high):
            if low is not None and high is not None and not low_open:
                bounds = f"between {low} and {high}"
            else:
                lo = "" if low is None else f"{'>' if low_open else '>='} {low}"
                bounds = " and ".join(p for p in (lo, "" if high is None else f"<= {high}") if p)
            raise argparse.ArgumentTypeError(f"must be {name} {bounds}, got {text!r}")
        return value

    return parse


def output_dir(text: str) -> Path:
    """An argparse ``type`` for an output folder: refused unless it is, or can be created as, a folder this
    process can write files into. Checked by writing (a temporary file or folder, removed at once), which
    permission bits cannot fool (root, read-only mounts, /proc); nothing is left behind, so a command that
    fails on a later argument has created nothing. The command creates the folder when it starts."""
    if not text:
        raise argparse.ArgumentTypeError("must name a folder, got ''")
    folder = Path(text)
    if os.path.lexists(folder) and not os.path.isdir(folder):
        raise argparse.ArgumentTypeError(f"{text!r} exists and is not a folder")
    existing = folder
    while not os.path.lexists(existing):  # the nearest existing ancestor (".", "/" always exist)
        existing = existing.parent
    if not os.path.isdir(existing):
        raise argparse.ArgumentTypeError(f"cannot create {text!r}: {str(existing)!r} is not a folder")
    try:
        if existing == folder:
            with tempfile.TemporaryFile(dir=folder):
                pass
        else:
            os.rmdir(tempfile.mkdtemp(dir=existing))
    except OSError as e:
        raise argparse.ArgumentTypeError(f"cannot write into {text!r}: {e.strerror or e}") from None
    return folder


def solver_argument(parser: argparse.ArgumentParser, note: str = "") -> None:
    """``--solver``: a name of the solver table (``firhc_jax.solvers``), default sdfs; ``note`` ends the help."""
    from ..solvers import SOLVERS, options_help

    parser.add_argument("--solver", choices=tuple(SOLVERS), default="sdfs",
                        help=f"search (default sdfs): {options_help()}" + (f"; {note}" if note else ""))


def horizon_argument(parser: argparse.ArgumentParser, most: int, default: int, note: str = "",
                     short: bool = True) -> None:
    """``--horizon`` (and ``-N`` with ``short``): the prediction horizon, an int in 1 .. ``most``; ``note``
    ends the help."""
    parser.add_argument("--horizon", *(["-N"] if short else []), type=number(int, 1, most), default=default,
                        metavar="N",
                        help=f"prediction horizon N (1-{most}, default {default}" + (f"; {note})" if note else ")"))
