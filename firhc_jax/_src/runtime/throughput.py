"""Expansion throughput of the user's own problem on this machine.

``profile(problem, states)`` times the searches a user can pick from on the
states they will search at (for instance the states of a closed loop): one
state per call with ``fj.sdfs`` at several pop widths and with
``fj.exhaustive``, and all states at once with ``fj.solve_batch``'s pool at
several lane counts. Each setting's first call compiles and is timed apart
(``compile_s``); the rates come from the median of the timed calls after it.
The fastest setting (most solves per second) is marked. The one-state
searches are jitted once per problem and setting, in the package's cache
(``firhc_jax._src.runtime.memory_cache``): profiling the same problem again compiles nothing.
"""
from __future__ import annotations

import statistics
import time
from typing import Callable

import jax
import numpy as np

from ..checks import positive_int
from ..problem.callables import search_inputs
from ..problem.problem import Problem
from ..search import solvers
from ..search.batch import solve_batch
from ..search.sdfs import INT32_MAX
from .memory_cache import cached
from .progress import Progress

POP_WIDTHS = (1, 2, 4, 8)
LANES = (16, 64, 256)
MAX_EXHAUSTIVE_NODES = 10_000_000


def _counts(name: str, values) -> tuple[int, ...]:
    try:
        values = tuple(values)
    except TypeError:
        raise TypeError(f"{name} must be a sequence of positive ints, got {values!r}") from None
    return tuple(positive_int(name, v) for v in values)


def _timed(run: Callable[[], list], repeats: int):
    """``(median seconds, first-call seconds, results)`` of ``run()`` (a list of
    results, each read back before the clock stops); the first call compiles."""
    t0 = time.perf_counter()
    results = jax.block_until_ready(run())
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        results = jax.block_until_ready(run())
        times.append(time.perf_counter() - t0)
    return statistics.median(times), first, results


def _search(problem: Problem, solver: str, X, **options) -> Callable:
    """The jitted one-state search of ``solver`` (the table's ``search``) with these options, from the cache;
    refused before compiling where one search from a row of ``X`` would not fit ``max_memory``."""
    options = solvers.check_options(solver, options)
    solvers.check_memory(solver, options, problem, X.shape[1], max(X.dtype.itemsize, 4))
    traced = {k: v for k, v in options.items() if k not in ("max_nodes", "max_memory")}
    search = solvers.get(solver).search
    return cached(("profile", solver, problem.key, tuple(sorted(traced.items()))), lambda: jax.jit(
        lambda x, p: search(problem, x, p, None, INT32_MAX, budgeted=False, **traced)))


def _each(search: Callable, pairs) -> Callable[[], list]:
    """Search from each ``(x, p)`` in turn, reading every result back before the
    next call (as a controller does)."""
    return lambda: [jax.block_until_ready(search(x, p)) for x, p in pairs]


def _row(solver: str, setting: str, seconds: float, first: float, results, solves: int, **options) -> dict:
    nodes = int(sum(np.sum(np.asarray(r.nodes, np.int64)) for r in results))
    iterations = int(sum(np.sum(np.asarray(r.iterations, np.int64)) for r in results))
    return {"solver": solver, "setting": setting, **options, "states": solves, "seconds": seconds,
            "compile_s": max(first - seconds, 0.0), "nodes": nodes, "iterations": iterations,
            "nodes_per_second": nodes / seconds, "solves_per_second": solves / seconds,
            "us_per_iteration": 1e6 * seconds / max(iterations, 1), "fastest": False}


def profile(problem: Problem, states, params=None, *, pop_widths=POP_WIDTHS, lanes=LANES, repeats: int = 3,
            max_exhaustive_nodes: int = MAX_EXHAUSTIVE_NODES, progress: bool | None = None) -> list[dict]:
    """Time every search setting on ``states`` and mark the fastest.

    Args:
      problem: the ``Problem``.
      states: ``[S, n]`` states to search from (e.g. a closed loop's).
      params: optional parameter pytree with leading axis S: state i is
        searched with ``params[i]`` (as ``fj.solve_batch``).
      pop_widths: the ``fj.sdfs`` pop widths to time, one state per call.
      lanes: the ``fj.solve_batch`` lane counts to time, all states in one
        call (default ``cores``: every core of a CPU).
      repeats: timed calls after the compiling one; their median is used.
      max_exhaustive_nodes: ``fj.exhaustive`` is timed on evenly spaced states
        visiting at most this many nodes in all (none if one tree is larger).
      progress: a bar counting the settings timed, with an estimate, on
        stderr or in the notebook, naming the setting being compiled and
        timed: ``None`` (default) once the call has taken 2 s, ``True`` at
        once, ``False`` never.

    Returns one dict per setting, in the order above: ``solver`` (``"sdfs"``,
    ``"exhaustive"`` or ``"solve_batch"``), ``setting`` (e.g.
    ``"sdfs pop_width=2"``), ``pop_width`` or ``lanes``, ``states`` (how many
    were solved), ``seconds`` (median time to solve them all; the one-state
    solvers are called once per state, each result read back),
    ``compile_s`` (the first call's extra time: never part of a rate),
    ``nodes``, ``iterations`` (summed ``SearchResult`` counts),
    ``nodes_per_second``, ``solves_per_second``, ``us_per_iteration``
    (``seconds`` over ``iterations``, whose meaning is each solver's, see
    ``SearchResult``) and ``fastest``: True on exactly one row, the setting
    with the most solves per second.
    """
    X, params = search_inputs(problem, states, params, batched=True, name="states")
    S = X.shape[0]
    pop_widths, lanes = _counts("pop_widths", pop_widths), _counts("lanes", lanes)
    repeats = positive_int("repeats", repeats)
    max_exhaustive_nodes = positive_int("max_exhaustive_nodes", max_exhaustive_nodes)
    if not pop_widths and not lanes:
        raise ValueError("pop_widths and lanes are both empty: nothing to profile")
    one = [(X[i], jax.tree_util.tree_map(lambda a, i=i: a[i], params)) for i in range(S)]

    settings = []  # (setting, solver, how many states, the timed run, its options)
    for k in pop_widths:
        settings.append((f"sdfs pop_width={k}", "sdfs", S, _each(_search(problem, "sdfs", X, pop_width=k), one),
                         {"pop_width": k}))
    count = min(S, max_exhaustive_nodes // problem.tree_size())
    if count:
        some = [one[i] for i in np.unique(np.linspace(0, S - 1, count).round().astype(int))]
        settings.append(("exhaustive", "exhaustive", len(some), _each(_search(problem, "exhaustive", X), some), {}))
    for slots in lanes:
        settings.append((f"solve_batch lanes={slots}", "solve_batch", S,
                         lambda slots=slots: [solve_batch(problem, X, params=params, lanes=slots, progress=False)],
                         {"lanes": slots}))
    rows = []
    with Progress(len(settings), "profile", enabled=progress) as bar:
        for setting, solver, solves, run, options in settings:
            bar.describe(f"profile: {setting} (compiling, then {repeats} timed runs)")
            t, first, res = _timed(run, repeats)
            rows.append(_row(solver, setting, t, first, res, solves, **options))
            bar.update(len(rows))
        bar.describe("profile")
    max(rows, key=lambda r: r["solves_per_second"])["fastest"] = True
    return rows
