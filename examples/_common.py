"""What every example shares: ``--quick`` (a smaller run, for tests and CI), ``--out`` (where figures go),
float64 arithmetic, and ``say`` (what the example is doing, on stderr, as it starts each long stage)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax


def arguments(description: str) -> argparse.Namespace:
    """The examples' command line; enables float64 (the library itself never changes JAX's settings)."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--quick", action="store_true", help="a smaller run (seconds), e.g. for tests")
    parser.add_argument("--out", type=Path, default=Path("out/examples"), help="folder for the figures")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_enable_x64", True)
    return args


def say(text: str) -> None:
    """One line on stderr, at once: what the example is doing now."""
    print(text, file=sys.stderr, flush=True)
