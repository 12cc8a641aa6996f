"""The node budget that buys a guarantee: ``B(N0)`` of docs/guide/budgets.md, for a search or a decision.

A budgeted search runs the exact problems of horizon 1, 2, ... (the levels) within half its budget, each
extended to the horizon by the greedy rollout; ``B(N0)`` is the least ``max_nodes`` at which levels 1 .. N0
all run to the end, so that the search is never dearer than the exact horizon-N0 decision extended. It
depends only on the horizon N, the number of inputs M, the pop width K and the candidates evaluated first.
"""
from __future__ import annotations

from ..checks import positive_int
from ..problem.problem import Problem
from ..search import solvers
from .controller import FIRHC


def budget_for(target: Problem | FIRHC, n0: int, *, pop_width: int = 1, warm_start: bool = False) -> int:
    """``B(n0)``: the least ``max_nodes`` that guarantees level ``n0`` (docs/guide/budgets.md).

    Args:
      target: a ``Problem`` (``fj.sdfs``, a row of ``fj.solve_batch``), or a ``FIRHC`` (its ``max_nodes``
        for a whole decision: its ``pop_width``, the previous plan it evaluates first, its warm start, and with a
        fallback twice the budget, since the fallback may get only half; each of the two searches then keeps
        the guarantee).
      n0: the level, ``1 <= n0 <= N - 1``.
      pop_width: the search's K (a ``Problem`` only).
      warm_start: whether a warm start's N nodes come first (a ``Problem`` only).

    Returns ``2 (sum_{D=1..n0} (T_D + N M) + K M + W)`` with ``T_D = M + ... + M^D`` and ``W`` the nodes of
    the candidates evaluated first (``N`` for a warm start; in a decision ``N - 1 + M`` for the previous plan
    shifted and completed, plus ``N`` for a callable warm start), doubled for a decision with a fallback.
    """
    if isinstance(target, FIRHC):
        if pop_width != 1 or warm_start:
            raise TypeError("pop_width and warm_start are read from the controller; give them for a Problem only")
        opts = target.options
        if not solvers.get(opts.solver).budgets:
            raise ValueError(f"solver={opts.solver!r} takes no node budget")
        problem, K = opts.problem, opts.solver_options["pop_width"]
        N, M = problem.horizon, problem.num_controls
        first = N - 1 + M + (N if callable(opts.warm_start) else 0)
        return _budget(N, M, K, _level(n0, N), first) * (2 if opts.relaxed is not None else 1)
    if not isinstance(target, Problem):
        raise TypeError(f"target must be a Problem or a FIRHC, got {type(target).__name__}")
    if not isinstance(warm_start, bool):
        raise TypeError(f"warm_start must be a bool (whether a warm start is given), got {type(warm_start).__name__}")
    N, M = target.horizon, target.num_controls
    return _budget(N, M, positive_int("pop_width", pop_width), _level(n0, N), N if warm_start else 0)


def _level(n0, N: int) -> int:
    n0 = positive_int("n0", n0)
    if n0 >= N:
        raise ValueError(f"n0 must be a level below the horizon, 1 <= n0 <= N - 1 = {N - 1}, got {n0}")
    return n0


def _budget(N: int, M: int, K: int, n0: int, first: int) -> int:
    trees = sum(sum(M**i for i in range(1, D + 1)) for D in range(1, n0 + 1))
    return 2 * (trees + n0 * N * M + K * M + first)
