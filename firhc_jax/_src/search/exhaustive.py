"""Vectorised exhaustive search: the reference every other search is checked
against, and the throughput yardstick.

The tree is expanded level by level, each level in one batched call. To bound
memory it is split at depth ``s``: the ``M^s`` prefixes of depth ``s`` are
expanded first, then processed in chunks of ``C`` prefixes by a ``lax.scan``;
each chunk expands its subtrees down to the leaves (at most ``chunk_nodes``
leaves at once) and keeps its cheapest feasible leaf. ``C`` divides ``M^s``, so
no chunk is padded. Leaves are visited in lexicographic order of their input
sequences and ties keep the first, so the result is the lexicographically
first optimal sequence.

Levels are unrolled in Python only while they widen (at most
``log_M(chunk_nodes)`` of them on each side of the split); with ``M = 1`` the
levels are one ``lax.scan``, so compile time does not grow with N.
``iterations`` counts batched calls of ``dynamics``: one per level of the
prefix, then one per level per chunk (``split + chunks * (N - split)``).
"""
from __future__ import annotations

import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..checks import positive_int
from ..problem.callables import cost_dtype
from ..problem.problem import Problem
from ..runtime.memory_cache import cached, compiled
from .nodes import best_leaf, expand, no_stats, tally
from .result import SearchResult, finish
from .sdfs import INT32_MAX

DEFAULT_CHUNK_NODES = 1 << 20


class Plan(NamedTuple):
    """How the tree is split (all static)."""

    split: int  # s, depth of the prefixes materialised at once
    chunk: int  # C, prefixes per chunk (a divisor of M^s)
    chunks: int  # M^s / C


def plan(problem: Problem, chunk_nodes: int = DEFAULT_CHUNK_NODES) -> Plan:
    """Choose the split so no batched call holds more than ``chunk_nodes`` nodes.

    Raises ``ValueError`` before anything is allocated when the tree cannot be
    searched that way (the prefix level itself exceeds ``chunk_nodes``) or its
    node count overflows int32.
    """
    N, M = problem.horizon, problem.num_controls
    chunk_nodes = positive_int("chunk_nodes", chunk_nodes)
    total = check_tree_size(problem)
    if M == 1:
        return Plan(0, 1, 1)
    split = next(s for s in range(N + 1) if M ** (N - s) <= chunk_nodes)
    if M**split > chunk_nodes:
        raise ValueError(
            f"exhaustive search of M={M}, N={N} ({total:,} nodes) does not fit chunk_nodes={chunk_nodes:,}: "
            f"it would need {M**split:,} prefixes in memory at once; raise chunk_nodes or use fj.sdfs")
    most = max(1, chunk_nodes // M ** (N - split))
    chunk = max(d for d in range(1, min(most, M**split) + 1) if M**split % d == 0)
    return Plan(split, chunk, M**split // chunk)


def check_tree_size(problem: Problem) -> int:
    """The tree's node count, refused (``ValueError``) beyond the int32 node counter: the one limit of every
    search that visits the whole tree."""
    total = problem.tree_size()
    if total > INT32_MAX:
        raise ValueError(f"exhaustive search of M={problem.num_controls}, N={problem.horizon} has {total:,} nodes, "
                         "more than the int32 node counter holds; use fj.sdfs or a shorter horizon")
    return total


def memory(problem: Problem, n: int, itemsize: int, chunk_nodes: int = DEFAULT_CHUNK_NODES) -> int:
    """Estimated peak bytes: three copies of the largest level chunk (``n + 4``
    numbers a node) and the prefix level."""
    p = plan(problem, chunk_nodes)
    leaves = p.chunk * problem.num_controls ** (problem.horizon - p.split)
    return itemsize * (3 * leaves * (n + 4) + problem.num_controls ** p.split * (n + 2))


def _descend(problem, x, cost, valid, params, stats, first_depth, levels, leaf_level):
    """Expand ``levels`` levels below ``[B]`` nodes of depth ``first_depth``,
    each level in one batched call, children flattened in lexicographic order.
    Returns the deepest level ``x [B*M^levels, n]``, ``cost``, ``valid`` (at
    the leaf level: feasible) and ``stats`` with the levels counted.
    Non-finite nodes are never expanded."""
    N = problem.horizon

    def level(x, cost, valid, stats, depth, last):
        ch = expand(problem, x, cost, params, steps_left=N - depth - 1, check_terminal=last)
        ok = valid[:, None] & ~ch.bad & ch.terminal_ok if last else valid[:, None] & ~ch.bad
        return ch.x.reshape(-1, x.shape[-1]), ch.cost.reshape(-1), ok.reshape(-1), tally(stats, ch, valid)

    inner = levels - 1 if leaf_level else levels
    done = 0
    if problem.num_controls == 1 and inner > 1:  # levels that do not widen: one scan, whatever N
        def step(carry, depth):
            return level(*carry, depth, False), None

        (x, cost, valid, stats), _ = jax.lax.scan(step, (x, cost, valid, stats), first_depth + jnp.arange(inner))
        done = inner
    for k in range(done, levels):
        x, cost, valid, stats = level(x, cost, valid, stats, first_depth + k, leaf_level and k == levels - 1)
    return x, cost, valid, stats


def _exhaustive(problem: Problem, x0, params, *, chunk_nodes: int) -> SearchResult:
    N, M = problem.horizon, problem.num_controls
    split, chunk, chunks = plan(problem, chunk_nodes)
    dtype = cost_dtype(problem, x0, params)
    inf = jnp.array(jnp.inf, dtype)
    px, pc, pok, stats = _descend(problem, x0[None], jnp.zeros((1,), dtype), jnp.ones((1,), bool), params,
                                  no_stats(), 0, split, leaf_level=split == N)
    sub = M ** (N - split)  # leaves per prefix

    def scan_chunk(carry, inp):
        best_cost, best_index, stats = carry
        k, x, c, ok = inp
        _, lc, lok, stats = _descend(problem, x, c, ok, params, stats, split, N - split, leaf_level=split < N)
        cost, i, improve = best_leaf(lc, True, lok, True, best_cost)  # lok already holds the terminal test
        return (jnp.where(improve, cost, best_cost), jnp.where(improve, k * chunk * sub + i, best_index), stats), None

    xs = (jnp.arange(chunks, dtype=jnp.int32), px.reshape(chunks, chunk, -1),
          pc.reshape(chunks, chunk), pok.reshape(chunks, chunk))
    (best_cost, best_index, stats), _ = jax.lax.scan(scan_chunk, (inf, jnp.array(0, jnp.int32), stats), xs)

    weights = jnp.array([M**k for k in range(N - 1, -1, -1)], jnp.int32) if M > 1 else jnp.ones((N,), jnp.int32)
    return finish(problem, best_cost, (best_index // weights) % M, stats, True, x0, params)


def levels_executable(problem: Problem, x0, params, chunk_nodes: int):
    """The level search for these shapes, compiled ahead of time and cached;
    None where XLA:CPU fails to compile it. Some deep level chains (seen with
    M = 2, 13 <= N <= 23) stop XLA:CPU with "Unknown MLIR failure"
    (docs/dev/xla_notes.md); the caller then visits the same tree depth first.
    Under an outer trace the jitted search is returned, to be inlined."""
    spec = jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype), (x0, params))
    key = ("levels", problem.key, chunk_nodes, str(spec), jax.tree_util.tree_structure(spec))

    def build():
        search = compiled(_exhaustive, problem, chunk_nodes=chunk_nodes)  # the bound is computed, unused, dropped
        try:
            return search, search.lower(*spec).compile()
        except jax.errors.JaxRuntimeError as e:
            if "MLIR" not in str(e):
                raise
            warnings.warn(f"XLA could not compile the level-by-level search of M={problem.num_controls}, "
                          f"N={problem.horizon}; visiting the same tree depth first instead (exact, slower)",
                          RuntimeWarning, stacklevel=4)
            return None, None

    search, executable = cached(key, build)
    if search is None:
        return None
    traced = any(isinstance(a, jax.core.Tracer) for a in jax.tree_util.tree_leaves((x0, params)))
    return search if traced else executable
