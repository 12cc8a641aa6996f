"""Parameters on every solver: exact against a brute force for random values,
and new values never retrace."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compiles import compile_count
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from param_problems import SHAPES, as_jax, cases, check_optimal, draw_params, problem
from reference import brute_force, same_cost

import firhc_jax as fj

SETTINGS = settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# pop_width 3 (2 is in tests/problem/test_limits.py): at most five compiled searches per shape serve every example.
# Also run with x64 off (pytest --float32).
@pytest.mark.float32
@SETTINGS
@given(cases())
def test_sdfs_and_exhaustive_with_params_match_brute_force(case):
    shape, params, x0 = case
    p, prm = problem(shape), as_jax(params)
    check_optimal(fj.sdfs(p, x0, params=prm), shape, params, x0, "sdfs")
    check_optimal(fj.sdfs(p, x0, params=prm, pop_width=3), shape, params, x0, "sdfs K=3")
    check_optimal(fj.exhaustive(p, x0, params=prm), shape, params, x0, "exhaustive")
    check_optimal(fj.exhaustive(p, x0, params=prm, method="dfs"), shape, params, x0, "exhaustive dfs")


# The solver options are compile-time constants: one test per option set, each on its own shape (all four
# covered), so that one compiled batch search serves each test's examples.
@pytest.mark.parametrize("solver, pop_width, lanes, shape", [
    ("sdfs", 1, 3, SHAPES[0]), ("sdfs", 2, 1, SHAPES[1]), ("sdfs-vmap", 2, None, SHAPES[2]),
    ("exhaustive", 1, None, SHAPES[3])])
@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2**32 - 1))
def test_solve_batch_with_random_params_per_row_matches_brute_force(solver, pop_width, lanes, shape, seed):
    rng = np.random.default_rng(seed)
    B = 4
    rows = [draw_params(rng, shape, t) for t in ("none", "loose", "tight", "loose")]
    batched = {k: jnp.asarray(np.stack([r[k] for r in rows])) for k in rows[0]}
    X0 = rng.uniform(-1, 1, (B, shape[0]))
    res = fj.solve_batch(problem(shape), X0, params=batched, solver=solver, pop_width=pop_width, lanes=lanes)
    for b in range(B):
        check_optimal(jax.tree_util.tree_map(lambda a, b=b: a[b], res), shape, rows[b], X0[b], f"{solver} row {b}")


def _counting(shape):
    """A problem of ``shape`` whose dynamics count their traces."""
    from param_problems import dynamics, stage_cost, terminal
    traces = []

    def counted(x, u, p):
        if isinstance(x, jax.core.Tracer):  # a trace, not an eager plant step
            traces.append(1)
        return dynamics(x, u, p)

    return fj.Problem(counted, jnp.arange(shape[2], dtype=jnp.float32), stage_cost, shape[3], terminal), traces


@pytest.mark.parametrize("solve", [
    lambda p, x, prm: fj.sdfs(p, x, params=prm),
    lambda p, x, prm: fj.sdfs(p, x, params=prm, max_nodes=50),
    lambda p, x, prm: fj.exhaustive(p, x, params=prm),
    lambda p, x, prm: fj.exhaustive(p, x, params=prm, method="dfs"),
    lambda p, x, prm: fj.solve_batch(p, jnp.stack([x, -x]), params=jax.tree_util.tree_map(
        lambda a: jnp.stack([a, a * 0.5]), prm)),
    lambda p, x, prm: fj.FIRHC(p, fallback="unconstrained")(x, prm),
], ids=["sdfs", "sdfs-budget", "exhaustive", "exhaustive-dfs", "solve_batch", "FIRHC"])
def test_new_param_values_never_retrace(solve):
    shape = SHAPES[1]
    p, traces = _counting(shape)
    rng = np.random.default_rng(0)
    x0 = jnp.asarray(rng.uniform(-1, 1, shape[0]))
    solve(p, x0, as_jax(draw_params(rng, shape)))
    calls = [(x0 * 0.3, as_jax(draw_params(rng, shape))) for _ in range(3)]
    before, compiled = len(traces), compile_count()
    assert before > 0
    for x, prm in calls:
        solve(p, x, prm)
    assert len(traces) == before and compile_count() == compiled


def test_simulate_with_new_params_does_not_retrace():
    shape = SHAPES[0]
    p, traces = _counting(shape)
    rng = np.random.default_rng(1)
    steps = 4
    ctrl = fj.FIRHC(p, fallback="unconstrained")

    def params():
        rows = [draw_params(rng, shape) for _ in range(steps)]
        return {k: jnp.asarray(np.stack([r[k] for r in rows])) for k in rows[0]}

    for compiled in (True, False):
        ctrl.simulate(jnp.zeros(shape[0]), steps, params=params(), compiled=compiled)
        x0, x1, p1, p2 = jnp.full(shape[0], 0.2, jnp.float64), jnp.zeros(shape[0]), params(), params()
        before, count = len(traces), compile_count()
        ctrl.simulate(x0, steps, params=p1, compiled=compiled)
        fj.FIRHC(p, fallback="unconstrained").simulate(x1, steps, params=p2,
                                                       compiled=compiled)  # a second controller, same problem
        assert len(traces) == before and compile_count() == count, compiled


# ----------------------------------------------------------------- closed loop with a moving reference
def _tracking():
    """A 2-state plant tracking a reference ``p["ref"]`` [N, 2] that moves within
    the horizon: the model state carries the step within the horizon."""
    N = 3
    U = np.array([-1.0, -0.3, 0.0, 0.4, 1.0])

    def plant(x, u):
        return np.array([x[0] + 0.1 * x[1], 0.9 * x[1] + 0.2 * u[0]])

    def dynamics(z, u, p):
        x, k = z[:2], z[2]
        x_next = jnp.stack([x[0] + 0.1 * x[1], 0.9 * x[1] + 0.2 * u[0]])
        return jnp.concatenate([x_next, (k + 1)[None]])

    def stage_cost(z, u, p):
        ref = p["ref"][jnp.clip(z[2].astype(int) - 1, 0, N - 1)]
        return jnp.sum((z[:2] - ref) ** 2) + p["w"] * u[0] ** 2

    def observe(x, u_prev, p):
        return jnp.concatenate([x, jnp.zeros(1, x.dtype)])

    return N, U, plant, fj.Problem(dynamics, U, stage_cost, N), observe


def test_closed_loop_with_moving_reference_matches_brute_force_receding_horizon():
    N, U, plant_np, prob, observe = _tracking()
    steps = 12
    t = np.arange(steps + N)
    ref = np.stack([0.5 * np.sin(0.4 * t), 0.2 * np.cos(0.4 * t)], 1)
    refs = np.stack([ref[k + 1:k + 1 + N] for k in range(steps)])  # [steps, N, 2]: step k sees ref(k+1..k+N)
    w = np.linspace(0.01, 0.2, steps)
    ctrl = fj.FIRHC(prob, observe=observe)
    run = ctrl.simulate(jnp.zeros(2), steps, plant=lambda x, u, p: jnp.stack(
        [x[0] + 0.1 * x[1], 0.9 * x[1] + 0.2 * u[0]]), params={"ref": jnp.asarray(refs), "w": jnp.asarray(w)})
    # The brute-force receding horizon loop, in NumPy: step k's horizon step t tracks refs[k, t].
    x = np.zeros(2)
    for k in range(steps):
        def step(z, u, t, k=k):
            z = np.stack([z[..., 0] + 0.1 * z[..., 1], 0.9 * z[..., 1] + 0.2 * u[..., 0]], -1)
            return z, np.sum((z - refs[k, t]) ** 2, -1) + w[k] * u[..., 0] ** 2

        best, seq = brute_force(step, U, x, N)
        assert same_cost(run.predicted_costs[k], best), k
        assert int(run.input_indices[k]) == seq[0], k
        x = plant_np(x, U[seq[0]:seq[0] + 1])
        np.testing.assert_allclose(np.asarray(run.states[k + 1]), x, rtol=1e-12, atol=1e-12)


def test_switching_penalty_matches_brute_force():
    """with_input_memory: lambda_u |u(k) - u(k-1)| inside the horizon and at its
    first step (against the input applied last)."""
    U = np.array([-1.0, 0.0, 1.0])
    N, lam = 3, 0.7

    def dyn(x, u):
        return jnp.stack([0.8 * x[0] + 0.3 * u[0]])

    base = fj.Problem(dyn, U, lambda x, u: (x[0] - 0.5) ** 2, N)
    mem = fj.with_input_memory(base, lambda u, u_prev: lam * jnp.sum(jnp.abs(u - u_prev)))

    def step(z, u, t):  # z = [x, the input applied last]
        x = 0.8 * z[..., :1] + 0.3 * u
        return np.concatenate([x, u], -1), (x[..., 0] - 0.5) ** 2 + lam * np.abs(u[..., 0] - z[..., 1])

    for x0, u_prev in ((0.0, -1.0), (0.4, 1.0), (-0.3, 0.0)):
        best, _ = brute_force(step, U, [x0, u_prev], N)
        z0 = mem.observe(jnp.array([x0]), jnp.array([u_prev]))
        for r in (fj.sdfs(mem.problem, z0), fj.exhaustive(mem.problem, z0)):
            assert same_cost(r.cost, best, rtol=1e-12), (x0, u_prev, float(r.cost), best)
    # In closed loop the applied input reaches the next decision: a large penalty holds the input.
    stiff = fj.with_input_memory(base, lambda u, u_prev: 100.0 * jnp.sum(jnp.abs(u - u_prev)))
    held = fj.FIRHC(stiff.problem, observe=stiff.observe).simulate(jnp.array([0.5]), 6, plant=dyn,
                                                                    u0=jnp.array([1.0]))
    assert np.all(np.asarray(held.inputs)[:, 0] == 1.0)
    free = fj.FIRHC(fj.with_input_memory(base, lambda u, u_prev: 0.0 * jnp.sum(u)).problem,
                    observe=mem.observe).simulate(jnp.array([0.5]), 6, plant=dyn, u0=jnp.array([1.0]))
    assert not np.all(np.asarray(free.inputs)[:, 0] == 1.0)


@pytest.mark.float32
def test_values_beyond_float32_are_refused_naming_the_leaf_with_x64_off():
    """With x64 off a finite float64 1e39 would be cast to inf and searched as inf (every state infeasible,
    "complete"): every entry point refuses it, naming the leaf; an int64 beyond int32 would wrap around."""
    if jax.config.jax_enable_x64:
        pytest.skip("the cast narrows only with x64 off (pytest --float32)")
    prob = fj.Problem(lambda x, u, p: x + u, jnp.array([-1.0, 0.0, 1.0]),
                      lambda x, u, p: 1e-30 * jnp.sum(jnp.abs(x - p["ref"])), 2)
    x0 = np.zeros(1, np.float32)
    with pytest.raises(ValueError, match=r"params leaf \['ref'\] holds 1e\+39, beyond the range of float32"):
        fj.sdfs(prob, x0, params={"ref": np.array([1e39])})
    with pytest.raises(ValueError, match=r"params leaf \['ref'\] holds 1e\+39, beyond the range of float32"):
        fj.solve_batch(prob, np.zeros((3, 1)), params={"ref": np.array([[0.0], [1e39], [0.0]])})
    with pytest.raises(ValueError, match=r"params leaf \['ref'\] holds 1e\+39"):
        fj.FIRHC(prob).simulate(x0, 2, params={"ref": np.full((2, 1), -1e39)})
    with pytest.raises(ValueError, match=r"x0 holds 1e\+39, beyond the range of float32"):
        fj.sdfs(prob, np.array([1e39]), params={"ref": np.zeros(1)})
    with pytest.raises(ValueError, match=r"X0 holds 1e\+39, beyond the range of float32 .* in rows \[1\]"):
        fj.solve_batch(prob, np.array([[0.0], [1e39]]), params={"ref": np.zeros((2, 1))})
    with pytest.raises(ValueError, match=r"params leaf \['k'\] holds 1.1e\+12, beyond the range of int32"):
        fj.sdfs(prob.replace(stage_cost=lambda x, u, p: jnp.sum(x ** 2) * p["k"]), x0, params={"k": np.int64(2**40)})
    result = fj.sdfs(prob, x0, params={"ref": np.array([3e38])})  # within float32's range: solved
    assert bool(result.feasible) and np.isfinite(float(result.cost))
