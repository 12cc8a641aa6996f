"""Every search returns the brute-force optimum on random nonlinear problems."""
import jax
import jax.numpy as jnp
import numpy as np
import param_problems as pp
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from random_problems import make
from reference import same_cost

import firhc_jax as fj

# Breadth of shapes (n, m, M, N drawn, M = 1 and N = 1 included): every example compiles its own problem, so
# few examples; tests/problem/test_params.py carries the breadth of values on one compile per shape.
SETTINGS = settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@st.composite
def problems(draw):
    n, m = draw(st.integers(1, 4)), draw(st.integers(1, 4))
    M, N = draw(st.integers(1, 6)), draw(st.integers(1, 6))
    if M**N > 20_000:  # keep the brute force and the compile cheap; both ends of the range stay covered
        N = max(1, int(np.log(20_000) / np.log(max(M, 2))))
    terminal = draw(st.sampled_from(["none", "loose", "tight"]))
    rp = make(draw(st.integers(0, 2**31 - 1)), n, m, M, N, terminal)
    x0 = np.asarray(draw(st.lists(st.floats(-1, 1), min_size=n, max_size=n)))
    return rp, x0


@SETTINGS
@given(problems(), st.sampled_from([1, 2, 3, 5]))
def test_every_search_matches_brute_force(case, pop_width):
    rp, x0 = case
    problem = rp.problem()
    ref_cost, _ = rp.brute_force(x0)
    results = {
        "sdfs": fj.sdfs(problem, x0, pop_width=1),
        f"sdfs K={pop_width}": fj.sdfs(problem, x0, pop_width=pop_width),
        "exhaustive": fj.exhaustive(problem, x0),
        f"exhaustive dfs K={pop_width}": fj.exhaustive(problem, x0, method="dfs", pop_width=pop_width),
    }
    for name, r in results.items():
        assert same_cost(float(r.cost), ref_cost), (name, float(r.cost), ref_cost)
        assert bool(r.feasible) == np.isfinite(ref_cost), name
        if np.isfinite(ref_cost):
            # The returned sequence really achieves the returned cost.
            again = rp.sequence_cost(x0, np.asarray(r.sequence))
            assert same_cost(again, float(r.cost)), name
            np.testing.assert_array_equal(r.first_input, rp.controls[int(r.sequence[0])])
        else:
            assert np.all(np.asarray(r.sequence) == -1) and np.all(np.isnan(r.first_input)), name
    # Exhaustive searches visit the whole tree.
    assert int(results["exhaustive"].nodes) == problem.tree_size()
    assert int(results[f"exhaustive dfs K={pop_width}"].nodes) == problem.tree_size()
    assert int(results["sdfs"].nodes) <= problem.tree_size()


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(pp.cases(), st.integers(0, 2**32 - 1))
def test_warm_start_keeps_the_optimum(case, seed):
    shape, params, x0 = case  # every number a parameter: two compiles per shape (with and without a seed)
    problem, prm, N = pp.problem(shape), pp.as_jax(params), shape[3]
    plain = fj.sdfs(problem, x0, params=prm)
    seq = np.random.default_rng(seed).integers(0, shape[2], N)
    warm = fj.sdfs(problem, x0, params=prm, warm_start=seq)
    assert same_cost(float(warm.cost), float(plain.cost))
    # Warm-started with the optimum itself, the search returns it and counts its N nodes.
    if bool(plain.feasible):
        opt = fj.sdfs(problem, x0, params=prm, warm_start=plain.sequence)
        np.testing.assert_array_equal(opt.sequence, plain.sequence)
        assert int(opt.nodes) <= int(plain.nodes) + N


def table1_reference(step, controls, N, terminal, x0):
    """Plain-Python rendering of the paper's Table 1 on a NumPy ``step(x, u) -> (x_next, stage cost)``, the
    inputs ``[M, m]`` and ``terminal(x) -> bool`` (None: unconstrained); returns (best_cost, best_path, nodes)."""
    best_cost, best_path, nodes = np.inf, None, 0
    stack = [(np.asarray(x0, float), 0.0, 0, ())]
    while stack:
        x, cost, depth, path = stack.pop()
        if cost < best_cost:
            temp = []
            for mode, u in enumerate(controls):
                x_new, c = step(x, u)
                c_new = cost + float(c)
                nodes += 1
                if c_new < best_cost and depth + 1 != N:
                    temp.append((x_new, c_new, depth + 1, path + (mode,)))
                if c_new < best_cost and depth + 1 == N and (terminal is None or terminal(x_new)):
                    best_cost, best_path = c_new, path + (mode,)
            temp.sort(key=lambda node: node[1], reverse=True)  # push the cheapest last
            stack.extend(temp)
    return best_cost, best_path, nodes


def _table1_of(rp, x0):
    return table1_reference(rp.step, rp.controls, rp.N, rp.terminal_np, x0)


@settings(max_examples=16, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(pp.cases())
def test_node_count_equals_table1(case):
    """Node counts, costs and paths of sdfs equal Table 1's on random problems (every number a parameter: one
    compile per shape, shared with the warm start test's plain search)."""
    shape, params, x0 = case
    ref_cost, ref_path, ref_nodes = table1_reference(pp.numpy_step(params), params["U"], shape[3],
                                                     lambda z: pp.terminal(z, params, xp=np), x0)
    r = fj.sdfs(pp.problem(shape), x0, params=pp.as_jax(params))
    assert int(r.nodes) == ref_nodes
    assert same_cost(float(r.cost), ref_cost)
    if ref_path is not None:
        assert tuple(np.asarray(r.sequence)) == ref_path


@pytest.mark.parametrize("args, x0, pruned", [
    ((7, 3, 1, 5, 6, "loose"), [0.3, -0.2, 0.1], True),  # deep: pruning cuts most of the tree
    ((2, 2, 3, 6, 2, "tight"), [0.5, -0.4], False)])  # shallow and wide, infeasible: the whole tree
def test_node_count_equals_table1_at_the_ends(args, x0, pruned):
    """Shapes beyond the property test's four, compared with Table 1."""
    rp, x0 = make(*args), np.array(x0)
    ref_cost, ref_path, ref_nodes = _table1_of(rp, x0)
    r = fj.sdfs(rp.problem(), x0)
    assert int(r.nodes) == ref_nodes and (ref_nodes < rp.problem().tree_size()) == pruned
    assert same_cost(float(r.cost), ref_cost)
    if ref_path is not None:
        assert tuple(np.asarray(r.sequence)) == ref_path


def test_exhaustive_chunking_changes_nothing():
    rp = make(3, 2, 2, 4, 5, "loose")
    p, x0 = rp.problem(), np.array([0.2, -0.4])
    whole = fj.exhaustive(p, x0)
    from firhc_jax._src.search.exhaustive import plan
    assert plan(p, 200).chunks > 1 and (4**plan(p, 200).split) % plan(p, 200).chunk == 0  # chunks, none padded
    chunked = fj.exhaustive(p, x0, chunk_nodes=200)
    assert float(chunked.cost) == float(whole.cost)
    np.testing.assert_array_equal(chunked.sequence, whole.sequence)
    assert int(chunked.nodes) == int(whole.nodes) == p.tree_size()
    for result, layout in ((whole, plan(p)), (chunked, plan(p, 200))):  # SearchResult.iterations' formula
        assert int(result.iterations) == layout.split + layout.chunks * (p.horizon - layout.split)


@pytest.fixture(scope="module")
def small():
    """One problem object for the two tests below: they share its compiled eager searches."""
    return make(11, 3, 2, 4, 4, "loose").problem()


def test_vmap_batch_equals_per_item(small):
    p = small
    X0 = jnp.asarray(np.random.default_rng(1).uniform(-1, 1, (6, 3)))
    for solve in (lambda x: fj.sdfs(p, x), lambda x: fj.sdfs(p, x, pop_width=3), lambda x: fj.exhaustive(p, x)):
        batch = jax.vmap(solve)(X0)
        for i in range(len(X0)):
            one = solve(X0[i])
            for field in ("cost", "sequence", "nodes", "feasible"):
                np.testing.assert_array_equal(getattr(batch, field)[i], getattr(one, field))


def test_jit_and_same_cost_bit_for_bit(small):
    p, x0 = small, jnp.array([0.1, 0.5, -0.3])
    a = jax.jit(lambda x: fj.sdfs(p, x))(x0)
    b = fj.exhaustive(p, x0)
    assert float(a.cost) == float(b.cost) < np.inf  # same accumulation order; elementwise dynamics


def test_edge_sizes_m1_n1():
    rp = make(2, 2, 1, 1, 1, "none")
    r = fj.sdfs(rp.problem(), np.array([0.1, 0.2]))
    assert int(r.nodes) == 1 and int(r.sequence[0]) == 0
    rp = make(2, 2, 1, 1, 5, "none")
    r = fj.sdfs(rp.problem(), np.array([0.1, 0.2]))
    assert int(r.nodes) == 5 and list(np.asarray(r.sequence)) == [0] * 5


@pytest.mark.parametrize("seed", [0, 7, 16, 29, 31, 3])
def test_pop_width_regression(seed):
    """Cases where an earlier sort-free ranking broke pop_width 2 (found by fuzzing; kept as regressions). The
    problems' numbers are parameters (the same problems): the six share two problems' compiled searches."""
    p, prm = pp.from_random(make(seed, 1, 1, 5, 3, ["none", "loose", "tight"][seed % 3]))
    x0 = np.array([0.3])
    ref = float(fj.exhaustive(p, x0, params=prm).cost)
    for k in (2, 3):
        assert same_cost(float(fj.sdfs(p, x0, params=prm, pop_width=k).cost), ref)
        assert same_cost(float(fj.exhaustive(p, x0, params=prm, method="dfs", pop_width=k).cost), ref)
