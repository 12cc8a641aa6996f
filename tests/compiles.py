"""Counting compilations, for the tests that say "never recompiles".

A user's callable is traced once per argument signature however many searches use it (``problem.call``
keeps its jaxpr), so counting its traces no longer shows every recompilation of a search around it.
``compile_count()`` counts every program JAX lowered in this process (``jax.monitoring``'s lowering event,
reported whether or not XLA then finds it in the persistent cache). Eager ``jnp`` operations lower a small
program the first time too: a test makes its inputs before it reads the count.
"""
import jax

from firhc_jax.apps._timing import LOWERED

_count = [0]


def _listen(event: str, duration: float, **kwargs) -> None:
    if event == LOWERED:
        _count[0] += 1


jax.monitoring.register_event_duration_secs_listener(_listen)


def compile_count() -> int:
    """Programs lowered so far in this process."""
    return _count[0]
