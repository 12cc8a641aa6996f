"""Every search bounded, every refusal clear."""
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from param_problems import as_jax, cases, check_optimal, problem
from reference import same_cost

import firhc_jax as fj


def _dyn(x, u):
    return 0.5 * x + u


P = fj.Problem(_dyn, [-1.0, 0.0, 1.0], fj.quadratic_cost(1.0, 0.0), 3)


# ---------------------------------------------------------------- node budget (also run with x64 off: pytest --float32)
@pytest.mark.float32
@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cases(tightness=("none", "loose")), st.integers(1, 400), st.sampled_from([1, 2]))
def test_a_budget_is_honest(case, budget, pop_width):
    shape, params, x0 = case
    prm = as_jax(params)
    full = fj.sdfs(problem(shape), x0, params=prm, pop_width=pop_width)
    cut = fj.sdfs(problem(shape), x0, params=prm, pop_width=pop_width, max_nodes=budget)
    assert int(cut.nodes) <= budget
    if bool(cut.complete):  # the seeds (docs/guide/budgets.md) may find a tied optimum first
        assert same_cost(float(cut.cost), float(full.cost))
    else:
        # It stopped only because the next iteration (up to K * M children) could pass the budget.
        assert int(cut.nodes) + pop_width * shape[2] > budget
        assert float(cut.cost) >= float(full.cost) or same_cost(float(cut.cost), float(full.cost))
    check_optimal(full, shape, params, x0)


@pytest.mark.float32
@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cases(tightness=("none", "loose")), st.integers(1, 40), st.integers(0, 2**32 - 1), st.booleans())
def test_a_budget_bounds_the_count_with_a_warm_start(case, budget, seed, none):
    """``nodes <= max_nodes`` in every case, a warm start's N nodes included: a warm start that does not fit in
    the budget is not evaluated (one compile per shape, shared with tests/search/test_exactness.py's warm start)."""
    shape, params, x0 = case
    N, M, prm = shape[3], shape[2], as_jax(params)
    warm = np.full(N, -1) if none else np.random.default_rng(seed).integers(0, M, N)
    full = fj.sdfs(problem(shape), x0, params=prm)
    cut = fj.sdfs(problem(shape), x0, params=prm, warm_start=warm, max_nodes=budget)
    assert int(cut.nodes) <= budget, (budget, int(cut.nodes))
    if (none or budget < N) and budget // 2 < M + N * M + M:
        # no warm start: no nodes counted for it, no incumbent from it; whole expansions only where the seeds
        # do not run (from half of B(1) on they do, and an extension replays its prefix one node a step)
        assert int(cut.nodes) % M == 0
    if bool(cut.complete):
        assert same_cost(float(cut.cost), float(full.cost))
    else:  # an incumbent (perhaps the warm start, costed by its own rollout: a few ulps), never below the optimum
        assert float(cut.cost) >= float(full.cost) or same_cost(float(cut.cost), float(full.cost))


def test_budget_stops_a_search_that_would_never_end():
    hard = fj.Problem(_dyn, np.linspace(-1, 1, 17), fj.quadratic_cost(1.0, 0.0), 40, terminal=lambda x: x[0] > 100.0)
    r = fj.sdfs(hard, jnp.ones(1), max_nodes=5_000)
    assert not bool(r.complete) and not bool(r.feasible) and int(r.nodes) <= 5_000
    b = fj.solve_batch(hard, jnp.ones((3, 1)), max_nodes=5_000, lanes=2)
    assert not np.asarray(b.complete).any() and (np.asarray(b.nodes) <= 5_000 + 17).all()
    run = fj.FIRHC(hard, fallback="unconstrained", max_nodes=2_000).simulate(jnp.ones(1), 2)
    assert not np.asarray(run.complete).any()  # the fallback acts within the half kept for it
    assert np.asarray(run.used_fallback).all() and not np.asarray(run.held).any()
    assert (np.asarray(run.decision_nodes) <= 2_000).all()
    with pytest.warns(RuntimeWarning, match="no feasible input sequence found .* at 2 of 2 steps"):
        run = fj.FIRHC(hard, max_nodes=2_000).simulate(jnp.ones(1), 2)
    assert bool(fj.sdfs(P, jnp.ones(1), max_nodes=10_000).complete)


# ---------------------------------------------------------------- memory and horizon limits
def test_sizes_are_checked_before_allocation():
    with pytest.raises(ValueError, match="solver='sdfs' on N=.* needs about"):
        fj.sdfs(fj.Problem(_dyn, np.linspace(-1, 1, 64), fj.quadratic_cost(1.0, 0.0), 20_000), jnp.ones(1))
    with pytest.raises(ValueError, match="max_memory"):
        fj.sdfs(P, jnp.ones(1), max_memory=100)
    with pytest.raises(ValueError, match="horizon"):
        fj.Problem(_dyn, [0.0, 1.0], fj.quadratic_cost(1.0, 0.0), 2**70)
    with pytest.raises(ValueError, match="int32 node counter"):
        fj.exhaustive(fj.Problem(_dyn, np.linspace(-1, 1, 17), fj.quadratic_cost(1.0, 0.0), 40), jnp.ones(1),
                      method="dfs")


def test_int64_controls_outside_int32_are_refused_without_x64():
    code = ("import numpy as np, firhc_jax as fj\n"
            "try:\n    fj.Problem(lambda x, u: x, np.array([2**32 + 5, 1], np.int64), lambda x, u: x[0], 2)\n"
            "except ValueError as e:\n    print('refused', e)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert "refused" in out.stdout and "wrap" in out.stdout, out.stdout + out.stderr


# ---------------------------------------------------------------- clear errors
def _simulate_vmapped():
    return jax.vmap(lambda x: fj.FIRHC(P).simulate(x, 2).states)(jnp.ones((2, 1)))


CLEAR = [
    ("controls None", lambda: fj.Problem(_dyn, None, fj.quadratic_cost(1.0, 0.0), 3), TypeError, "controls"),
    ("controls ragged", lambda: fj.Problem(_dyn, [[1.0, 2.0], [1.0]], fj.quadratic_cost(1.0, 0.0), 3), ValueError,
     "controls"),
    ("x0 None", lambda: fj.sdfs(P, None), TypeError, "x0"),
    ("x0 complex", lambda: fj.sdfs(P, jnp.ones(1, complex)), TypeError, "x0"),
    ("FIRHC(None)", lambda: fj.FIRHC(None), TypeError, "problem"),
    ("unknown option", lambda: fj.FIRHC(P, chunk_nodes=3), TypeError, "chunk_nodes"),
    ("NaN weight", lambda: fj.quadratic_cost(np.nan, 0.0), ValueError, "lam"),
    ("devices 'cpu'", lambda: fj.solve_batch(P, jnp.ones((2, 1)), devices="cpu"), TypeError, "devices"),
    ("devices [0]", lambda: fj.solve_batch(P, jnp.ones((2, 1)), devices=[0]), TypeError, "devices"),
    ("params NaN row 1", lambda: fj.solve_batch(P.replace(dynamics=lambda x, u, p: x, stage_cost=lambda x, u, p: x[0]
                                                          ** 2), jnp.ones((2, 1)), params=jnp.array([1.0, np.nan])),
     ValueError, "params"),
    ("params string", lambda: fj.sdfs(P, jnp.ones(1), params={"a": "x"}), TypeError, "params"),
    ("plant shape", lambda: fj.FIRHC(P).simulate(jnp.ones(1), 2, plant=lambda x, u: jnp.ones(2)), TypeError,
     "plant"),
    ("plant tuple", lambda: fj.FIRHC(P).simulate(jnp.ones(1), 2, plant=lambda x, u: (x, x)), TypeError, "plant"),
    ("plant shape, python loop", lambda: fj.FIRHC(P).simulate(jnp.ones(1), 2, plant=lambda x, u: np.ones(2),
                                                              compiled=False), TypeError, "plant"),
    ("grad", lambda: jax.grad(lambda x: fj.sdfs(P, x).cost)(jnp.ones(1)), TypeError, "differentiable"),
    ("grad batch", lambda: jax.grad(lambda x: fj.solve_batch(P, x).cost.sum())(jnp.ones((2, 1))), TypeError,
     "differentiable"),
]


@pytest.mark.parametrize("name, call, exc, match", CLEAR, ids=[c[0] for c in CLEAR])
def test_mistakes_get_clear_errors(name, call, exc, match):
    with pytest.raises(exc, match=match):
        call()


def test_corners_that_work():
    assert _simulate_vmapped().shape == (2, 3, 1)  # simulate under vmap without a fallback
    built = jax.jit(lambda x: fj.sdfs(fj.Problem(_dyn, np.array([-1.0, 0.0, 1.0]), fj.quadratic_cost(1.0, 0.0), 3),
                                      x).cost)(jnp.ones(1))
    assert same_cost(built, fj.sdfs(P, jnp.ones(1)).cost)  # a Problem built inside jit
    for value in (np.int64(2), 2):  # one validator: NumPy integers everywhere
        fj.sdfs(P, jnp.ones(1), pop_width=value)
        fj.exhaustive(P, jnp.ones(1), chunk_nodes=np.int64(100) * value)
        fj.solve_batch(P, jnp.ones((2, 1)), lanes=value, max_memory=np.int64(10**8))
        fj.FIRHC(P).simulate(jnp.ones(1), value)


COUNTS = {  # every count argument: refuses what is not an int >= 1, naming itself
    "pop_width": lambda v: fj.sdfs(P, jnp.ones(1), pop_width=v),
    "max_nodes": lambda v: fj.sdfs(P, jnp.ones(1), max_nodes=v),
    "chunk_nodes": lambda v: fj.exhaustive(P, jnp.ones(1), chunk_nodes=v),
    "lanes": lambda v: fj.solve_batch(P, jnp.ones((2, 1)), lanes=v),
    "max_memory": lambda v: fj.solve_batch(P, jnp.ones((2, 1)), max_memory=v),
    "steps": lambda v: fj.FIRHC(P).simulate(jnp.ones(1), v),
    "horizon": lambda v: fj.Problem(_dyn, [0.0, 1.0], fj.quadratic_cost(1.0, 0.0), v),
}


@pytest.mark.parametrize("name", sorted(COUNTS))
def test_every_count_argument_refuses_non_positive_ints_by_name(name):
    for value in (0, -1, True, 2.5, "3", np.float64(2.0)):
        with pytest.raises((TypeError, ValueError), match=name):
            COUNTS[name](value)
    COUNTS[name](jnp.int32({"max_memory": 10**8, "chunk_nodes": 100}.get(name, 3)))  # a 0-d JAX int is an int


def test_options_a_solver_does_not_use_are_refused():
    with pytest.raises(TypeError, match="lanes is an option of solvers 'sdfs', 'pool'"):
        fj.solve_batch(P, jnp.ones((2, 1)), solver="sdfs-vmap", lanes=8)
    with pytest.raises(TypeError, match="max_nodes is an option of solvers 'sdfs', 'pool', 'sdfs-vmap'"):
        fj.solve_batch(P, jnp.ones((2, 1)), solver="exhaustive", max_nodes=100)
    with pytest.raises(ValueError, match="pop_width"):
        fj.solve_batch(P, jnp.ones((2, 1)), solver="exhaustive", pop_width=2)
    with pytest.raises(ValueError, match="pop_width"):
        fj.exhaustive(P, jnp.ones(1), pop_width=2)
    with pytest.raises(TypeError, match="chunk_nodes"):
        fj.solve_batch(P, jnp.ones((2, 1)), solver="sdfs", chunk_nodes=2.0)


# ---------------------------------------------------------------- fuzzing the entry points
BAD = st.one_of(st.none(), st.text(max_size=3), st.floats(allow_nan=True), st.integers(-3, 0), st.just([1, [2]]),
                st.just(np.zeros((2, 2, 2))), st.just(np.array(["a"])), st.just(jnp.full(1, jnp.nan)),
                st.just(np.ones(5)), st.booleans())
ENTRY = {
    "sdfs x0": lambda v: fj.sdfs(P, v), "sdfs warm_start": lambda v: fj.sdfs(P, jnp.ones(1), warm_start=v),
    "exhaustive x0": lambda v: fj.exhaustive(P, v), "solve_batch X0": lambda v: fj.solve_batch(P, v),
    "Problem controls": lambda v: fj.Problem(_dyn, v, fj.quadratic_cost(1.0, 0.0), 2),
    **{f"count {name}": call for name, call in COUNTS.items()},
}
NAMES = {"sdfs x0": "x0", "exhaustive x0": "x0", "solve_batch X0": "X0", "Problem controls": "controls"}


def _five(v):
    return isinstance(v, np.ndarray) and v.shape == (5,)


ACCEPTED = {  # the values of BAD that are right for an entry (P's callables work on any number of states)
    "sdfs warm_start": lambda v: v is None, "count max_nodes": lambda v: v is None, "count lanes": lambda v: v is None,
    "sdfs x0": _five, "exhaustive x0": _five, "Problem controls": _five,  # 5 states; 5 inputs of 1.0
}


def _check_entry(name, value):
    """Every value of BAD is refused with a clear error naming the argument, except the few that ACCEPTED lists
    as right for that entry, which must work: a bad argument accepted silently fails."""
    import threading
    out = {}

    def target():
        try:
            ENTRY[name](value)
            out["r"] = ("ok", "")
        except (ValueError, TypeError) as e:
            out["r"] = ("clear", str(e))
        except Exception as e:  # noqa: BLE001
            out["r"] = ("raw", f"{type(e).__name__}: {e}")

    t = threading.Thread(target=target, daemon=True)
    t.start()
    t.join(120)
    assert not t.is_alive(), f"{name}={value!r} hangs"
    kind, msg = out["r"]
    assert kind == ("ok" if ACCEPTED.get(name, lambda v: False)(value) else "clear"), (name, value, kind, msg)
    if kind == "clear":
        arg = NAMES.get(name, name.split()[-1])
        assert arg in msg or "params" in msg or "dynamics" in msg, (name, value, msg)


# One value of each of BAD's kinds, tried on every entry (the fuzz test below draws from them at random).
SAMPLES = [None, "", "3", 2.0, float("nan"), float("inf"), -1, 0, [1, [2]], np.zeros((2, 2, 2)), np.array(["a"]),
           jnp.full(1, jnp.nan), np.ones(5), True]


@pytest.mark.parametrize("name", sorted(ENTRY))
def test_every_entry_refuses_each_kind_of_bad_value(name):
    for value in SAMPLES:
        _check_entry(name, value)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(sorted(ENTRY)), BAD)
def test_bad_arguments_get_a_value_or_type_error_naming_the_argument(name, value):
    _check_entry(name, value)


class _Slotted:
    """A callable object JAX cannot hold by weak reference (``__slots__`` without ``__weakref__``)."""

    __slots__ = ()

    def __call__(self, x, u):
        return 0.5 * x + u


def test_callables_made_inside_a_jit_or_without_weak_references_are_traced_as_they_are():
    """A user's callable is traced once per signature and kept (``problem.call``): one that closes over a
    tracer of the user's own ``jit`` must still see each call's value, and one that cannot be held weakly is
    called directly."""
    controls, cost = np.array([-1.0, 0.0, 1.0]), fj.quadratic_cost(1.0, 0.0)

    def solve(gain, x):
        return fj.sdfs(fj.Problem(lambda x, u: gain * x + u, controls, cost, 3), x).cost

    jitted = jax.jit(solve)
    for n, (gain, x) in enumerate(((0.5, 1.0), (0.9, -0.7), (1.3, 0.4)), start=1):  # n: a new trace each
        assert same_cost(jitted(gain, jnp.full(n, x)), solve(gain, np.full(n, x)))
    x0 = jnp.full(1, 0.8)
    slotted = fj.sdfs(fj.Problem(_Slotted(), controls, cost, 3), x0)
    assert same_cost(slotted.cost, fj.sdfs(fj.Problem(lambda x, u: 0.5 * x + u, controls, cost, 3), x0).cost)
