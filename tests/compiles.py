"""Counting compilations, for the tests that say "never recompiles".

A user's callable is traced once per argument signature however many searches use it (``problem.call``
keeps its jaxpr), so counting its traces no longer shows every recompilation of a search around it.
``compile_count()`` counts every program JAX lowered in this process (``jax.monitoring``'s lowering event,
reported whether or not XLA then finds it in the persistent cache). Eager ``jnp`` operations lower a small
program the first time too: a test makes its inputs before it reads the count.
"""
import jax

from firhc_jax.apps._timing import LOWERED, compile_events

_count = [0]


def _listen(event: str, duration: float, **kwargs) -> None:
    if event == LOWERED:
        _count[0] += 1


jax.monitoring.register_event_duration_secs_listener(_listen)


def compile_count() -> int:
    """Programs lowered so far in this process."""
    return _count[0]


def compiles_inside(monkeypatch, owner, name: str, run) -> tuple:
    """``(run's value, everything, inside)``: the compilations (``(name, seconds)``) while ``run()`` runs, and
    those made inside ``owner.name`` (patched to record them), e.g. the closed loop an application times, so that
    a test can tell what compiled before that loop from what compiled in it."""
    inside, method = [], getattr(owner, name)

    def recorded(*args, **kwargs):
        with compile_events() as seen:
            out = method(*args, **kwargs)
        inside.extend(seen)
        return out

    monkeypatch.setattr(owner, name, recorded)
    with compile_events() as everything:
        value = run()
    return value, everything, inside
