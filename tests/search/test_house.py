"""The controller's structure: options as a frozen record whose key is derived from every field, and the
table of solvers that every entry point reads."""
import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest
import random_problems
from hypothesis import given, settings
from hypothesis import strategies as st

import firhc_jax as fj
from firhc_jax._src.control.controller import Options
from firhc_jax._src.search import solvers


def _dyn(x, u):
    return 0.9 * x + u


P = fj.Problem(_dyn, jnp.array([[-1.0], [0.0], [1.0]]), fj.quadratic_cost(1.0, jnp.zeros(1)), 3,
               terminal=lambda x: jnp.abs(x[0]) < 0.5)


def test_every_option_changes_the_key():
    """A field left out of the key would let two different controllers share one compiled step."""
    base = fj.FIRHC(P).options
    other = {"problem": P.replace(horizon=4), "solver": "pool",
             "solver_options": dict(base.solver_options, pop_width=2), "fallback": "unconstrained",
             "warm_start": True, "observe": lambda x, u: x, "actuate": lambda x, u: u, "u_safe": np.array([1.0])}
    assert set(other) == {f.name for f in dataclasses.fields(Options)}  # a new field needs a line here
    keys = {base.key}
    for name, value in other.items():
        keys.add(dataclasses.replace(base, **{name: value}).key)
    assert len(keys) == 1 + len(other)
    for name in base.solver_options:  # and every solver option
        changed = dict(base.solver_options, **{name: 5 if base.solver_options[name] != 5 else 6})
        assert dataclasses.replace(base, solver_options=changed).key != base.key, name
    # Equal options give equal keys (defaults filled in: pop_width=1 is the default); a budget's value travels
    # with the state, so only whether there is one is in the key.
    assert fj.FIRHC(P, pop_width=1).options.key == fj.FIRHC(P).options.key
    assert fj.FIRHC(P, max_nodes=50).options.key == fj.FIRHC(P, max_nodes=700).options.key != base.key


def test_every_solver_in_the_table_is_a_controller_solver_with_its_own_options():
    for name, solver in solvers.SOLVERS.items():
        ctrl = fj.FIRHC(P, name)
        assert ctrl.solver_options == dict(solver.options)
        with pytest.raises(TypeError, match=f"solver={name!r}"):
            fj.FIRHC(P, name, no_such_option=1)
    with pytest.raises(ValueError, match="solver must be one of"):
        fj.FIRHC(P, "bfs")


@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), solver=st.sampled_from(sorted(solvers.SOLVERS)),
       lanes=st.integers(1, 4), terminal=st.sampled_from(["none", "loose", "tight"]))
def test_every_solver_decides_the_brute_force_optimum(seed, solver, lanes, terminal):
    rp = random_problems.make(seed % 1000, n=2, m=1, M=3, N=3, terminal=terminal)
    options = {"lanes": lanes} if "lanes" in solvers.SOLVERS[solver].options else {}
    ctrl = fj.FIRHC(rp.problem(), solver, fallback="unconstrained", **options)
    x0 = np.random.default_rng(seed).uniform(-1, 1, 2)
    result, used = ctrl.solve(x0)
    cost, _ = rp.brute_force(x0)
    if np.isfinite(cost):
        assert not bool(used)
        np.testing.assert_allclose(float(result.cost), cost, rtol=1e-9)
        np.testing.assert_allclose(rp.sequence_cost(x0, np.asarray(result.sequence)), cost, rtol=1e-9)
    else:
        assert bool(used)  # the fallback decided: the unconstrained optimum
        free = random_problems.make(seed % 1000, n=2, m=1, M=3, N=3)
        np.testing.assert_allclose(float(result.cost), free.brute_force(x0)[0], rtol=1e-9)


@pytest.mark.slow
def test_the_pool_as_a_decision_stays_within_its_budget_and_warm_starts():
    rp = random_problems.make(5, n=2, m=1, M=4, N=4)
    x0 = np.array([0.4, -0.3])
    whole = fj.FIRHC(rp.problem(), "pool", lanes=3, warm_start=True).simulate(x0, 5)
    plain = fj.FIRHC(rp.problem()).simulate(x0, 5)
    np.testing.assert_allclose(np.asarray(whole.predicted_costs), np.asarray(plain.predicted_costs), rtol=1e-12)
    assert not np.asarray(whole.held).any() and int(np.max(np.asarray(whole.nodes))) > 30
    for budget in (12, 30):  # below what the whole search needs
        run = fj.FIRHC(rp.problem(), "pool", lanes=3, max_nodes=budget, warm_start=True).simulate(x0, 5)
        assert int(np.max(np.asarray(run.decision_nodes))) <= budget and not np.asarray(run.complete).all()


def test_max_memory_is_checked_by_the_table_before_compiling():
    with pytest.raises(ValueError, match="solver='pool' .* max_memory=1,000"):
        fj.FIRHC(P, "pool", max_memory=1000).step(fj.FIRHC(P).init(np.zeros(1)), np.zeros(1))
