"""The store of a depth-first search: a stack of peer batches, one row per depth.

sDFS expands nodes of its deepest live batch only and pushes their children
one depth lower, so at most one batch per depth is live and the batch of depth
``d`` has a fixed place: row ``d``. Pushing a batch at row ``d`` overwrites
that row; rows below stay as they are.

Batches are stored as expanded, never sorted: ``pop`` takes the ``k`` cheapest
remaining nodes of a row (by key, then by lowest index: the order of a stable
sort) and marks them taken. A row is live while its cheapest remaining key is
below the bound given (the incumbent), so dropping the rest of a batch costs
nothing. A node's *key* is what the search orders and prunes by (its cost, or
cost plus a lower bound of the cost to come).

Paths: node ``i`` of row ``d`` is input ``i % M`` applied to the ``i // M``-th
parent of the row (the nodes popped together from row ``d - 1``), whose paths
the row keeps. Row 0 holds the root (index 0), whose path is empty (all -1).

Everything here handles one stack; batched searches ``jax.vmap`` it.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .nodes import first_min


class Stack(NamedTuple):
    """Rows ``[D]`` of ``L = K M`` nodes (K parents of M inputs each)."""

    x: jax.Array  # [D, L, n] node states
    cost: jax.Array  # [D, L] accumulated costs
    key: jax.Array  # [D, L] pruning and order key; +inf: taken or discarded
    low: jax.Array  # [D] smallest key of each row (+inf: empty)
    parents: jax.Array  # [D, K, N] int32 paths of each row's parents (-1: no input yet)


class Popped(NamedTuple):
    """Nodes taken out of one row, cheapest first."""

    x: jax.Array  # [k, n]
    cost: jax.Array  # [k]
    key: jax.Array  # [k] +inf: the row had fewer than k nodes left
    path: jax.Array  # [k, N] int32 inputs from the root (-1 beyond the node's depth)


def init(depth: int, parents: int, inputs: int, horizon: int, x0, cost_dtype) -> Stack:
    """A stack of ``depth`` rows of ``parents * inputs`` nodes holding only the
    root ``x0`` ``[n]`` (row 0, index 0, cost and key 0)."""
    L, n = parents * inputs, x0.shape[0]
    inf = jnp.array(jnp.inf, cost_dtype)
    return Stack(x=jnp.zeros((depth, L, n), x0.dtype).at[0, 0].set(x0),
                 cost=jnp.zeros((depth, L), cost_dtype),
                 key=jnp.full((depth, L), inf).at[0, 0].set(0),
                 low=jnp.full((depth,), inf).at[0].set(0),
                 parents=jnp.full((depth, parents, horizon), -1, jnp.int32))


def push(stack: Stack, row, x, cost, key, parents) -> Stack:
    """Store a batch at ``row`` (a traced int32): ``x`` ``[L, n]``, ``cost``,
    ``key`` ``[L]`` (+inf for nodes never to expand) and the paths of its K
    parents ``[K, N]``. Only that row is written."""
    return Stack(x=jax.lax.dynamic_update_index_in_dim(stack.x, x, row, 0),
                 cost=jax.lax.dynamic_update_index_in_dim(stack.cost, cost, row, 0),
                 key=jax.lax.dynamic_update_index_in_dim(stack.key, key, row, 0),
                 low=stack.low.at[row].set(jnp.min(key)),
                 parents=jax.lax.dynamic_update_index_in_dim(stack.parents, parents, row, 0))


def top(stack: Stack, bound):
    """Deepest row with a node whose key is below ``bound``; -1 if none."""
    rows = jnp.arange(stack.low.shape[0], dtype=jnp.int32)
    return jnp.max(jnp.where(stack.low < bound, rows, -1))


def pop(stack: Stack, row, k: int) -> tuple[Stack, Popped]:
    """Take the ``k`` cheapest remaining nodes of ``row`` (a traced int32; a
    row outside the stack takes nothing and returns +inf keys)."""
    inside = (row >= 0) & (row < stack.low.shape[0])
    r = jnp.clip(row, 0, stack.low.shape[0] - 1)
    key = jnp.where(inside, stack.key[r], jnp.inf)  # [L]
    taken = []
    for _ in range(k):  # k is small and static: k passes of a first-minimum reduction
        low, i = first_min(key)
        taken.append((low, i))
        key = key.at[i].set(jnp.inf)
    keys, idx = jnp.stack([t[0] for t in taken]), jnp.stack([t[1] for t in taken])
    M = stack.x.shape[1] // stack.parents.shape[1]
    depth = jnp.arange(stack.parents.shape[2]) == r - 1  # the entry this row's input fills
    path = jnp.where(depth, (idx % M)[:, None], stack.parents[r][idx // M])
    popped = Popped(x=stack.x[r][idx], cost=stack.cost[r][idx], key=keys, path=path)
    stack = stack._replace(key=jax.lax.dynamic_update_index_in_dim(stack.key, jnp.where(inside, key, stack.key[r]),
                                                                   r, 0),
                           low=stack.low.at[r].set(jnp.where(inside, jnp.min(key), stack.low[r])))
    return stack, popped


def child_path(path, row, inputs: int, i):
    """Path ``[N]`` of child ``i`` (input ``i % M`` of node ``i // M``) of
    nodes with paths ``[K, N]`` at depth ``row``."""
    return jnp.where(jnp.arange(path.shape[1]) == row, i % inputs, path[i // inputs])
