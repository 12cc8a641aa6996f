"""The linear helpers and fj.LinearTracking at the edges: any scaling of the weights and units stays exact, a
target or reference that does not fit the plant is refused instead of broadcast, complex or infinite models are
refused, a NaN is flagged, and the sizes that would exhaust the memory are refused before any work."""
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from reference import same_cost
from trackers import NONE, Case

import firhc_jax as fj
from firhc_jax._src.linear.tracking import input_classes
from firhc_jax.models import three_level

FEW = settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def decoupled(seed):
    """A mimo case whose first output is one state that only the first input moves, tracked from rest at 0:
    with a priority weight on it (Q = diag(1e30, 1)) the optimum keeps it at 0 and the rest is an ordinary
    tracking cost, so J is small while F's singular values span 15 orders of magnitude."""
    case = Case("mimo", False, seed)
    case.A[0, 1:], case.A[1:, 0], case.B[0, 1:], case.B[1:, 0] = 0, 0, 0, 0
    case.C[0], case.C[1, 0] = [1.0, 0.0, 0.0], 0.0
    case.x[0], case.y_ref[:, 0], case.d[:, 0] = 0.0, 0.0, 0.0
    case.Q = np.diag([1e30, 1.0])
    return case


@FEW
@given(st.integers(0, 2**32 - 1))
@example(10)  # the cost-to-go counted the light output as out of reach: J = 0.262 against 0.038
def test_a_priority_weight_keeps_the_search_exact(seed):
    case = decoupled(seed)
    result = case.tracker().solve(case.x, case.u_prev, case.y_ref, case.d, warm_start=NONE)
    best = case.brute_force()
    assert same_cost(float(result.cost), best, rtol=1e-9, atol=1e-12), (float(result.cost), best)


@FEW
@given(st.integers(0, 2**32 - 1))
@example(0)
def test_the_merge_of_equal_effects_does_not_depend_on_the_units(seed):
    """B = 1e-15 B, Q = 1e30 Q: the same classes and the same J (the tolerance was absolute: one class)."""
    case = Case("common", True, seed)
    classes = input_classes(case.B, case.controls)
    assert len(classes) == 19
    np.testing.assert_array_equal(input_classes(1e-15 * case.B, case.controls), classes)
    np.testing.assert_array_equal(input_classes(1e15 * case.B, case.controls), classes)
    best = case.brute_force()
    case.B, case.Q, case.d, case.x = 1e-15 * case.B, 1e30 * case.Q, 1e-15 * case.d, 1e-15 * case.x
    case.y_ref = 1e-15 * case.y_ref
    lt = case.tracker()
    assert lt.num_classes == 19
    result = lt.solve(case.x, case.u_prev, case.y_ref, case.d, warm_start=NONE)
    assert same_cost(float(result.cost), case.brute_force())
    assert same_cost(case.brute_force(), best, rtol=1e-6)  # the same problem in other units


def test_a_switching_cost_of_any_size_is_a_cost():
    """lambda_u = 1e30 from a u_prev off the grid: every sequence pays more than 5e29 to switch (it read as "no
    input": infeasible)."""
    case = Case("siso", False, 1)
    case.lambda_u, case.u_prev = 1e30, np.array([2.5])
    result = case.tracker().solve(case.x, case.u_prev, case.y_ref, case.d)
    best = case.brute_force()
    assert best > 1e30 and bool(result.feasible)
    assert same_cost(float(result.cost), best)


@pytest.fixture(scope="module")
def mimo():
    case = Case("mimo", True, 3)
    return case, case.tracker()


def test_a_nan_state_reaching_the_tracker_is_flagged(mimo):
    case, lt = mimo
    params = lt.params(case.y_ref, case.d)
    ctrl = fj.FIRHC(lt.problem, observe=lt.observe)
    state = ctrl.init(case.x, u0=case.u_prev)
    _, _, info = ctrl.step(state, np.array([np.nan, 0.0, 0.0]), params)
    assert bool(info.result.nan_encountered) and bool(info.held)
    solved = jax.jit(lt.solve)(jnp.array([np.nan, 0.0, 0.0]), case.u_prev, case.y_ref, case.d)
    assert bool(solved.nan_encountered) and not bool(solved.feasible)


def test_a_nan_reference_reaching_the_tracker_is_flagged(mimo):
    case, lt = mimo
    z0 = lt.observe(case.x, case.u_prev)
    y_ref = np.where(np.arange(case.N)[:, None] == 1, np.nan, case.y_ref)

    @jax.jit
    def search(y):
        return fj.sdfs(lt.problem, z0, params=lt.params(y, case.d))

    assert bool(search(y_ref).nan_encountered)
    assert not bool(search(case.y_ref).nan_encountered)
    assert bool(jax.jit(lt.solve)(case.x, case.u_prev, y_ref, case.d).nan_encountered)


def test_the_per_step_params_carry_only_the_steps_data():
    """A closed loop's params are each step's data: their size does not grow with the input set (the model,
    with its classes of inputs, was copied into every step: 2.4 kB a step on the README's inverter)."""
    A, B = three_level.model()
    steps, N = 50, 4
    y = np.random.default_rng(0).normal(size=(steps, N, 2))
    few = fj.LinearTracking(A, B, [[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]], N, lambda_u=0.1)
    many = fj.LinearTracking(A, B, three_level.SWITCH_STATES, N, lambda_u=0.1, max_step=1.0)
    sizes = [sum(a.nbytes for a in jax.tree_util.tree_leaves(lt.params(y))) for lt in (few, many)]
    assert sizes[0] == sizes[1]
    itemsize = np.dtype(jnp.zeros(()).dtype).itemsize
    n, m, p = 2, 3, 2
    assert sizes[1] == steps * N * ((2 * n + p + m) + 3 + p + n) * itemsize


def test_the_factorisation_memory_is_estimated_and_refused():
    A, B = three_level.model()
    with pytest.raises(ValueError, match=r"horizon N = 60 .* needs about [\d,]+ bytes, more than max_memory=1,000,000"):
        fj.LinearTracking(A, B, three_level.SWITCH_STATES, 60, max_memory=10**6)
    with pytest.raises(ValueError, match="max_memory"):
        fj.LinearTracking(A, B, three_level.SWITCH_STATES, 1000)  # about 640 GB
    with pytest.raises(ValueError, match="max_memory must be an int >= 1"):
        fj.LinearTracking(A, B, three_level.SWITCH_STATES, 2, max_memory=0)


def test_product_controls_beyond_int32_are_refused():
    with pytest.raises(ValueError, match=r"12,157,665,459,056,928,801 inputs .* int32"):
        fj.product_controls([0, 1, 2], repeat=40)


@settings(max_examples=20, deadline=None)
@given(st.lists(st.lists(st.one_of(st.integers(-3, 3), st.floats(-2, 2)), min_size=1, max_size=3), min_size=1,
                max_size=3), st.integers(1, 2))
def test_product_controls_lists_every_combination_in_order(levels, repeat):
    expected = np.array(list(itertools.product(*levels, repeat=repeat)))
    out = fj.product_controls(*levels, repeat=repeat)
    assert out.dtype == expected.dtype
    np.testing.assert_array_equal(out, expected)


GOOD = np.array([[0.5]])


@pytest.mark.parametrize("make, name", [
    (lambda: fj.LinearTracking(GOOD * (1 + 1j), [[1.0]], [-1.0, 1.0], 2), "A"),
    (lambda: fj.LinearTracking(GOOD, [[1.0]], [-1.0, 1.0], 2, C=[[1j]]), "C"),
    (lambda: fj.LinearTracking(GOOD, [[1.0]], [-1.0, 1.0], 2, Q=[[1.0 + 0j]]), "Q"),
    (lambda: fj.discretize([[-1.0 + 1j]], [[1.0]], 0.1), "A"),
    (lambda: fj.linear_dynamics(GOOD, [[1j]]), "B"),
    (lambda: fj.linear_dynamics(GOOD, [[1.0]], d=[1j]), "d"),
    (lambda: fj.tracking_cost(C=[[1j]]), "C"),
    (lambda: fj.tracking_cost(Q=[[2j]]), "Q"),
    (lambda: fj.quadratic_cost(lam=np.array([1.0 + 0j]), x_s=np.zeros(1)), "lam"),
])
def test_complex_models_and_weights_are_refused(make, name):
    with pytest.raises(TypeError, match=rf"{name} must be real, got (a )?complex"):
        make()


@pytest.mark.parametrize("make, name", [
    (lambda a: fj.LinearTracking(a, [[1.0]], [-1.0, 1.0], 2), "A"),
    (lambda a: fj.LinearTracking(GOOD, a, [-1.0, 1.0], 2), "B"),
    (lambda a: fj.linear_dynamics(a, [[1.0]]), "A"),
    (lambda a: fj.discretize(GOOD, a, 0.1), "B"),
    (lambda a: fj.tracking_cost(C=a), "C"),
])
def test_model_matrices_follow_one_rule(make, name):
    """A traced matrix and an empty one are refused by name, before any work, by LinearTracking and the linear
    helpers alike (a traced one was a raw JAX conversion error in the helpers, an empty one was accepted)."""
    with pytest.raises(TypeError, match=rf"{name} must be concrete values, not a traced array"):
        jax.jit(make)(jnp.asarray(GOOD))
    with pytest.raises(ValueError, match=rf"{name} must be a non-empty 2-D matrix, got shape \(0, 1\)"):
        make(np.zeros((0, 1)))


@pytest.mark.parametrize("Ts", ["a", None, [0.1, 0.2], 1j])
def test_discretize_names_a_bad_sampling_period(Ts):
    with pytest.raises((TypeError, ValueError), match="Ts must be"):
        fj.discretize([[0.0]], [[1.0]], Ts)


def test_discretize_refuses_a_model_that_overflows():
    with pytest.raises(ValueError, match=r"exp\(A Ts\) is not finite .* shorten Ts"):
        fj.discretize([[1000.0]], [[1.0]], 1.0)
    Ad, Bd = fj.discretize([[-1.0]], [[1.0]], 0.5)  # still exact where it is finite
    np.testing.assert_allclose([Ad[0, 0], Bd[0, 0]], [np.exp(-0.5), 1 - np.exp(-0.5)], rtol=1e-12)


def _plant(x, u, *_):
    return 0.9 * x + u.astype(x.dtype)


def test_a_target_of_the_wrong_length_is_refused_before_compiling():
    cost = fj.quadratic_cost(lam=1.0, x_s=[0.0, 0.0, 0.0])
    problem = fj.Problem(_plant, [-1.0, 0.0, 1.0], cost, 2)
    with pytest.raises(ValueError, match=r"x_s has shape \(3,\), which does not fit the state x_next of shape \(1,\)"):
        fj.sdfs(problem, np.ones(1))
    with pytest.raises(ValueError, match=r"x_s has shape \(2,\) but lam has shape \(3,\)"):
        fj.quadratic_cost(lam=np.ones(3), x_s=np.zeros(2))
    for kwargs, name in (({"lam": np.ones(2), "x_s": 0.0}, "lam"), ({"lam": 1.0, "x_s": 0.0, "u_e": [0, 0]}, "u_e"),
                         ({"lam": 1.0, "x_s": 0.0, "beta": np.eye(2)}, "beta")):
        with pytest.raises(ValueError, match=rf"{name} has shape"):
            fj.sdfs(fj.Problem(_plant, [-1.0, 0.0, 1.0], fj.quadratic_cost(**kwargs), 2), np.ones(1))
    fine = fj.sdfs(fj.Problem(_plant, [-1.0, 0.0, 1.0], fj.quadratic_cost(lam=[2.0], x_s=[0.5]), 2), np.ones(1))
    assert bool(fine.feasible)


def test_a_reference_for_other_outputs_is_refused_before_compiling():
    ref = np.zeros((2, 2))  # 2 outputs, but the plant has 1
    stepwise = fj.Problem(_plant, [-1.0, 0.0, 1.0], fj.tracking_cost(), 2, step_index=True)
    with pytest.raises(ValueError, match=r"params\['ref'\] has shape \(2, 2\), but C x has shape \(1,\): the "
                                         r"reference must be \[N, 1\]"):
        fj.sdfs(stepwise, np.ones(1), params={"ref": ref})
    set_point = fj.Problem(_plant, [-1.0, 0.0, 1.0], fj.tracking_cost(C=[[1.0]]), 2)
    with pytest.raises(ValueError, match=r"params\['ref'\] has shape \(2,\), but C x has shape \(1,\)"):
        fj.sdfs(set_point, np.ones(1), params={"ref": np.zeros(2)})
    with pytest.raises(ValueError, match=r"C has shape \(1, 2\), which does not fit the state x_next"):
        fj.sdfs(fj.Problem(_plant, [-1.0, 1.0], fj.tracking_cost(C=[[1.0, 1.0]]), 2), np.ones(1),
                params={"ref": np.zeros(1)})
    ok = fj.sdfs(stepwise, np.ones(1), params={"ref": np.zeros((2, 1))})
    assert bool(ok.feasible)


def test_horizon_windows_start_picks_the_states_or_the_inputs_window():
    signal = np.arange(10.0)
    states = fj.horizon_windows(signal, 4, 3)  # x(t+1) .. x(t+N)
    np.testing.assert_array_equal(states, fj.horizon_windows(signal, 4, 3, start=1))
    np.testing.assert_array_equal(states[2], [3.0, 4.0, 5.0])
    inputs = fj.horizon_windows(signal, 4, 3, start=0)  # u(t) .. u(t+N-1)
    np.testing.assert_array_equal(inputs[2], [2.0, 3.0, 4.0])
    assert fj.horizon_windows(signal, 8, 3, start=0).shape == (8, 3)  # steps + N - 1 samples suffice
    with pytest.raises(ValueError, match=r"steps \+ start \+ horizon - 1 = 11"):
        fj.horizon_windows(signal, 8, 3)
    with pytest.raises(ValueError, match="start must be an int >= 0"):
        fj.horizon_windows(signal, 4, 3, start=-1)


def test_lower_bound_is_evaluated_at_the_leaves_and_ignored_there():
    """What docs/guide/formulation.md says: ``lower_bound`` is called with steps_left = 0 .. N - 1 (0 for the
    leaves, never N), and at 0 its value is not used (a leaf's key is its cost): a bound that is absurd at 0
    changes nothing."""
    seen = []

    def bound(x, steps_left):
        jax.debug.callback(lambda s: seen.append(int(s)), steps_left)
        return jnp.where(steps_left == 0, 1e9, 0.0)

    problem = fj.Problem(_plant, [-1.0, 0.0, 1.0], fj.quadratic_cost(lam=1.0, x_s=0.0), 3, lower_bound=bound)
    result = fj.sdfs(problem, np.ones(1))
    exact = fj.exhaustive(problem.replace(lower_bound=None), np.ones(1))
    assert same_cost(float(result.cost), float(exact.cost))
    assert set(seen) == {0, 1, 2}
