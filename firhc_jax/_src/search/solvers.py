"""The table of solvers: every search strategy under one traced signature.

A ``Solver`` is what the controller (``FIRHC(solver=...)``), ``solve_batch``,
``simulate_batch``, ``profile``, the apps' ``--solver`` choices and the docs
know of a search. Its two traced entry points share one signature (mctx's
``search(params, ...)`` taking its strategy as functions):

* ``search(problem, x, params, warm_start, max_nodes, *, budgeted, reserve=None, **options)``
  solves one state ``x`` ``[n]``: ``warm_start`` ``[N]`` or ``[C, N]`` int32
  candidates or None (all -1: none; budgeted, a prefix followed by -1 is
  completed by the greedy rollout), ``max_nodes`` ``[]`` int32
  (``INT32_MAX``: no budget; traced, so budgets never recompile), ``budgeted``
  (static) whether a budget was set at all (a budgeted search seeds its
  incumbent first, docs/guide/budgets.md), ``reserve`` ``[]`` int32 (or
  None) nodes held back while the search has no sequence (a controller's
  fallback gets them).
* ``batch(problem, X, params, warm_start, max_nodes, n_valid, *, budgeted,
  reserve=None, **options)`` solves the rows ``X[:n_valid]`` of ``[R, n]``
  (``params`` leaves ``[R, ...]``, ``warm_start`` ``[R, N]``, ``[R, C, N]``
  or None, ``max_nodes`` and ``reserve`` ``[R]``); rows from ``n_valid`` on
  are padding, their results unused.
  ``steal=False``: no nodes are shared between rows, so every row is searched
  node for node as ``search`` searches it (a budget cuts it where it cuts
  ``search``).

Both run inside a trace and trust their arguments: the options are checked
once, by ``check_options``, at the public boundary. ``memory`` estimates the
bytes of one search and ``batch_memory`` those of a batch, ``(fixed, per_row)``.

Adding a solver is its module plus one entry in ``SOLVERS``.
"""
from __future__ import annotations

from typing import Any, Callable, Mapping, NamedTuple

import jax
import jax.numpy as jnp

from ..checks import is_tracer, positive_int
from ..problem.problem import Problem
from . import exhaustive as exhaustive_module
from .pool import pool_memory, pool_row_memory, pool_search
from .result import SearchResult
from .sdfs import DEFAULT_MAX_MEMORY, INT32_MAX, stack_memory
from .sdfs import check_memory as check_max_memory
from .sdfs import search as sdfs_search

DEFAULT_LANES = 64  # pool slots of a batch when ``lanes`` is not given: at most this many, at most the rows
DECISION_LANES = 4  # pool slots of one decision of solver="pool"


class Solver(NamedTuple):
    """One search strategy (module docstring)."""

    search: Callable[..., SearchResult]  # one state: (problem, x [n], params, warm_start, max_nodes, *, budgeted, ...)
    batch: Callable[..., SearchResult]  # rows: (problem, X [R, n], params, warm_start, max_nodes [R], n_valid, ...)
    options: Mapping[str, Any]  # every option it takes, with its default (None: chosen per call)
    memory: Callable[..., int]  # (problem, n, itemsize, **options) -> bytes of one search
    batch_memory: Callable[..., tuple[int, int]]  # (problem, n, itemsize, rows, param_bytes, **opts) -> bytes
    budgets: bool  # takes max_nodes
    prunes: bool  # False: visits every node of the tree
    warm_starts: bool  # takes a warm start
    doc: str  # one line for tables and --help
    shares_rows: bool = False  # a batch's rows share one pool: its node counts (and, cut by a budget, its
    # incumbents) depend on which rows are solved together


def _vmapped(search: Callable) -> Callable:
    """A ``batch`` that runs ``search`` on every row, each to its own end (lanes lock-step: a vmapped
    while-loop runs until its slowest row is done)."""
    def batch(problem, X, params, warm_start, max_nodes, n_valid, reserve=None, **options):
        one = lambda x, p, w, b, r: search(problem, x, p, w, b, reserve=r, **options)  # noqa: E731
        return jax.vmap(one, in_axes=(0, 0, None if warm_start is None else 0, 0, None if reserve is None else 0))(
            X, params, warm_start, max_nodes, reserve)
    return batch


def _pool_batch(problem, X, params, warm_start, max_nodes, n_valid, *, budgeted, pop_width, lanes, steal=True,
                reserve=None, **_):
    return pool_search(problem, X, params, n_valid, max_nodes, lanes_for(lanes, X.shape[0]), pop_width, budgeted,
                       warm_start=warm_start, steal=steal, reserve=reserve)


def _pool_one(problem, x, params, warm_start, max_nodes, *, budgeted, pop_width, lanes, reserve=None, **_):
    """One decision on ``lanes`` slots: the root on one, the others steal its nodes."""
    lanes = DECISION_LANES if lanes is None else lanes
    row = lambda a: None if a is None else jnp.asarray(a)[None]  # noqa: E731
    out = pool_search(problem, x[None], jax.tree_util.tree_map(row, params), 1, row(max_nodes), lanes, pop_width,
                      budgeted, warm_start=row(warm_start), reserve=row(reserve))
    return jax.tree_util.tree_map(lambda a: a[0], out)


def _pool_decisions(problem, X, params, warm_start, max_nodes, n_valid, *, steal=True, **options):
    """``"pool"``'s batch: the rows share one pool (``steal``), or each row is one decision's pool of its own
    (``_pool_one`` vmapped), where its slots steal from each other as in ``search``."""
    if steal:
        return _pool_batch(problem, X, params, warm_start, max_nodes, n_valid, **options)
    return _vmapped(_pool_one)(problem, X, params, warm_start, max_nodes, n_valid, **options)


def _exhaustive(problem, x, params, warm_start, max_nodes, *, method, chunk_nodes, pop_width, **_):
    if method == "dfs" or exhaustive_module.levels_executable(problem, x, params, chunk_nodes) is None:
        # the sDFS machinery with pruning off (and the bound unused: the reference); also where XLA:CPU
        # cannot compile the level search (docs/dev/xla_notes.md)
        return sdfs_search(problem.replace(lower_bound=None), x, params, None, INT32_MAX, pop_width=pop_width,
                           prune=False)
    return exhaustive_module._exhaustive(problem, x, params, chunk_nodes=chunk_nodes)


def _stack_memory(problem, n, itemsize, *, pop_width, **_):
    return stack_memory(problem, n, itemsize, pop_width)


def _one_pool_memory(problem, n, itemsize, *, pop_width, lanes, **_):
    return sum(_pool_memory(problem, n, itemsize, 1, 0, pop_width=pop_width, lanes=DECISION_LANES if lanes is None
                            else lanes))


def _rows_of(memory: Callable) -> Callable:
    """A ``batch_memory`` of rows that each need ``memory`` (and their params)."""
    return lambda problem, n, itemsize, rows, param_bytes, **options: (0, memory(problem, n, itemsize, **options)
                                                                       + param_bytes)


def _pool_memory(problem, n, itemsize, rows, param_bytes, *, pop_width, lanes, **_):
    slots = lanes_for(lanes, rows)
    return (pool_memory(problem, n, itemsize, slots, pop_width, param_bytes),
            pool_row_memory(problem, n, itemsize, param_bytes))


def _exhaustive_memory(problem, n, itemsize, *, method, chunk_nodes, pop_width, **_):
    if method == "dfs":
        return stack_memory(problem, n, itemsize, pop_width)
    return exhaustive_module.memory(problem, n, itemsize, chunk_nodes)


def lanes_for(lanes, rows: int) -> int:
    """Pool slots for ``rows`` rows: ``lanes``, or by default the rows, at most ``DEFAULT_LANES``."""
    return min(DEFAULT_LANES, rows) if lanes is None else lanes


_SDFS_OPTIONS = {"pop_width": 1, "max_nodes": None, "max_memory": DEFAULT_MAX_MEMORY}
SOLVERS: dict[str, Solver] = {
    "sdfs": Solver(search=sdfs_search, batch=_pool_batch, options={**_SDFS_OPTIONS, "lanes": None},
                   memory=_stack_memory, batch_memory=_pool_memory, budgets=True, prunes=True, warm_starts=True,
                   doc="sorted depth-first search (the paper's Table 1); a batch shares a work pool",
                   shares_rows=True),
    "pool": Solver(search=_pool_one, batch=_pool_decisions, options={**_SDFS_OPTIONS, "lanes": None},
                   memory=_one_pool_memory, batch_memory=_pool_memory, budgets=True, prunes=True,
                   warm_starts=True,
                   doc=f"sDFS on a work pool: one decision on `lanes` slots (default {DECISION_LANES}) by stealing",
                   shares_rows=True),
    "sdfs-vmap": Solver(search=sdfs_search, batch=_vmapped(sdfs_search), options=_SDFS_OPTIONS,
                        memory=_stack_memory, batch_memory=_rows_of(_stack_memory), budgets=True, prunes=True,
                        warm_starts=True,
                        doc="sDFS vmapped over a batch's rows (each row its own loop, lanes in lock-step)"),
    "exhaustive": Solver(search=_exhaustive, batch=_vmapped(_exhaustive),
                         options={"method": "levels", "chunk_nodes": exhaustive_module.DEFAULT_CHUNK_NODES,
                                  "pop_width": 1, "max_memory": DEFAULT_MAX_MEMORY},
                         memory=_exhaustive_memory, batch_memory=_rows_of(_exhaustive_memory), budgets=False,
                         prunes=False, warm_starts=False, doc="every node of the tree (the reference)"),
}
_COUNTS = ("pop_width", "max_nodes", "max_memory", "chunk_nodes", "lanes")


def get(name: str) -> Solver:
    """The solver called ``name``, or a ``ValueError`` naming the choices."""
    if not isinstance(name, str) or name not in SOLVERS:
        raise ValueError(f"solver must be one of {list(SOLVERS)}, got {name!r}")
    return SOLVERS[name]


def check_options(name: str, options: Mapping[str, Any]) -> dict:
    """Every option of solver ``name``: those given, checked, and the defaults of the rest. An option the solver
    does not take is refused with the solvers that do take it. A traced ``max_nodes`` passes as it is (budgets
    are traced: they never recompile)."""
    solver = get(name)
    unknown = sorted(set(options) - set(solver.options))
    if unknown:
        takers = {key: [other for other, s in SOLVERS.items() if key in s.options] for key in unknown}
        where = "; ".join(f"{key} is an option of {_names(takers[key])}" if takers[key] else f"{key} is no option"
                          for key in unknown)
        raise TypeError(f"unknown option(s) {unknown} for solver={name!r}, which takes {sorted(solver.options)}: "
                        f"{where}")
    out = {**solver.options, **options}
    for key in _COUNTS:
        none_allowed = key in solver.options and solver.options[key] is None  # None: none, or chosen per call
        if key in out and not is_tracer(out[key]) and not (out[key] is None and none_allowed):
            out[key] = positive_int(key, out[key])
    if "method" in out and out["method"] not in ("levels", "dfs"):
        raise ValueError(f"method must be 'levels' or 'dfs', got {out['method']!r}")
    if out.get("method") == "levels" and out.get("pop_width") != 1:
        raise ValueError("pop_width applies to method='dfs'; method='levels' expands whole levels")
    return out


def _names(names: list) -> str:
    return ("solver " if len(names) == 1 else "solvers ") + ", ".join(repr(n) for n in names)


def check_tree(name: str, options: Mapping[str, Any], problem: Problem) -> None:
    """Refuse (``ValueError``) a tree that solver ``name`` cannot search with these options: an exhaustive
    search's node count beyond the int32 counter, or levels that do not fit ``chunk_nodes``."""
    if name == "exhaustive" and options["method"] == "levels":
        exhaustive_module.plan(problem, options["chunk_nodes"])
    elif not get(name).prunes:
        exhaustive_module.check_tree_size(problem)


def check_memory(name: str, options: Mapping[str, Any], problem: Problem, n: int, itemsize: int) -> int:
    """Bytes of one search (``check_tree`` first), refused (``ValueError``) beyond ``max_memory``."""
    check_tree(name, options, problem)
    need = get(name).memory(problem, n, itemsize, **options)
    check_max_memory(need, options["max_memory"], f"solver={name!r} on N={problem.horizon}, M={problem.num_controls}")
    return need


def options_help() -> str:
    """One line per solver, for ``--help`` texts and docs."""
    return "; ".join(f"{name}: {s.doc}" for name, s in SOLVERS.items())
