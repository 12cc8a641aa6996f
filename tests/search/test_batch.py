"""fj.solve_batch: exactness per row, parameters, validation, memory, retracing."""
import functools
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compiles import compile_count
from jaxlib import xla_client
from random_problems import make
from reference import brute_force, same_cost
from repository import ROOT, TESTS

import firhc_jax as fj
from firhc_jax._src.runtime.sharding import usable_cores
from firhc_jax._src.search import batch as batch_module
from firhc_jax._src.search.batch import row_memory, solve_batch
from firhc_jax._src.search.pool import pool_memory, pool_row_memory

SOLVERS = ("sdfs", "sdfs-vmap", "exhaustive")


@functools.lru_cache(maxsize=None)
def problem_of(*spec):
    """``make(*spec).problem()``, one object per spec: the same callables, so tests share its compiled batches."""
    return make(*spec).problem()


def states(seed, B, n, scale=1.0):
    return jnp.asarray(np.random.default_rng(seed).uniform(-scale, scale, (B, n)))


def assert_exact(rp, X0, batch):
    """Per row: the NumPy brute force's optimal cost and feasibility, and the
    returned sequence really has that cost (ties may pick another optimum)."""
    for b in range(len(X0)):
        ref_cost, _ = rp.brute_force(X0[b])
        assert same_cost(batch.cost[b], ref_cost), (b, float(batch.cost[b]), ref_cost)
        assert bool(batch.feasible[b]) == np.isfinite(ref_cost), b
        if np.isfinite(ref_cost):
            assert same_cost(rp.sequence_cost(X0[b], np.asarray(batch.sequence[b])), ref_cost), b
            np.testing.assert_array_equal(batch.first_input[b], rp.controls[int(batch.sequence[b][0])])
        else:
            assert np.all(np.asarray(batch.sequence[b]) == -1)


@pytest.mark.parametrize("seed, n, m, M, N, terminal, solvers", [
    (0, 3, 2, 5, 4, "loose", SOLVERS), (1, 2, 1, 4, 5, "tight", ("sdfs",)), (2, 3, 1, 6, 3, "none", ("sdfs",)),
    (3, 2, 1, 3, 1, "loose", ("sdfs",))])
def test_exact_per_row(seed, n, m, M, N, terminal, solvers):
    rp = make(seed, n, m, M, N, terminal)
    p, X0 = rp.problem(), states(seed, 9, n)
    for solver in solvers:
        batch = solve_batch(p, X0, solver=solver)
        assert batch.cost.shape == (9,) and batch.sequence.shape == (9, N)
        assert_exact(rp, np.asarray(X0), batch)
    if terminal == "tight":
        assert not np.all(batch.feasible) and np.any(batch.feasible)  # both cases were exercised


@pytest.mark.parametrize("lanes, pop_width", [(3, 1), (4, 2), (32, 1)])
def test_pool_exact_with_more_or_fewer_lanes_than_rows(lanes, pop_width):
    """Rows queue for slots (or slots outnumber rows); free slots steal nodes of the last rows' searches."""
    rp = make(8, 3, 1, 5, 5, "loose")
    X0 = states(8, 11, 3)
    batch = solve_batch(problem_of(8, 3, 1, 5, 5, "loose"), X0, lanes=lanes, pop_width=pop_width)
    assert_exact(rp, np.asarray(X0), batch)


def test_one_lane_is_fj_sdfs_row_by_row():
    """One slot searches the rows one after another (nobody to steal from), in
    fj.sdfs's order: the same nodes, iterations and sequence as the plain vmap
    of fj.sdfs, row by row."""
    p = problem_of(9, 3, 2, 4, 4, "loose")
    X0 = states(9, 7, 3)
    for pop_width in (1, 2):
        pool = solve_batch(p, X0, lanes=1, pop_width=pop_width)
        plain = solve_batch(p, X0, solver="sdfs-vmap", pop_width=pop_width)
        for field in ("nodes", "iterations", "sequence", "feasible"):
            np.testing.assert_array_equal(getattr(pool, field), getattr(plain, field), err_msg=field)
        np.testing.assert_allclose(pool.cost, plain.cost, rtol=1e-14)


# ---------------------------------------------------------------- parameters
CONTROLS = np.array([-1.0, -0.5, 0.0, 0.5, 1.0])


def param_dynamics(x, u, p, xp=jnp):
    return xp.stack([x[..., 0] + 0.2 * x[..., 1], 0.9 * x[..., 1] + 0.2 * u - 0.05 * xp.sin(x[..., 0])], -1)


def param_problem(N=4):
    """Tracking problem whose set point ``p["r"]`` and input weight ``p["w"]`` are parameters."""
    return fj.Problem(lambda x, u, p: param_dynamics(x, u[0], p), jnp.asarray(CONTROLS),
                      lambda x, u, p: jnp.sum((x - p["r"]) ** 2) + p["w"] * u[0] ** 2, N,
                      lambda x, p: jnp.abs(x[0] - p["r"][0]) < 0.4)


def param_brute_force(x0, r, w, N=4):
    """NumPy optimum of ``param_problem`` for one parameter set, over all M^N sequences."""
    def step(x, u, t):
        x = param_dynamics(x, u[..., 0], None, xp=np)
        return x, np.sum((x - r) ** 2, axis=-1) + w * u[..., 0] ** 2
    return brute_force(step, CONTROLS, x0, N, lambda x: np.abs(x[..., 0] - r[0]) < 0.4)[0]


def test_params_give_each_row_its_set_point():
    prob = param_problem()
    B = 7
    rng = np.random.default_rng(3)
    params = {"r": jnp.asarray(rng.uniform(-0.5, 0.5, (B, 2))), "w": jnp.asarray(rng.uniform(0, 0.3, B))}
    X0 = jnp.zeros((B, 2))  # same state, different set points: only params tell rows apart
    for solver in SOLVERS:
        batch = solve_batch(prob, X0, solver=solver, params=params)
        assert np.all(batch.feasible) and len(set(np.asarray(batch.cost).tolist())) == B
        for b in range(B):
            ref = param_brute_force(X0[b], np.asarray(params["r"][b]), float(params["w"][b]))
            assert same_cost(batch.cost[b], ref), (solver, b)


def test_params_compile_once_for_any_values():
    prob = param_problem()
    traces = []
    counted = fj.Problem(lambda x, u, p: (traces.append(1), prob.dynamics(x, u, p))[1], prob.controls,
                         prob.stage_cost, prob.horizon, prob.terminal)
    rng = np.random.default_rng(4)

    def run(B):
        params = {"r": jnp.asarray(rng.uniform(-1, 1, (B, 2))), "w": jnp.asarray(rng.uniform(0, 0.3, B))}
        return solve_batch(counted, jnp.asarray(rng.uniform(-1, 1, (B, 2))), params=params)

    run(5)
    after_first, compiled = len(traces), compile_count()
    run(5)
    assert len(traces) == after_first and compile_count() == compiled  # new states and parameter values


def test_no_retrace_on_second_call():
    rp = make(5, 2, 1, 4, 3, "loose")
    traces = []
    p = fj.Problem(lambda x, u: (traces.append(1), rp.dynamics(x, u))[1], jnp.asarray(rp.controls),
                   lambda x, u: rp.stage_cost(x, u), rp.N, lambda x: rp.terminal(x))
    for solver in SOLVERS:
        solve_batch(p, states(0, 6, 2), solver=solver)
        after_first, compiled = len(traces), compile_count()
        second = solve_batch(p, states(1, 6, 2), solver=solver)
        assert len(traces) == after_first and compile_count() == compiled, solver
        assert second.cost.shape == (6,)


# ---------------------------------------------------------------- validation
def test_bad_input_is_refused_clearly():
    p = make(0, 3, 2, 4, 3, "none").problem()
    X0 = states(0, 4, 3)
    with pytest.raises(ValueError, match=r"\[B, n\]"):
        solve_batch(p, X0[0])
    with pytest.raises(ValueError, match="empty batch"):
        solve_batch(p, jnp.zeros((0, 3)))
    with pytest.raises((TypeError, ValueError), match=r"dynamics\(x, u\) failed on inputs of shape"):
        solve_batch(p, states(0, 4, 2))  # n does not match dynamics
    with pytest.raises(TypeError, match="floating"):
        solve_batch(p, jnp.zeros((4, 3), jnp.int32))
    with pytest.raises(ValueError, match=r"NaN or inf in rows \[2\]"):
        solve_batch(p, X0.at[2, 1].set(jnp.nan))
    with pytest.raises(ValueError, match="solver must be one of"):
        solve_batch(p, X0, solver="dfs")
    with pytest.raises(ValueError, match="pop_width"):
        solve_batch(p, X0, pop_width=0)
    with pytest.raises(ValueError, match="max_memory"):
        solve_batch(p, X0, max_memory=0)
    with pytest.raises(ValueError, match="cores"):
        solve_batch(p, X0, cores=0)
    with pytest.raises(ValueError, match="cores=2 splits the rows of an un-jitted"):
        jax.jit(lambda X: solve_batch(p, X, cores=2).cost)(X0)


def test_bad_params_are_refused_clearly():
    prob = param_problem()
    X0 = jnp.zeros((4, 2))
    good = {"r": jnp.zeros((4, 2)), "w": jnp.zeros(4)}
    with pytest.raises(ValueError, match=r"\['w'\] must have leading axis B = 4"):
        solve_batch(prob, X0, params={"r": good["r"], "w": jnp.zeros(3)})
    with pytest.raises(ValueError, match="leading axis"):
        solve_batch(prob, X0, params={"r": good["r"], "w": jnp.float64(0.1)})
    with pytest.raises(TypeError, match="dynamics"):
        solve_batch(make(0, 2, 1, 3, 3).problem(), X0, params=good)  # callables without p
    with pytest.raises(ValueError, match="no array leaves"):
        solve_batch(prob, X0, params={})
    with pytest.raises(ValueError, match="cores=2 splits the rows of an un-jitted"):  # traced params, concrete X0
        jax.jit(lambda p: solve_batch(prob, X0, params=p, cores=2).cost)(good)


# ---------------------------------------------------------------- memory
@pytest.mark.parametrize("solver", SOLVERS)
def test_memory_limit_chunks_or_refuses(solver):
    p = make(6, 3, 1, 5, 4, "loose").problem()
    X0 = states(6, 10, 3)
    lanes = {"lanes": 4} if solver == "sdfs" else {}  # the pool's option (the other solvers refuse it)
    whole = solve_batch(p, X0, solver=solver, **lanes)
    if solver == "sdfs":
        fixed, one_row = pool_memory(p, 3, X0.dtype.itemsize, 4), pool_row_memory(p, 3, X0.dtype.itemsize)
    else:
        fixed, one_row = 0, row_memory(p, 3, X0.dtype.itemsize, solver)
    chunked = solve_batch(p, X0, solver=solver, max_memory=fixed + 3 * one_row, **lanes)  # 3 rows, last one short
    # The pool's node counts depend on which rows share it; costs and sequences do not.
    for field in ("cost", "sequence", "feasible") + (("nodes",) if solver != "sdfs" else ()):
        np.testing.assert_array_equal(getattr(chunked, field), getattr(whole, field))
    with pytest.raises(ValueError, match="max_memory"):
        solve_batch(p, X0, solver=solver, max_memory=fixed + one_row - 1, **lanes)
    if solver == "sdfs":
        with pytest.raises(ValueError, match="lanes"):
            solve_batch(p, X0, lanes=0)


# ---------------------------------------------------------------- devices
FOUR_DEVICES = """
import jax, numpy as np
jax.config.update("jax_enable_x64", True)
from firhc_jax._src.search.batch import solve_batch
from random_problems import make
from reference import brute_force, same_cost
assert jax.local_device_count() == 4, jax.local_devices()
rp = make(7, 3, 1, 5, 4, "loose")
p = rp.problem()
for solver in SOLVERS:
    B = 10 if solver == "sdfs" else 12  # 10: padded to 12 rows, three per device
    X0 = np.random.default_rng(B).uniform(-1, 1, (B, 3))
    one = solve_batch(p, X0, solver=solver, devices=jax.local_devices()[:1])
    four = solve_batch(p, X0, solver=solver)
    if B == 12:
        assert len(four.cost.sharding.device_set) == 4, four.cost.sharding  # the rows were split
    # The pool's node counts depend on which rows share a device; costs and sequences do not.
    for field in ("sequence", "feasible", "first_input") + (("nodes",) if solver != "sdfs" else ()):
        np.testing.assert_array_equal(getattr(one, field), getattr(four, field), err_msg=f"{solver} {field}")
    # Same sequences; their costs may differ in the last bit where XLA vectorises
    # a transcendental differently for 3 and 12 rows per device.
    np.testing.assert_allclose(one.cost, four.cost, rtol=1e-14, atol=0, err_msg=solver)
    assert np.any(one.feasible), solver
print("same on 1 and 4 devices")
"""


@pytest.mark.slow
def test_four_host_devices_give_the_same_results():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu",
               PYTHONPATH=os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]))
    script = f"SOLVERS = {SOLVERS!r}\n" + FOUR_DEVICES
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env,
                         cwd=ROOT)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "same on 1 and 4 devices" in out.stdout


def test_error_flags_reach_the_caller():
    p = fj.Problem(lambda x, u: x + u, jnp.array([-1.0, 1.0]), lambda x, u: x[0], 3)  # cost < 0 below x = 0
    with pytest.raises(ValueError, match="negative"):
        solve_batch(p, jnp.array([[2.0], [-0.5]]))
    nan = fj.Problem(lambda x, u: jnp.where(u[0] > 0, jnp.nan, x - 0.1), jnp.array([-1.0, 1.0]),
                     lambda x, u: x[0] ** 2, 2)
    with pytest.warns(RuntimeWarning, match="NaN"):
        r = solve_batch(nan, jnp.array([[1.0], [2.0]]))
    np.testing.assert_array_equal(r.sequence, [[0, 0], [0, 0]])
    assert np.all(r.nan_encountered) and not np.any(r.negative_cost)


# ---------------------------------------------------------------- property test of the pool
import param_problems as pp  # noqa: E402
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

# Lanes and pop width are compile-time constants: one setting per shape (each setting on two shapes), so that
# one compiled pool per shape serves every example of it.
POOL_SETTING = {shape: [(2, 1), (16, 2)][i % 2] for i, shape in enumerate(pp.SHAPES)}


@settings(max_examples=16, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(pp.SHAPES), st.integers(0, 2**32 - 1), st.sampled_from(["none", "loose", "tight"]))
def test_pool_matches_brute_force_per_row(shape, seed, tightness):
    """Random problems, one random parameter set and state per row, 7 rows: with 2 lanes rows queue and the
    last rows' searches are shared by stealing; with 16 lanes idle slots steal from the start. Every row's
    cost is the brute-force optimum (one compile per shape: everything is a parameter)."""
    lanes, K = POOL_SETTING[shape]
    rng = np.random.default_rng(seed)
    rows = [pp.draw_params(rng, shape, tightness) for _ in range(7)]
    params = {k: jnp.asarray(np.stack([r[k] for r in rows])) for k in rows[0]}
    X0 = rng.uniform(-1, 1, (7, shape[0]))
    res = solve_batch(pp.problem(shape), X0, params=params, lanes=lanes, pop_width=K)
    for b in range(7):
        ref, _ = pp.cost_to_go(shape, rows[b], X0[b], shape[3])
        assert pp.same_cost(float(res.cost[b]), ref), (b, float(res.cost[b]), ref)
        assert bool(res.feasible[b]) == np.isfinite(ref)
        if np.isfinite(ref):  # the stored path (stolen subtrees included) really achieves the cost
            again = pp.sequence_cost(rows[b], X0[b], np.asarray(res.sequence[b]))
            assert pp.same_cost(again, float(res.cost[b])), (b, again, float(res.cost[b]))


# ---------------------------------------------------------------- budgets
def test_a_budget_below_one_expansion_expands_nothing():
    """As fj.sdfs, which stops before an iteration could take the count above max_nodes: a row whose budget
    cannot cover one expansion (K M = 5 children) gets no nodes and complete=False (the pool once expanded
    every row's root, 5 nodes per row with max_nodes=1). The shapes of the lanes test above: no compile."""
    X0 = states(8, 11, 3)
    for max_nodes in (1, 4):
        res = solve_batch(problem_of(8, 3, 1, 5, 5, "loose"), X0, lanes=3, max_nodes=max_nodes)
        np.testing.assert_array_equal(res.nodes, 0)
        assert not np.any(res.complete) and not np.any(res.feasible)


def test_one_lane_keeps_any_budget_exactly_as_fj_sdfs():
    """One slot never shares a row, so the documented overshoot (lanes - 1) K M is 0: with any budget the pool
    is fj.sdfs row by row (node counts, completeness, incumbents), also below one expansion (K M = 4). The shapes
    of test_one_lane_is_fj_sdfs_row_by_row: no compile."""
    p = problem_of(9, 3, 2, 4, 4, "loose")
    X0 = states(9, 7, 3)
    for max_nodes in (3, 4, 7, 30, 90):
        pool = solve_batch(p, X0, lanes=1, max_nodes=max_nodes)
        plain = solve_batch(p, X0, solver="sdfs-vmap", max_nodes=max_nodes)
        for field in ("nodes", "complete", "sequence", "feasible", "iterations"):
            np.testing.assert_array_equal(getattr(pool, field), getattr(plain, field), err_msg=f"{max_nodes} {field}")
        assert np.all(np.asarray(pool.nodes) <= max_nodes)



def test_a_progress_bar_never_changes_a_batchs_results(capsys):
    """54 rows with tight terminal sets on a pool of 2 lanes under a budget of 30 nodes: with a bar
    (``progress=True``) every field of every row is that of the call without one, for the solvers whose rows
    share a pool (the bar then shows the time elapsed) and for those that solve each row on its own (it counts
    the rows, in chunks). Chunks of rows would regroup a pool's rows, and where a budget cuts a shared row its
    incumbent depends on the rows beside it: row 28 here is infeasible in one call and found a sequence in its
    chunk."""
    shape = pp.SHAPES[0]
    rng = np.random.default_rng(2)
    rows = [pp.draw_params(rng, shape, "tight") for _ in range(54)]
    params = {k: jnp.asarray(np.stack([r[k] for r in rows])) for k in rows[0]}
    X0 = rng.uniform(-1, 1, (54, shape[0]))
    for solver, options in (("pool", {"lanes": 2}), ("sdfs", {"lanes": 2}), ("sdfs-vmap", {})):
        plain = solve_batch(pp.problem(shape), X0, params=params, solver=solver, max_nodes=30, progress=False,
                            **options)
        assert capsys.readouterr().err == ""
        shown = solve_batch(pp.problem(shape), X0, params=params, solver=solver, max_nodes=30, progress=True,
                            **options)
        for field in fj.SearchResult._fields:
            np.testing.assert_array_equal(getattr(shown, field), getattr(plain, field), err_msg=f"{solver} {field}")
        err = capsys.readouterr().err
        assert ("54/54" in err) == (solver == "sdfs-vmap") and "solve_batch" in err, err


# ---------------------------------------------------------------- every core of a CPU
def dispatches(monkeypatch) -> list:
    """Record the execution stream of every dispatch of a compiled batch (``solve_batch`` calls the compiled
    batch once per part)."""
    seen, real = [], batch_module.compiled

    def counting(*args, **kwargs):
        run = real(*args, **kwargs)

        def dispatch(*a):
            seen.append(xla_client._xla.get_execution_stream_id())
            return run(*a)
        return dispatch

    monkeypatch.setattr(batch_module, "compiled", counting)
    return seen


@pytest.mark.slow
@pytest.mark.skipif(usable_cores() < 2, reason="needs a process that may use at least 2 cores")
def test_a_default_solve_keeps_every_core_busy(monkeypatch):
    """On one CPU device, a default solve dispatches one part per usable core without waiting between them,
    each on its own execution stream (executions on one stream wait for each other; on different streams they
    run side by side): as many executions in flight as cores. Where one part's pool alone fills max_memory,
    one execution."""
    seen = dispatches(monkeypatch)
    rp = make(3, 2, 1, 3, 3, "loose")
    p, X0 = rp.problem(), states(3, 11, 2)
    res = solve_batch(p, X0, devices=jax.devices()[:1])
    assert len(seen) == min(usable_cores(), 11) and len(set(seen)) == len(seen) and 0 not in seen, seen
    assert_exact(rp, np.asarray(X0), res)
    seen.clear()
    # One pool of 11 lanes and one row: k >= 2 parts would need k pools of ceil(11 / k) lanes and k rows.
    whole = pool_memory(p, 2, X0.dtype.itemsize, 11) + pool_row_memory(p, 2, X0.dtype.itemsize)
    solve_batch(p, X0, devices=jax.devices()[:1], max_memory=whole)
    assert seen == [0]  # one execution, on the thread's own stream


def lower_bound(x, steps_left, p):
    """Admissible: every step costs at least its cheapest input's weight."""
    return steps_left * jnp.sum(p["w"] * jnp.min(p["U"] ** 2, axis=0))


def test_parts_give_the_single_execution_result():
    """Every solver, with per-row parameters, a lower bound and (sDFS solvers) a node budget: 3 parts give the
    costs, sequences, flags and node counts of one execution. The pool has one lane here, so that a row cut by
    the budget was searched alone, in fj.sdfs's order, whatever the parts (with shared rows the incumbent at the
    cut depends on the sharing); the default pool over parts is checked against brute force above."""
    shape = pp.SHAPES[0]
    rng = np.random.default_rng(5)
    rows = [pp.draw_params(rng, shape, "loose") for _ in range(7)]
    params = {k: jnp.asarray(np.stack([r[k] for r in rows])) for k in rows[0]}
    X0 = rng.uniform(-1, 1, (7, shape[0]))
    p = pp.problem(shape, lower_bound=lower_bound)
    cut = False
    for solver, options in (("sdfs", {"lanes": 1, "max_nodes": 12}), ("sdfs-vmap", {"max_nodes": 12}),
                            ("exhaustive", {})):
        one = solve_batch(p, X0, solver=solver, params=params, cores=1, **options)
        three = solve_batch(p, X0, solver=solver, params=params, cores=3, **options)
        for field in ("sequence", "feasible", "complete", "first_input", "nodes", "iterations", "negative_cost",
                      "nan_encountered", "overflow"):
            np.testing.assert_array_equal(getattr(three, field), getattr(one, field), err_msg=f"{solver} {field}")
        np.testing.assert_allclose(three.cost, one.cost, rtol=1e-14, atol=0, err_msg=solver)
        cut |= not np.all(one.complete)
    assert cut  # the budget stopped some rows
