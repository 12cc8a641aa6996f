"""Edges where a controller in the field ends up: nothing made up,
nothing silently rounded, no raw XLA errors, no needless recompiles."""
import dataclasses
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from reference import brute_force, same_cost

import firhc_jax as fj
from firhc_jax._src.tools.diagnostics import check_problem


def _shift(x, u):
    return x + u.astype(x.dtype)


# 1. Infeasible never yields a real input, whatever the controls' dtype. The target is a parameter: one
# compiled search per dtype and solver serves every example.
CONTROLS = {np.float32: [3, 0, 1], np.float64: [3, 0, 1], np.int32: [3, 0, 1], np.bool_: [False, True]}
_TARGET_COST = fj.quadratic_cost(1.0, 0.0, beta=0.5, u_e=0.3)


def _target_step(x, u, p):
    return _shift(x, u)


def _target_cost(x, u, p):
    return _TARGET_COST(x, u)


def _at_target(x, p):
    return x[0] >= p - 1e-9


@settings(max_examples=24, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(sorted(CONTROLS, key=str)), st.booleans(), st.floats(-2, 2))
def test_every_control_dtype_gives_nan_when_infeasible_and_the_optimum_otherwise(dtype, reachable, x0):
    controls = np.array(CONTROLS[dtype], dtype=dtype)
    N = 2
    c = controls.astype(float)
    target = x0 + 2 * float(np.max(c)) if reachable else 100.0
    prob = fj.Problem(_target_step, controls, _target_cost, N, terminal=_at_target)
    best, _ = brute_force(lambda x, u, t: (x + u, np.sum((x + u) ** 2 + 0.5 * (u - 0.3) ** 2, -1)), c, [x0], N,
                          lambda x: x[..., 0] >= target - 1e-9)  # u_e stays 0.3 whatever the controls' dtype
    assert np.isfinite(best) == reachable
    p = jnp.asarray(target)
    for r in (fj.sdfs(prob, jnp.array([x0]), params=p), fj.exhaustive(prob, jnp.array([x0]), params=p),
              jax.tree_util.tree_map(lambda a: a[0], fj.solve_batch(prob, jnp.array([[x0]]), params=p[None]))):
        assert jnp.issubdtype(r.first_input.dtype, jnp.floating)
        assert bool(r.feasible) == reachable
        if reachable:
            assert same_cost(r.cost, best, rtol=1e-12)
            assert float(r.first_input[0]) == c[int(r.sequence[0])]  # the real input, not cast
        else:
            assert np.isnan(np.asarray(r.first_input)).all() and (np.asarray(r.sequence) == -1).all()


def test_simulate_never_applies_a_made_up_input():
    prob = fj.Problem(_shift, jnp.array([3, 0, 1], jnp.int32), fj.quadratic_cost(1.0, 0.0), 3,
                      terminal=lambda x: x[0] > 100.0)
    with pytest.warns(RuntimeWarning, match="no feasible input"):
        run = fj.FIRHC(prob).simulate(jnp.zeros(1), 2, u0=jnp.array([1.0]))
    assert (np.asarray(run.inputs) == 1.0).all() and np.asarray(run.held).all()  # u0 held, flagged
    assert (np.asarray(run.input_indices) == -1).all() and np.isinf(np.asarray(run.predicted_costs)).all()
    with pytest.raises(fj.InfeasibleError, match="terminal constraint"):
        fj.FIRHC(prob)(jnp.zeros(1))


# 1b. No input found: never a NaN to the plant, whatever the fallback. Two triggers: a budget that
# stops every search before any leaf, and +inf stage costs without a terminal set (no fallback search runs).
def _no_leaf_in_budget():
    prob = fj.Problem(lambda x, u: 0.5 * x + u, jnp.array([-1.0, 0.0, 1.0]), fj.quadratic_cost(1.0, 0.0), 5,
                      terminal=lambda x: jnp.abs(x[0]) < 10.0)
    return prob, {"max_nodes": 10}, "max_nodes=10"


def _infinite_costs():
    prob = fj.Problem(lambda x, u: 0.5 * x + u, jnp.array([-1.0, 0.0, 1.0]), lambda x, u: jnp.inf + 0 * x[0], 5)
    return prob, {}, "finite cost"


@pytest.mark.parametrize("trigger", [_no_leaf_in_budget, _infinite_costs], ids=["budget", "inf-costs"])
def test_no_input_found_holds_a_safe_input_and_says_so(trigger):
    prob, opts, why = trigger()
    x0 = jnp.ones(1)
    ctrl = fj.FIRHC(prob, fallback="unconstrained", **opts)
    with pytest.warns(RuntimeWarning, match="held"):
        run = ctrl.simulate(x0, 3, u0=jnp.array([1.0]))
    assert np.isfinite(np.asarray(run.states)).all() and np.isfinite(np.asarray(run.inputs)).all()
    assert np.asarray(run.held).all() and (np.asarray(run.inputs) == 1.0).all()  # u0, held
    assert (np.asarray(run.decision_nodes) <= opts.get("max_nodes", prob.tree_size())).all()
    with pytest.raises(fj.InfeasibleError, match=why) as e:
        ctrl(x0)
    assert "terminal" not in str(e.value) or prob.terminal is not None
    # A user-given safe input goes through actuate; the one-shot call raises whatever the fallback.
    safe = fj.FIRHC(prob, **opts, u_safe=jnp.array([0.0]), actuate=lambda x, u: u + 0.25)
    with pytest.warns(RuntimeWarning, match="u_safe"):
        run = safe.simulate(x0, 2, u0=jnp.array([1.0]))
    assert (np.asarray(run.inputs) == 0.25).all() and np.asarray(run.held).all()
    u, state, info = safe.step(safe.init(x0), x0)
    assert float(u[0]) == 0.25 and bool(info.held) and float(state.u[0]) == 0.0
    with pytest.raises(fj.InfeasibleError):
        safe(x0)


def test_infeasible_message_names_only_what_the_problem_has():
    """With terminal=None there is no terminal constraint to blame."""
    prob = fj.Problem(lambda x, u: 0.5 * x + u, jnp.array([-1.0, 1.0]), lambda x, u: jnp.inf + 0 * x[0], 2)
    with pytest.raises(fj.InfeasibleError) as e:
        fj.FIRHC(prob)(jnp.ones(1))
    assert "terminal" not in str(e.value) and "finite cost" in str(e.value)
    with pytest.raises(fj.InfeasibleError, match="terminal constraint"):
        fj.FIRHC(prob.replace(stage_cost=fj.quadratic_cost(1.0, 0.0), terminal=lambda x: x[0] > 9.0))(jnp.ones(1))


# 2. quadratic_cost keeps real targets with integer controls.
def test_quadratic_cost_does_not_truncate_u_e():
    cost = fj.quadratic_cost(0.0, 0.0, beta=1.0, u_e=0.6)
    assert same_cost(cost(jnp.zeros(1), jnp.array([1], jnp.int32)), 0.16, rtol=1e-12)
    assert same_cost(cost(jnp.zeros(1), jnp.array([True])), 0.16, rtol=1e-12)


# 3. Parameters reach the callables exactly as given.
def test_params_keep_their_dtype_and_value_in_every_solver():
    big = 2**24 + 1  # odd; as float32 it would be 2**24, even

    def dyn(x, u, p):
        return x + u

    def cost(x, u, p):  # input 1 is free when the int parameter is odd, input 0 when even
        parity = (p["n"] % 2).astype(x.dtype)
        fine = (p["f"] > 1.0).astype(x.dtype)  # 1 + 1e-12 only survives in float64
        return (u[0] - parity) ** 2 + fine * 0.0 + (1 - fine) * 5.0 + 0 * x[0]

    prob = fj.Problem(dyn, jnp.array([0.0, 1.0], jnp.float32), cost, 1)
    p = {"n": jnp.array(big, jnp.int32), "f": jnp.array(1 + 1e-12, jnp.float64)}
    x0 = jnp.zeros(1, jnp.float32)
    for r in (fj.sdfs(prob, x0, params=p), fj.exhaustive(prob, x0, params=p)):
        assert int(r.sequence[0]) == 1 and float(r.cost) == 0.0
    pb = jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), p)
    for solver in ("sdfs", "sdfs-vmap", "exhaustive"):
        r = fj.solve_batch(prob, jnp.zeros((2, 1), jnp.float32), params=pb, solver=solver)
        assert (np.asarray(r.sequence[:, 0]) == 1).all() and (np.asarray(r.cost) == 0).all(), solver


# 4. Long horizons compile (the fused (value, index) argmin failed at N >= 12).
@pytest.mark.parametrize("N", [12, 14])
@pytest.mark.filterwarnings("ignore:XLA could not compile")  # N = 14: the depth-first fallback (docs/dev/xla_notes.md)
def test_exhaustive_compiles_long_horizons(N):
    prob = fj.Problem(lambda x, u: jnp.stack([0.5 * x[0] + u[0], x[1]]), jnp.array([0.0, 1.0]),
                      fj.quadratic_cost(1.0, jnp.zeros(2)), N)
    r = fj.exhaustive(prob, jnp.array([0.3, 0.1]))
    assert int(r.nodes) == prob.tree_size() and same_cost(r.cost, fj.sdfs(prob, jnp.array([0.3, 0.1])).cost)
    assert bool(fj.solve_batch(prob, jnp.array([[0.3, 0.1]]), solver="exhaustive").feasible[0])
    assert int(fj.FIRHC(prob, "exhaustive").simulate(jnp.array([0.3, 0.1]), 2).input_indices[0]) >= 0


def test_exhaustive_compile_does_not_grow_with_horizon_when_levels_do_not_widen():
    prob = fj.Problem(lambda x, u: 0.5 * x + u, jnp.array([1.0]), fj.quadratic_cost(1.0, 0.0), 1000)
    assert int(fj.exhaustive(prob, jnp.zeros(1)).nodes) == 1000  # unrolled, this took minutes to compile


# 5. Overflow is not infeasibility.
def test_cost_overflow_is_flagged_not_reported_as_infeasible():
    prob = fj.Problem(lambda x, u: x + u, jnp.array([0.0, 1.0], jnp.float32),
                      lambda x, u: jnp.float32(2e38) + 0 * x[0], 3)
    x0 = jnp.zeros(1, jnp.float32)
    for solve in (fj.sdfs, fj.exhaustive):
        with pytest.warns(RuntimeWarning, match="overflow"):
            r = solve(prob, x0)
        assert bool(r.overflow) and not bool(r.feasible)
    with pytest.raises(fj.InfeasibleError, match="overflow"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fj.FIRHC(prob)(x0)
    ok = fj.sdfs(prob.replace(stage_cost=lambda x, u: jnp.float32(1.0) + 0 * x[0]), x0)
    assert not bool(ok.overflow)


# 6. A negative cost in a pruned subtree is never seen: inherent; check_problem finds it.
def test_negative_cost_in_a_pruned_subtree_is_caught_by_check_problem():
    # x = [t, first input]. Input 1 costs 1 now and -10 on the next step: sdfs finds 0 + 0 first and prunes it.
    def dyn(x, u):
        return jnp.stack([x[0] + 1.0, jnp.where(x[0] == 0, u[0], x[1])])

    def cost(x, u):
        return jnp.where(x[0] >= 2.0, jnp.where(x[1] > 0, -10.0, 0.0), u[0])

    prob = fj.Problem(dyn, jnp.array([0.0, 1.0]), cost, 2)
    r = fj.sdfs(prob, jnp.zeros(2))
    assert float(r.cost) == 0.0 and not bool(r.negative_cost)  # suboptimal (optimum -9), unseen: documented
    with pytest.raises(ValueError, match="negative"):
        fj.exhaustive(prob, jnp.zeros(2))
    found = check_problem(prob, jnp.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]]))
    assert [v.state for v in found] == [2] and found[0].value == -10.0
    assert check_problem(prob.replace(stage_cost=lambda x, u: u[0] ** 2), jnp.zeros((3, 2))) == []


# 7. Same callables, shapes and dtypes never recompile.
def _counting():
    traces = []

    def dyn(x, u):
        if isinstance(x, jax.core.Tracer):
            traces.append(1)
        return 0.5 * x + u

    return dyn, traces


def test_no_recompilation_for_python_loops_second_controllers_or_rebuilt_problems():
    dyn, traces = _counting()
    cost = fj.quadratic_cost(1.0, 0.0)
    prob = fj.Problem(dyn, [-1.0, 0.0, 1.0], cost, 3)
    fj.FIRHC(prob).simulate(jnp.ones(1), 3, compiled=False)
    fj.FIRHC(prob).simulate(jnp.ones(1), 3)
    fj.solve_batch(fj.Problem(lambda x, u, p: dyn(x, u) * p, [-1.0, 0.0, 1.0], lambda x, u, p: cost(x, u), 3),
                   jnp.ones((2, 1)), params=jnp.ones(2))
    before = len(traces)
    fj.FIRHC(prob).simulate(jnp.full(1, 0.3), 3, compiled=False)
    fj.FIRHC(fj.Problem(dyn, [-1.0, 0.0, 1.0], cost, 3)).simulate(jnp.ones(1), 3)
    fj.solve_batch(fj.Problem(lambda x, u, p: dyn(x, u) * p, [-1.0, 0.0, 1.0], lambda x, u, p: cost(x, u), 3),
                   jnp.ones((2, 1)), params=jnp.full(2, 0.5))
    # The rebuilt problem's lambdas are new objects, so that one retraces (by design: the callables are
    # the key); everything else reuses its executable.
    assert len(traces) - before <= 2
    fields = {f.name for f in dataclasses.fields(fj.Problem)}
    assert set(vars(prob)) == fields | {"_key"}  # solving wrote no cache into the frozen dataclass


# 8. What is guaranteed about costs across solvers.
def test_solvers_agree_on_the_optimum_within_rounding_of_the_stage_costs():
    rng = np.random.default_rng(3)
    W = rng.uniform(-1, 1, (5, 2)).astype(np.float32)
    prob = fj.Problem(lambda x, u: 0.9 * x + u, jnp.asarray(W), fj.quadratic_cost(jnp.array([1.0, 0.5]),
                                                                                   jnp.zeros(2), 0.1), 4)
    X0 = jnp.asarray(rng.uniform(-2, 2, (24, 2)), jnp.float32)
    costs = [np.asarray(jax.vmap(lambda x: fj.sdfs(prob, x).cost)(X0)),
             np.asarray(jax.vmap(lambda x: fj.exhaustive(prob, x).cost)(X0))]
    costs += [np.asarray(fj.solve_batch(prob, X0, solver=s).cost) for s in ("sdfs", "sdfs-vmap", "exhaustive")]
    tol = 8 * prob.horizon * np.finfo(np.float32).eps
    for c in costs[1:]:
        np.testing.assert_allclose(c, costs[0], rtol=tol)


# 9. From a new user.
def test_infinite_states_are_flagged():
    prob = fj.Problem(lambda x, u: x * jnp.where(u[0] > 1.5, jnp.inf, 1.0), jnp.array([2.0, 1.0]),
                      fj.quadratic_cost(0.0, 0.0), 2)
    with pytest.warns(RuntimeWarning, match="non-finite"):
        r = fj.sdfs(prob, jnp.ones(1))
    assert bool(r.nan_encountered) and bool(r.feasible) and int(r.sequence[0]) == 1


def test_closed_loop_splits_fallback_nodes_and_an_infeasible_warm_start_costs_nothing():
    prob = fj.Problem(lambda x, u: 0.5 * x + u, jnp.array([-1.0, 0.0, 1.0]), fj.quadratic_cost(1.0, 0.0), 3,
                      terminal=lambda x: x[0] > 100.0)
    run = fj.FIRHC(prob, fallback="unconstrained").simulate(jnp.ones(1), 3)
    assert (np.asarray(run.nodes) <= prob.tree_size()).all() and (np.asarray(run.fallback_nodes) > 0).all()
    assert np.asarray(run.used_fallback).all() and not np.asarray(run.feasible).any()
    none = fj.sdfs(prob.replace(terminal=None), jnp.ones(1), warm_start=jnp.full(3, -1))
    plain = fj.sdfs(prob.replace(terminal=None), jnp.ones(1))
    assert int(none.nodes) == int(plain.nodes) and float(none.cost) == float(plain.cost)
