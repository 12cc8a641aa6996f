"""Vectorised exhaustive search: the reference every other search is checked
against, and the throughput yardstick.

The tree is expanded level by level, each level in one batched call. To bound
memory it is split at depth ``s``: the ``M^s`` prefixes of depth ``s`` are
expanded first, then processed in chunks of ``C`` prefixes by a ``lax.scan``;
each chunk expands its subtrees down to the leaves (at most ``chunk_nodes``
leaves at once) and keeps its cheapest feasible leaf. Leaves are visited in
lexicographic order of their input sequences and ties keep the first, so the
result is the lexicographically first optimal sequence.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from .nodes import expand
from .problem import Problem, check_state, cost_dtype
from .result import SearchResult, finish, raise_on_errors

DEFAULT_CHUNK_NODES = 1 << 20
_INT32_MAX = 2**31 - 1


class Plan(NamedTuple):
    """How the tree is split (all static)."""

    split: int  # s, depth of the prefixes materialised at once
    chunk: int  # C, prefixes per chunk
    chunks: int  # number of chunks (the last one padded)


def plan(problem: Problem, chunk_nodes: int = DEFAULT_CHUNK_NODES) -> Plan:
    """Choose the split so no batched call holds more than ``chunk_nodes`` nodes.

    Raises ``ValueError`` before anything is allocated when the tree cannot be
    searched that way (the prefix level itself exceeds ``chunk_nodes``) or its
    node count overflows int32.
    """
    N, M = problem.horizon, problem.num_controls
    if not isinstance(chunk_nodes, int) or chunk_nodes < 1:
        raise ValueError(f"chunk_nodes must be an int >= 1, got {chunk_nodes!r}")
    total = problem.tree_size()
    if total > _INT32_MAX:
        raise ValueError(f"exhaustive search of M={M}, N={N} has {total:,} nodes, more than the int32 node "
                         "counter holds; use fj.sdfs or a shorter horizon")
    split = next(s for s in range(N + 1) if M ** (N - s) <= chunk_nodes)
    if M**split > chunk_nodes:
        raise ValueError(
            f"exhaustive search of M={M}, N={N} ({total:,} nodes) does not fit chunk_nodes={chunk_nodes:,}: "
            f"it would need {M**split:,} prefixes in memory at once; raise chunk_nodes or use fj.sdfs")
    chunk = min(M**split, chunk_nodes // M ** (N - split))
    return Plan(split, chunk, math.ceil(M**split / chunk))


def _descend(problem, x, cost, valid, levels, leaf_level):
    """Expand ``levels`` levels below ``[B]`` nodes, each level in one batched
    call, children flattened in lexicographic order. Returns the deepest level
    ``x [B*M^levels, n]``, ``cost``, ``valid`` (at the leaf level: feasible),
    the node count and the error flags. NaN nodes are never expanded."""
    M = problem.num_controls
    nodes = jnp.array(0, jnp.int32)
    neg = nan = jnp.array(False)
    for level in range(levels):
        last = leaf_level and level == levels - 1
        ch = expand(problem, x, cost, check_terminal=last)
        parent = valid[:, None]
        nodes = nodes + M * jnp.sum(valid, dtype=jnp.int32)
        neg = neg | jnp.any(parent & ch.negative)
        nan = nan | jnp.any(parent & ch.bad)
        ok = parent & ~ch.bad & ch.terminal_ok if last else parent & ~ch.bad
        x, cost, valid = ch.x.reshape(-1, x.shape[-1]), ch.cost.reshape(-1), ok.reshape(-1)
    return x, cost, valid, nodes, neg, nan


def _exhaustive(problem: Problem, x0, chunk_nodes: int) -> SearchResult:
    N, M = problem.horizon, problem.num_controls
    split, chunk, chunks = plan(problem, chunk_nodes)
    dtype = cost_dtype(problem, x0)
    inf = jnp.array(jnp.inf, dtype)

    # Prefix level s, padded to chunks * C with invalid entries.
    px, pc, pok, nodes, neg, nan = _descend(problem, x0[None], jnp.zeros((1,), dtype), jnp.ones((1,), bool),
                                            split, leaf_level=split == N)
    pad = chunks * chunk - M**split
    px = jnp.concatenate([px, jnp.zeros((pad,) + px.shape[1:], px.dtype)])
    pc = jnp.concatenate([pc, jnp.zeros((pad,), dtype)])
    pok = jnp.concatenate([pok, jnp.zeros((pad,), bool)])
    sub = M ** (N - split)  # leaves per prefix

    def scan_chunk(carry, inp):
        best_cost, best_leaf, nodes, neg, nan = carry
        k, x, c, ok = inp
        lx, lc, lok, n_, neg_, nan_ = _descend(problem, x, c, ok, N - split, leaf_level=split < N)
        leaf_cost = jnp.where(lok, lc, inf)
        i = jnp.argmin(leaf_cost)
        improve = leaf_cost[i] < best_cost
        return (jnp.where(improve, leaf_cost[i], best_cost),
                jnp.where(improve, k * chunk * sub + i.astype(jnp.int32), best_leaf),
                nodes + n_, neg | neg_, nan | nan_), None

    init = (inf, jnp.array(0, jnp.int32), nodes, neg, nan)
    xs = (jnp.arange(chunks, dtype=jnp.int32), px.reshape(chunks, chunk, -1),
          pc.reshape(chunks, chunk), pok.reshape(chunks, chunk))
    (best_cost, best_leaf, nodes, neg, nan), _ = jax.lax.scan(scan_chunk, init, xs)

    digits = (best_leaf // (M ** jnp.arange(N - 1, -1, -1, dtype=jnp.int32))) % M
    return finish(problem.controls, best_cost, digits, nodes, jnp.array(chunks, jnp.int32), neg, nan)


_exhaustive_jit = jax.jit(_exhaustive, static_argnames=("chunk_nodes",))


def exhaustive(problem: Problem, x0, *, method: str = "levels", chunk_nodes: int = DEFAULT_CHUNK_NODES,
               pop_width: int = 1) -> SearchResult:
    """Exact optimum by visiting every node of the tree (``nodes == problem.tree_size()``).

    Args:
      method: ``"levels"`` (default) the vectorised level-by-level search, the
        fastest way to visit every node; ``"dfs"`` the sDFS machinery with
        pruning off (``pop_width`` applies), the like-for-like baseline that
        isolates what pruning saves.
      chunk_nodes: most nodes held in one batched call by ``"levels"``; bounds
        memory at about ``chunk_nodes * (n + 4) * itemsize * 3`` bytes.
    """
    if method == "dfs":
        from .sdfs import exhaustive_dfs
        return exhaustive_dfs(problem, x0, pop_width=pop_width)
    if method != "levels":
        raise ValueError(f"method must be 'levels' or 'dfs', got {method!r}")
    x0 = check_state(problem, x0)
    plan(problem, chunk_nodes)  # refuse before tracing
    return raise_on_errors(_exhaustive_jit(problem, x0, chunk_nodes=chunk_nodes))
