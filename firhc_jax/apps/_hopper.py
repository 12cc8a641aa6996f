"""The hopper's controller (not a command): what the ``hopper`` and ``bench`` commands run, and
``firhc_jax.apps.hopper.controller`` for a user's own closed loop."""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

import firhc_jax as fj
from firhc_jax.models import hopper as hm


def warm_candidate(problem: fj.Problem, x, previous, params=None):
    """The warm start for a search from ``x``: the cheaper of ``previous`` (the last decision's sequence ``[N]``)
    shifted by one step and ``previous`` unshifted, all -1 (none) when neither meets the terminal test or there
    is no previous sequence.

    Why two: the plant loses energy to friction that the model does not have, so the shifted plan often just
    misses the terminal band (no incumbent at all), while the same plan one period later meets it. Exact either
    way: a warm start only sets the search's first incumbent.
    """
    shifted = jnp.concatenate([previous[1:], previous[-1:]])
    candidates = jnp.stack([shifted, previous])  # [2, N]
    dtype = jnp.promote_types(x.dtype, jnp.float32)
    costs = jax.vmap(lambda w: fj.rollout_cost(problem, x, w, dtype, params)[0])(jnp.maximum(candidates, 0))
    i = jnp.argmin(costs)
    return jnp.where((previous[0] >= 0) & jnp.isfinite(costs[i]), candidates[i], -1)


@functools.lru_cache(maxsize=None)
def controller(horizon: int, params: hm.HopperParams | None = None, solver: str = "sdfs",
               bound: bool = False, warm: bool = False, **options) -> fj.FIRHC:
    """FIRHC on valve b; valve a by ``side_a_law``; both sealed in flight.

    ``hm.actuate`` turns the searched input into the plant's commands ``[2]``
    (a, b) in {-1, 0, 1}: in flight at the sample both are 0. Should no
    sequence be found at all (it has not happened) the safe input applies:
    valve b closed (``u_safe``), the step flagged in ``ClosedLoop.held``.
    Cached so that repeated closed loops reuse one compiled executable.
    ``bound``: ``hm.make_problem``'s bound, the fallback search with the bound
    of the problem without terminal set; ``warm`` (sdfs only): seed each search
    with ``warm_candidate`` (the better of the previous solution shifted and
    unshifted); ``options`` go to the solver (e.g. ``max_nodes``). ``params``: ``hm.HopperParams()`` if None.
    """
    params = params or hm.HopperParams()
    fallback = hm.make_problem(horizon, params, bound=True, terminal=False) if bound else "unconstrained"
    return fj.FIRHC(hm.make_problem(horizon, params, bound), solver, fallback=fallback,
                    warm_start=warm_candidate if warm else False, observe=hm.observe,
                    actuate=lambda X, u: hm.actuate(X, u, params), u_safe=np.zeros(1), **options)
