"""Limits on the work a command line may start, checked with its arguments.

Each application registers ``check(args)`` (``set_defaults(check=...)``),
which ``cli.main`` calls after parsing and before any work; a refusal is
argparse's one-line error (exit status 2). A range on each option bounds it
alone; these bound what options size together, such as an exhaustive search's
nodes over a whole run.
"""
from __future__ import annotations

import argparse


def tree_nodes(num_controls: int, horizon: int) -> int:
    """Nodes of one exhaustive search: sum_{i=1..N} M^i (``Problem.tree_size``)."""
    M, N = num_controls, horizon
    return N if M == 1 else (M ** (N + 1) - M) // (M - 1)


def exhaustive_run(parser: argparse.ArgumentParser, steps: int, num_controls: int, horizon: int, budget: float,
                   rate: str, hint: str) -> None:
    """Refuse (``parser.error``) an exhaustive closed loop of ``steps`` decisions visiting more than ``budget``
    nodes in all; ``rate`` says what that is in time, ``hint`` what to change."""
    per_step = tree_nodes(num_controls, horizon)
    if steps * per_step > budget:
        parser.error(f"exhaustive search at N = {horizon} visits {per_step:,} nodes per step, "
                     f"{steps * per_step:,} over {steps:,} steps: more than the {budget:,.0f} allowed ({rate}); "
                     f"{hint}")
