"""Batched closed loops: ``ctrl.simulate_batch`` runs B loops in one compiled run, loop b deciding as
``ctrl.simulate`` of loop b, with everything a single loop has."""
import jax.numpy as jnp
import numpy as np
import pytest
import random_problems
from compiles import compile_count
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from loops import (
    CONTROLS,
    PROBLEM,
    N,
    T,
    actuate,
    assert_same_loop,
    counting_controller,
    loop_params,
    observe,
    plant,
    row,
)
from repository import ROOT, TESTS
from trackers import Case

import firhc_jax as fj

CONTROLLERS = {
    "full": dict(fallback="unconstrained", warm_start=True, observe=observe, actuate=actuate),
    # Budgets that cut searches (no stealing, node for node): the fallback acts within its half of the budget;
    # without a fallback some decisions find no input (held).
    "budget": dict(fallback="unconstrained", warm_start=True, observe=observe, actuate=actuate, max_nodes=16,
                   lanes=2),
    "budget, no fallback": dict(warm_start=True, observe=observe, actuate=actuate, max_nodes=24, lanes=2,
                                u_safe=np.array([0.0])),
    "lanes": dict(fallback="unconstrained", observe=observe, actuate=actuate, lanes=2),
    "exhaustive": dict(solver="exhaustive", fallback="unconstrained", observe=observe, actuate=actuate),
}


@pytest.fixture(scope="module", params=["full", *(pytest.param(name, marks=pytest.mark.slow)
                                                  for name in ("budget", "budget, no fallback", "lanes",
                                                               "exhaustive"))])
def ctrl(request):
    return request.param, fj.FIRHC(PROBLEM, **CONTROLLERS[request.param])


@settings(max_examples=3, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**31 - 1), B=st.sampled_from([1, 3, 5]))
def test_loop_b_is_simulate_of_loop_b(ctrl, seed, B):
    name, c = ctrl
    rng = np.random.default_rng(seed)
    X0 = rng.uniform(-1, 1, (B, 2))
    U0 = rng.choice(CONTROLS, (B, 1))
    params = loop_params(rng, B)
    holds = name == "budget, no fallback"
    with pytest.warns() if holds else _nothing():
        run = c.simulate_batch(X0, T, plant, params=params, u0=U0)
    assert run.states.shape == (B, T + 1, 2) and run.plans.shape == (B, T, N) and run.nodes.shape == (B, T)
    for b in range(B):
        with pytest.warns() if holds else _nothing():
            one = c.simulate(X0[b], T, plant, params=row(params, b), u0=U0[b])
        # nobody steals under a budget or in the exhaustive search: the same nodes
        assert_same_loop(row(run, b), one, f"{name}: loop {b}", nodes=name.startswith("budget") or name == "exhaustive")
    if name.startswith("budget"):
        assert int(np.max(np.asarray(run.decision_nodes))) <= c.solver_options["max_nodes"]
        assert not np.asarray(run.complete).all()


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def test_the_cases_cover_what_they_claim(ctrl):
    """Fallback decisions, held steps and cut searches all happen in these loops."""
    name, c = ctrl
    rng = np.random.default_rng(7)
    params = loop_params(rng, 5)
    with pytest.warns(RuntimeWarning) if name == "budget, no fallback" else _nothing():
        run = c.simulate_batch(rng.uniform(-1, 1, (5, 2)), T, plant, params=params)
    if c.fallback is not None:
        assert np.asarray(run.used_fallback).any() and not np.asarray(run.used_fallback).all()
    if name.startswith("budget"):
        assert not np.asarray(run.complete).all()
        assert np.asarray(run.held).any() == (c.fallback is None) and not np.asarray(run.held).all()


@pytest.mark.parametrize("seed", [0, 1])
def test_random_problems_batched_equal_their_single_loops(seed):
    """Random nonlinear problems with a terminal set: the pool's loops equal the single loops' costs."""
    rp = random_problems.make(seed, n=2, m=1, M=3, N=3, terminal="loose")
    c = fj.FIRHC(rp.problem(), fallback="unconstrained", warm_start=True)
    X0 = np.random.default_rng(seed).uniform(-1, 1, (6, 2))
    run = c.simulate_batch(X0, 5)
    for b in range(6):
        assert_same_loop(row(run, b), c.simulate(X0[b], 5), f"loop {b}")


def test_new_values_never_recompile():
    traces = []
    c = counting_controller(traces)
    rng = np.random.default_rng(3)
    c.simulate_batch(rng.uniform(-1, 1, (4, 2)), T, plant, params=loop_params(rng, 4), u0=np.array([1.0]))
    before, compiled = len(traces), compile_count()
    for _ in range(2):
        c.simulate_batch(rng.uniform(-1, 1, (4, 2)), T, plant, params=loop_params(rng, 4),
                         u0=rng.choice(CONTROLS, (4, 1)))
    assert before > 0 and len(traces) == before and compile_count() == compiled


def test_bad_batches_are_refused_before_any_work():
    c = fj.FIRHC(PROBLEM, observe=observe, actuate=actuate)
    params = loop_params(np.random.default_rng(0), 3)
    X0 = np.zeros((3, 2))
    with pytest.raises(ValueError, match=r"X0 must be a 2-D batch"):
        c.simulate_batch(np.zeros(2), T, plant, params=params)
    with pytest.raises(ValueError, match=r"params leaf \['ref'\] must have leading axes"):
        c.simulate_batch(X0, T, plant, params=dict(params, ref=params["ref"][:, :-1]))
    with pytest.raises(ValueError, match=r"params leaf \['gain'\] must have leading axes"):
        c.simulate_batch(X0, T, plant, params=dict(params, gain=params["gain"][:2]))
    with pytest.raises(ValueError, match=r"u0 must be one input of shape \(1,\)"):
        c.simulate_batch(X0, T, plant, params=params, u0=np.zeros((2, 1)))
    with pytest.raises(ValueError, match="X0 contains NaN"):
        c.simulate_batch(np.full((3, 2), np.nan), T, plant, params=params)


def test_a_batched_run_saves_loads_and_plots(tmp_path):
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    c = fj.FIRHC(PROBLEM, fallback="unconstrained", observe=observe, actuate=actuate)
    rng = np.random.default_rng(1)
    run = c.simulate_batch(rng.uniform(-1, 1, (6, 2)), T, plant, params=loop_params(rng, 6), dt=0.1)
    path = run.save(tmp_path / "batch.npz")
    back = fj.ClosedLoop.load(path)
    for field in fj.ClosedLoop._fields:
        a, b = getattr(run, field), getattr(back, field)
        if a is None:
            assert b is None
        else:
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=field)
    fig = run.plot()
    assert isinstance(fig, Figure) and fig.axes and all(ax.get_xlabel() or ax.get_ylabel() for ax in fig.axes)


@pytest.mark.float32
def test_float32_loops_equal_their_single_loops():
    c = fj.FIRHC(fj.Problem(lambda x, u: 0.9 * x + u, jnp.array([[-0.5], [0.0], [0.5]], jnp.float32),
                            fj.quadratic_cost(1.0, jnp.zeros(1, jnp.float32), 0.1), 3))
    X0 = np.linspace(-2, 2, 5, dtype=np.float32)[:, None]
    run = c.simulate_batch(X0, 6)
    assert run.states.dtype == jnp.float32
    for b in range(5):
        one = c.simulate(X0[b], 6)
        np.testing.assert_allclose(np.asarray(run.states[b]), np.asarray(one.states), rtol=1e-6)
        np.testing.assert_allclose(np.asarray(run.predicted_costs[b]), np.asarray(one.predicted_costs), rtol=1e-6)


@pytest.mark.slow
def test_linear_tracking_loops_apply_first_input_of_as_single_loops():
    """A LinearTracking problem (classes of inputs, first_input_of picking the member) batched over loops
    with per-loop references and disturbances."""
    case = Case("common", True, 5)
    lt = case.tracker()
    B, steps = 3, 4
    rng = np.random.default_rng(2)
    params = lt.params(rng.normal(size=(B, steps) + case.y_ref.shape), 0.3 * rng.normal(size=(B, steps) + case.d.shape))
    ctrl = fj.FIRHC(lt.problem, observe=lt.observe, warm_start=True)

    def lin_plant(x, u, p):
        return jnp.asarray(case.A) @ x + jnp.asarray(case.B) @ u + p.d[0]

    X0 = case.x + 0.5 * rng.normal(size=(B,) + case.x.shape)
    run = ctrl.simulate_batch(X0, steps, lin_plant, params=params, u0=case.controls[0])
    for b in range(B):
        one = ctrl.simulate(X0[b], steps, lin_plant, params=row(params, b), u0=case.controls[0])
        assert assert_same_loop(row(run, b), one, f"loop {b}") == steps  # no ties here


FOUR_DEVICES = """
import jax, numpy as np
jax.config.update("jax_enable_x64", True)
import firhc_jax as fj
from loops import PROBLEM, T, actuate, assert_same_loop, loop_params, observe, plant, row
assert jax.local_device_count() == 4, jax.local_devices()
ctrl = fj.FIRHC(PROBLEM, fallback="unconstrained", warm_start=True, observe=observe, actuate=actuate)
rng = np.random.default_rng(4)
B = 6
X0, params = rng.uniform(-1, 1, (B, 2)), loop_params(rng, B)
run = ctrl.simulate_batch(X0, T, plant, params=params)
for b in range(B):
    assert_same_loop(row(run, b), ctrl.simulate(X0[b], T, plant, params=row(params, b)), f"loop {b}")
print("loops on 4 devices equal their single loops")
"""


@pytest.mark.slow
def test_loops_split_over_four_devices_equal_their_single_loops():
    import os
    import subprocess
    import sys

    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu",
               PYTHONPATH=os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-c", FOUR_DEVICES], capture_output=True, text=True, env=env,
                         cwd=ROOT, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "loops on 4 devices equal their single loops" in out.stdout


BUDGET_PROBLEM = random_problems.make(5, n=2, m=1, M=4, N=5).problem()  # random inputs: no ties
BUDGET_CASES = [(solver, budget) for solver in ("sdfs", "pool", "sdfs-vmap") for budget in (None, 60)] \
    + [("exhaustive", None)]


@pytest.mark.parametrize("solver,max_nodes", [pytest.param(*case, marks=() if case == ("pool", 60) else
                                                           pytest.mark.slow) for case in BUDGET_CASES])
def test_every_solver_batches_its_loops_as_simulate(solver, max_nodes):
    """Every solver, with and without a node budget: each batched loop makes its own simulate's decisions
    (no ties here, so every step), node for node wherever no nodes are shared between loops."""
    budget = {} if max_nodes is None else {"max_nodes": max_nodes}
    c = fj.FIRHC(BUDGET_PROBLEM, solver, warm_start=solver != "exhaustive", **budget)
    X0 = np.random.default_rng(11).uniform(-1, 1, (5, 2))
    run = c.simulate_batch(X0, 6)
    nodes = max_nodes is not None or solver in ("sdfs-vmap", "exhaustive")
    for b in range(5):
        assert assert_same_loop(row(run, b), c.simulate(X0[b], 6), f"{solver}: loop {b}", nodes=nodes) == 6
    if max_nodes is not None:  # the budget cuts every search
        assert not np.asarray(run.complete).any() and int(np.max(np.asarray(run.decision_nodes))) <= max_nodes
