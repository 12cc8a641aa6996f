"""``fj.export_c``: the generated C search and controller give ``fj.sdfs``'s and ``ctrl.step``'s answers.

Each case exports, compiles with the system C compiler and calls the code through ``ctypes``. Costs agree to
1e-9 relative; sequences are equal or, at an exact tie, of equal cost; node counts are equal (every case
here rounds alike in both).
"""
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from random_problems import make

import firhc_jax as fj

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler (cc) on this machine")
SETTINGS = settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def same_search(problem, c_out, r, params=None, x0=None):
    """The C result ``(code, sequence, cost, nodes)`` is ``fj.sdfs``'s ``r``."""
    code, sequence, cost, nodes = c_out
    assert code == int(bool(r.feasible)), (code, r)
    if np.isfinite(float(r.cost)):
        np.testing.assert_allclose(cost, float(r.cost), rtol=1e-9)
        if not np.array_equal(sequence, np.asarray(r.sequence)):  # a tie: the C sequence costs the same
            again = fj.rollout_cost(problem, x0, jnp.asarray(sequence, jnp.int32), params=params)[0]
            np.testing.assert_allclose(float(again), float(r.cost), rtol=1e-9)
    else:
        assert np.isinf(cost) and np.all(sequence == -1)
    assert nodes == int(r.nodes)


def featured(seed: int, N: int, M: int, terminal: str, step_index: bool, previous_state: bool,
             constraint: bool, terminal_cost: bool, bound: bool, first_input: bool) -> tuple[fj.Problem, dict]:
    """A random problem with the chosen features, and its params (a reference along the horizon)."""
    rp = make(seed, 2, 1, M, N, terminal)
    w_min = float(np.min(rp.w[0] * rp.controls[:, 0] ** 2))

    def k_of(args):
        return args[0] if step_index else 0

    def dynamics(x, u, *rest):
        p = rest[-1]
        return rp.dynamics(x, u) + 0.05 * p["ref"][k_of(rest)]

    def stage_cost(*args):
        if previous_state:
            x, x_next, u, *rest = args
            extra = 0.1 * jnp.sum((x_next - x) ** 2)
        else:
            x_next, u, *rest = args
            extra = 0.0
        p = rest[-1]
        return rp.stage_cost(x_next, u) + p["weight"] * jnp.sum((x_next - p["ref"][k_of(rest)]) ** 2) + extra

    def limit(*args):
        x_next = args[1] if previous_state else args[0]
        return jnp.max(jnp.abs(x_next)) < 1.2

    return fj.Problem(
        dynamics, rp.controls, stage_cost, N,
        terminal=None if rp.radius is None else (lambda x, p: rp.terminal(x)),
        terminal_cost=(lambda x, p: 0.3 * jnp.sum(x**2)) if terminal_cost else None,
        constraint=limit if constraint else None,
        # Any bound will do for C against fj.sdfs (both prune with it); +inf in part of the space tests discards.
        lower_bound=(lambda x, s, p: jnp.where(x[0] > 0.6, jnp.inf, s * w_min)) if bound else None,
        first_input_of=(lambda x0, seq, p: jnp.asarray(rp.controls, x0.dtype)[seq[0]] * 0.5) if first_input else None,
        step_index=step_index, previous_state=previous_state,
    ), {"ref": jnp.asarray(np.random.default_rng(seed).normal(0, 0.3, (N, 2))), "weight": jnp.asarray(0.2)}


@SETTINGS
@given(st.integers(0, 2**31 - 1), st.integers(1, 5), st.integers(1, 5), st.sampled_from(["none", "loose", "tight"]),
       st.lists(st.booleans(), min_size=6, max_size=6), st.sampled_from([None, 3, 40, 400]))
def test_generated_search_equals_sdfs_on_random_problems(tmp_path_factory, seed, N, M, terminal, features, max_nodes):
    problem, params = featured(seed, N, M, terminal, *features)
    lib = fj.export_c(problem, tmp_path_factory.mktemp("c"), name="rand", params=params, x0=np.zeros(2),
                      max_nodes=max_nodes).compile()
    for x0 in np.random.default_rng(seed).uniform(-1, 1, (3, 2)):
        same_search(problem, lib.solve(x0, params), fj.sdfs(problem, x0, params=params, max_nodes=max_nodes),
                    params, x0)


MODELS = ("hopper", "tanks", "tanks-bound", "inverter", "pumping", "synthetic", "spacecraft", "three_level",
          "grid_converter", "thermal")


def model_case(name: str):
    """``(problem, params, states)`` of a model of ``firhc_jax.models``, built when its test runs."""
    from firhc_jax import models

    if name == "hopper":
        from firhc_jax.models import hopper

        P = hopper.HopperParams()
        contact = np.asarray(hopper.observe(jnp.asarray(hopper.initial_state(P)), jnp.zeros(1))).copy()
        contact[1] = -0.5  # moving down, in contact: a real decision
        return hopper.make_problem(3, P, bound=True), None, [contact]
    if name.startswith("tanks"):
        from firhc_jax.models import tanks

        if name == "tanks-bound":
            return tanks.make_problem(3, terminal_tol=0.05, bound=True), None, [tanks.initial_state()]
        return tanks.make_problem(3, switch_penalty=5.0), None, [tanks.initial_state(),
                                                                tanks.initial_state((0.1, 0.3, 0.05), 3)]
    if name == "inverter":
        from firhc_jax.models import inverter

        mem = inverter.make_problem(3)
        ref = inverter.horizon_references(inverter.InverterParams(), 1, 3)[0]
        p = {"ref": jnp.asarray(ref), "lambda_u": jnp.asarray(0.1)}
        return mem.problem, p, [np.asarray(mem.observe(jnp.array([1.0, -2.0]), jnp.array([1.0, 0.0, 0.0]), p))]
    if name == "pumping":
        from firhc_jax.models import pumping

        price, demand = pumping.forecast(6)
        hours = jax.tree_util.tree_map(lambda a: jnp.asarray(a[0]), pumping.horizon_params(price, demand, 1, 4))
        return pumping.make_problem(4, bound="target"), hours, [np.asarray(pumping.INITIAL_LEVELS)]
    if name == "synthetic":
        from firhc_jax.models import synthetic

        return synthetic.make_problem(3, dtype=np.float64), None, [np.asarray(synthetic.benchmark_state())]
    if name == "spacecraft":
        from firhc_jax.models import spacecraft

        x0s, inertia = spacecraft.random_loops(1, np.random.default_rng(0))
        return spacecraft.make_problem(2), {"inertia": jnp.asarray(inertia[0]), "fuel": jnp.asarray(5.0)}, [x0s[0]]
    import importlib

    lt = importlib.import_module(f"{models.__name__}.{name}").make_problem(3)
    rng = np.random.default_rng(1)
    u_prev = jnp.asarray(lt.controls[2], jnp.float64)
    return (lt.problem, lt.params(rng.normal(0, 1, (3, lt.C.shape[0]))),
            [np.asarray(lt.observe(jnp.asarray(rng.normal(0, 1, lt.n)), u_prev))])


@pytest.mark.parametrize("name", MODELS)
def test_generated_search_equals_sdfs_on_every_model(name, tmp_path):
    problem, params, states = model_case(name)
    lib = fj.export_c(problem, tmp_path, name=name.replace("-", "_"), params=params, x0=states[0]).compile()
    for x0 in states:
        same_search(problem, lib.solve(x0, params), fj.sdfs(problem, x0, params=params), params, x0)


@settings(max_examples=4, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2**31 - 1), st.sampled_from(["loose", "tight"]), st.sampled_from([None, "unconstrained"]),
       st.booleans(), st.sampled_from([None, 25, 90]), st.booleans())
def test_generated_controller_steps_as_firhc(tmp_path_factory, seed, terminal, fallback, warm, max_nodes, safe):
    rp = make(seed, 2, 1, 3, 4, terminal)
    problem = rp.problem()
    ctrl = fj.FIRHC(problem, fallback=fallback, warm_start=warm, u_safe=rp.controls[0] if safe else None,
                    observe=lambda x, u_prev: x * 0.9 + 0.01 * u_prev[0],
                    actuate=lambda x, u: jnp.concatenate([u, u * 2.0]),
                    **({} if max_nodes is None else {"max_nodes": max_nodes}))
    lib = fj.export_c(ctrl, tmp_path_factory.mktemp("c"), name="ctrl", x0=np.zeros(2)).compile()
    x = np.random.default_rng(seed).uniform(-1, 1, 2)
    state, c_state = ctrl.init(x, rp.controls[1]), lib.init(x, rp.controls[1])
    for _ in range(6):
        u, state, info = ctrl.step(state, x)
        code, c_u = lib.step(c_state, x)
        assert code == (0 if info.held else 2 if info.used_fallback else 1)
        np.testing.assert_allclose(c_u, np.asarray(u), rtol=1e-12)
        np.testing.assert_array_equal(np.asarray(c_state.plan), np.asarray(state.plan))
        assert (c_state.nodes, c_state.fallback_nodes) == (int(info.nodes), int(info.fallback_nodes))
        assert bool(c_state.complete) == bool(info.complete)
        x = np.asarray(rp.dynamics(jnp.asarray(x), jnp.asarray(u[:1])))


def test_input_memory_controller_with_params(tmp_path):
    from firhc_jax.models import inverter

    mem = inverter.make_problem(2)
    ctrl = fj.FIRHC(mem.problem, observe=mem.observe, warm_start=True)
    refs = inverter.horizon_references(inverter.InverterParams(), 5, 2)
    p0 = {"ref": jnp.asarray(refs[0]), "lambda_u": jnp.asarray(0.1)}
    exported = fj.export_c(ctrl, tmp_path, name="inv", params=p0)
    lib = exported.compile()
    import ctypes

    lib.lib.inv_work_bytes.restype = ctypes.c_size_t
    assert lib.lib.inv_work_bytes() == exported.work_bytes and ctypes.sizeof(lib.State) == exported.state_bytes
    plant = inverter.make_plant()
    x = np.array([1.0, -2.0])
    state, c_state = ctrl.init(x), lib.init(x)
    for t in range(5):
        p = {"ref": jnp.asarray(refs[t]), "lambda_u": jnp.asarray(0.1)}
        u, state, info = ctrl.step(state, x, p)
        code, c_u = lib.step(c_state, x, p)
        assert code == 1
        np.testing.assert_array_equal(c_u, np.asarray(u))
        assert c_state.nodes == int(info.nodes)
        x = np.asarray(plant(jnp.asarray(x), jnp.asarray(u)))


def test_codes_for_bad_values_and_negative_costs(tmp_path):
    problem = fj.Problem(lambda x, u, p: x * p["a"] + u, np.array([-1.0, 1.0]),
                         lambda x, u, p: jnp.sum(x**2) - p["shift"], 2)
    params = {"a": jnp.asarray(0.5), "shift": jnp.asarray(0.0)}
    lib = fj.export_c(problem, tmp_path, name="codes", params=params, x0=np.zeros(1)).compile()
    assert lib.solve(np.array([0.3]), params)[0] == 1
    assert lib.solve(np.array([np.nan]), params)[0] == -1
    assert lib.solve(np.array([0.3]), {"a": jnp.asarray(np.inf), "shift": jnp.asarray(0.0)})[0] == -2
    assert lib.solve(np.array([0.3]), {"a": jnp.asarray(0.5), "shift": jnp.asarray(10.0)})[0] == -3
    with pytest.raises(ValueError, match="negative"):
        fj.sdfs(problem, np.array([0.3]), params={"a": jnp.asarray(0.5), "shift": jnp.asarray(10.0)})


def test_an_unsupported_primitive_is_refused_by_name(tmp_path):
    problem = fj.Problem(lambda x, u: x + u, np.array([-1.0, 1.0]), lambda x, u: jnp.sort(x)[0] ** 2, 2)
    with pytest.raises(ValueError, match="stage_cost.*'sort'"):
        fj.export_c(problem, tmp_path, x0=np.zeros(2))
    with pytest.raises(ValueError, match="C identifier"):
        fj.export_c(problem, tmp_path, name="not a name", x0=np.zeros(2))
    with pytest.raises(ValueError, match="callable warm_start"):
        fj.export_c(fj.FIRHC(problem, warm_start=lambda problem, x, prev, p: prev), tmp_path, x0=np.zeros(2))


@pytest.mark.parametrize("solver, options", [("sdfs", {"pop_width": 3}), ("pool", {"lanes": 3, "pop_width": 2}),
                                             ("exhaustive", {}), ("exhaustive", {"method": "dfs"})])
def test_a_controller_of_any_solver_is_exported_with_its_search(tmp_path, solver, options):
    """The generated step runs the controller's solver: the node counts and iterations of each decision are
    that solver's, and the work arrays are those ``work_bytes`` states."""
    import ctypes

    rp = make(3, 2, 1, 3, 4, "loose")
    ctrl = fj.FIRHC(rp.problem(), solver, **options)
    exported = fj.export_c(ctrl, tmp_path, name="any", x0=np.zeros(2))
    lib = exported.compile()
    lib.lib.any_work_bytes.restype = ctypes.c_size_t
    assert lib.lib.any_work_bytes() == exported.work_bytes
    x = np.random.default_rng(3).uniform(-1, 1, 2)
    state, c_state = ctrl.init(x), lib.init(x)
    for _ in range(4):
        u, state, info = ctrl.step(state, x)
        code, c_u = lib.step(c_state, x)
        np.testing.assert_allclose(c_u, np.asarray(u), rtol=1e-12)
        assert (c_state.nodes, c_state.iterations) == (int(info.nodes), int(info.result.iterations))
        x = np.asarray(rp.dynamics(jnp.asarray(x), jnp.asarray(u[:1])))


def test_the_state_size_is_found_from_the_callables(tmp_path):
    A = np.array([[1.0, 0.1, 0.0], [0.0, 0.9, 0.1], [0.0, 0.0, 0.8]])
    problem = fj.Problem(lambda x, u: jnp.asarray(A) @ x + u[0], np.array([-1.0, 1.0]), fj.quadratic_cost(1.0, 0.0), 2)
    assert fj.export_c(problem, tmp_path, name="sized").state_size == 3
    elementwise = fj.Problem(lambda x, u: x + u, np.array([-1.0, 1.0]), lambda x, u: jnp.sum(x**2), 2)
    with pytest.raises(ValueError, match="x0="):
        fj.export_c(elementwise, tmp_path, name="unsized")


def c_function(fn, *args):
    """``fn(*args)`` translated to C, compiled and called: its outputs as NumPy arrays."""
    import ctypes
    import subprocess
    import tempfile
    from pathlib import Path

    from firhc_jax._src.export.c_code import PRELUDE, c_type, translate

    specs = [jax.ShapeDtypeStruct(np.shape(a), np.asarray(a).dtype) for a in args]
    outs = jax.tree_util.tree_leaves(jax.eval_shape(fn, *args))
    tables = {}
    body = translate("f", lambda *a: jax.tree_util.tree_leaves(fn(*a)), specs, [f"a{i}" for i in range(len(args))],
                     [c_type(o.dtype) for o in outs], tables, "fn")
    source = "#include <stdint.h>\n#include <tgmath.h>\n" + PRELUDE + "\n".join(d for _, d in tables.values()) \
        + body.replace("static void f(", "void f(")
    folder = Path(tempfile.mkdtemp())
    (folder / "f.c").write_text(source)
    subprocess.run(["cc", "-std=c99", "-O1", "-shared", "-fPIC", "-o", str(folder / "f.so"), str(folder / "f.c"),
                    "-lm"], check=True)
    lib = ctypes.CDLL(str(folder / "f.so"))
    inputs = [np.ascontiguousarray(a) for a in args]
    results = [np.zeros(o.shape, o.dtype) for o in outs]
    lib.f(*[ctypes.c_void_p(a.ctypes.data) for a in inputs + results])
    return results


@jax.custom_jvp
def _soft(x):
    return jnp.log1p(jnp.exp(x))


_soft.defjvp(lambda primals, tangents: (_soft(primals[0]), tangents[0]))


@jax.custom_vjp
def _twice(x):
    return 2.0 * x


_twice.defvjp(lambda x: (_twice(x), None), lambda _, g: (2.0 * g,))


def _many(x, M, i, k):
    """One function using the primitives the translation covers."""
    loop = jax.lax.fori_loop(0, 3, lambda j, c: c * 0.5 + x[j % 3], x)
    scanned = jax.lax.scan(lambda c, r: (c + r, c * r), jnp.zeros(3), M)[1]
    looped = jax.lax.while_loop(lambda c: c[0] < 5.0, lambda c: (c[0] + 1.5, c[1] * 1.1), (0.0, x[0]))[1]
    branch = jax.lax.switch(k, [lambda v: v + 1.0, lambda v: v * 3.0, lambda v: jnp.sin(v)], x)
    y = x.at[i].set(7.0).at[1].add(2.0)
    return {
        "loops": (loop, scanned, looped, branch, y),
        "math": (jnp.tanh(x), jnp.exp(x), jnp.log1p(jnp.abs(x)), jnp.expm1(x), jnp.sqrt(jnp.abs(x)),
                 jnp.arctan2(x, 1.5), x ** 3, jnp.power(jnp.abs(x), 1.7), jnp.sign(x), jnp.round(x * 3), jnp.floor(x),
                 jnp.fmod(x, 0.7), jax.lax.rsqrt(jnp.abs(x) + 1), jax.nn.sigmoid(x), jax.scipy.special.erf(x),
                 jnp.clip(x, -0.5, 0.5), jnp.maximum(x, 0.1), jnp.minimum(x, M[0]), _soft(x), _twice(x)),
        "shapes": (M @ x, M.T @ M, jnp.einsum("ij,ij->i", M, M), M[i], M[:, i], M[::2, 1:], jnp.concatenate([x, x[:2]]),
                   jnp.stack([x, -x], axis=1), jnp.flip(M, 0), jnp.pad(x, (1, 2)), jnp.cumsum(x), jnp.argmax(x),
                   jnp.argmin(M, axis=1), jnp.max(M, axis=0), jnp.prod(x), jnp.where(x > 0, x, -2 * x),
                   jnp.any(x > 0.5), jnp.all(M < 2), M.reshape(-1)[::3], jnp.outer(x, x),
                   jax.lax.dynamic_slice(M, (i, jnp.int32(0)), (1, 3)),
                   jax.lax.dynamic_update_slice(M, x[None], (i, jnp.int32(0))),
                   jnp.take(x, jnp.array([2, 0, 1])), x.astype(jnp.int32), (x > 0).astype(jnp.float64),
                   jnp.arange(3) * i, jnp.linalg.norm(x), jnp.sum(M, axis=1, keepdims=True),
                   jnp.split(M, [1], axis=0)[1], jnp.right_shift(i * 8 + 3, 1), jnp.left_shift(k, 2),
                   jax.lax.cumlogsumexp(x), jax.lax.cummax(x), jnp.cumprod(x)),
    }


@pytest.mark.parametrize("i, k", [(0, 0), (2, 1), (-1, 2), (5, 7)])
def test_the_translation_computes_what_jax_computes(i, k):
    x = np.array([0.3, -1.2, 2.5])
    M = np.array([[0.5, -1.0, 2.0], [1.5, 0.25, -0.75], [3.0, 1.0, -2.0]])
    args = (x, M, np.int32(i), np.int32(k))
    expected = jax.tree_util.tree_leaves(jax.jit(_many)(*args))
    for got, want in zip(c_function(_many, *args), expected, strict=True):
        np.testing.assert_allclose(got, np.asarray(want), rtol=1e-13, atol=1e-15)


def test_the_command_line_exports_an_application_and_compares_it(tmp_path, capsys):
    from firhc_jax import cli

    cli.main(["export", "inverter", "--horizon", "2", "--out", str(tmp_path), "--name", "inv", "--compare", "6"])
    out = capsys.readouterr().out
    assert (tmp_path / "inv.h").exists() and (tmp_path / "inv.c").exists()
    assert "checked 6 closed-loop decisions against ctrl.step: all equal" in out, out


@pytest.mark.slow
def test_a_tie_broken_the_other_way_is_told_apart_from_a_difference(tmp_path, capsys):
    """The inverter at N = 5 meets decisions whose two zero vectors cost the same to the last bits, where XLA and
    the C code may pick either: the comparison names them as ties, resumes from the library's choice, and fails
    only on a real difference."""
    from firhc_jax import cli

    cli.main(["export", "inverter", "--horizon", "5", "--out", str(tmp_path), "--compare", "200"])
    out = capsys.readouterr().out
    assert "checked 200 closed-loop decisions against ctrl.step: " in out and " differ" not in out, out
    for line in out.splitlines():
        if "a tie broken the other way" in line:
            costs = [float(c.split(",")[0].rstrip(")")) for c in line.split("cost ")[1:]]
            assert costs[0] == pytest.approx(costs[1], rel=1e-9), line


def test_a_derived_lower_bound_exports_and_prunes_as_in_the_library(tmp_path):
    rp = make(3, 2, 1, 3, 4, "tight")
    problem = rp.problem().replace(lower_bound="auto")
    lib = fj.export_c(problem, tmp_path, name="auto", x0=np.zeros(2)).compile()
    for x0 in np.random.default_rng(3).uniform(-1, 1, (3, 2)):
        r = fj.sdfs(problem, x0)
        assert int(r.nodes) < problem.tree_size()
        same_search(problem, lib.solve(x0), r, None, x0)


def test_a_linear_tracking_controller_exports_with_its_parameter_map(tmp_path):
    from firhc_jax.models import thermal

    lt, plant = thermal.make_problem(3), thermal.make_plant()
    ctrl = fj.FIRHC(lt.problem, observe=lt.observe, warm_start=True)
    lib = fj.export_c(lt, tmp_path, name="zones").compile()
    rng = np.random.default_rng(0)
    x = rng.normal(20, 1, lt.n)
    state, c_state = ctrl.init(x), lib.init(x)
    for _ in range(4):
        y_ref, d = rng.normal(21, 0.5, (3, lt.C.shape[0])), rng.normal(0, 0.01, (3, lt.n))
        u, state, info = ctrl.step(state, x, lt.params(y_ref, d))
        code, c_u = lib.step(c_state, x, (y_ref, d))
        assert code == 1 and c_state.nodes == int(info.nodes)
        np.testing.assert_array_equal(c_u, np.asarray(u))
        x = np.asarray(plant(jnp.asarray(x), jnp.asarray(u)))
    with pytest.raises(ValueError, match="y_ref"):
        fj.export_c(lt, tmp_path, params=(np.zeros((2, 2)), np.zeros((3, lt.n))))


@pytest.mark.float32
def test_an_export_computes_in_the_sessions_float(tmp_path):
    """With x64 off (the default; ``--float32``) the callables' jaxprs are float32 and so is the generated code's
    arithmetic (states and costs are handed over as double): the same decisions as the float32 search, costs
    to float32's precision. Exporting changes no JAX setting, and the library's own calls afterwards still run."""
    x64 = jax.config.jax_enable_x64
    rp = make(5, 2, 1, 4, 4, "loose")
    problem = rp.problem()
    real = jax.dtypes.canonicalize_dtype(np.float64)
    lib = fj.export_c(problem, tmp_path, name="f32", x0=np.zeros(2, real)).compile()
    assert jax.config.jax_enable_x64 == x64
    for x0 in np.random.default_rng(5).uniform(-1, 1, (4, 2)).astype(real):
        code, sequence, cost, nodes = lib.solve(x0)
        r = fj.sdfs(problem, x0)
        assert code == int(bool(r.feasible))
        if np.isfinite(float(r.cost)):
            np.testing.assert_allclose(cost, float(r.cost), rtol=1e-5)
            np.testing.assert_array_equal(sequence, np.asarray(r.sequence))


def test_a_fallback_problem_of_its_own_exports_with_its_callables(tmp_path):
    rp = make(3, 2, 1, 3, 4, "tight")
    problem = rp.problem()
    fallback = fj.Problem(problem.dynamics, problem.controls, lambda x, u: jnp.sum(jnp.abs(x)), 4,
                          first_input_of=lambda x0, s: jnp.asarray(problem.controls, x0.dtype)[s[0]] * 0.5)
    ctrl = fj.FIRHC(problem, fallback=fallback, warm_start=True, max_nodes=50)
    lib = fj.export_c(ctrl, tmp_path, name="fb", x0=np.zeros(2)).compile()
    x = np.array([0.5, -0.3])
    state, c_state, used = ctrl.init(x), lib.init(x), 0
    for _ in range(6):
        u, state, info = ctrl.step(state, x)
        code, c_u = lib.step(c_state, x)
        used += bool(info.used_fallback)
        assert code == (0 if info.held else 2 if info.used_fallback else 1)
        assert (c_state.nodes, c_state.fallback_nodes) == (int(info.nodes), int(info.fallback_nodes))
        np.testing.assert_allclose(c_u, np.asarray(u), rtol=1e-12)
        x = np.asarray(rp.dynamics(jnp.asarray(x), jnp.asarray(u)))
    assert used
