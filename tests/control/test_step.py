"""One decision at a time: ``init``/``step`` is the closed loop's own code path, pure, cheap to call
eagerly, and within the decision's node budget."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compiles import compile_count
from loops import PROBLEM, actuate, counting_controller, observe, plant

import firhc_jax as fj

T = 12


def per_step_params():
    k = np.arange(T)
    return {"ref": jnp.asarray(0.5 * np.sin(0.5 * k)), "gain": jnp.asarray(1.0 + 0.05 * np.cos(k)),
            "band": jnp.asarray(np.where(k % 4 == 1, 1e-6, 0.6))}


@pytest.fixture(scope="module")
def ctrl():
    return fj.FIRHC(PROBLEM, fallback="unconstrained", warm_start=True, observe=observe, actuate=actuate)


def _row(params, k):
    return jax.tree_util.tree_map(lambda a: a[k], params)


def test_a_python_loop_of_step_is_simulate_bit_for_bit(ctrl):
    """The user's loop runs the plant jitted, as simulate compiles it (an eager plant of several operations
    can round differently in the last bit where XLA fuses a multiply and an add)."""
    params, x0, u0 = per_step_params(), jnp.array([0.8, 0.0]), jnp.array([1.0])
    jitted = jax.jit(plant)
    runs = [ctrl.simulate(x0, T, plant, params=params, u0=u0),
            ctrl.simulate(x0, T, jitted, params=params, u0=u0, compiled=False)]
    state, x, xs, us, infos = ctrl.init(x0, u0), x0, [x0], [], []
    for k in range(T):
        u, state, info = ctrl.step(state, x, _row(params, k))
        x = jitted(x, u, _row(params, k))
        xs.append(x), us.append(u), infos.append(info)
    for run in runs:
        np.testing.assert_array_equal(np.asarray(run.states), np.stack(xs))
        np.testing.assert_array_equal(np.asarray(run.inputs), np.stack(us))
        np.testing.assert_array_equal(np.asarray(run.plans), np.stack([i.result.sequence for i in infos]))
        np.testing.assert_array_equal(np.asarray(run.used_fallback), [bool(i.used_fallback) for i in infos])
    # The case covers what it claims: the fallback decided some steps and not others, the plant's input has
    # two entries, and the plant is not the model.
    used = np.asarray(runs[0].used_fallback)
    assert used.any() and not used.all() and runs[0].inputs.shape == (T, 2) and not np.asarray(runs[0].held).any()


@pytest.mark.optimized
def test_step_under_jit_vmap_and_scan(ctrl):
    params = per_step_params()
    X = jnp.array([[0.8, 0.0], [-0.4, 0.3], [0.1, -0.2]])
    U = jnp.array([[1.0], [0.0], [-1.0]])
    p0 = _row(params, 0)
    eager = [ctrl.step(ctrl.init(x, u), x, p0) for x, u in zip(X, U, strict=True)]
    states = jax.vmap(ctrl.init)(X, U)
    u, _, info = jax.jit(jax.vmap(ctrl.step, in_axes=(0, 0, None)))(states, X, p0)
    for b, (ue, _, ie) in enumerate(eager):
        np.testing.assert_array_equal(np.asarray(u[b]), np.asarray(ue))
        assert int(info.result.sequence[b, 0]) == int(ie.result.sequence[0])

    def body(carry, p):
        state, x = carry
        u, state, _ = ctrl.step(state, x, p)
        return (state, plant(x, u, p)), x

    x0 = X[0]
    (_, x_end), _ = jax.lax.scan(body, (ctrl.init(x0, U[0]), x0), params)
    run = ctrl.simulate(x0, T, plant, params=params, u0=U[0])
    np.testing.assert_array_equal(np.asarray(x_end), np.asarray(run.states[-1]))


def test_eager_steps_never_retrace_or_recheck():
    """Numpy, JAX and weakly typed states and parameters of one dtype share one compiled step, and checks
    run while it compiles, not per call."""
    traces = []
    ctrl = counting_controller(traces)
    p = {"ref": np.float64(0.2), "gain": jnp.asarray(1.0, jnp.float64), "band": np.asarray(0.5)}
    state = ctrl.init(np.array([0.5, 0.0]))
    u, state, _ = ctrl.step(state, np.array([0.5, 0.0]), p)
    calls = ((jnp.array([0.4, 0.1]), {"ref": 0.1, "gain": 1.0, "band": 0.5}),  # Python floats: weak
             (jnp.full(2, 0.3), dict(p, ref=jnp.asarray(0.3))),  # weakly typed JAX arrays
             ([0.2, 0.1], p))
    before, compiled = len(traces), compile_count()
    for x, q in calls:
        u, state, info = ctrl.step(state, x, q)
    assert len(traces) == before and compile_count() == compiled
    with pytest.raises(TypeError, match="ControllerState"):
        ctrl.step((state.u, state.plan), np.zeros(2), p)
    with pytest.raises(ValueError, match="x0 .*shape|shape.*x0|observe"):
        ctrl.step(state, np.zeros(3), p)  # a state of the wrong size is caught when its step compiles
    with pytest.raises(TypeError, match="params"):
        ctrl.step(state, np.zeros(2), dict(p, ref="a"))


@pytest.mark.parametrize("budget", [20, 37, 60])
def test_max_nodes_bounds_the_whole_decision(budget):
    """The fallback search gets what the first one left: nodes + fallback_nodes <= max_nodes."""
    # The terminal set is out of reach and the bound says so at the root's children (+inf): the first search
    # ends after M nodes and every decision falls back, within what is left.
    prob = fj.Problem(lambda x, u: 0.5 * x + u, np.linspace(-1, 1, 4), fj.quadratic_cost(1.0, 0.0), 4,
                      terminal=lambda x: x[0] > 100.0, lower_bound=lambda x, steps_left: jnp.inf + 0 * x[0])
    ctrl = fj.FIRHC(prob, fallback="unconstrained", max_nodes=budget)
    run = ctrl.simulate(jnp.array([0.7]), 3)
    total = np.asarray(run.nodes) + np.asarray(run.fallback_nodes)
    assert (total <= budget).all() and (np.asarray(run.fallback_nodes) > 0).any(), total
    assert np.array_equal(np.asarray(run.decision_nodes), total)
    _, _, info = ctrl.step(ctrl.init(jnp.array([0.7])), jnp.array([0.7]))
    assert int(info.decision_nodes) <= budget and bool(info.used_fallback)
    assert not np.asarray(run.held).any()  # the fallback found a sequence within what was left


def test_one_shot_call_is_the_first_step_and_reports_the_fallback(ctrl):
    p, x = _row(per_step_params(), 1), jnp.array([0.8, 0.0])  # step 1's band is out of reach
    u, info = ctrl(x, p, u_prev=jnp.array([1.0]))
    u_step, _, info_step = ctrl.step(ctrl.init(x, jnp.array([1.0])), x, p)
    np.testing.assert_array_equal(np.asarray(u), np.asarray(u_step))
    assert float(info.result.cost) == float(info_step.result.cost)
    assert float(info.result.cost) != float(ctrl(x, p)[1].result.cost)  # u_prev reached observe
    assert bool(info.used_fallback) and bool(info_step.used_fallback) and not bool(info.feasible)
    result, used = ctrl.solve(observe(x, jnp.array([1.0]), p), p)
    assert bool(used) and int(result.sequence[0]) == int(info.result.sequence[0])


@pytest.mark.slow
def test_default_float32_path():
    """Without x64 (the suite turns it on): step == simulate bit for bit, and a decision that finds nothing
    holds a finite input."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent("""
        import warnings
        import jax, jax.numpy as jnp, numpy as np
        import firhc_jax as fj
        assert not jax.config.jax_enable_x64
        prob = fj.Problem(lambda x, u: jnp.stack([x[0] + 0.1 * x[1], x[1] + 0.1 * u[0]]), [-1.0, 0.0, 1.0],
                          fj.quadratic_cost(jnp.array([1.0, 0.1]), jnp.zeros(2), 0.01), 3,
                          terminal=lambda x: jnp.abs(x[0]) < 0.9)
        ctrl = fj.FIRHC(prob, fallback="unconstrained", warm_start=True)
        plant = jax.jit(lambda x, u: jnp.stack([x[0] + 0.1 * x[1], 0.98 * x[1] + 0.1 * u[0]]))
        x0 = np.array([1.0, 0.0], np.float32)
        run = ctrl.simulate(x0, 10, plant)
        state, x, xs = ctrl.init(x0), x0, [x0]
        for k in range(10):
            u, state, info = ctrl.step(state, x)
            x = plant(x, u)
            xs.append(x)
        assert run.states.dtype == jnp.float32 and np.array_equal(np.asarray(run.states), np.stack(xs))
        assert np.asarray(run.used_fallback).any()
        stuck = fj.FIRHC(prob.replace(terminal=lambda x: x[0] > 50.0), u_safe=[0.0])
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            out = stuck.simulate(x0, 3, plant)
        assert np.asarray(out.held).all() and np.isfinite(np.asarray(out.inputs)).all() and w
        print("ok")
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.stdout.strip().endswith("ok"), out.stdout + out.stderr
