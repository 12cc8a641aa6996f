"""The MPC formulation: step indices along the horizon, terminal cost,
hard constraints, matrix weights, in every solver, against a brute force
written here.

One problem family covers every feature: its random numbers are parameters,
so each solver compiles once for all hypothesis examples, and each feature is
switched off by parameter values (zero reference and disturbance, zero
terminal weight, a constraint far away, a terminal set that holds everywhere).
"""
from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference
from compiles import compile_count
from hypothesis import given, settings
from hypothesis import strategies as st
from repository import DOCS

import firhc_jax as fj

N, M, n = 3, 3, 2
CONTROLS = np.array([-1.0, 0.0, 1.0])
FAR = 1e6  # a constraint or terminal radius that never binds (params must be finite)


# --- the problem, in JAX and in NumPy -------------------------------------------------
def dynamics(x, u, k, p):  # a disturbance along the horizon
    z = p["W"] @ x + p["V"] * u[0]
    return jnp.tanh(z) * p["a"] + p["d"][k]


def stage_cost(x_next, u, k, p):  # a reference along the horizon, a full weight matrix
    e = x_next - p["ref"][k]
    return e @ p["Q"] @ e + p["r"] * u[0] ** 2 + p["w"][k]


def constraint(x_next, u, k, p):  # a limit that may change along the horizon
    return x_next[0] <= p["xmax"][k]


def terminal(x, p):
    return jnp.sum(x**2) < p["radius"]


def terminal_cost(x, p):
    return p["g"] * jnp.sum((x - p["ref"][-1]) ** 2)


PROBLEM = fj.Problem(dynamics, CONTROLS, stage_cost, N, terminal, terminal_cost=terminal_cost,
                     constraint=constraint, step_index=True)


def np_rollout(p, x0, seq):
    """``(cost, margin)`` of one index sequence in plain NumPy, without the feasibility test: ``margin`` is
    the smallest slack of the constraints and the terminal set (< 0: infeasible)."""
    x, total, margin = np.asarray(x0, float), 0.0, np.inf
    for k, i in enumerate(seq):
        u = CONTROLS[i]
        x = np.tanh(p["W"] @ x + p["V"] * u) * p["a"] + p["d"][k]
        margin = min(margin, p["xmax"][k] - x[0])
        e = x - p["ref"][k]
        total += e @ p["Q"] @ e + p["r"] * u**2 + p["w"][k]
    margin = min(margin, p["radius"] - np.sum(x**2))
    return total + p["g"] * np.sum((x - p["ref"][-1]) ** 2), margin


def np_cost(p, x0, seq):
    """Cost of one index sequence: +inf if a constraint or the terminal set fails."""
    cost, margin = np_rollout(p, x0, seq)
    return cost if margin > 0 else np.inf


def brute_force(p, x0):
    return min(np_cost(p, x0, s) for s in itertools.product(range(M), repeat=N))


@st.composite
def instances(draw):
    """(x0, params) with each feature on or off."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    L = rng.normal(size=(n, n)) * draw(st.sampled_from([0.0, 1.0]))  # Q = diag + L L': full or diagonal
    p = {"W": rng.normal(0, 0.8, (n, n)), "V": rng.normal(0, 1.0, n), "a": rng.uniform(0.5, 1.5, n),
         "d": rng.normal(0, 0.3, (N, n)) * draw(st.sampled_from([0.0, 1.0])),
         "ref": rng.normal(0, 0.5, (N, n)) * draw(st.sampled_from([0.0, 1.0])),
         "Q": np.diag(rng.uniform(0, 2, n)) + L @ L.T, "r": rng.uniform(0, 0.5),
         "w": rng.uniform(0, 0.2, N),
         "xmax": np.full(N, FAR) if draw(st.booleans()) else rng.normal(draw(st.sampled_from([0.3, -3.0])), 0.3, N),
         "radius": FAR if draw(st.booleans()) else rng.uniform(0.05, 1.0),
         "g": rng.uniform(0, 3) * draw(st.sampled_from([0.0, 1.0]))}
    return rng.normal(0, 0.7, n), p


def check(result, p, x0, expected=None):
    """``result`` is the optimum. With x64 off (``pytest --float32``) the reference runs in float64 on the
    float32 values the library saw, a sequence within 1e-4 of a constraint's or the terminal set's edge
    counts as either side, and costs agree to float32 rounding."""
    if jax.config.jax_enable_x64:
        assert reference.same_cost(result.cost, expected), (float(result.cost), expected)
        assert bool(result.feasible) == np.isfinite(expected)
        if np.isfinite(expected):
            assert reference.same_cost(np_cost(p, x0, np.asarray(result.sequence)), expected)  # it achieves it
        else:
            assert np.all(np.asarray(result.sequence) == -1) and np.all(np.isnan(result.first_input))
        return
    assert result.cost.dtype == np.float32
    seen = jax.tree_util.tree_map(lambda a: np.asarray(a, np.float32).astype(float), (p, x0))
    rolled = [np_rollout(*seen, s) for s in itertools.product(range(M), repeat=N)]
    high = min((c for c, m in rolled if m > 1e-4), default=np.inf)  # surely feasible
    low = min((c for c, m in rolled if m > -1e-4), default=np.inf)  # maybe feasible
    if np.isfinite(high):
        assert bool(result.feasible)
    if not bool(result.feasible):
        assert not np.isfinite(low) or not np.isfinite(high)
        assert np.all(np.isnan(result.first_input))
        return
    cost = float(result.cost)
    assert low * (1 - 1e-4) - 1e-4 <= cost <= high * (1 + 1e-4) + 1e-4, (cost, low, high)
    c, m = np_rollout(*seen, np.asarray(result.sequence))
    assert m > -1e-4 and abs(c - cost) <= 1e-4 * max(1.0, abs(c))


SINGLE = {
    "sdfs": lambda x, p: fj.sdfs(PROBLEM, x, params=p),
    "sdfs K=2": lambda x, p: fj.sdfs(PROBLEM, x, params=p, pop_width=2),
    "exhaustive": lambda x, p: fj.exhaustive(PROBLEM, x, params=p),
    "exhaustive dfs": lambda x, p: fj.exhaustive(PROBLEM, x, params=p, method="dfs"),
}


@pytest.mark.float32
@pytest.mark.parametrize("solver", sorted(SINGLE))
@settings(max_examples=30, deadline=None)
@given(instances())
def test_single_solvers_match_brute_force(solver, inst):
    x0, p = inst
    check(SINGLE[solver](x0, p), p, x0, brute_force(p, x0) if jax.config.jax_enable_x64 else None)


@pytest.mark.float32
@pytest.mark.parametrize("solver", ["sdfs", "sdfs-vmap", "exhaustive"])
@settings(max_examples=10, deadline=None)
@given(instances(), instances())
def test_solve_batch_matches_brute_force(solver, a, b):
    X0 = np.stack([a[0], b[0]])
    params = jax.tree_util.tree_map(lambda u, v: np.stack([u, v]), a[1], b[1])
    out = fj.solve_batch(PROBLEM, X0, params=params, solver=solver)
    for i, (x0, p) in enumerate((a, b)):
        expected = brute_force(p, x0) if jax.config.jax_enable_x64 else None
        check(jax.tree_util.tree_map(lambda f, i=i: f[i], out), p, x0, expected)


@settings(max_examples=15, deadline=None)
@given(instances(), st.lists(st.integers(0, M - 1), min_size=N, max_size=N))
def test_warm_start_and_rollout_cost_include_every_term(inst, seq):
    x0, p = inst
    cost, _ = fj.rollout_cost(PROBLEM, jnp.asarray(x0), jnp.asarray(seq, jnp.int32), jnp.float64,
                                      jax.tree_util.tree_map(jnp.asarray, p))
    assert reference.same_cost(cost, np_cost(p, x0, seq))
    check(fj.sdfs(PROBLEM, x0, params=p, warm_start=np.array(seq)), p, x0, brute_force(p, x0))


def test_every_child_discarded_is_infeasible_never_a_made_up_input():
    x0, rng = np.zeros(n), np.random.default_rng(0)
    p = {"W": rng.normal(0, 0.8, (n, n)), "V": rng.normal(0, 1.0, n), "a": np.ones(n), "d": np.zeros((N, n)),
         "ref": np.zeros((N, n)), "Q": np.eye(n), "r": 0.1, "w": np.zeros(N), "xmax": np.full(N, -5.0),
         "radius": FAR, "g": 0.0}  # tanh * 1 >= -1 > -5: every child breaks the constraint
    for name, solve in SINGLE.items():
        r = solve(x0, p)
        assert not bool(r.feasible) and np.isinf(r.cost) and np.all(np.isnan(r.first_input)), name
        assert not bool(r.nan_encountered), name  # a discarded child is no numerical error
    assert int(fj.sdfs(PROBLEM, x0, params=p).nodes) == M  # the root's children, none expanded


def test_matrix_weights_are_quadratic_forms():
    Q = np.array([[2.0, 1.0], [1.0, 2.0]])
    cost = fj.quadratic_cost(lam=Q, x_s=np.zeros(2))
    assert float(cost(jnp.array([1.0, -1.0]), jnp.zeros(1))) == pytest.approx(2.0)  # dx' Q dx, not 6
    R = np.array([[1.0, 0.5], [0.5, 1.0]])
    cost = fj.quadratic_cost(lam=1.0, x_s=np.zeros(1), beta=R, u_e=np.array([0.5, 0.0]))
    du = np.array([1.0, 2.0]) - [0.5, 0.0]
    assert float(cost(jnp.zeros(1), jnp.array([1.0, 2.0]))) == pytest.approx(du @ R @ du)
    vec = fj.quadratic_cost(lam=np.array([2.0, 3.0]), x_s=np.zeros(2))  # vectors keep their meaning
    assert float(vec(jnp.array([1.0, -1.0]), jnp.zeros(1))) == pytest.approx(5.0)


@settings(max_examples=5, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_quadratic_cost_with_random_psd_matrix_in_a_search(seed):
    rng = np.random.default_rng(seed)
    L = rng.normal(size=(n, 1))
    Q = L @ L.T  # rank one: semidefinite, not definite
    x_s = rng.normal(0, 0.5, n)
    A = rng.normal(0, 0.6, (n, n))
    B = rng.normal(0, 1.0, (n, 1))
    problem = fj.Problem(fj.linear_dynamics(A, B), CONTROLS, fj.quadratic_cost(Q, x_s, beta=0.1), 3)
    x0 = rng.normal(0, 1.0, n)

    def step(x, u, t):
        x = x @ A.T + u @ B.T
        dx = x - x_s
        return x, np.einsum("...i,ij,...j->...", dx, Q, dx) + 0.1 * np.sum(u**2, -1)

    best, _ = reference.brute_force(step, CONTROLS, x0, 3)
    assert reference.same_cost(fj.sdfs(problem, x0).cost, best)
    assert reference.same_cost(fj.exhaustive(problem, x0).cost, best)


@pytest.mark.parametrize("bad", [[[1.0, 2.0], [0.0, 1.0]], [[1.0, 2.0], [2.0, 1.0]], [[1.0, 0.0, 0.0]]])
@pytest.mark.parametrize("name", ["lam", "beta"])
def test_non_symmetric_or_indefinite_weights_are_refused(bad, name):
    kwargs = {"lam": 1.0, "x_s": np.zeros(2), "beta": 0.0, name: np.array(bad)}
    with pytest.raises(ValueError, match=name):
        fj.quadratic_cost(**kwargs)
    with pytest.raises(ValueError, match="Q"):
        fj.tracking_cost(Q=np.array(bad))


def test_a_step_index_the_problem_does_not_pass_is_refused_clearly():
    takes_k = fj.Problem(lambda x, u, k: x + u, CONTROLS, lambda x, u, k: jnp.sum(x**2), 2)
    with pytest.raises(TypeError, match="step_index=True"):
        fj.sdfs(takes_k, np.zeros(1))
    no_k = fj.Problem(lambda x, u: x + u, CONTROLS, lambda x, u: jnp.sum(x**2), 2, step_index=True)
    with pytest.raises(TypeError, match=r"dynamics\(x, u, k\)"):
        fj.sdfs(no_k, np.zeros(1))
    with pytest.raises(TypeError, match="step_index"):
        fj.Problem(lambda x, u: x + u, CONTROLS, lambda x, u: jnp.sum(x**2), 2, step_index=1)


def test_constraint_and_terminal_cost_must_return_the_right_kind():
    base = fj.Problem(lambda x, u: x + u, CONTROLS, lambda x, u: jnp.sum(x**2), 2)
    with pytest.raises(TypeError, match="constraint.*boolean scalar"):
        fj.sdfs(base.replace(constraint=lambda x, u: x[0] - 1.0), np.zeros(1))
    with pytest.raises(ValueError, match="terminal_cost.*scalar"):
        fj.sdfs(base.replace(terminal_cost=lambda x: x), np.zeros(1) + [0.5])


def test_new_reference_values_never_retrace():
    traces = {"n": 0}

    def counted(x, u, k, p):
        traces["n"] += 1
        return dynamics(x, u, k, p)

    problem = PROBLEM.replace(dynamics=counted)
    rng = np.random.default_rng(1)
    x0 = np.zeros(n)
    for i in range(3):
        p = {"W": rng.normal(0, 0.8, (n, n)), "V": rng.normal(0, 1, n), "a": np.ones(n), "d": rng.normal(0, .3, (N, n)),
             "ref": rng.normal(0, 1, (N, n)), "Q": np.eye(n), "r": 0.1, "w": np.zeros(N), "xmax": np.full(N, FAR),
             "radius": FAR, "g": 1.0}
        fj.sdfs(problem, x0 + i, params=p)
        if i == 0:
            after_first, compiled = traces["n"], compile_count()
    assert traces["n"] == after_first > 0 and compile_count() == compiled


def test_closed_loop_with_references_along_the_horizon():
    """FIRHC and simulate with per-step parameters of leading axis T, each [N, ...] along the horizon."""
    rng = np.random.default_rng(3)
    T = 4
    base = {"W": rng.normal(0, 0.5, (n, n)), "V": rng.normal(0, 1, n), "a": np.full(n, 0.9),
            "Q": np.eye(n), "r": 0.05, "w": np.zeros(N), "xmax": np.full(N, 0.8), "radius": FAR, "g": 0.5}
    ref = 0.5 * np.sin(0.7 * np.arange(T + N))[:, None] * np.ones(n)
    steps = [dict(base, ref=ref[t + 1:t + 1 + N], d=np.zeros((N, n))) for t in range(T)]
    params = jax.tree_util.tree_map(lambda *a: np.stack(a), *steps)
    ctrl = fj.FIRHC(PROBLEM)
    x0 = np.array([0.1, -0.2])
    run = ctrl.simulate(x0, T, params=params)
    for t in range(T):
        assert reference.same_cost(run.predicted_costs[t], brute_force(steps[t], np.asarray(run.states[t])))
    u, info = ctrl(np.asarray(run.states[1]), steps[1])
    assert reference.same_cost(info.result.cost, run.predicted_costs[1])


def test_check_problem_and_check_lower_bound_see_every_step_index():
    w = np.array([0.0, 0.0, 5.0])

    def cost(x_next, u, k, p):
        return p["w"][k] + 0.0 * x_next[0]

    problem = fj.Problem(lambda x, u, k, p: x + u, CONTROLS, cost, N, step_index=True,
                         lower_bound=lambda x, s, p: jnp.where(s >= 1, 5.0, 0.0))
    X = np.zeros((2, 1))
    # The exact cost of the last s steps is 5 for every s (w[N - s:] always holds the 5): the bound is exact.
    assert fj.check_lower_bound(problem, X, params={"w": w}) == []
    too_high = problem.replace(lower_bound=lambda x, s, p: jnp.where(s >= 1, 5.5, 0.0))
    assert len(fj.check_lower_bound(too_high, X, params={"w": w})) == 2 * N
    negative_last = {"w": np.array([0.0, 0.0, -1.0])}
    assert [v.state for v in fj.check_problem(problem, X, params=negative_last)] == [0, 1]


def test_exhaustive_dfs_visits_every_node_whatever_the_bound():
    problem = fj.Problem(lambda x, u: x + u, CONTROLS, lambda x, u: jnp.sum(x**2), 4,
                         lower_bound=lambda x, s: jnp.inf)
    out = fj.exhaustive(problem, np.zeros(1), method="dfs")
    assert int(out.nodes) == problem.tree_size() == 120


def test_fallback_keeps_constraints_and_terminal_cost():
    """The unconstrained fallback drops the terminal set only: hard constraints and the terminal cost stay."""
    rng = np.random.default_rng(5)
    p = {"W": rng.normal(0, 0.8, (n, n)), "V": rng.normal(0, 1, n), "a": np.ones(n), "d": np.zeros((N, n)),
         "ref": np.zeros((N, n)), "Q": np.eye(n), "r": 0.1, "w": np.zeros(N), "xmax": np.full(N, 0.2),
         "radius": 1e-9, "g": 2.0}  # the terminal set is (almost surely) out of reach
    x0 = np.array([0.3, -0.1])
    ctrl = fj.FIRHC(PROBLEM, fallback="unconstrained")
    u, info = ctrl(x0, p)
    relaxed = dict(p, radius=FAR)
    assert bool(info.used_fallback) and reference.same_cost(info.result.cost, brute_force(relaxed, x0))


@pytest.mark.slow
def test_the_documented_plants_run():
    """docs/guide/formulation.md's three plants, as written there (each block in its own namespace)."""
    import re
    text = (DOCS / "guide" / "formulation.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert len(blocks) == 3
    for block in blocks:
        exec(compile(block, "docs/guide/formulation.md", "exec"), {})


def _leg(x, u, p):
    return p["A"] @ x + p["B"] * u[0]


def _leg_cost(x_next, u, p):
    return jnp.sum((x_next - p["ref"]) ** 2)


LEG = fj.with_input_memory(fj.Problem(_leg, CONTROLS, _leg_cost, N), fj.input_change_cost(0.05, norm="abs"),
                           transition=lambda u, u_prev, p: jnp.all(jnp.abs(u - u_prev) <= 1))


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([-1.0, 0.0, 1.0]))
def test_forbidden_transitions_are_never_taken(seed, u_prev):
    """A three-level leg never jumps between -1 and +1, the first step against the input applied last."""
    rng = np.random.default_rng(seed)
    p = {"A": rng.normal(0, 0.6, (n, n)), "B": rng.normal(0, 1, n), "ref": rng.normal(0, 2, n)}
    x0 = rng.normal(0, 1, n)

    def cost(seq):
        us = CONTROLS[list(seq)]
        if np.any(np.abs(np.diff(np.concatenate([[u_prev], us]))) > 1):
            return np.inf
        x, total, last = x0, 0.0, u_prev
        for u in us:
            x = p["A"] @ x + p["B"] * u
            total += np.sum((x - p["ref"]) ** 2) + 0.05 * abs(u - last)
            last = u
        return total

    best = min(cost(s) for s in itertools.product(range(M), repeat=N))
    z0 = LEG.observe(jnp.asarray(x0), jnp.array([u_prev]), p)
    for r in (fj.sdfs(LEG.problem, z0, params=p), fj.exhaustive(LEG.problem, z0, params=p)):
        assert reference.same_cost(r.cost, best) and np.isfinite(cost(np.asarray(r.sequence)))


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-5, 5), min_size=3, max_size=3), st.floats(-2, 1), st.floats(0, 3), st.floats(0, 4))
def test_band_penalty_is_the_weighted_l1_distance_outside_the_band(x, lower, width, weight):
    """Against the definition, element by element, with numbers and with the bounds read from params."""
    x = np.asarray(x)
    upper = lower + width
    want = weight * sum(max(lower - v, 0.0) + max(v - upper, 0.0) for v in x[1:])
    fixed = fj.band_penalty(lower, upper, weight, index=slice(1, None))
    read = fj.band_penalty("lo", "hi", "w", index=slice(1, None))
    p = {"lo": np.float64(lower), "hi": np.float64(upper), "w": np.float64(weight)}
    np.testing.assert_allclose(float(fixed(jnp.asarray(x))), want, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(float(read(jnp.asarray(x), p)), want, rtol=1e-12, atol=1e-12)
    assert float(fj.band_penalty(upper=upper)(jnp.asarray(x))) == pytest.approx(sum(max(v - upper, 0) for v in x))


def test_a_band_penalty_keeps_a_problem_exact_and_feasible_where_a_hard_band_is_not():
    """A heater that cannot hold the band late in the horizon: the hard constraint leaves no sequence, the soft
    one the brute-force optimum of the penalised cost."""
    dyn = lambda x, u: 0.8 * x + u  # noqa: E731
    controls = np.array([[0.0], [1.0], [2.0]])
    band = fj.band_penalty(4.0, 6.0, 10.0)
    soft = fj.Problem(dyn, controls, lambda x, u: 0.1 * u[0] + band(x), 4)
    hard = fj.Problem(dyn, controls, lambda x, u: 0.1 * u[0], 4, constraint=lambda x, u: (x[0] >= 9.0))
    x0 = np.array([0.0])
    assert not bool(fj.sdfs(hard, x0).feasible)
    best = min(sum(0.1 * u + float(band(np.array([x]))) for x, u in zip(_states(s), s, strict=True))
               for s in itertools.product([0.0, 1.0, 2.0], repeat=4))
    r = fj.sdfs(soft, x0)
    assert bool(r.feasible)
    np.testing.assert_allclose(float(r.cost), best, rtol=1e-12)


def _states(inputs):
    x, out = 0.0, []
    for u in inputs:
        x = 0.8 * x + u
        out.append(x)
    return out


def test_band_penalty_refuses_what_it_cannot_mean():
    with pytest.raises(ValueError, match="lower or an upper"):
        fj.band_penalty()
    with pytest.raises(ValueError, match="weight must be >= 0"):
        fj.band_penalty(0.0, 1.0, -1.0)
    with pytest.raises(ValueError, match="lower must not exceed upper"):
        fj.band_penalty(2.0, 1.0)
    with pytest.raises(TypeError, match="solve with params"):
        fj.band_penalty("lo")(jnp.zeros(2))


def _ramp_problem(N, previous_state=True):
    """x' = 0.9 x + u with a ramp limit |x' - x| <= 1.2 and a cost of the change, both of the state before."""
    def constraint(x, x_next, u):
        return jnp.abs(x_next[0] - x[0]) <= 1.2

    def stage_cost(x, x_next, u):
        return x_next[0] ** 2 + 0.5 * (x_next[0] - x[0]) ** 2

    return fj.Problem(lambda x, u: 0.9 * x + u, np.array([[-1.0], [0.0], [1.0], [2.0]]), stage_cost, N,
                      constraint=constraint, previous_state=previous_state)


@settings(max_examples=10, deadline=None)
@given(st.floats(-3, 3), st.integers(1, 4))
def test_stage_cost_and_constraint_of_the_state_before_the_step_are_the_brute_force_optimum(x0, N):
    problem = _ramp_problem(N)
    best = np.inf
    for seq in itertools.product(range(4), repeat=N):
        x, cost = x0, 0.0
        for i in seq:
            x_next = 0.9 * x + problem.controls[i, 0]
            if abs(x_next - x) > 1.2:
                cost = np.inf
                break
            cost += x_next ** 2 + 0.5 * (x_next - x) ** 2
            x = x_next
        best = min(best, cost)
    r = fj.sdfs(problem, np.array([x0]))
    tol = dict(rtol=1e-12, atol=1e-300)  # XLA:CPU flushes subnormal costs (x0 near 1e-156) to zero
    if np.isinf(best):
        assert not bool(r.feasible)
    else:
        np.testing.assert_allclose(float(r.cost), best, **tol)
        np.testing.assert_allclose(float(fj.rollout_cost(problem, np.array([x0]), r.sequence)[0]), best, **tol)
    np.testing.assert_allclose(float(fj.exhaustive(problem, np.array([x0])).cost), best, **tol)


def test_the_state_before_the_step_reaches_the_closed_loop_and_input_memory():
    """The realised cost of a closed loop prices each step from the state before it; with_input_memory passes
    the state before the step through; a problem that does not ask for it is refused with its signature."""
    problem = _ramp_problem(3)
    run = fj.FIRHC(problem).simulate(np.array([2.5]), 6)
    xs = np.asarray(run.states)[:, 0]
    want = sum(xs[t + 1] ** 2 + 0.5 * (xs[t + 1] - xs[t]) ** 2 for t in range(6))
    np.testing.assert_allclose(run.realised_cost(problem), want, rtol=1e-12)
    assert np.all(np.abs(np.diff(xs)) <= 1.2 + 1e-12)
    mem = fj.with_input_memory(problem, fj.input_change_cost(0.1))
    r = fj.sdfs(mem.problem, mem.observe(np.array([2.5]), np.array([0.0])))
    assert bool(r.feasible) and float(r.cost) >= float(fj.sdfs(problem, np.array([2.5])).cost)
    with pytest.raises(TypeError, match=r"stage_cost\(x_next, u\)"):
        fj.sdfs(_ramp_problem(2, previous_state=False), np.array([1.0]))
