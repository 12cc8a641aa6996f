"""Admissible lower bounds keep every search exact and prune more."""
import functools
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import param_problems as pp
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from param_problems import (
    SHAPES,
    as_jax,
    cases,
    cost_to_go,
    draw_params,
    dynamics,
    problem,
    same_cost,
    stage_cost,
    terminal,
)

import firhc_jax as fj
from firhc_jax._src.tools.diagnostics import check_lower_bound

SETTINGS = settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@functools.lru_cache(maxsize=None)
def exact_bound(shape):
    """``p["scale"]`` times the exact cost-to-go, by brute force in JAX: every sequence of length N - 1 is rolled
    out once, and the optimum for ``steps_left = s`` is the least cost among their length-s prefixes that end in
    the terminal set (0 for s = 0). Admissible for scale in [0, 1); +inf (terminal set out of reach) is kept.
    (One scan for every s, not a ``lax.switch`` branch per s: the same values up to rounding, less to trace and
    compile.)"""
    n, m, M, N = shape
    seqs = jnp.asarray(np.array(list(itertools.product(range(M), repeat=N - 1)), np.int32).reshape(-1, N - 1))

    def bound(x, steps_left, p):
        def roll(seq):  # [N - 1]: the cost of the first j + 1 steps of seq, +inf where they miss the terminal set
            def step(carry, i):
                z, c = carry
                u = jnp.array([i], jnp.float32)
                z = dynamics(z, u, p)
                c = c + stage_cost(z, u, p)
                return (z, c), jnp.where(terminal(z, p), c, jnp.inf)
            return jax.lax.scan(step, (x, jnp.zeros((), x.dtype)), seq)[1]

        ctg = jnp.min(jax.vmap(roll)(seqs), axis=0)  # [N - 1]: the exact cost-to-go of 1, ..., N - 1 steps
        s = jnp.clip(steps_left, 0, N - 1)
        c = jnp.where(s == 0, jnp.zeros((), x.dtype), ctg[jnp.maximum(s - 1, 0)])
        return jnp.where(jnp.isinf(c), c, p["scale"] * c)  # +inf stays +inf (scale 0 would make it NaN)

    return problem(shape, True, bound)


# The pop width is a compile-time constant: one per shape (2 and 3 both covered), so that each shape compiles
# its five searches once and every example of that shape reuses them (K = 1 is the "sdfs" entry).
POP_WIDTH = {shape: 2 + i % 2 for i, shape in enumerate(SHAPES)}


@SETTINGS
@given(cases(tightness=("loose", "tight")), st.floats(0.0, 0.99))
def test_admissible_bounds_keep_every_solver_exact(case, scale):
    shape, params, x0 = case
    pop_width = POP_WIDTH[shape]
    prm = dict(as_jax(params), scale=jnp.asarray(scale))
    bounded = exact_bound(shape)
    ref, _ = cost_to_go(shape, params, x0, shape[3])
    plain = fj.sdfs(problem(shape), x0, params=as_jax(params))
    results = {"sdfs": fj.sdfs(bounded, x0, params=prm), "sdfs K": fj.sdfs(bounded, x0, params=prm,
                                                                             pop_width=pop_width),
               "exhaustive": fj.exhaustive(bounded, x0, params=prm),
               "pool": jax.tree_util.tree_map(lambda a: a[0], fj.solve_batch(
                   bounded, jnp.asarray(x0)[None], params=jax.tree_util.tree_map(lambda a: a[None], prm)))}
    for name, r in results.items():
        assert same_cost(float(r.cost), ref), (name, float(r.cost), ref)
    assert int(results["sdfs"].nodes) <= int(plain.nodes)  # a bound never costs nodes at K = 1


def test_zero_bound_gives_table_1_node_counts():
    shape = SHAPES[1]
    rng = np.random.default_rng(5)
    zero = problem(shape, True, lambda x, s, p: jnp.zeros((), x.dtype))
    for _ in range(4):
        params, x0 = as_jax(draw_params(rng, shape)), rng.uniform(-1, 1, shape[0])
        a, b = fj.sdfs(problem(shape), x0, params=params), fj.sdfs(zero, x0, params=params)
        assert int(a.nodes) == int(b.nodes) and int(a.iterations) == int(b.iterations)


def test_infinite_bound_reports_infeasible():
    shape = SHAPES[0]
    never = problem(shape, True, lambda x, s, p: jnp.where(s > 0, jnp.inf, 0.0).astype(x.dtype))
    params = as_jax(draw_params(np.random.default_rng(0), shape))
    r = fj.sdfs(never, np.zeros(shape[0]), params=params)
    assert not bool(r.feasible) and np.isnan(np.asarray(r.first_input)).all()
    assert int(r.nodes) == shape[2]  # the root's children only: every one is unreachable


def test_check_lower_bound_catches_an_inadmissible_bound():
    shape = SHAPES[1]
    rng = np.random.default_rng(2)
    params = as_jax(draw_params(rng, shape))
    states = jnp.asarray(rng.uniform(-1, 1, (6, shape[0])))
    good = exact_bound(shape)
    assert check_lower_bound(good, states, params=dict(params, scale=jnp.asarray(0.9))) == []
    bad = check_lower_bound(good, states, params=dict(params, scale=jnp.asarray(1.5)))
    assert bad and all(v.value > v.limit for v in bad)


def test_an_exact_float32_bound_is_not_a_violation():
    """An exact bound computed in another order (s * c against the search's c + c + ...) differs from the
    float32 sums by an ulp or two: the default ``rtol`` follows the dtype, so that is no violation (with
    1e-9 it was), while a bound 0.1% too high still is."""
    def cost(x, u):
        return 0.1 * x[0] ** 2 + 0.3 + 0.0 * u[0]

    def bound(x, s):
        return s * cost(x, jnp.zeros(1, x.dtype))

    still = fj.Problem(lambda x, u: x, jnp.zeros((1, 1), jnp.float32), cost, 6, lower_bound=bound)
    states = jnp.asarray(np.random.default_rng(0).uniform(-1, 1, (16, 1)), jnp.float32)
    assert check_lower_bound(still, states) == []
    assert check_lower_bound(still, states, rtol=0.0)  # the ulps are there: the default tolerates them
    high = still.replace(lower_bound=lambda x, s: 1.001 * bound(x, s))
    assert len(check_lower_bound(high, states)) == 16 * 6


def test_a_nan_bound_prunes_nothing_in_every_solver():
    """A bound that returns NaN (a bug in the user's bound) is treated as 0: every solver stays exact."""
    shape = pp.SHAPES[0]
    params = pp.draw_params(np.random.default_rng(5), shape, "loose")
    x0 = np.array([0.3])
    nan_bound = pp.problem(shape, lower_bound=lambda x, s, p: jnp.nan * x[0])
    ref, _ = pp.cost_to_go(shape, params, x0, shape[3])
    prm = pp.as_jax(params)
    assert pp.same_cost(float(fj.sdfs(nan_bound, x0, params=prm).cost), ref)
    batch = fj.solve_batch(nan_bound, x0[None], params=jax.tree_util.tree_map(lambda a: a[None], prm))
    assert pp.same_cost(float(batch.cost[0]), ref)
    assert check_lower_bound(nan_bound, x0[None], params=prm, max_steps=1)  # and the check reports it
