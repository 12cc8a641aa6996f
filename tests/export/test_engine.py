"""``engine="c"``: eager searches and decisions in generated C give the XLA program's outputs, field by field.

Every field of ``fj.sdfs``'s result, and every output of ``ctrl.step`` (the applied input, the next state,
every ``StepInfo`` and ``SearchResult`` field), is compared with the default engine's along short closed
loops: floats to 1e-9 relative (the C code rounds as the C compiler does), integers and flags exactly, dtypes
and shapes equal.
"""
import re
import shutil
import threading

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from random_problems import make

import firhc_jax as fj
from firhc_jax._src.export import engine as c_engine

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler (cc) on this machine")


def same_outputs(xla, c, rtol=1e-9):
    """Two ``(u, state, info)`` triples agree leaf by leaf."""
    assert jax.tree_util.tree_structure(xla) == jax.tree_util.tree_structure(c)
    for path, a in jax.tree_util.tree_leaves_with_path(xla):
        b = c
        for key in path:
            b = b[key.idx] if hasattr(key, "idx") else getattr(b, key.name)
        a, b = np.asarray(a), np.asarray(b)
        where = jax.tree_util.keystr(path)
        assert (a.dtype, a.shape) == (b.dtype, b.shape), where
        if np.issubdtype(a.dtype, np.floating):
            np.testing.assert_allclose(b, a, rtol=rtol, atol=0, equal_nan=True, err_msg=where)
        else:
            np.testing.assert_array_equal(b, a, err_msg=where)


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2**31 - 1), st.integers(1, 5), st.integers(1, 5), st.sampled_from(["none", "loose", "tight"]),
       st.sampled_from([None, 7, 40]), st.booleans(), st.booleans(), st.integers(1, 3))
def test_c_searches_give_fj_sdfs_results(seed, N, M, terminal, max_nodes, warm, params, pop_width):
    rp = make(seed, 2, 1, M, N, terminal)
    problem = rp.problem()
    if params:
        problem = problem.replace(dynamics=lambda x, u, p: rp.dynamics(x, u) + 0.05 * p["ref"][0],
                                  stage_cost=lambda x, u, p: rp.stage_cost(x, u) + p["w"] * jnp.sum(x**2),
                                  terminal=None if rp.radius is None else (lambda x, p: rp.terminal(x)))
    rng = np.random.default_rng(seed)
    for x0 in rng.uniform(-1, 1, (3, 2)):
        p = {"ref": rng.normal(0, 0.3, (N, 2)), "w": np.float64(0.2)} if params else None
        ws = rng.integers(0, M, N) if warm else None
        same_outputs(fj.sdfs(problem, x0, params=p, warm_start=ws, max_nodes=max_nodes, pop_width=pop_width),
                     fj.sdfs(problem, x0, params=p, warm_start=ws, max_nodes=max_nodes, pop_width=pop_width,
                             engine="c"))


@pytest.mark.parametrize("pop_width", [2, 3])
def test_c_searches_popping_several_nodes_give_fj_sdfs_results(pop_width):
    """No warm start: the leaves of every popped node decide."""
    for seed in range(3):
        rp = make(seed, 2, 1, 4, 4, "none")
        problem = rp.problem()
        for x0 in np.random.default_rng(seed).uniform(-1, 1, (5, 2)):
            same_outputs(fj.sdfs(problem, x0, pop_width=pop_width), fj.sdfs(problem, x0, pop_width=pop_width,
                                                                             engine="c"))


def test_a_c_search_checks_and_raises_as_fj_sdfs():
    problem = fj.Problem(lambda x, u, p: x * p["a"] + u, np.array([-1.0, 1.0]),
                         lambda x, u, p: jnp.sum(x**2) - p["shift"], 3)
    good = {"a": np.float64(0.5), "shift": np.float64(0.0)}
    fj.sdfs(problem, np.array([0.3]), params=good, warm_start=np.array([0, 1, 0]), engine="c")
    for call, match in [((np.array([np.nan]), good, None), "NaN or inf"),
                        ((np.array([0.3]), {"a": np.float64(np.inf), "shift": np.float64(0.0)}, None), "NaN or inf"),
                        ((np.array([0.3]), {"a": np.float64(0.5), "shift": np.float64(10.0)}, None), "negative"),
                        ((np.array([0.3]), good, np.array([0, 2, 0])), "warm_start indices")]:
        with pytest.raises(ValueError, match=match):  # the values of a call that skips the checks (lean)
            x0, p, ws = call
            fj.sdfs(problem, x0, params=p, warm_start=ws, engine="c")
    with pytest.raises(ValueError, match="engine must be one of"):
        fj.sdfs(problem, np.array([0.3]), params=good, engine="C")
    traced = jax.jit(lambda x: fj.sdfs(problem, x, params=good, engine="c").cost)(jnp.array([0.3]))  # XLA
    np.testing.assert_allclose(float(traced), float(fj.sdfs(problem, np.array([0.3]), params=good).cost))


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2**31 - 1), st.sampled_from(["none", "loose", "tight"]),
       st.sampled_from([None, "unconstrained"]), st.booleans(), st.sampled_from([None, 25, 90]), st.booleans(),
       st.booleans())
def test_c_steps_give_the_xla_steps_outputs(seed, terminal, fallback, warm, max_nodes, safe, params):
    rp = make(seed, 2, 1, 3, 4, terminal)
    base = rp.problem()
    if params:  # a per-step reference the callables read
        problem = base.replace(dynamics=lambda x, u, p: rp.dynamics(x, u) + 0.05 * p["ref"][0],
                               stage_cost=lambda x, u, p: rp.stage_cost(x, u) + p["w"] * jnp.sum(x**2),
                               terminal=None if rp.radius is None else (lambda x, p: rp.terminal(x)))
    else:
        problem = base
    options = dict(fallback=fallback, warm_start=warm, u_safe=rp.controls[0] if safe else None,
                   observe=lambda x, u_prev, *p: x * 0.9 + 0.01 * u_prev[0],
                   actuate=lambda x, u, *p: jnp.concatenate([u, u * 2.0]),
                   **({} if max_nodes is None else {"max_nodes": max_nodes}))
    xla, c = fj.FIRHC(problem, **options), fj.FIRHC(problem, engine="c", **options)
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1, 1, 2)
    s_xla, s_c = xla.init(x, rp.controls[1]), c.init(x, rp.controls[1])
    for _ in range(6):
        p = {"ref": rng.normal(0, 0.3, (4, 2)), "w": np.float64(0.2)} if params else None
        out_xla, out_c = xla.step(s_xla, x, p), c.step(s_c, x, p)
        same_outputs(out_xla, out_c)
        (u, s_xla, _), (_, s_c, _) = out_xla, out_c
        x = np.asarray(rp.dynamics(jnp.asarray(x), jnp.asarray(u[:1])))


SOLVERS = [("sdfs", {"pop_width": 2}), ("sdfs-vmap", {"pop_width": 3}), ("pool", {}),
           ("pool", {"lanes": 3, "pop_width": 2}), ("pool", {"lanes": 1}), ("exhaustive", {}),
           ("exhaustive", {"method": "dfs", "pop_width": 2})]


@pytest.mark.parametrize("solver, options", SOLVERS)
@settings(max_examples=3, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2**31 - 1), st.integers(2, 5), st.integers(2, 4), st.sampled_from(["none", "loose", "tight"]),
       st.sampled_from([None, 20, 60]))
def test_c_steps_of_every_solver_give_the_xla_steps_outputs(solver, options, seed, M, N, terminal, max_nodes):
    """Each solver's search in C, node for node: the pool's slots and steals, K nodes a pop, the level search's
    lexicographic order and the exhaustive depth-first search, with budgets, warm starts and the fallback."""
    rp = make(seed, 2, 1, M, N, terminal)
    budget = {} if max_nodes is None or solver == "exhaustive" else {"max_nodes": max_nodes}
    kwargs = dict(options, fallback="unconstrained" if terminal == "tight" else None,
                  warm_start=solver != "exhaustive", **budget)
    xla, c = fj.FIRHC(rp.problem(), solver, **kwargs), fj.FIRHC(rp.problem(), solver, engine="c", **kwargs)
    x = np.random.default_rng(seed).uniform(-1, 1, 2)
    s_xla, s_c = xla.init(x), c.init(x)
    for _ in range(5):
        out_xla, out_c = xla.step(s_xla, x), c.step(s_c, x)
        same_outputs(out_xla, out_c)
        (u, s_xla, _), (_, s_c, _) = out_xla, out_c
        x = np.asarray(rp.dynamics(jnp.asarray(x), jnp.asarray(u)))


@pytest.mark.parametrize("solver, options", SOLVERS + [("sdfs", {}), ("pool", {"lanes": 4, "pop_width": 2})])
def test_exact_ties_go_to_the_sequence_xla_picks(solver, options):
    """Integer costs: many sequences cost exactly the same, and the order of pops, steals and leaves decides which
    one a search returns; the C engine returns XLA's, with its node count."""
    problem = fj.Problem(lambda x, u: x + u, np.array([[-1.0, 0.0], [0.0, 1.0], [1.0, -1.0], [0.0, 0.0]]),
                         lambda x, u: jnp.sum(jnp.abs(x)), 5)
    for budget in [None] if solver == "exhaustive" else [None, 60]:
        kwargs = dict(options, **({} if budget is None else {"max_nodes": budget}))
        xla, c = fj.FIRHC(problem, solver, **kwargs), fj.FIRHC(problem, solver, engine="c", **kwargs)
        for x in ([2.0, -1.0], [3.0, 2.0], [-2.0, 1.0], [0.0, 3.0]):
            x = np.array(x)
            same_outputs(xla.step(xla.init(x), x), c.step(c.init(x), x))


def test_the_inverter_controller_decides_as_in_xla():
    from firhc_jax.models import inverter

    prm = inverter.InverterParams()
    mem = inverter.make_problem(2, prm)
    refs = inverter.horizon_references(prm, 30, 2)
    xla = fj.FIRHC(mem.problem, observe=mem.observe, warm_start=True, max_nodes=40, fallback="unconstrained")
    c = fj.FIRHC(mem.problem, observe=mem.observe, warm_start=True, max_nodes=40, fallback="unconstrained",
                 engine="c")
    plant = jax.jit(inverter.make_plant(prm))
    x = np.asarray(inverter.initial_currents(prm))
    s_xla, s_c = xla.init(x), c.init(x)
    for k in range(30):
        p = {"ref": refs[k], "lambda_u": np.float64(0.1)}
        out_xla, out_c = xla.step(s_xla, x, p), c.step(s_c, x, p)
        same_outputs(out_xla, out_c)
        (u, s_xla, _), (_, s_c, _) = out_xla, out_c
        x = np.asarray(plant(x, u))


def test_one_shot_calls_check_and_raise_as_in_xla():
    problem = fj.Problem(lambda x, u, p: x * p["a"] + u, np.array([-1.0, 1.0]),
                         lambda x, u, p: jnp.sum(x**2) - p["shift"], 2, terminal=lambda x, p: jnp.sum(x**2) < 1.0)
    xla, c = fj.FIRHC(problem), fj.FIRHC(problem, engine="c")
    good = {"a": np.float64(0.5), "shift": np.float64(0.0)}
    same_outputs(xla(np.array([0.3]), good), c(np.array([0.3]), good))
    same_outputs(xla(np.array([0.3]), good, u_prev=np.array([1.0])), c(np.array([0.3]), good, u_prev=np.array([1.0])))
    with pytest.raises(fj.InfeasibleError):
        c(np.array([90.0]), good)
    with pytest.raises(ValueError, match="NaN or inf"):
        c(np.array([np.nan]), good)
    with pytest.raises(ValueError, match="NaN or inf"):
        c(np.array([0.3]), {"a": np.float64(np.inf), "shift": np.float64(0.0)})
    with pytest.raises(ValueError, match="negative"):
        c(np.array([0.3]), {"a": np.float64(0.5), "shift": np.float64(10.0)})
    # a step reports instead of raising, as the XLA step does
    _, _, info = c.step(c.init(np.array([0.3])), np.array([np.nan]), good)
    assert info.held and info.result.nan_encountered and not info.result.feasible


def test_the_engine_is_checked_when_the_controller_is_made(monkeypatch):
    problem = fj.Problem(lambda x, u: x + u, np.array([-1.0, 1.0]), lambda x, u: jnp.sum(x**2), 2)
    with pytest.raises(ValueError, match="engine must be one of"):
        fj.FIRHC(problem, engine="fortran")
    with pytest.raises(ValueError, match="callable warm_start"):
        fj.FIRHC(problem, engine="c", warm_start=lambda problem, x, prev, p: prev)
    monkeypatch.setenv("CC", "no-such-compiler-here")
    with pytest.raises(RuntimeError, match="no-such-compiler-here"):
        fj.FIRHC(problem, engine="c")


def test_a_search_too_large_for_the_threads_stack_is_refused():
    problem = fj.Problem(lambda x, u: x + u, np.array([-1.0, 0.0, 1.0]), lambda x, u: jnp.sum(x**2), 40)
    ctrl = fj.FIRHC(problem, "pool", lanes=128, pop_width=16, engine="c")
    with pytest.raises(ValueError, match="stack: this one needs"):
        ctrl.step(ctrl.init(np.zeros(2)), np.zeros(2))


def test_an_untranslatable_callable_is_named_at_the_first_step():
    problem = fj.Problem(lambda x, u: x + u, np.array([-1.0, 1.0]), lambda x, u: jnp.sort(x)[0] ** 2, 2)
    ctrl = fj.FIRHC(problem, engine="c")
    with pytest.raises(ValueError, match="stage_cost.*'sort'"):
        ctrl.step(ctrl.init(np.zeros(2)), np.zeros(2))


def test_a_signature_builds_once_and_traced_calls_run_in_xla(monkeypatch):
    builds = []
    real = c_engine.CStep.__init__
    monkeypatch.setattr(c_engine.CStep, "__init__", lambda self, *a: builds.append(1) or real(self, *a))
    problem = fj.Problem(lambda x, u: 0.5 * x + u, np.array([-1.0, 0.0, 1.0]), lambda x, u: jnp.sum(x**2), 3)
    ctrl = fj.FIRHC(problem, engine="c", warm_start=True)
    state = ctrl.init(np.zeros(2))
    for x in np.random.default_rng(0).uniform(-1, 1, (5, 2)):
        u, state, info = ctrl.step(state, x)
    twin = fj.FIRHC(problem, engine="c", warm_start=True)  # equal options share the built code
    twin.step(twin.init(np.zeros(2)), np.ones(2))
    assert len(builds) == 1
    ctrl.step(state, np.zeros(3))
    assert len(builds) == 2
    u_jit, _, info_jit = jax.jit(ctrl.step)(state, jnp.zeros(2))  # traced: the XLA decision
    u_eager, _, info_eager = ctrl.step(state, np.zeros(2))
    np.testing.assert_allclose(np.asarray(u_jit), u_eager)
    assert isinstance(u_jit, jax.Array) and isinstance(u_eager, np.ndarray)


def test_threads_decide_as_one_thread():
    problem = fj.Problem(lambda x, u: jnp.tanh(x) + u, np.linspace(-1, 1, 5)[:, None],
                         lambda x, u: jnp.sum(x**2) + 0.1 * jnp.sum(u**2), 4)
    ctrl = fj.FIRHC(problem, engine="c")
    xs = np.random.default_rng(1).uniform(-2, 2, (40, 1))
    serial = [ctrl(x)[1].result.cost for x in xs]
    out = [None] * len(xs)

    def work(rows):
        for i in rows:
            out[i] = ctrl(xs[i])[1].result.cost

    threads = [threading.Thread(target=work, args=(range(t, len(xs), 4),)) for t in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    np.testing.assert_array_equal(out, serial)


@pytest.mark.float32
def test_the_c_engine_returns_the_sessions_dtypes():
    """With x64 off the outputs have the float32 decision's dtypes; the C code computes in float32 as the
    exported callables do, so the values agree to float32's precision."""
    rp = make(7, 2, 1, 4, 3, "loose")
    xla, c = fj.FIRHC(rp.problem(), warm_start=True), fj.FIRHC(rp.problem(), warm_start=True, engine="c")
    x = np.array([0.4, -0.2], jax.dtypes.canonicalize_dtype(np.float64))  # float32 with x64 off
    out_xla, out_c = xla.step(xla.init(x), x), c.step(c.init(x), x)
    same_outputs(out_xla, out_c, rtol=1e-5)


def test_a_plant_with_sub_steps_is_searched_across_the_control_set():
    """A child that is a loop (a plant's sub-steps) is translated operation by operation across the control set
    for the engine (the form a compiler vectorises): the same results as XLA's, and the same as the row-by-row
    translation ``fj.export_c`` writes."""
    def dynamics(x, u):
        def sub_step(i, h):
            return h + 0.05 * (u - jnp.sqrt(jnp.abs(h)) * jnp.array([1.0, 0.7]))
        return jax.lax.fori_loop(0, 4, sub_step, x)

    problem = fj.Problem(dynamics, np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0], [0.5, 0.2]]),
                         lambda x, u: jnp.sum((x - 0.6) ** 2) + 0.01 * jnp.sum(u), 4,
                         terminal=lambda x: jnp.all(jnp.abs(x - 0.6) < 0.5))
    rows = fj.export_c(problem, c_engine._build_folder(), name="rows_form", x0=np.zeros(2)).compile()
    for x0 in np.random.default_rng(3).uniform(0, 1.5, (6, 2)):
        c = fj.sdfs(problem, x0, engine="c")
        same_outputs(fj.sdfs(problem, x0), c)
        code, sequence, cost, nodes = rows.solve(x0)
        assert nodes == int(c.nodes) and (cost == float(c.cost) or np.isinf(cost) == np.isinf(float(c.cost)))
    run = lean_run(problem)
    assert "_rows(" in run.lib.exported.source.read_text()  # the engine took the across form
    assert "_rows(" not in rows.exported.source.read_text()


def lean_run(problem):
    """The engine's compiled search of ``problem`` for a float64 ``[2]`` state, as ``fj.sdfs`` keeps it."""
    from firhc_jax._src.runtime import lean

    entry = ("sdfs", problem, int, 1, False, int, fj.sdfs.__kwdefaults__["max_memory"], "c")
    return lean.recall(entry, (np.zeros(2), None, None))


@settings(max_examples=4, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2**31 - 1), st.integers(1, 4), st.booleans(), st.sampled_from([None, 30]), st.booleans())
def test_c_tracking_solves_give_lt_solve_results(seed, N, warm, max_nodes, disturbance):
    """``lt.solve(..., engine="c")`` (observe, the parameter map, the search over classes and the members in C)
    gives ``lt.solve``'s result field by field, warm starts (indices into ``controls``) and budgets included."""
    from firhc_jax.models import three_level

    lt = three_level.make_problem(N)
    rng = np.random.default_rng(seed)
    for _ in range(3):
        x, u = rng.normal(0, 1, lt.n), np.asarray(lt.controls[rng.integers(len(lt.controls))], np.float64)
        y, d = rng.normal(0, 1, (N, lt.C.shape[0])), rng.normal(0, 0.1, (N, lt.n)) if disturbance else None
        ws = rng.integers(0, len(lt.controls), N) if warm else None
        same_outputs(lt.solve(x, u, y, d, warm_start=ws, max_nodes=max_nodes),
                     lt.solve(x, u, y, d, warm_start=ws, max_nodes=max_nodes, engine="c"), rtol=1e-12)


def test_a_c_tracking_solve_checks_and_raises_as_lt_solve():
    from firhc_jax.models import three_level

    lt = three_level.make_problem(2)
    x, u, y = np.zeros(lt.n), np.zeros(lt.m), np.zeros((2, lt.C.shape[0]))
    lt.solve(x, u, y, engine="c")
    for args, match in [((np.full(lt.n, np.nan), u, y, None), "NaN or inf"),
                        ((x, np.full(lt.m, np.inf), y, None), "NaN or inf"),
                        ((x, u, np.full_like(y, np.nan), None), "NaN or inf"),
                        ((x, u, y, np.full(2, 99)), "warm_start indices")]:
        with pytest.raises(ValueError, match=match):  # the values of a call that skips the checks (lean)
            lt.solve(*args[:3], warm_start=args[3], engine="c")
    with pytest.raises(ValueError, match="engine must be one of"):
        lt.solve(x, u, y, engine="fpga")


def test_what_a_child_computes_from_its_input_alone_is_folded_into_tables():
    """The engine's export computes at export what a child derives from its input alone (a LinearTracking
    child's class lookup), read per row from tables; ``fj.export_c`` keeps computing it in the loop. Both give
    ``lt.solve``'s nodes."""
    from firhc_jax._src.runtime import lean
    from firhc_jax.models import three_level

    lt = three_level.make_problem(2)
    x, u, y = np.full(lt.n, 0.3), np.zeros(lt.m), np.ones((2, lt.C.shape[0]))
    c = lt.solve(x, u, y, engine="c")
    run = lean.recall(("lt.solve", lt, True, "c"), (x, u, y, None, None))
    assert re.search(r"fj_table\d+\[child \* ", run.lib.exported.source.read_text())
    plain = fj.export_c(lt, c_engine._build_folder(), name="plain_lt", params=(y, np.zeros((2, lt.n))), x0=x)
    assert not re.search(r"fj_table\d+\[child \* ", plain.source.read_text())
    assert int(c.nodes) == int(lt.solve(x, u, y).nodes)
