"""The searches of one state as users call them, ``fj.sdfs`` and ``fj.exhaustive``: their arguments checked once,
by the solver table's rules (``solvers.check_options``, ``check_tree``, ``check_memory``), then one compiled
search per problem, options and argument shapes."""
from __future__ import annotations

import jax
import numpy as np

from ..annotations import ArrayLike, PyTree
from ..checks import as_sequence, is_tracer
from ..problem.callables import search_inputs
from ..problem.problem import Problem
from ..runtime import engines, lean
from ..runtime.memory_cache import cached, compiled
from ..runtime.packed import compile_packed
from . import solvers
from .exhaustive import DEFAULT_CHUNK_NODES, levels_executable
from .result import SearchResult, alarms, raise_on_errors
from .sdfs import DEFAULT_MAX_MEMORY, INT32_MAX, node_budget
from .sdfs import search as sdfs_search


def sdfs(problem: Problem, x0: ArrayLike, *, params: PyTree = None, pop_width: int = 1,
         warm_start: ArrayLike | None = None, max_nodes: int | ArrayLike | None = None,
         max_memory: int = DEFAULT_MAX_MEMORY, engine: str = "xla") -> SearchResult:
    """Exact optimal input sequence by sorted depth-first search.

    Args:
      problem: the ``Problem``.
      x0: ``[n]`` current state.
      params: optional parameter pytree passed to every callable as its last
        argument (see ``firhc_jax._src.problem.problem``). New values of the same shapes and
        dtypes reuse the compiled search.
      pop_width: K, nodes popped and expanded per iteration (K * M children in
        one batched call). 1 is the paper's algorithm; larger K trades some
        pruning for fewer, wider iterations. Always exact.
      warm_start: optional ``[N]`` candidate sequence (e.g. the previous
        solution shifted by one step), evaluated first; if it meets the
        terminal test it is the initial incumbent. ``nodes`` counts its N
        nodes. All ``-1`` means none (no nodes counted); so does a
        ``max_nodes`` below N (its nodes would not fit in the budget).
      max_nodes: optional node budget (real-time use): ``nodes <= max_nodes``
        always (a warm start's N nodes included). Up to half of it first
        seeds the incumbent (the exact problems of horizon 1, 2, ... each
        extended to N by a greedy rollout; docs/guide/budgets.md states what that
        guarantees). The search stops before an iteration could take the
        count above it and returns its incumbent with ``complete=False``
        (infeasible if it has none yet; ``True``: proven optimal). A traced
        value: changing it does not recompile.
      max_memory: bytes the stack may take (``stack_memory``); larger problems
        are refused before anything is allocated.
      engine: what runs an eager call: ``"xla"`` (default), the compiled JAX
        search; ``"c"``, the search exported as C (``fj.export_c``), compiled
        with the system's C compiler on the first call for each argument
        shape and called through ``ctypes`` (the result's fields, shapes
        and dtypes as ``"xla"``'s, costs to the last bits as
        the C compiler rounds). A traced call runs in XLA either way.

    Works under ``jax.jit`` and ``jax.vmap`` over ``x0`` and ``params``. In an
    un-jitted call a negative stage cost raises ``ValueError``. Not
    differentiable (a discrete search); see ``fj.rollout_cost``.
    """
    budgeted = max_nodes is not None
    entry = ("sdfs", problem, type(pop_width), pop_width, budgeted, type(max_memory), max_memory,
             engine)  # True is not 1
    args = (x0, params, warm_start)
    run = None if is_tracer(max_nodes) else lean.recall(entry, args)
    if run is None:  # the first call of this signature (or a traced one): every check
        x0, params = search_inputs(problem, x0, params)
        options = solvers.check_options("sdfs", {"pop_width": pop_width, "max_nodes": max_nodes,
                                                 "max_memory": max_memory})
        solvers.check_memory("sdfs", options, problem, x0.shape[0], max(x0.dtype.itemsize, 4))
        ws = as_sequence(warm_start, problem.horizon, problem.num_controls)
        if any(map(is_tracer, (x0, ws, max_nodes, *jax.tree_util.tree_leaves(params)))):
            run = compiled(sdfs_search, problem, pop_width=options["pop_width"], budgeted=budgeted)
            return raise_on_errors(run(x0, params, ws, node_budget(max_nodes)))
        checked = (x0, params, ws, node_budget(max_nodes))
        outside = engines.engine(engine)
        if outside is not None:
            outside.check_search()
            build = lambda: outside.build_search(problem, x0, params, budgeted, options["pop_width"])  # noqa: E731
        else:
            build = lambda: compile_packed(_eager_search(problem, options["pop_width"], budgeted), *checked)  # noqa: E731
        run = lean.first_call(entry, args, lambda: cached(
            ("eager", engine, sdfs_search, problem.key, options["pop_width"], budgeted, lean.spec(checked[:3])),
            build))
        args = checked[:3]
    result, alarm = run(*args[:2], _indices(args[2]), node_budget(max_nodes))
    if alarm:  # the value checks of the first call, on these values (each raises with its own message), then
        search_inputs(problem, x0, params)  # the result's error flags
        as_sequence(warm_start, problem.horizon, problem.num_controls)
        raise_on_errors(result)
    return result


def _indices(warm_start):
    return None if warm_start is None else np.asarray(warm_start, np.int32)


def _eager_search(problem: Problem, pop_width: int, budgeted: bool):
    """The search of an eager ``fj.sdfs`` call, and one alarm: its values would fail the checks (``lean``), or
    it raised an error flag (``raise_on_errors``)."""
    def run(x0, params, warm_start, max_nodes):
        bad = lean.non_finite(x0, params) | lean.bad_sequence(warm_start, problem.num_controls)
        result = sdfs_search(problem, x0, params, warm_start, max_nodes, pop_width=pop_width, budgeted=budgeted)
        return result, bad | alarms(result)
    return run


def exhaustive(problem: Problem, x0: ArrayLike, *, params: PyTree = None, method: str = "levels",
               chunk_nodes: int = DEFAULT_CHUNK_NODES, pop_width: int = 1) -> SearchResult:
    """Exact optimum by visiting every node of the tree (``nodes == problem.tree_size()``).

    Args:
      params: optional parameter pytree passed to every callable (as ``fj.sdfs``).
      method: ``"levels"`` (default) the vectorised level-by-level search, the
        fastest way to visit every node; ``"dfs"`` the sDFS machinery with
        pruning off (``pop_width`` applies), the like-for-like baseline that
        isolates what pruning saves.
      chunk_nodes: most nodes held in one batched call by ``"levels"``; bounds
        memory at about ``chunk_nodes * (n + 4) * itemsize * 3`` bytes
        (``memory``).

    The lower bound, if the problem has one, is not used: this is the reference.
    """
    x0, params = search_inputs(problem, x0, params)
    options = solvers.check_options("exhaustive", {"method": method, "chunk_nodes": chunk_nodes,
                                                   "pop_width": pop_width})
    if options["method"] == "dfs":
        solvers.check_memory("exhaustive", options, problem, x0.shape[0], max(x0.dtype.itemsize, 4))
        search = None
    else:
        solvers.check_tree("exhaustive", options, problem)
        search = levels_executable(problem, x0, params, options["chunk_nodes"])
    if search is None:  # method="dfs", or XLA:CPU could not compile the levels: the same tree, depth first
        dfs = compiled(sdfs_search, problem.replace(lower_bound=None), pop_width=options["pop_width"], prune=False)
        return raise_on_errors(dfs(x0, params, None, np.int32(INT32_MAX)))
    return raise_on_errors(search(x0, params))
