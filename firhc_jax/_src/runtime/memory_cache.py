"""One bounded cache for everything the package compiles or checks per problem.

Every solver keeps its compiled search here, keyed by the problem's callables,
horizon and control values (``Problem.key``) and the solver's static options:
the same callables, shapes and dtypes reuse one executable, and a rebuilt
``Problem`` with the same callables finds it again. The cache holds at most
``max_size`` entries (default 64) and evicts the least recently used; an evicted
entry's ``jax.jit`` object, and with it its executables, is freed. So a process
that builds problem after problem (a notebook, a parameter study, a controller
that re-identifies its plant) keeps a bounded amount of compiled code instead
of pinning one executable per problem for ever (measured in docs/guide/caching.md).

``clear_cache()`` empties it; ``set_cache_size(n)`` changes the bound (at
least ``MIN_SIZE``: one call must never evict its own entries, docs/guide/caching.md);
``cache_info()`` reports its use.
"""
from __future__ import annotations

import collections
import functools
from typing import Any, Callable, Hashable

import jax

DEFAULT_MAX_SIZE = 64
# At least the most entries one call uses (12: a closed loop with a fallback on the exhaustive solver and a
# progress bar, while it compiles; docs/guide/caching.md), with room for a few more: LRU at this size keeps them
# all, so a repeated call finds every one; below it, a call can evict its own and recompile every time.
# tests/runtime/test_soak.py checks every kind of call.
MIN_SIZE = 16
_entries: "collections.OrderedDict[Hashable, Any]" = collections.OrderedDict()
_max_size = DEFAULT_MAX_SIZE
_stats = {"hits": 0, "misses": 0}


def cached(key: Hashable, build: Callable[[], Any]) -> Any:
    """The entry for ``key``, built by ``build()`` on a miss (least recently
    used entries are evicted beyond ``max_size``)."""
    try:
        value = _entries[key]
    except KeyError:
        _stats["misses"] += 1
        value = _entries[key] = build()
        while len(_entries) > _max_size:
            _entries.popitem(last=False)
        return value
    _stats["hits"] += 1
    _entries.move_to_end(key)
    return value


def peek(key: Hashable) -> Any:
    """The entry for ``key``, or None (nothing is built)."""
    value = _entries.get(key)
    if value is not None:
        _stats["hits"] += 1
        _entries.move_to_end(key)
    return value


def put(key: Hashable, value: Any) -> None:
    """Keep ``value`` under ``key`` (a record of something built already: no miss is counted)."""
    _entries[key] = value
    _entries.move_to_end(key)
    while len(_entries) > _max_size:
        _entries.popitem(last=False)


def compiled(fn: Callable, problem, **static) -> Callable:
    """``jax.jit`` of ``fn(problem, *args, **static)`` for this problem and
    these static options, from the cache."""
    key = ("jit", fn, problem.key, tuple(sorted(static.items())))
    return cached(key, lambda: jax.jit(functools.partial(fn, problem, **static)))


def clear_cache() -> None:
    """Drop every cached compiled search and check (``jax.clear_caches()``
    also drops JAX's own caches)."""
    _entries.clear()


def set_cache_size(max_size: int) -> None:
    """Keep at most ``max_size`` (>= ``MIN_SIZE``) compiled searches and checks."""
    from ..checks import positive_int

    global _max_size
    max_size = positive_int("max_size", max_size)
    if max_size < MIN_SIZE:
        raise ValueError(f"max_size must be at least {MIN_SIZE}, got {max_size}: one call (a closed loop with a "
                         "fallback) uses several entries, and a smaller cache could evict them and recompile on "
                         "every call")
    _max_size = max_size
    while len(_entries) > _max_size:
        _entries.popitem(last=False)


def cache_info() -> dict:
    """``{"size", "max_size", "hits", "misses"}`` of the cache."""
    return {"size": len(_entries), "max_size": _max_size, **_stats}
