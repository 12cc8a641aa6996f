"""The table of searches: every solver's name, options and memory, as ``FIRHC``, ``solve_batch``,
``simulate_batch``, ``profile`` and the command line's ``--solver`` read them.

``SOLVERS`` maps a name to a ``Solver``; ``check_options(name, options)`` returns every option of a solver,
checked, with the defaults of the rest. ``stack_memory`` and ``exhaustive_memory`` give the bytes a search
holds, the figures checked against ``max_memory`` before anything is allocated. ``budget_for(problem or
controller, n0)`` is the node budget ``B(n0)`` that guarantees level n0 (docs/guide/budgets.md).
"""
from ._src.control.budget import budget_for
from ._src.search.exhaustive import DEFAULT_CHUNK_NODES
from ._src.search.exhaustive import memory as exhaustive_memory
from ._src.search.sdfs import DEFAULT_MAX_MEMORY, stack_memory
from ._src.search.solvers import DECISION_LANES, DEFAULT_LANES, SOLVERS, Solver, check_options, get, options_help

__all__ = ["SOLVERS", "Solver", "get", "check_options", "options_help", "stack_memory", "exhaustive_memory",
           "DEFAULT_MAX_MEMORY", "DEFAULT_CHUNK_NODES", "DEFAULT_LANES", "DECISION_LANES", "budget_for"]
