"""``Problem(lower_bound="auto")``: the derived bound is admissible, keeps every solver exact, finds
infeasibility deep in the horizon at the root, and compiles once per problem."""
import jax
import jax.numpy as jnp
import numpy as np
import param_problems as pp
import pytest
from compiles import compile_count
from hypothesis import HealthCheck, given, settings
from reference import same_cost

import firhc_jax as fj
from firhc_jax._src.problem.auto_bound import AutoBound

SETTINGS = settings(max_examples=4, deadline=None, suppress_health_check=[HealthCheck.too_slow])
POP_WIDTH = {shape: 2 + i % 2 for i, shape in enumerate(pp.SHAPES)}


def auto(shape):
    return pp.problem(shape, True, "auto")


@pytest.mark.float32
@SETTINGS
@given(pp.cases(tightness=("none", "loose", "tight")))
def test_every_solver_stays_exact_with_the_derived_bound(case):
    shape, params, x0 = case
    prm = pp.as_jax(params)
    problem = auto(shape)
    results = {"sdfs": fj.sdfs(problem, x0, params=prm),
               "sdfs K": fj.sdfs(problem, x0, params=prm, pop_width=POP_WIDTH[shape]),
               "exhaustive": fj.exhaustive(problem, x0, params=prm),
               "pool": jax.tree_util.tree_map(lambda a: a[0], fj.solve_batch(
                   problem, jnp.asarray(x0)[None], params=jax.tree_util.tree_map(lambda a: a[None], prm)))}
    for name, r in results.items():
        pp.check_optimal(r, shape, params, x0, name)


@pytest.mark.float32
@pytest.mark.parametrize("shape", pp.SHAPES[:3])
def test_the_derived_bound_passes_check_lower_bound(shape):
    rng = np.random.default_rng(sum(shape))
    for tightness in ("loose", "tight"):
        params = pp.as_jax(pp.draw_params(rng, shape, tightness))
        states = jnp.asarray(rng.uniform(-1.5, 1.5, (8, shape[0])), jnp.asarray(0.0).dtype)
        assert fj.check_lower_bound(auto(shape), states, params=params) == []


def _band_problem(horizon=6):
    """A room: temperature x[0] and wall x[1], heater levels, a comfort band and a reference along the horizon
    (step index), a cost of changing the heater's effect (previous state), and a terminal cost."""
    def dynamics(x, u, k, p):
        air = x[0] + 0.25 * (x[1] - x[0]) + 0.1 * (p["outside"][k] - x[0]) + 0.8 * u[0]
        wall = x[1] + 0.05 * (x[0] - x[1])
        return jnp.stack([air, wall])

    def stage_cost(x, x_next, u, k, p):
        return 0.3 * u[0] + (x_next[0] - p["ref"][k]) ** 2 + 0.05 * jnp.abs(x_next[0] - x[0])

    def constraint(x, x_next, u, k, p):
        return (x_next[0] >= p["low"][k]) & (x_next[0] <= 26.0)

    return fj.Problem(dynamics, jnp.array([0.0, 1.0, 2.0, 3.0]), stage_cost, horizon,
                      terminal_cost=lambda x, p: 0.5 * (x[0] - 21.0) ** 2, constraint=constraint, step_index=True,
                      previous_state=True, lower_bound="auto")


def _band_params(rng, horizon, late_low):
    low = np.full(horizon, 16.0)
    low[-2:] = late_low  # occupied late in the horizon
    dtype = jnp.asarray(0.0).dtype
    return {"outside": jnp.asarray(rng.uniform(0, 10, horizon), dtype), "low": jnp.asarray(low, dtype),
            "ref": jnp.asarray(rng.uniform(19, 22, horizon), dtype)}


@pytest.mark.float32
def test_step_index_previous_state_constraint_and_terminal_cost_stay_exact():
    problem = _band_problem()
    plain = problem.replace(lower_bound=None)
    rng = np.random.default_rng(3)
    for _ in range(6):
        params = _band_params(rng, problem.horizon, rng.uniform(18, 23))
        x0 = jnp.asarray(rng.uniform([15, 14], [22, 20]), jnp.asarray(0.0).dtype)
        ref = fj.exhaustive(plain, x0, params=params)
        found = fj.sdfs(problem, x0, params=params)
        batch = fj.solve_batch(problem, x0[None], params=jax.tree_util.tree_map(lambda a: a[None], params))
        assert same_cost(float(found.cost), float(ref.cost)), (float(found.cost), float(ref.cost))
        assert same_cost(float(batch.cost[0]), float(ref.cost))
        assert int(found.nodes) <= int(fj.sdfs(plain, x0, params=params).nodes)
        states = jnp.stack([x0, x0 + 1.0])
        assert fj.check_lower_bound(problem, states, params=params) == []


def test_infeasibility_late_in_the_horizon_is_found_at_the_root():
    problem = _band_problem(horizon=7)
    params = _band_params(np.random.default_rng(0), problem.horizon, late_low=40.0)  # out of reach
    x0 = jnp.array([18.0, 17.0])
    plain = fj.sdfs(problem.replace(lower_bound=None), x0, params=params)
    found = fj.sdfs(problem, x0, params=params)
    assert not bool(found.feasible) and not bool(plain.feasible)
    assert int(found.nodes) == problem.num_controls  # the root's children, each with a bound of +inf
    assert int(plain.nodes) > 1000


def test_an_unsupported_primitive_is_named_at_the_first_solve():
    def stage_cost(x, u):
        return jax.lax.while_loop(lambda c: c < 1.0, lambda c: c + 0.5, jnp.sum(x**2))

    problem = fj.Problem(lambda x, u: 0.5 * x + u, jnp.array([-1.0, 1.0]), stage_cost, 3, lower_bound="auto")
    with pytest.raises(NotImplementedError, match="stage_cost.*'while'"):
        fj.sdfs(problem, jnp.zeros(1))


def test_a_string_other_than_auto_is_refused():
    with pytest.raises(ValueError, match='"auto"'):
        fj.Problem(lambda x, u: x, [0.0, 1.0], lambda x, u: jnp.sum(x**2), 3, lower_bound="automatic")


def test_copies_derive_the_bound_again_and_equal_problems_compile_once():
    def dynamics(x, u):
        return 0.9 * x + u

    def cost(x, u):
        return jnp.sum(x**2) + 0.1 * jnp.sum(u**2)

    def build():
        return fj.Problem(dynamics, jnp.array([-1.0, 0.0, 1.0]), cost, 4, lower_bound="auto")

    first = build()
    assert isinstance(first.lower_bound, AutoBound) and first.key == build().key
    x0 = jnp.array([0.7])
    fj.sdfs(first, x0)
    compiled = compile_count()
    fj.sdfs(build(), x0)
    assert compile_count() == compiled, "an equal problem with the derived bound compiled again"

    def slower(x, u):
        return 0.5 * x + u

    copy = first.replace(dynamics=slower)
    assert copy.lower_bound.dynamics is slower and copy.key != first.key
    assert first.replace(lower_bound=None).lower_bound is None


def test_the_controller_and_its_fallback_take_the_derived_bound():
    problem = fj.Problem(lambda x, u: 0.8 * x + u, jnp.array([-0.5, 0.0, 0.5]),
                         lambda x, u: jnp.sum(x**2) + 0.1 * jnp.sum(u**2), 5,
                         terminal=lambda x: jnp.abs(x[0]) < 0.05, lower_bound="auto")
    ctrl = fj.FIRHC(problem, fallback="unconstrained")
    relaxed = ctrl.options.relaxed
    assert isinstance(relaxed.lower_bound, AutoBound) and relaxed.lower_bound.terminal is None
    bounded = ctrl.simulate(jnp.array([6.0]), 6)
    plain = fj.FIRHC(problem.replace(lower_bound=None), fallback="unconstrained").simulate(jnp.array([6.0]), 6)
    np.testing.assert_array_equal(np.asarray(bounded.inputs), np.asarray(plain.inputs))
    assert np.asarray(bounded.used_fallback).any()  # the band is out of reach at first


def test_input_memory_derives_the_bound_of_the_whole_wrapped_model():
    base = fj.Problem(lambda x, u: 0.7 * x + u, jnp.array([-1.0, 0.0, 1.0]), lambda x, u: jnp.sum(x**2), 5,
                      lower_bound="auto")
    mem = fj.with_input_memory(base, fj.input_change_cost(0.5),
                               transition=lambda u, u_prev: jnp.all(jnp.abs(u - u_prev) <= 1))
    assert isinstance(mem.problem.lower_bound, AutoBound) and mem.problem.lower_bound.dynamics is mem.problem.dynamics
    z = mem.observe(jnp.array([2.5]), jnp.array([-1.0]))
    found = fj.sdfs(mem.problem, z)
    assert same_cost(float(found.cost), float(fj.exhaustive(mem.problem, z).cost))
    assert int(found.nodes) < int(fj.sdfs(mem.problem.replace(lower_bound=None), z).nodes)
