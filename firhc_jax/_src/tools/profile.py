"""Expansion throughput of the user's own problem on this machine, and what a node's time is spent on.

``profile(problem, states)`` times the searches a user can pick from on the states they will search at (for
instance the states of a closed loop): one state per call with ``fj.sdfs`` at several pop widths and with
``fj.exhaustive``, and all states at once with ``fj.solve_batch`` at its default and at several lane
counts. It also times each callable of the problem as a search evaluates it, vmapped over a batch of
children, to split a node's time into dynamics, stage cost, constraint, bound and terminal tests.

Every setting is first called once, which compiles it (timed apart, ``compile_s``); then ``repeats`` rounds
time every setting once each, in an order rotated from round to round, so that a change in the machine's
load falls on all settings alike. A row keeps the median and the range of its runs. The fastest setting
(most solves per second) wins clearly only when its slowest run beats every other setting's fastest; the
settings whose range reaches the fastest's are ``within_noise`` of it. The jitted searches and callables
are kept in the package's cache (``memory_cache``): profiling the same problem again compiles nothing.

Two pieces of advice come with the rows, as warnings and in ``Profile.advice``. With a ``lower_bound``,
``fj.sdfs`` at pop width 1 is also timed without it (interleaved with the rest): a bound that makes the
search more than ``BOUND_SLOWDOWN`` slower costs more to evaluate than its pruning saves. Without one, a
search that computes more than ``UNPRUNED_SHARE`` of the tree's nodes on average (trees of at least
``UNPRUNED_MIN_TREE`` nodes) prunes little: a bound (``lower_bound="auto"`` or one written by hand) may help.
"""
from __future__ import annotations

import statistics
import time
import warnings
from typing import Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..annotations import ArrayLike, PyTree
from ..checks import positive_int
from ..problem.callables import search_inputs
from ..problem.problem import Problem, call
from ..runtime.memory_cache import cached
from ..runtime.progress import Progress
from ..search import solvers
from ..search.batch import solve_batch
from ..search.sdfs import INT32_MAX

POP_WIDTHS = (1, 2, 4, 8)
LANES = (16, 64, 256)
MAX_EXHAUSTIVE_NODES = 10_000_000
CHILDREN = 16_384  # children per timed call of a callable: enough work that the call's dispatch is a small part
BOUND_SLOWDOWN = 1.2  # a bound that makes sDFS slower than this factor is reported as costing more than it saves
UNPRUNED_SHARE = 0.1  # a search without a bound that computes more of the tree than this is told to try one
UNPRUNED_MIN_TREE = 1_000  # ... where the tree has at least this many nodes


class Profile(list):
    """``fj.profile``'s result: a list of rows, one dict per search setting, with what they rest on.

    Attributes: ``node_costs`` (one dict per callable of the problem, in the order a node evaluates them:
    ``callable``, ``ns`` (median ns per child), ``ns_min``, ``ns_max``, ``children`` (the children of one
    timed call), ``compile_s``), ``repeats`` (timed runs of every setting), ``compile_seconds`` (the first
    calls' extra time, summed over the searches and callables), ``seconds`` (the whole profile's time) and
    ``for_controller`` (the fastest was chosen among the rows of one decision per call), ``bound`` (with a
    ``lower_bound``: ``fj.sdfs`` at pop width 1 with and without it, ``seconds``, ``seconds_without``,
    ``nodes``, ``nodes_without`` over all states and ``slowdown``, the ratio of the two times; else None)
    and ``advice`` (the warnings the profile gave, module docstring).
    """

    def __init__(self, rows: list[dict], node_costs: list[dict], repeats: int, compile_seconds: float,
                 seconds: float, for_controller: bool = False, bound: dict | None = None,
                 advice: Sequence[str] = ()):
        super().__init__(rows)
        self.node_costs, self.repeats = node_costs, repeats
        self.compile_seconds, self.seconds, self.for_controller = compile_seconds, seconds, for_controller
        self.bound, self.advice = bound, list(advice)

    @property
    def clear_winner(self) -> bool:
        """Whether the fastest setting's slowest run beat every other setting's fastest run (of those it was
        chosen among; never with one run per setting, which measures no noise)."""
        return self.repeats > 1 and sum(r["within_noise"] for r in self) == 1


class _Job(NamedTuple):
    name: str
    run: Callable[[], list]  # a list of results, each read back


def _counts(name: str, values) -> tuple[int, ...]:
    try:
        values = tuple(values)
    except TypeError:
        raise TypeError(f"{name} must be a sequence of positive ints, got {values!r}") from None
    return tuple(positive_int(name, v) for v in values)


def _clock(run: Callable[[], list]):
    """``(seconds, results)`` of one ``run()``, every result read back before the clock stops."""
    t0 = time.perf_counter()
    results = jax.block_until_ready(run())
    return time.perf_counter() - t0, results


def _measure(jobs: list[_Job], repeats: int, bar):
    """``(first-call seconds, [repeats] seconds, last results)`` of each job: every job's compiling call, then
    ``repeats`` rounds of one call each, each round starting one job later than the last."""
    firsts, times, results = [], [[] for _ in jobs], [None] * len(jobs)
    for j, job in enumerate(jobs):
        bar.describe(f"profile: {job.name} (compiling)")
        first, results[j] = _clock(job.run)
        firsts.append(first)
        bar.update(len(firsts))
    for r in range(repeats):
        for i, j in enumerate(np.roll(np.arange(len(jobs)), -r)):
            bar.describe(f"profile: round {r + 1} of {repeats}, {jobs[j].name}")
            seconds, results[j] = _clock(jobs[j].run)
            times[j].append(seconds)
            bar.update((r + 1) * len(jobs) + i + 1)
    return firsts, times, results


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


def _node_parts(problem: Problem) -> dict:
    """``{name: jitted f(x [W, n], xs [W, M, n], p [W])}`` for each callable a node evaluates, vmapped over the
    states and every input as the searches vmap them (step index 0, ``N - 1`` steps left), from the cache."""
    def children(f, per_input):  # f(x or x_child, u, p) over [W] states and [M] inputs
        inner = jax.vmap(f, in_axes=(0 if per_input else None, 0, None))
        return jax.vmap(lambda x, p: inner(x, jnp.asarray(problem.controls), p))

    def steps(f):  # f(x, x_child, u, p) over [W] states, each with its [M] children and inputs
        inner = jax.vmap(f, in_axes=(None, 0, 0, None))
        return jax.vmap(lambda x, xs, p: inner(x, xs, jnp.asarray(problem.controls), p))

    steps_left = jnp.int32(problem.horizon - 1)
    parts = {"dynamics": lambda x, xs, p: children(lambda x, u, p: problem.next_state(x, u, 0, p), False)(x, p),
             "stage_cost": lambda x, xs, p: steps(lambda x, xc, u, p: problem.cost_of_step(x, xc, u, 0, p))(x, xs, p)}
    if problem.constraint is not None:
        parts["constraint"] = lambda x, xs, p: steps(lambda x, xc, u, p: problem.allowed(x, xc, u, 0, p))(x, xs, p)
    for name, fn, more in (("lower_bound", problem.lower_bound, (steps_left,)), ("terminal", problem.terminal, ()),
                           ("terminal_cost", problem.terminal_cost, ())):
        if fn is not None:
            parts[name] = lambda x, xs, p, fn=fn, more=more: children(
                lambda x, u, p: call(fn, p, x, *more), True)(xs, p)
    return cached(("profile nodes", problem.key), lambda: {k: jax.jit(f) for k, f in parts.items()})


def _node_jobs(problem: Problem, X, params) -> tuple[list[_Job], int]:
    """A job per callable on ``ceil(CHILDREN / M)`` of the states (repeated as needed) times every input,
    and the children of one call. The first job, ``dynamics``, computes the children the others take."""
    M = problem.num_controls
    rows = np.arange(-(-CHILDREN // M)) % X.shape[0]
    x = jnp.asarray(X)[rows]
    p = jax.tree_util.tree_map(lambda a: jnp.asarray(a)[rows], params)
    parts = _node_parts(problem)
    children = {}

    def dynamics():
        children["xs"] = parts["dynamics"](x, None, p)
        return [children["xs"]]

    jobs = [_Job("dynamics", dynamics)] + [_Job(name, lambda f=f: [f(x, children["xs"], p)])
                                           for name, f in parts.items() if name != "dynamics"]
    return jobs, rows.size * M


def _row(solver: str, setting: str, times: list, first: float, results, solves: int, default: bool,
         **options) -> dict:
    seconds = statistics.median(times)
    nodes = int(sum(np.sum(np.asarray(r.nodes, np.int64)) for r in results))
    iterations = int(sum(np.sum(np.asarray(r.iterations, np.int64)) for r in results))
    return {"solver": solver, "setting": setting, **options, "states": solves, "seconds": seconds,
            "seconds_min": min(times), "seconds_max": max(times), "compile_s": max(first - seconds, 0.0),
            "nodes": nodes, "iterations": iterations, "nodes_per_second": nodes / seconds,
            "solves_per_second": solves / seconds, "us_per_iteration": 1e6 * seconds / max(iterations, 1),
            "default": default, "per_decision": solver != "solve_batch", "fastest": False, "within_noise": False}


def _mark(rows: list[dict], for_controller: bool) -> None:
    """Mark the fastest row (most solves per second; ``for_controller``: of the rows of one decision per call)
    and every row within the noise of it: whose fastest run per state is no slower than the fastest row's
    slowest run per state."""
    among = [r for r in rows if r["per_decision"] or not for_controller]
    best = max(among, key=lambda r: r["solves_per_second"])
    best["fastest"] = True
    for r in among:
        r["within_noise"] = r["seconds_min"] / r["states"] <= best["seconds_max"] / best["states"]


def profile(problem: Problem, states: ArrayLike, params: PyTree = None, *, pop_widths: Sequence[int] = POP_WIDTHS,
            lanes: Sequence[int] = LANES, repeats: int = 3, max_exhaustive_nodes: int = MAX_EXHAUSTIVE_NODES,
            progress: bool | None = None, for_controller: bool = False) -> Profile:
    """Time every search setting on ``states``, interleaved and repeated; mark the default and the fastest.

    Args:
      problem: the ``Problem``.
      states: ``[S, n]`` states to search from (e.g. a closed loop's).
      params: optional parameter pytree with leading axis S: state i is
        searched with ``params[i]`` (as ``fj.solve_batch``).
      pop_widths: the ``fj.sdfs`` pop widths to time, one state per call
        (1, the default, is always among them unless this is empty).
      lanes: the ``fj.solve_batch`` lane counts to time, all states in one
        call, after ``solve_batch``'s default (timed unless this is empty).
      repeats: timed rounds after the compiling call; each times every
        setting once, in an order rotated from round to round.
      max_exhaustive_nodes: ``fj.exhaustive`` is timed on evenly spaced states
        visiting at most this many nodes in all (none if one tree is larger).
      progress: a bar counting the runs, with an estimate, on stderr or in
        the notebook, naming the setting being compiled and timed: ``None``
        (default) once the call has taken 2 s, ``True`` at once, ``False``
        never.
      for_controller: the fastest is chosen among the rows that run one
        decision per call (``per_decision``: ``fj.sdfs`` at each pop width
        and ``fj.exhaustive``), what a ``FIRHC`` deciding once per sampling
        period runs (its ``pop_width`` and ``solver``); ``solve_batch``'s
        rows, which share every core among all the states at once, are
        still timed. Default: among every row.

    Returns a ``Profile``: a list with one dict per setting, in the order
    above: ``solver`` (``"sdfs"``, ``"exhaustive"`` or ``"solve_batch"``),
    ``setting`` (e.g. ``"sdfs pop_width=2"``), ``pop_width`` or ``lanes``
    (None: the default), ``states`` (how many were solved: what every figure
    of the row rests on), ``seconds`` (median time to solve them all; the
    one-state solvers are called once per state, each result read back),
    ``seconds_min``, ``seconds_max`` (the range of the ``repeats`` runs),
    ``compile_s`` (the first call's extra time: never part of a rate),
    ``nodes``, ``iterations`` (summed ``SearchResult`` counts),
    ``nodes_per_second``, ``solves_per_second``, ``us_per_iteration``
    (``seconds`` over ``iterations``, whose meaning is each solver's, see
    ``SearchResult``), ``default`` (the setting a call without options
    gets), ``per_decision`` (the row times one decision per call, as a
    controller makes them), ``fastest`` (True on exactly one row, the most
    solves per second; of the ``per_decision`` rows with ``for_controller``)
    and ``within_noise`` (its fastest run per state is no slower than the
    fastest row's slowest: no clear difference; only the rows the fastest
    was chosen among). Its ``node_costs`` split a
    node's time into the problem's callables; ``clear_winner``,
    ``compile_seconds`` and ``seconds`` (the whole profile) say what the
    rows rest on (``Profile``).
    """
    start = time.perf_counter()
    X, params = search_inputs(problem, states, params, batched=True, name="states")
    S = X.shape[0]
    pop_widths, lanes = _counts("pop_widths", pop_widths), _counts("lanes", lanes)
    repeats = positive_int("repeats", repeats)
    max_exhaustive_nodes = positive_int("max_exhaustive_nodes", max_exhaustive_nodes)
    if not pop_widths and not lanes:
        raise ValueError("pop_widths and lanes are both empty: nothing to profile")
    one = [(X[i], jax.tree_util.tree_map(lambda a, i=i: a[i], params)) for i in range(S)]

    settings = []  # (solver, setting, how many states, default, options), one per job
    jobs = []
    for k in (1,) * (1 not in pop_widths and bool(pop_widths)) + pop_widths:
        settings.append(("sdfs", f"sdfs pop_width={k}", S, k == 1, {"pop_width": k}))
        jobs.append(_Job(settings[-1][1], _each(_search(problem, "sdfs", X, pop_width=k), one)))
    count = min(S, max_exhaustive_nodes // problem.tree_size())
    if count:
        some = [one[i] for i in np.unique(np.linspace(0, S - 1, count).round().astype(int))]
        settings.append(("exhaustive", "exhaustive", len(some), False, {}))
        jobs.append(_Job("exhaustive", _each(_search(problem, "exhaustive", X), some)))
    for slots in (None,) * bool(lanes) + lanes:
        name = "solve_batch default lanes" if slots is None else f"solve_batch lanes={slots}"
        settings.append(("solve_batch", name, S, slots is None, {"lanes": slots}))
        jobs.append(_Job(name, lambda slots=slots: [solve_batch(problem, X, params=params, lanes=slots,
                                                                progress=False)]))
    node_jobs, children = _node_jobs(problem, X, params)
    unbounded = []
    if problem.lower_bound is not None and 1 in pop_widths:
        plain = problem.replace(lower_bound=None)
        unbounded = [_Job("sdfs pop_width=1 without lower_bound", _each(_search(plain, "sdfs", X, pop_width=1), one))]

    everything = jobs + unbounded + node_jobs
    with Progress(len(everything) * (1 + repeats), "profile", enabled=progress) as bar:
        firsts, times, results = _measure(everything, repeats, bar)
        bar.describe("profile")
    rows = [_row(solver, setting, times[j], firsts[j], results[j], solves, default, **options)
            for j, (solver, setting, solves, default, options) in enumerate(settings)]
    _mark(rows, for_controller)
    bound = None
    if unbounded:
        j = len(jobs)
        row = next(r for r in rows if r["setting"] == "sdfs pop_width=1")
        without = statistics.median(times[j])
        bound = {"seconds": row["seconds"], "seconds_without": without, "nodes": row["nodes"],
                 "nodes_without": int(sum(int(r.nodes) for r in results[j])),
                 "slowdown": row["seconds"] / without}
    advice = _advice(problem, rows, bound)
    for text in advice:
        warnings.warn(text, stacklevel=2)
    node_costs = []
    for j, job in enumerate(node_jobs, start=len(jobs) + len(unbounded)):
        median = statistics.median(times[j])
        node_costs.append({"callable": job.name, "ns": 1e9 * median / children,
                           "ns_min": 1e9 * min(times[j]) / children, "ns_max": 1e9 * max(times[j]) / children,
                           "children": children, "compile_s": max(firsts[j] - median, 0.0)})
    compile_seconds = sum(r["compile_s"] for r in rows) + sum(c["compile_s"] for c in node_costs)
    return Profile(rows, node_costs, repeats, compile_seconds, time.perf_counter() - start, for_controller, bound,
                   advice)


def _advice(problem: Problem, rows: list[dict], bound: dict | None) -> list[str]:
    """The profile's warnings (module docstring)."""
    if bound is not None and bound["slowdown"] > BOUND_SLOWDOWN:
        return [f"the lower_bound makes fj.sdfs {bound['slowdown']:.2f}x slower on these states "
                f"({bound['nodes_without']:,} nodes without it, {bound['nodes']:,} with it): evaluating it costs "
                "more than its pruning saves; compare Profile.node_costs, and consider lower_bound=None"]
    sdfs_row = next((r for r in rows if r["setting"] == "sdfs pop_width=1"), None)
    tree = problem.tree_size()
    if problem.lower_bound is None and sdfs_row is not None and tree >= UNPRUNED_MIN_TREE:
        share = sdfs_row["nodes"] / sdfs_row["states"] / tree
        if share > UNPRUNED_SHARE:
            return [f"fj.sdfs computed {share:.0%} of the tree's {tree:,} nodes per state on average: without a "
                    "lower_bound it prunes only by the cost so far; try Problem(..., lower_bound=\"auto\") or a "
                    "bound of your own (docs/guide/bounds.md)"]
    return []
