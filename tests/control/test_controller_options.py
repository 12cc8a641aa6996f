"""FIRHC's fallback problem, warm-start callable and progress bar."""
import jax.numpy as jnp
import numpy as np
import pytest
from reference import same_cost

import firhc_jax as fj


def dyn(x, u):
    return jnp.stack([0.9 * x[0] + 0.3 * u[0], x[1] + 0.1 * x[0]])


CONTROLS = jnp.array([[-1.0], [0.0], [1.0]])
COST = fj.quadratic_cost(jnp.array([1.0, 0.5]), jnp.zeros(2), 0.1)


def test_warm_start_callable_seeds_each_search():
    p = fj.Problem(dyn, CONTROLS, COST, 4)
    calls = []

    def seed(problem, x, previous, params):
        calls.append(problem.horizon)
        return jnp.full((4,), 1, jnp.int32)  # "hold the input at 0": a valid, poor candidate

    x = jnp.array([1.0, -0.5])
    plain = fj.FIRHC(p).simulate(x, 3, compiled=False)
    seeded = fj.FIRHC(p, warm_start=seed).simulate(x, 3, compiled=False)
    assert calls  # the callable was used
    np.testing.assert_allclose(seeded.predicted_costs, plain.predicted_costs, rtol=1e-12)
    assert np.any(np.asarray(seeded.nodes) != np.asarray(plain.nodes))  # the seed's rollout counts N nodes


def test_fallback_problem_decides_when_infeasible():
    tight = fj.Problem(dyn, CONTROLS, COST, 3, terminal=lambda x: x[1] > 50.0)  # out of reach
    relaxed = fj.Problem(dyn, CONTROLS, fj.quadratic_cost(jnp.array([0.0, 1.0]), jnp.zeros(2), 0.0), 3)
    x = jnp.array([1.0, -0.5])
    result, used = fj.FIRHC(tight, fallback=relaxed).solve(x)
    assert bool(used)
    ref = fj.sdfs(relaxed, x)
    assert float(result.cost) == float(ref.cost) and list(result.sequence) == list(ref.sequence)
    with pytest.raises(ValueError, match="horizon and inputs"):
        fj.FIRHC(tight, fallback=fj.Problem(dyn, CONTROLS, COST, 4))


def test_bad_options_are_refused():
    p = fj.Problem(dyn, CONTROLS, COST, 3)
    with pytest.raises(TypeError, match="warm_start"):
        fj.FIRHC(p, warm_start="shift")
    with pytest.raises(ValueError, match="fallback"):
        fj.FIRHC(p, fallback="relaxed")
    with pytest.raises(ValueError, match="warm_start applies to the sDFS solvers, not solver='exhaustive'"):
        fj.FIRHC(p, "exhaustive", warm_start=lambda *a: None)


def test_a_progress_bar_costs_at_most_TICKS_host_callbacks(capsys, ticks):
    """A host callback per step made progress=True 23x slower: a run reports every
    interval(T) steps and at its end, whatever T, compiled or not."""
    from firhc_jax._src.runtime import progress

    ctrl = fj.FIRHC(fj.Problem(dyn, CONTROLS, COST, 2))
    for steps, compiled in ((1_000, True), (1_001, True), (250, False)):
        ticks.clear()
        ctrl.simulate(jnp.array([1.0, -0.5]), steps, progress=True, compiled=compiled)
        every = progress.interval(steps)
        expected = sorted({k for k in range(steps) if (k + 1) % every == 0} | {steps - 1})
        assert ticks == expected and len(ticks) <= progress.TICKS + 1, (steps, compiled)
        assert f"{steps}/{steps}" in capsys.readouterr().err


def test_unconstrained_fallback_keeps_terminal_cost_and_constraints():
    """It drops the terminal set and the lower bound only: hard constraints are physical limits, and the
    terminal cost is part of the objective."""
    no_up = lambda x_next, u: u[0] < 0.5  # noqa: E731 (input +1 is forbidden)
    end_cost = lambda x: 5.0 * x[1] ** 2  # noqa: E731
    p = fj.Problem(dyn, CONTROLS, COST, 3, terminal=lambda x: x[1] > 50.0,
                   lower_bound=lambda x, steps_left: 0.0 * x[0], terminal_cost=end_cost, constraint=no_up)
    x = jnp.array([-1.0, -0.5])
    result, used = fj.FIRHC(p, fallback="unconstrained").solve(x)
    ref = fj.sdfs(p.replace(terminal=None, lower_bound=None), x)
    bare = fj.sdfs(fj.Problem(dyn, CONTROLS, COST, 3), x)
    assert bool(used) and float(result.cost) == float(ref.cost) and list(result.sequence) == list(ref.sequence)
    assert 2 not in list(result.sequence) and 2 in list(bare.sequence)  # the constraint still binds
    # Nothing satisfies a constraint that forbids every input: the message names the constraint, no terminal set.
    stuck = fj.Problem(dyn, CONTROLS, COST, 2, constraint=lambda x_next, u: u[0] > 5.0)
    with pytest.raises(fj.InfeasibleError, match="constraint") as e:
        fj.FIRHC(stuck)(x)
    assert "terminal" not in str(e.value)


def test_step_index_problems_run_in_the_closed_loop():
    """With step_index the model's callables get k; the closed loop's applied step is k = 0."""
    def dyn_k(x, u, k):
        return dyn(x, u) * (1.0 + 0.1 * k)

    def cost_k(x_next, u, k):
        return COST(x_next, u) * (1.0 + k)

    p = fj.Problem(dyn_k, CONTROLS, cost_k, 3, step_index=True)
    run = fj.FIRHC(p).simulate(jnp.array([1.0, -0.5]), 4)
    x, u = run.states[0], CONTROLS[int(run.input_indices[0])]
    assert float(run.stage_costs[0]) == float(cost_k(dyn_k(x, u, 0), u, 0))
    np.testing.assert_array_equal(np.asarray(run.states[1]), np.asarray(dyn_k(x, u, 0)))


@pytest.mark.parametrize("solver", ["sdfs", "pool"])
def test_a_budget_beyond_int32_is_clamped_as_fj_sdfs_clamps_it(solver):
    """max_nodes = 2**31 or more is more than the int32 node counter can count: the controller clamps it
    as fj.sdfs does (one compiled decision for every such budget) and decides exactly."""
    p = fj.Problem(dyn, CONTROLS, COST, 4)
    x = jnp.array([1.0, -0.5])
    huge = fj.FIRHC(p, solver, max_nodes=2**31)
    assert huge.solver_options["max_nodes"] == 2**31 - 1
    assert fj.FIRHC(p, solver, max_nodes=2**40).options.key == huge.options.key
    u, info = huge(x)
    ref = fj.sdfs(p, x, max_nodes=2**31)
    exact = fj.exhaustive(p, x).cost  # the decision is compiled apart from fj.sdfs: equal up to the last bits
    assert bool(info.complete) and same_cost(info.result.cost, exact) and same_cost(ref.cost, exact)
    run = huge.simulate(x, 3)
    assert np.asarray(run.complete).all()


def test_a_plant_defined_anew_for_each_call_is_named_when_the_loop_compiles_again():
    """The plant is part of the compiled closed loop, keyed by the object: a lambda written in the call (a
    sweep's list comprehension) compiles the loop each time, and says so in one line; the same object, the
    default plant, another plant's code and the Python loop (which compiles no plant) do not warn."""
    import warnings

    c = fj.FIRHC(fj.Problem(dyn, CONTROLS, COST, 2))
    x = np.array([1.0, -0.5])
    plant = lambda x, u: dyn(x, u)  # noqa: E731
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # none of these warns
        c.simulate(x, 2)
        for _ in range(2):
            c.simulate(x, 2, plant)
        c.simulate(x, 2, lambda x, u: 0.5 * dyn(x, u))  # another plant's code
        c.simulate(x, 2, lambda x, u: 0.5 * dyn(x, u), compiled=False)
        c.simulate(x, 2, plant)  # compiled before: nothing compiles
    with pytest.warns(UserWarning, match=r"compiles its closed loop again for a new plant object"):
        c.simulate(x, 2, type(plant)(plant.__code__, globals()))  # plant's code in a new function object
    seen = []
    for _ in range(2):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            c.simulate_batch(x[None], 2, lambda x, u: 0.9 * dyn(x, u))
        seen.append([str(w.message) for w in caught])
    assert seen[0] == [] and len(seen[1]) == 1, seen  # the first lambda of this line follows another code
    assert "\n" not in seen[1][0] and "new plant object with the code of the last one (<lambda> at " in seen[1][0]
    assert "define it once and pass that same object" in seen[1][0]


def test_a_sweep_of_budgets_compiles_each_closed_loop_and_step_once():
    """max_nodes travels with the state (ControllerState.budget), an argument of the compiled decision: a
    controller of another budget compiles nothing again, and each decision stays within its own budget."""
    from compiles import compile_count

    p = fj.Problem(dyn, CONTROLS, COST, 5, terminal=lambda x: jnp.abs(x[0]) < 0.3)
    x = np.array([1.0, -0.5])
    first = fj.FIRHC(p, fallback="unconstrained", max_nodes=40)
    np.asarray(first.simulate(x, 4, progress=False).decision_nodes)  # the eager sum of the nodes lowers once
    _, _, info = first.step(first.init(x), x)
    int(info.decision_nodes), int(first(x)[1].decision_nodes)
    before = compile_count()
    for budget in (40, 90, 300):
        ctrl = fj.FIRHC(p, fallback="unconstrained", max_nodes=budget)
        run = ctrl.simulate(x, 4, progress=False)
        assert (np.asarray(run.decision_nodes) <= budget).all(), (budget, np.asarray(run.decision_nodes))
        u, state, info = ctrl.step(ctrl.init(x), x)
        assert int(state.budget) == budget and int(info.decision_nodes) <= budget
        assert int(ctrl(x)[1].decision_nodes) <= budget
    assert compile_count() == before
    # A state made by hand, without a budget, decides within the controller's own.
    _, state, info = ctrl.step(fj.ControllerState(u=np.zeros(1), plan=np.full(5, -1, np.int32)), x)
    assert int(state.budget) == 300 and int(info.decision_nodes) <= 300
