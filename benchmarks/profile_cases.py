"""Application plants as cases for ``python -m firhc_jax profile`` (functions returning ``(problem, states)``).

    cd benchmarks && python -m firhc_jax profile profile_cases:tanks --out ../out/profile-tanks

Each function runs the application's sDFS closed loop once and returns the problem with the states it
searched at (``firhc_jax.apps.bench``'s cases).
"""
from __future__ import annotations


def tanks(horizon: int = 4):
    """The three tanks (17 modes), the states of a 40 s closed loop (20 decisions) at N = ``horizon``."""
    from firhc_jax.apps import bench

    case = bench.tanks_case(horizon, seconds=40.0)
    return case.problem, case.states


def hopper(horizon: int = 6):
    """The hopping robot (3 inputs), the in-contact states of a 0.5 s closed loop at N = ``horizon``."""
    from firhc_jax.apps import bench

    case = bench.hopper_case(horizon, seconds=0.5)
    return case.problem, case.states
