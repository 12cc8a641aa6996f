"""Budgeted searches (``max_nodes``) on random problems with near-ties: honest
results, exact when the budget allows, the iterative-deepening guarantee of
docs/guide/budgets.md, and budgets never passed (warm start, fallback, pool).

The problems quantise their stage and terminal costs (steps of 1/grain) and
add a tiny input term, so many sequences cost exactly or nearly the same:
where pruning starts late. Every number is a parameter, so each shape
compiles once; the reference is a NumPy brute force."""
from __future__ import annotations

import functools
import itertools
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from loops import assert_same_loop
from param_problems import as_jax, as_seen
from reference import same_cost, tolerance

import firhc_jax as fj

SHAPES = ((2, 1, 3, 5), (1, 1, 4, 4))  # (n, m, M, N)
LONG = (2, 1, 3, 7)  # where a budget holds a few levels but not the tree


def _u(u, p, xp):
    return p["U"][u[..., 0].astype(int)] if xp is jnp else u


def dynamics(x, u, p, xp=jnp):
    v = _u(u, p, xp)
    n = p["W"].shape[-1]
    z = p["b"] + sum(p["W"][:, j] * x[..., j, None] for j in range(n)) + p["V"][:, 0] * v[..., 0, None]
    return xp.tanh(z) + p["a"] * x


def stage_cost(x, u, p, xp=jnp):
    v = _u(u, p, xp)
    raw = xp.sum(p["q"] * (x - p["r"]) ** 2, axis=-1)
    return xp.round(raw * p["grain"]) / p["grain"] + p["eps"] * v[..., 0] ** 2


def terminal_cost(x, p, xp=jnp):
    return p["tw"] * xp.round(xp.sum((x - p["r"]) ** 2, axis=-1) * p["grain"]) / p["grain"]


def terminal(x, p, xp=jnp):
    return xp.sum((x - p["r"]) ** 2, axis=-1) < p["radius"]


@functools.lru_cache(maxsize=None)
def problem(shape) -> fj.Problem:
    n, m, M, N = shape
    return fj.Problem(dynamics, jnp.arange(M, dtype=jnp.float32), stage_cost, N, terminal,
                      terminal_cost=terminal_cost)


@st.composite
def cases(draw, shapes=SHAPES):
    """(shape, params, x0): near-ties from a coarse grain (1-4 steps per unit cost) and a tiny input term."""
    shape = draw(st.sampled_from(shapes))
    n, m, M, N = shape
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    radius = draw(st.sampled_from([1.0, 0.3, 1e30]))
    params = {"W": rng.normal(0, 0.8, (n, n)), "V": rng.normal(0, 1.0, (n, 1)), "b": rng.normal(0, 0.2, n),
              "a": rng.uniform(0.2, 0.9, n), "q": rng.uniform(0.0, 2.0, n), "r": rng.normal(0, 0.5, n),
              "U": rng.uniform(-1.5, 1.5, (M, 1)), "grain": np.float64(draw(st.sampled_from([1.0, 2.0, 4.0]))),
              "eps": np.float64(draw(st.sampled_from([0.0, 1e-3]))), "tw": np.float64(rng.uniform(0, 3)),
              "radius": np.float64(radius * n)}
    x0 = rng.uniform(-1, 1, n)
    return shape, params, x0


# ---------------------------------------------------------------- the NumPy reference
def _children(p, x, cost):
    """States ``[M, n]`` and accumulated costs ``[M]`` of every input from ``x``."""
    U = p["U"]
    xs = dynamics(np.broadcast_to(x, (len(U), len(x))), U, p, xp=np)
    return xs, cost + stage_cost(xs, U, p, xp=np)


def sequence_cost(p, x0, seq, N):
    """Cost of an index sequence: stage costs, the terminal cost, +inf outside the terminal set."""
    x, c = np.asarray(x0, float), 0.0
    for i in seq:
        xs, cs = _children(p, x, c)
        x, c = xs[i], cs[i]
    return c + terminal_cost(x, p, xp=np) if terminal(x, p, xp=np) else np.inf


def optimum(p, x0, shape):
    """The exhaustive optimum (every sequence at once)."""
    n, m, M, N = shape
    seqs = np.array(list(itertools.product(range(M), repeat=N)))
    x, c = np.broadcast_to(np.asarray(x0, float), (len(seqs), n)), np.zeros(len(seqs))
    for k in range(N):
        u = p["U"][seqs[:, k]]
        x = dynamics(x, u, p, xp=np)
        c = c + stage_cost(x, u, p, xp=np)
    return float(np.min(np.where(terminal(x, p, xp=np), c + terminal_cost(x, p, xp=np), np.inf)))


def seeds_bound(p, x0, shape, N0):
    """The largest full-horizon cost among the exact horizon-N0 decisions (all the tied optima of stage costs
    plus the terminal cost at x(N0)) extended by the greedy rollout of docs/guide/budgets.md."""
    n, m, M, N = shape
    rtol, atol = tolerance()
    scored = []
    for s in itertools.product(range(M), repeat=N0):
        x, c = np.asarray(x0, float), 0.0
        for i in s:
            xs, cs = _children(p, x, c)
            x, c = xs[i], cs[i]
        scored.append((c + terminal_cost(x, p, xp=np), x, c))
    best = min(v for v, _, _ in scored)
    worst = -np.inf
    for value, x, c in scored:
        if value > best + rtol * abs(best) + atol:
            continue
        for k in range(N0, N):  # the greedy rule: cost + terminal cost of the child; the last step: feasible
            xs, cs = _children(p, x, c)
            if k < N - 1:
                i = int(np.argmin(cs + terminal_cost(xs, p, xp=np)))
            else:
                total = np.where(terminal(xs, p, xp=np), cs + terminal_cost(xs, p, xp=np), np.inf)
                i = int(np.argmin(total))
            x, c = xs[i], cs[i]
        worst = max(worst, c + terminal_cost(x, p, xp=np) if terminal(x, p, xp=np) else np.inf)
    return worst


def documented_budget(shape, N0, pop_width=1, warm_start=False):
    """B(N0) of docs/guide/budgets.md, as written there: twice levels 1..N0 (each its whole tree and its
    extension) and one expansion, plus twice a warm start's N nodes."""
    n, m, M, N = shape
    T = [sum(M**i for i in range(1, D + 1)) for D in range(N0 + 1)]
    return 2 * (sum(T[D] + N * M for D in range(1, N0 + 1)) + pop_width * M) + (2 * N if warm_start else 0)


def guaranteed_levels(shape, budget):
    """The N0 whose guarantee holds at ``budget``: ``B(N0) <= budget``."""
    return [N0 for N0 in range(1, shape[3]) if documented_budget(shape, N0) <= budget]


def check_result(r, shape, params, x0, budget, opt, name="", lanes=1):
    """Honest: within the budget, a feasible sequence whose reference cost is the reported one, never below the
    optimum, optimal when ``complete``; complete when the budget holds the seeds and the whole tree (and an
    expansion by each pool slot that may share the row)."""
    n, m, M, N = shape
    cost = float(r.cost)
    assert int(r.nodes) <= budget, (name, int(r.nodes), budget)
    if bool(r.feasible):
        seq = np.asarray(r.sequence)
        assert same_cost(sequence_cost(params, x0, seq, N), cost), (name, seq, cost)
        assert cost >= opt or same_cost(cost, opt), (name, cost, opt)
    else:
        assert np.all(np.asarray(r.sequence) == -1)
    if bool(r.complete):
        assert same_cost(cost, opt) or (np.isinf(opt) and np.isinf(cost)), (name, cost, opt)
    if budget >= 2 * (problem(shape).tree_size() + lanes * M):
        assert bool(r.complete), name


# ---------------------------------------------------------------- fj.sdfs
@pytest.mark.float32
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cases(), st.integers(1, 1200))
def test_a_budgeted_search_is_honest_and_exact_when_it_can_be(case, budget):
    shape, params, x0 = case
    seen, x_seen = as_seen(params, x0)
    r = fj.sdfs(problem(shape), x0, params=as_jax(params), max_nodes=budget)
    check_result(r, shape, seen, x_seen, budget, optimum(seen, x_seen, shape))


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cases(shapes=(LONG,)), st.integers(40, 900))
def test_a_budgeted_decision_is_never_dearer_than_the_exact_shorter_one_extended(case, budget):
    """The guarantee: at a budget that holds levels 1..N0, never dearer over the horizon than the exact
    horizon-N0 decision extended by the greedy rollout."""
    shape, params, x0 = case
    seen, x_seen = as_seen(params, x0)
    r = fj.sdfs(problem(shape), x0, params=as_jax(params), max_nodes=budget)
    rtol, atol = tolerance()
    for N0 in guaranteed_levels(shape, budget):
        bound = seeds_bound(seen, x_seen, shape, N0)
        assert float(r.cost) <= bound + rtol * abs(bound) + atol, (N0, float(r.cost), bound)


@pytest.mark.float32
@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cases(shapes=(LONG,)), st.integers(1, LONG[3] - 1), st.booleans())
def test_the_guarantee_holds_at_exactly_the_documented_budget_at_every_level(case, N0, warm):
    """At ``max_nodes = B(N0)`` exactly (with a warm start: its ``+ 2 N``, the warm start the worst sequence
    there is, so that it never decides), N0 from 1: never dearer than the horizon-N0 decision extended."""
    shape, params, x0 = case
    seen, x_seen = as_seen(params, x0)
    budget = documented_budget(shape, N0, warm_start=warm)
    warm_start = None
    if warm:
        costs = [sequence_cost(seen, x_seen, s, shape[3]) for s in itertools.product(range(shape[2]), repeat=shape[3])]
        finite = [c if np.isfinite(c) else -1 for c in costs]
        warm_start = np.array(list(itertools.product(range(shape[2]), repeat=shape[3]))[int(np.argmax(finite))])
    r = fj.sdfs(problem(shape), x0, params=as_jax(params), max_nodes=budget, warm_start=warm_start)
    bound = seeds_bound(seen, x_seen, shape, N0)
    rtol, atol = tolerance()
    assert int(r.nodes) <= budget
    assert float(r.cost) <= bound + rtol * abs(bound) + atol, (N0, budget, float(r.cost), bound)


def test_the_guarantee_at_level_one_where_the_terminal_cost_alone_points_the_way():
    """x' = x + u, u in {0, 1, 2}, the stage cost 0.01 u, the terminal cost 100 (x_N - 12)^2, N = 6: the exact
    level-1 decision (u = 2) extended by the rollout is [2] * 6 at 0.12, while the first dive of the full search
    sees the terminal cost only at the leaves (3600.06). From B(1) on, fj.sdfs and a pool row are never dearer."""
    shape = (1, 1, 3, 6)
    tiny = fj.Problem(lambda x, u: x + u, jnp.array([0.0, 1.0, 2.0]), lambda x, u: 0.01 * u[0], 6,
                      terminal_cost=lambda x: 100 * (x[0] - 12) ** 2)
    x0 = jnp.zeros(1)
    extended = 0.12
    assert documented_budget(shape, 1) == 48
    for budget in [*range(48, 78), *(documented_budget(shape, N0) for N0 in range(2, 6))]:
        r = fj.sdfs(tiny, x0, max_nodes=budget)
        assert float(r.cost) <= extended + 1e-6, (budget, float(r.cost), np.asarray(r.sequence))
    rows = fj.solve_batch(tiny, jnp.zeros((2, 1)), max_nodes=48, lanes=2, cores=1)
    assert np.all(np.asarray(rows.cost) <= extended + 1e-6), np.asarray(rows.cost)


# ---------------------------------------------------------------- budgets never passed
@pytest.mark.float32
@pytest.mark.filterwarnings("ignore:closed loop. no feasible input:RuntimeWarning")  # small budgets hold inputs
@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cases(shapes=SHAPES[:1]), st.integers(1, 400), st.integers(0, 2**32 - 1))
def test_budgets_are_never_passed_warm_start_pool_and_fallback(case, budget, seed):
    """The pool at 3 lanes for 3 rows: slots steal from rows, the case where a row could pass the budget (one
    lane is fj.sdfs row by row: test_a_pool_row_matches_fj_sdfs_under_a_budget)."""
    lanes = 3
    shape, params, x0 = case
    n, m, M, N = shape
    seen, x_seen = as_seen(params, x0)
    opt = optimum(seen, x_seen, shape)
    prm = as_jax(params)
    warm = np.random.default_rng(seed).integers(0, M, N)
    r = fj.sdfs(problem(shape), x0, params=prm, warm_start=warm, max_nodes=budget)
    check_result(r, shape, seen, x_seen, budget, opt, "warm start")
    X = np.stack([x0, -x0, 0.5 * x0])
    P = jax.tree_util.tree_map(lambda a: jnp.stack([a] * 3), prm)
    b = fj.solve_batch(problem(shape), X, params=P, max_nodes=budget, lanes=lanes, cores=1)
    for i in range(3):
        row = jax.tree_util.tree_map(lambda a, i=i: a[i], b)
        _, xi = as_seen(params, X[i])
        check_result(row, shape, seen, xi, budget, optimum(seen, xi, shape), f"pool row {i}", lanes)
    run = fj.FIRHC(problem(shape), fallback="unconstrained", warm_start=True, max_nodes=budget).simulate(
        x0, 3, params=jax.tree_util.tree_map(lambda a: jnp.stack([a] * 3), prm))
    assert (np.asarray(run.decision_nodes) <= budget).all(), np.asarray(run.decision_nodes)


def test_a_pool_row_matches_fj_sdfs_under_a_budget():
    """lanes=1: each row is fj.sdfs with the same seeds, node for node."""
    shape = SHAPES[0]
    rng = np.random.default_rng(3)
    n, m, M, N = shape
    params = {"W": rng.normal(0, 0.8, (n, n)), "V": rng.normal(0, 1.0, (n, 1)), "b": rng.normal(0, 0.2, n),
              "a": rng.uniform(0.2, 0.9, n), "q": rng.uniform(0.0, 2.0, n), "r": rng.normal(0, 0.5, n),
              "U": rng.uniform(-1.5, 1.5, (M, 1)), "grain": np.float64(2.0), "eps": np.float64(1e-3),
              "tw": np.float64(1.0), "radius": np.float64(1.0)}
    X = rng.uniform(-1, 1, (3, n))  # three rows, as above: the same compiled pool
    prm = as_jax(params)
    P = jax.tree_util.tree_map(lambda a: jnp.stack([a] * 3), prm)
    for budget in (30, 150, 400):
        b = fj.solve_batch(problem(shape), X, params=P, max_nodes=budget, lanes=1, cores=1)
        for i in range(3):
            r = fj.sdfs(problem(shape), X[i], params=prm, max_nodes=budget)
            assert float(b.cost[i]) == float(r.cost) and int(b.nodes[i]) == int(r.nodes), (budget, i)
            assert np.array_equal(np.asarray(b.sequence[i]), np.asarray(r.sequence))


# ---------------------------------------------------------------- the benchmark's pumping station
@pytest.mark.parametrize("bound", ["demand", "target"])
def test_the_pumping_station_is_exact_and_its_bounds_admissible(bound):
    """sDFS equals exhaustive search at N = 3 from levels near and at the limits, budgeted never cheaper, and
    both lower bounds pass ``check_lower_bound``."""
    from firhc_jax.models import pumping as pm

    N = 3
    problem_ = pm.make_problem(N, bound=bound)
    params = pm.horizon_params(*pm.forecast(20), 12, N)
    states = np.array([[2.2, 2.0], [0.6, 4.4], [4.4, 0.55], [1.0, 1.0]])
    for t, x in zip((0, 5, 9, 11), states, strict=True):
        p = jax.tree_util.tree_map(lambda a, t=t: a[t], params)
        ref = fj.exhaustive(problem_, x, params=p)
        assert same_cost(float(fj.sdfs(problem_, x, params=p).cost), float(ref.cost)), (t, x)
        cut = fj.sdfs(problem_, x, params=p, max_nodes=100)
        assert float(cut.cost) >= float(ref.cost) or same_cost(float(cut.cost), float(ref.cost))
        assert not fj.diagnostics.check_lower_bound(problem_, x[None], p)


# ---------------------------------------------------------------- the previous plan, shifted and completed
def shifted_plan_cost(p, x, plan, shape, terminal_set: bool):
    """The cost from ``x`` of ``plan[1:]`` completed by the greedy last step (the cheapest leaf, with its
    terminal cost, among those in the terminal set when ``terminal_set``), the NumPy reference."""
    c = 0.0
    for i in plan[1:]:
        xs, cs = _children(p, x, c)
        x, c = xs[i], cs[i]
    xs, cs = _children(p, x, c)
    leaves = cs + terminal_cost(xs, p, xp=np)
    if terminal_set:
        leaves = np.where(terminal(xs, p, xp=np), leaves, np.inf)
    return float(np.min(leaves))


def check_shifted_plans(run, seen, shape, label=""):
    """Every decision after a found one predicts no more than the previous plan shifted and completed, under
    the problem that decided (the fallback's has no terminal set); never held where that plan exists."""
    rtol, atol = tolerance()
    states, plans = np.asarray(run.states, np.float64), np.asarray(run.plans)
    pred, used, held = (np.asarray(a) for a in (run.predicted_costs, run.used_fallback, run.held))
    for k in range(1, len(plans)):
        if plans[k - 1, 0] < 0:
            continue
        ref = shifted_plan_cost(seen, states[k], plans[k - 1], shape, terminal_set=not used[k])
        assert not (held[k] and np.isfinite(ref)), (label, k, ref)
        assert held[k] or float(pred[k]) <= ref + rtol * abs(ref) + atol, (label, k, float(pred[k]), ref)


def constant_params(params, T):
    return jax.tree_util.tree_map(lambda a: jnp.stack([a] * T), as_jax(params))


@pytest.mark.filterwarnings("ignore:closed loop. no feasible input:RuntimeWarning")
@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cases(shapes=SHAPES[:1]), st.integers(14, 120), st.booleans())
def test_a_budgeted_loop_never_predicts_dearer_than_its_previous_plan_shifted(case, budget, fallback):
    """Random problems with near-ties, the plant the model, a budget from 2 (N - 1 + M) (the previous plan's
    nodes, for each of the two searches), no warm start (the previous plan is a candidate all the same)."""
    shape, params, x0 = case
    seen, _ = as_seen(params, x0)
    ctrl = fj.FIRHC(problem(shape), fallback="unconstrained" if fallback else None, max_nodes=budget)
    check_shifted_plans(ctrl.simulate(x0, 6, params=constant_params(params, 6)), seen, shape)


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:closed loop. no feasible input:RuntimeWarning")
@pytest.mark.parametrize("solver", ["sdfs", "pool", "sdfs-vmap"])
@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(case=cases(shapes=SHAPES[:1]), budget=st.integers(14, 120), warm=st.booleans())
def test_every_budgeted_solver_keeps_the_previous_plan_in_step_simulate_and_simulate_batch(solver, case, budget,
                                                                                           warm):
    """With a fallback and warm starts on or off: simulate, a Python loop of step (the same decisions) and
    simulate_batch (each loop's decisions as its simulate; for "pool", whose single decision steals, the
    guarantee only)."""
    shape, params, x0 = case
    seen, _ = as_seen(params, x0)
    T = 6
    P = constant_params(params, T)
    ctrl = fj.FIRHC(problem(shape), solver, fallback="unconstrained", warm_start=warm, max_nodes=budget)
    run = ctrl.simulate(x0, T, params=P)
    check_shifted_plans(run, seen, shape, "simulate")
    state, x, plans = ctrl.init(x0), jnp.asarray(x0), []
    for k in range(T):
        _, state, info = ctrl.step(state, x, jax.tree_util.tree_map(lambda a, k=k: a[k], P))
        plans.append(np.asarray(state.plan))
        x = run.states[k + 1]
    assert np.array_equal(np.array(plans), np.asarray(run.plans)), "step"
    X0 = np.stack([x0, np.random.default_rng(budget).uniform(-1, 1, x0.shape)])
    batch = ctrl.simulate_batch(X0, T, params=jax.tree_util.tree_map(lambda a: jnp.stack([a] * 2), P))
    for b in range(2):
        one = jax.tree_util.tree_map(lambda a, b=b: a[b], batch)
        check_shifted_plans(one, seen, shape, f"simulate_batch loop {b}")
        if solver != "pool":
            assert_same_loop(one, run if b == 0 else ctrl.simulate(X0[b], T, params=P), f"loop {b}", nodes=True)


# ---------------------------------------------------------------- a terminal set, a fallback and a budget
def swing(x, u):
    """A pendulum (angle from upright) with a torque far too weak to lift it."""
    omega = x[1] + 0.1 * (9.81 * jnp.sin(x[0]) - 0.1 * x[1] + u[0])
    return jnp.stack([x[0] + 0.1 * omega, omega])


PENDULUM = fj.Problem(swing, jnp.array([-1.0, 1.0]), lambda x, u: 1 - jnp.cos(x[0]) + 0.01 * x[1] ** 2, 6,
                      lambda x: (jnp.cos(x[0]) > 0.95) & (jnp.abs(x[1]) < 1.0))  # upright: out of reach
HANGING = np.array([np.pi, 0.0])


@pytest.mark.float32
@pytest.mark.parametrize("solver", ["sdfs", pytest.param("pool", marks=pytest.mark.slow),
                                    pytest.param("sdfs-vmap", marks=pytest.mark.slow)])
def test_a_fallback_gets_enough_of_the_budget_to_act(solver):
    """Hanging, the terminal set is out of reach, and without a bound the terminal-constrained search needs its
    whole tree (126 nodes) to prove it. At the documented budget (``budget_for``: twice B(1), the fallback
    getting half) every decision comes from the fallback and none is held, in simulate, step and
    simulate_batch."""
    ctrl = fj.FIRHC(PENDULUM, solver, fallback="unconstrained", warm_start=True, max_nodes=92)
    run = ctrl.simulate(HANGING, 8)
    assert np.asarray(run.used_fallback).all() and not np.asarray(run.held).any()
    assert (np.asarray(run.decision_nodes) <= 92).all()
    _, _, info = ctrl.step(ctrl.init(HANGING), HANGING)
    assert bool(info.used_fallback) and not bool(info.held)
    batch = ctrl.simulate_batch(np.stack([HANGING, HANGING + np.array([0.2, 0.0])]), 8)
    assert not np.asarray(batch.held).any() and (np.asarray(batch.decision_nodes) <= 92).all()
    assert fj.solvers.budget_for(ctrl, 1) == 92
    if solver == "sdfs":  # its first dive from 2 (N K M + N - 1 + M) = 38 nodes on
        dive = fj.FIRHC(PENDULUM, solver, fallback="unconstrained", warm_start=True, max_nodes=38)
        assert not np.asarray(dive.simulate(HANGING, 8).held).any()


def test_a_holding_controller_says_so_at_the_first_held_step():
    """No fallback, a target out of reach from step 5 on: the first held step is named as it happens: in a Python
    loop before the next step's plant is called, in a compiled run with a progress bar at the end of its chunk
    (the bar short of the end), for one loop and for a batch; a count follows the run."""
    T = 40
    hop = fj.Problem(lambda x, u, p: x + u, jnp.array([-1.0, 0.0, 1.0]), lambda x, u, p: (x[0] - p) ** 2, 3,
                     lambda x, p: jnp.abs(x[0] - p) < 0.5)
    target = jnp.asarray(np.where(np.arange(T) < 5, 0.0, 100.0))
    ctrl = fj.FIRHC(hop)
    seen = []

    def plant(x, u, p):  # what had been said when each step's plant is called
        seen.append(len(log))
        return x + u

    from firhc_jax._src.runtime import progress
    bar = []
    show = warnings.showwarning

    def at_warning(message, *args, **kwargs):
        bar.append(progress.current()._bar.n if progress.current() and progress.current()._bar else None)
        return show(message, *args, **kwargs)

    with warnings.catch_warnings(record=True) as log:
        warnings.simplefilter("always")
        ctrl.simulate(jnp.zeros(1), T, plant, params=target, compiled=False)
    assert seen[:6] == [0] * 6 and seen[6] == 1, seen  # said after step 5's plant, before step 6's
    assert "at step 5, the first such step" in str(log[0].message) and "35 of 40" in str(log[1].message)
    for total, run in ((T, lambda: ctrl.simulate(jnp.zeros(1), T, params=target, progress=True)),
                       (2 * T, lambda: ctrl.simulate_batch(jnp.zeros((2, 1)), T, params=jnp.stack([target] * 2),
                                                           progress=True))):
        with warnings.catch_warnings(record=True) as log:
            warnings.simplefilter("always")
            warnings.showwarning = at_warning
            bar.clear()
            run()
        messages = [str(w.message) for w in log]
        assert "at step 5, the first such step" in messages[0], messages
        assert bar[0] is not None and bar[0] < total, bar  # said while the run went on


# ---------------------------------------------------------------- budget_for
def test_budget_for_is_the_documented_formula_and_buys_the_guarantee():
    shape = LONG
    p = problem(shape)
    for n0 in range(1, shape[3]):
        for K in (1, 3):
            assert fj.solvers.budget_for(p, n0, pop_width=K) == documented_budget(shape, n0, pop_width=K)
        assert fj.solvers.budget_for(p, n0, warm_start=True) == documented_budget(shape, n0, warm_start=True)
    n, m, M, N = shape
    plain = documented_budget(shape, 2, pop_width=2) + 2 * (N - 1 + M)  # the previous plan comes first
    assert fj.solvers.budget_for(fj.FIRHC(p, pop_width=2, max_nodes=50), 2) == plain
    assert fj.solvers.budget_for(fj.FIRHC(p, fallback="unconstrained", pop_width=2), 2) == 2 * plain
    seed = lambda problem, x, previous, params: previous  # noqa: E731
    assert fj.solvers.budget_for(fj.FIRHC(p, warm_start=seed), 2) == documented_budget(shape, 2) + 2 * (2 * N - 1 + M)
    with pytest.raises(ValueError, match="n0"):
        fj.solvers.budget_for(p, N)
    with pytest.raises(ValueError, match="n0"):
        fj.solvers.budget_for(p, 0)
    with pytest.raises(TypeError, match="target"):
        fj.solvers.budget_for("problem", 1)
    with pytest.raises(TypeError, match="pop_width"):
        fj.solvers.budget_for(fj.FIRHC(p), 1, pop_width=2)
    with pytest.raises(ValueError, match="exhaustive"):
        fj.solvers.budget_for(fj.FIRHC(p, "exhaustive"), 1)
    # and it buys the guarantee: the level-1 example at exactly budget_for, one node less is not promised
    tiny = fj.Problem(lambda x, u: x + u, jnp.array([0.0, 1.0, 2.0]), lambda x, u: 0.01 * u[0], 6,
                      terminal_cost=lambda x: 100 * (x[0] - 12) ** 2)
    r = fj.sdfs(tiny, jnp.zeros(1), max_nodes=fj.solvers.budget_for(tiny, 1))
    assert float(r.cost) <= 0.12 + 1e-6
