"""Input validation, error reporting, retracing and the FIRHC controller."""
import subprocess
import sys
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compiles import compile_count
from random_problems import make
from reference import same_cost

import firhc_jax as fj


def dyn(x, u):
    return jnp.stack([x[0] + 0.1 * x[1], x[1] + 0.1 * u[0]])


COST = fj.quadratic_cost(jnp.array([1.0, 0.1]), jnp.zeros(2), 0.01)
CONTROLS = jnp.array([-1.0, 0.0, 1.0])
X0 = jnp.array([1.0, 0.0])


def problem(**kw):
    args = dict(dynamics=dyn, controls=CONTROLS, stage_cost=COST, horizon=4)
    args.update(kw)
    return fj.Problem(**args)


# ---------------------------------------------------------------- bad input
@pytest.mark.parametrize("controls, match", [
    (jnp.zeros((0,)), "empty"), (jnp.zeros((0, 2)), "empty"), (jnp.zeros((2, 2, 2)), "1-D .* or 2-D"),
    (jnp.zeros(()), "1-D .* or 2-D"), (jnp.array([1.0, jnp.nan]), "NaN"), (jnp.zeros((3, 0)), "dimension 0")])
def test_bad_controls(controls, match):
    with pytest.raises(ValueError, match=match):
        problem(controls=controls)


@pytest.mark.parametrize("horizon, exc", [(0, ValueError), (-3, ValueError), (2.5, TypeError), ("3", TypeError),
                                          (True, TypeError), (None, TypeError)])
def test_bad_horizon(horizon, exc):
    with pytest.raises(exc, match="horizon"):
        problem(horizon=horizon)


def test_numpy_int_horizon_is_accepted():
    assert problem(horizon=np.int64(3)).horizon == 3


def test_traced_controls_are_refused():
    with pytest.raises(TypeError, match="concrete"):
        jax.jit(lambda c: problem(controls=c).horizon)(CONTROLS)


def test_callables_must_be_callable():
    with pytest.raises(TypeError, match="dynamics"):
        problem(dynamics=3)
    with pytest.raises(TypeError, match="terminal"):
        problem(terminal="x")


def test_x0_shape_mismatch_names_both_shapes():
    with pytest.raises(ValueError, match=r"\(3,\).*\(2,\)|\(2,\).*\(3,\)"):
        fj.sdfs(problem(dynamics=lambda x, u: x[:2] + u), jnp.zeros(3))
    with pytest.raises(ValueError, match="1-D"):
        fj.sdfs(problem(), jnp.zeros((2, 2)))


def test_dynamics_changing_dtype():
    with pytest.raises(TypeError, match="dtype"):
        fj.sdfs(problem(dynamics=lambda x, u: dyn(x, u).astype(jnp.float32)), X0)


def test_dynamics_raising_is_named():
    with pytest.raises(TypeError, match="dynamics"):
        fj.sdfs(problem(dynamics=lambda x, u: x @ jnp.ones((5, 5))), X0)


def test_stage_cost_not_scalar():
    with pytest.raises(ValueError, match="scalar"):
        fj.sdfs(problem(stage_cost=lambda x, u: x**2), X0)


@pytest.mark.parametrize("terminal", [lambda x: x[0], lambda x: x < 1.0, lambda x: jnp.sum(x) < 1.0 + 0.0 * x])
def test_terminal_not_boolean_scalar(terminal):
    with pytest.raises(TypeError, match="terminal"):
        fj.sdfs(problem(terminal=terminal), X0)


def test_nan_and_integer_x0():
    with pytest.raises(ValueError, match="NaN"):
        fj.sdfs(problem(), jnp.array([jnp.nan, 0.0]))
    with pytest.raises(TypeError, match="floating"):
        fj.sdfs(problem(), jnp.array([1, 0]))


@pytest.mark.parametrize("solve", [fj.sdfs, fj.exhaustive, lambda p, x: fj.exhaustive(p, x, method="dfs")])
def test_negative_stage_cost_raises(solve):
    p = problem(stage_cost=lambda x, u: x[0] - 2.0)
    with pytest.raises(ValueError, match="negative"):
        solve(p, X0)
    # Under jit the flag is in the result instead.
    assert bool(jax.jit(lambda x: solve(p, x))(X0).negative_cost)


def test_nan_nodes_are_discarded_and_reported():
    # Input 0 drives the state to NaN; the optimum must avoid it, and a warning says so.
    p = problem(dynamics=lambda x, u: jnp.where(u[0] < -0.5, jnp.nan, dyn(x, u)))
    for solve in (fj.sdfs, fj.exhaustive):
        with pytest.warns(RuntimeWarning, match="NaN"):
            r = solve(p, X0)
        assert bool(r.nan_encountered) and bool(r.feasible) and np.isfinite(float(r.cost))
        assert 0 not in np.asarray(r.sequence)


def test_infeasible_is_reported_not_invented():
    p = problem(terminal=lambda x: x[0] > 100.0)
    for r in (fj.sdfs(p, X0), fj.exhaustive(p, X0), fj.sdfs(p, X0, pop_width=2)):
        assert not bool(r.feasible) and np.isinf(float(r.cost))
        assert np.all(np.asarray(r.sequence) == -1) and np.all(np.isnan(r.first_input))


def test_bad_search_options():
    with pytest.raises(ValueError, match="pop_width"):
        fj.sdfs(problem(), X0, pop_width=0)
    with pytest.raises(ValueError, match="warm_start"):
        fj.sdfs(problem(), X0, warm_start=[0, 1])
    with pytest.raises(ValueError, match="warm_start"):
        fj.sdfs(problem(), X0, warm_start=[0, 1, 2, 3])
    with pytest.raises(ValueError, match="method"):
        fj.exhaustive(problem(), X0, method="bfs")


def test_exhaustive_refuses_what_cannot_fit_before_allocating():
    big = problem(controls=jnp.linspace(-1, 1, 17), horizon=9)
    with pytest.raises(ValueError, match="int32|does not fit"):
        fj.exhaustive(big, X0)
    with pytest.raises(ValueError, match="does not fit"):
        fj.exhaustive(problem(controls=jnp.linspace(-1, 1, 17), horizon=6), X0, chunk_nodes=1000)


def test_float32_problem_stays_float32():
    p = problem(controls=CONTROLS.astype(jnp.float32))
    r = fj.sdfs(p, X0.astype(jnp.float32))
    assert r.cost.dtype == jnp.float32
    r64 = fj.sdfs(problem(), X0)
    assert same_cost(r.cost, r64.cost, rtol=1e-5)


# ---------------------------------------------------------------- retracing
def test_same_problem_twice_does_not_retrace():
    traces = []

    def counting_dyn(x, u):
        traces.append(1)
        return dyn(x, u)

    p = problem(dynamics=counting_dyn)
    # NumPy, JAX and weakly typed JAX states of one dtype share one search (eager calls keep NumPy states NumPy).
    states = (X0 + 0.5, np.asarray(X0), jnp.asarray(X0), jnp.full(np.shape(X0), 0.3), list(np.asarray(X0)))
    for solve in (fj.sdfs, fj.exhaustive, lambda p, x: fj.sdfs(p, x, pop_width=2)):
        solve(p, X0)
        before, compiled = len(traces), compile_count()
        # A rebuilt Problem with the same callables and control values reuses the compiled search too.
        solve(fj.Problem(counting_dyn, np.asarray(CONTROLS), COST, 4), X0)
        for x in states:
            solve(p, x)
        assert len(traces) == before, "the second solve re-traced dynamics"
        assert compile_count() == compiled, "the second solve compiled again"
    # Other control values are compiled in as constants: that is a new search (dynamics, whose arguments have
    # the same shapes, is not traced again).
    fj.sdfs(fj.Problem(counting_dyn, CONTROLS * 2, COST, 4), X0)
    assert compile_count() > compiled


def test_closed_loop_does_not_retrace():
    traces = []

    def counting_dyn(x, u):
        traces.append(1)
        return dyn(x, u)

    ctrl = fj.FIRHC(problem(dynamics=counting_dyn))
    ctrl.simulate(X0, 5)
    x0 = X0 * 0.5
    before, compiled = len(traces), compile_count()
    ctrl.simulate(x0, 5)
    assert len(traces) == before and compile_count() == compiled


# ---------------------------------------------------------------- controller
def test_firhc_closed_loop_sdfs_equals_exhaustive_and_reaches_target():
    p = problem(horizon=5, terminal=lambda x: jnp.abs(x[0]) < 0.97)
    a = fj.FIRHC(p).simulate(X0, 40)
    b = fj.FIRHC(p, "exhaustive").simulate(X0, 40)
    c = fj.FIRHC(p, warm_start=True).simulate(X0, 40)
    np.testing.assert_array_equal(a.input_indices, b.input_indices)
    np.testing.assert_array_equal(a.input_indices, c.input_indices)
    assert np.all(np.asarray(b.nodes) == p.tree_size())
    assert np.all(np.asarray(a.nodes) <= p.tree_size()) and bool(np.all(a.feasible))
    assert abs(float(a.states[-1, 0])) < 0.05
    assert a.states.shape == (41, 2) and a.inputs.shape == (40, 1)


def test_firhc_call_applies_first_input():
    ctrl = fj.FIRHC(problem())
    u, info = ctrl(X0)
    np.testing.assert_array_equal(u, CONTROLS[int(info.result.sequence[0])][None])
    assert not bool(info.used_fallback) and not bool(info.held)


def test_firhc_python_loop_matches_compiled_loop_with_other_plant():
    plant = lambda x, u: dyn(x, u) * 0.99  # model error  # noqa: E731
    ctrl = fj.FIRHC(problem())
    a = ctrl.simulate(X0, 10, plant)
    b = ctrl.simulate(X0, 10, lambda x, u: np.asarray(plant(x, u)), compiled=False)
    np.testing.assert_array_equal(a.input_indices, b.input_indices)
    np.testing.assert_allclose(a.states, b.states, rtol=1e-12)


def test_firhc_infeasible_without_and_with_fallback():
    p = problem(terminal=lambda x: x[0] > 100.0)
    with pytest.raises(fj.InfeasibleError):
        fj.FIRHC(p)(X0)
    with pytest.warns(RuntimeWarning, match="no feasible"):
        run = fj.FIRHC(p).simulate(X0, 3)
    assert run.first_infeasible_step == 0 and np.all(run.held) and np.all(np.asarray(run.inputs) == 0)  # u0 held
    fb = fj.FIRHC(p, fallback="unconstrained").simulate(X0, 3)
    assert not np.any(fb.feasible) and np.all(fb.used_fallback) and np.all(np.isfinite(fb.inputs))
    free = fj.FIRHC(problem()).simulate(X0, 3)
    np.testing.assert_array_equal(fb.input_indices, free.input_indices)


def test_firhc_bad_options():
    with pytest.raises(ValueError, match="solver"):
        fj.FIRHC(problem(), "bfs")
    with pytest.raises(ValueError, match="fallback"):
        fj.FIRHC(problem(), fallback="hold")
    with pytest.raises(ValueError, match="steps"):
        fj.FIRHC(problem()).simulate(X0, 0)


def test_progress_bar_reports_from_compiled_loop(capsys, ticks):
    """Every step of a compiled closed loop ticks the bar (the bar's own exit would show 4/4 anyway), and
    with progress off the compiled loop has no host callback at all."""
    for compiled in (True, False):
        ticks.clear()
        fj.FIRHC(problem()).simulate(X0, 4, progress=True, compiled=compiled)
        assert ticks == [0, 1, 2, 3], compiled
    assert "4/4" in capsys.readouterr().err
    ticks.clear()
    fj.FIRHC(problem()).simulate(X0, 5, progress=False)
    assert ticks == []


def test_cli_help():
    out = subprocess.run([sys.executable, "-m", "firhc_jax", "--help"], capture_output=True, text=True, check=True)
    assert "example" in out.stdout


def test_public_api():
    for name in ("Problem", "quadratic_cost", "sdfs", "exhaustive", "FIRHC", "SearchResult"):
        assert hasattr(fj, name)
    with pytest.raises(ValueError, match="non-negative"):
        fj.quadratic_cost(-1.0, 0.0)
    # x64 is on here (conftest); a fresh interpreter shows that importing the library does not turn it on.
    out = subprocess.run([sys.executable, "-c", "import jax, firhc_jax; print(jax.config.jax_enable_x64)"],
                         capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_random_problem_warns_nothing_normally():
    rp = make(1, 2, 1, 3, 3, "loose")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fj.sdfs(rp.problem(), np.array([0.1, 0.1]))
