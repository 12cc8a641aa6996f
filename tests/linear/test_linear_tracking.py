"""fj.LinearTracking: exact against a brute force of J written here, equal to the
plain sorted search of the same problem in its own coordinates, warm starts,
no recompilation, the closed loop and batches."""
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from reference import same_cost
from trackers import NONE, Case

import firhc_jax as fj
from firhc_jax._src.linear import tracking
from firhc_jax._src.linear.tracking import Node
from firhc_jax.apps._timing import TRACED
from firhc_jax.apps._timing import compile_events as compilations
from firhc_jax.models import thermal, three_level

SETTINGS = settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])

def check(case, result, what):
    best = case.brute_force()
    assert same_cost(float(result.cost), best), (what, float(result.cost), best)
    assert bool(result.feasible) == np.isfinite(best), what
    if np.isfinite(best):  # the sequence really achieves it
        seq = np.asarray(result.sequence)
        assert same_cost(case.J(seq[None])[0], best), (what, seq)
        np.testing.assert_array_equal(np.asarray(result.first_input), case.controls[seq[0]])
    else:
        assert np.all(np.asarray(result.sequence) == -1) and np.all(np.isnan(np.asarray(result.first_input)))


def best_starting_with(case, u):
    """The least J over the sequences whose first input is ``u`` ``[m]``."""
    first = int(np.flatnonzero(np.all(case.controls == np.asarray(u), axis=1))[0])
    rest = itertools.product(range(len(case.controls)), repeat=case.N - 1)
    return float(np.min(case.J(np.array([(first,) + r for r in rest]))))


cases = st.builds(Case, st.sampled_from(["mimo", "common"]), st.booleans(), st.integers(0, 2**32 - 1))


@pytest.mark.float32
@SETTINGS
@given(cases)
def test_solve_is_the_brute_force_minimum_of_J(case):
    """Also in the float32 run (x64 off: the search in float32, against the float64 brute force)."""
    lt = case.tracker()
    result = lt.solve(case.x, case.u_prev, case.y_ref, case.d, warm_start=NONE)
    check(case, result, "solve")
    assert result.cost.dtype == jnp.zeros(()).dtype and bool(result.complete)


@pytest.mark.float32
@settings(SETTINGS, max_examples=4)  # lt.problem holds its model as constants: each example compiles its search
@given(cases)
def test_the_problem_searches_the_classes_and_applies_an_optimal_first_input(case):
    """lt.problem searches classes to J's minimum; the input it applies starts an optimal sequence
    (first_input_of)."""
    lt = case.tracker()
    classes = fj.sdfs(lt.problem, lt.observe(case.x, case.u_prev), params=lt.params(case.y_ref, case.d),
                      warm_start=NONE)
    best = case.brute_force()
    assert same_cost(float(classes.cost), best) and bool(classes.feasible) == np.isfinite(best)
    if bool(classes.feasible):
        assert same_cost(best_starting_with(case, classes.first_input), best)


@settings(SETTINGS, max_examples=4)  # lt.problem holds its model as constants: each example compiles its search
@given(cases, st.integers(0, 2**32 - 1), st.sampled_from([None, 40, 400]))
@example(Case("common", True, 0), 1, None)
def test_solve_and_the_problem_expand_the_same_nodes(case, seed, max_nodes):
    """lt.solve (shared_problem, the model in the params) and fj.sdfs on lt.problem (the model as constants)
    are one search: the same nodes, iterations and result on the same decision, with or without a warm start
    and a budget (lt.solve without max_nodes ran a budgeted search, whose seeding cost nodes)."""
    lt = case.tracker()
    rng = np.random.default_rng(seed)
    ws = rng.integers(0, len(case.controls), case.N) if rng.random() < 0.5 else NONE
    solved = lt.solve(case.x, case.u_prev, case.y_ref, case.d, warm_start=ws, max_nodes=max_nodes)
    classes = np.where(ws >= 0, lt.class_of[np.maximum(ws, 0)], -1)
    searched = fj.sdfs(lt.problem, lt.observe(case.x, case.u_prev), params=lt.params(case.y_ref, case.d),
                       warm_start=classes, max_nodes=max_nodes)
    for field in ("nodes", "iterations", "cost", "feasible", "complete"):
        assert np.asarray(getattr(solved, field)) == np.asarray(getattr(searched, field)), field
    np.testing.assert_array_equal(lt.class_of[np.asarray(solved.sequence)][np.asarray(solved.sequence) >= 0],
                                  np.asarray(searched.sequence)[np.asarray(searched.sequence) >= 0])


abs_cases = st.builds(Case, st.sampled_from(["mimo", "common", "long"]), st.booleans(), st.integers(0, 2**32 - 1),
                      st.just("abs"))


@pytest.mark.float32
@SETTINGS
@given(abs_cases)
def test_the_l1_switching_cost_is_the_brute_force_minimum(case):
    """norm="abs": J with lambda_u ||du||_1, solved exactly (lt.solve), also in the float32 run."""
    result = case.tracker().solve(case.x, case.u_prev, case.y_ref, case.d, warm_start=np.full(case.N, -1))
    check(case, result, "solve, L1")


def members_of(lt, node):
    """``[R, m]`` the members of the class of ``node`` (a ``Node`` below the root), in the order of its ``o``
    (padding repeats the first)."""
    row = lt.classes[int(node.j)]
    return lt.controls[np.where(row >= 0, row, row[0])]


def discrete_cost_to_go(case, k, x, u_last):
    """min over the controls u(k .. N-1) of J's steps k .. N-1 from x(k) = x after u_last (brute force)."""
    rest = Case.__new__(Case)
    rest.__dict__.update(case.__dict__)
    rest.N, rest.x, rest.u_prev, rest.y_ref, rest.d = case.N - k, x, u_last, case.y_ref[k:], case.d[k:]
    return rest.brute_force()


@settings(SETTINGS, max_examples=6)
@given(abs_cases)
@example(Case("long", False, 5, "abs"))
def test_the_l1_bound_is_below_every_discrete_completion(case):
    """With norm="abs" the bound of a node k steps deep is at most the cheapest completion over the controls,
    member by member (each member's switching so far plus its completion)."""
    case.lambda_u = 3.0  # a switching term that weighs: L1 and squared norms far apart (steps of 2 without max_step)
    lt = case.tracker()
    params = lt.params(case.y_ref, case.d)
    rng = np.random.default_rng(int(case.x[0] * 1e6) % 2**32)
    child = jax.jit(lt.problem.dynamics)
    n, m = case.x.shape[0], case.controls.shape[1]
    for k in range(1, case.N):
        parent = lt.observe(rng.normal(size=n), case.controls[rng.integers(len(case.controls))])
        z = child(parent, lt.problem.controls[rng.integers(lt.num_classes)], np.int32(k - 1), params)
        node = Node.unpack(np.asarray(z), lt.class_size, m)
        reached = node.o >= 0
        if not reached.any():  # max_step: no child, its bound unused
            continue
        best = min(float(o) + discrete_cost_to_go(case, k, np.asarray(node.x), np.asarray(u))
                   for u, o, ok in zip(members_of(lt, node), node.o, reached, strict=True) if ok)
        assert float(node.W) <= best * (1 + 1e-9) + 1e-12, (k, float(node.W), best)


def test_unit_steps_make_the_l1_and_squared_trackers_one_search():
    """The inverter's legs step by one level (max_step = 1), where ||du||_1 = ||du||^2: both norms are the same
    problem with the same bound, so the same nodes and J."""
    A, B = three_level.model()
    refs = np.random.default_rng(0).normal(scale=20.0, size=(4, 5, 2))
    squared, l1 = (fj.LinearTracking(A, B, three_level.SWITCH_STATES, 5, lambda_u=2.0, max_step=1.0, norm=norm)
                   for norm in ("squared", "abs"))
    for y_ref, u_prev in zip(refs, three_level.SWITCH_STATES[[0, 4, 13, 26]], strict=True):
        a, b = (lt.solve(y_ref[0], u_prev, y_ref) for lt in (squared, l1))
        assert int(a.nodes) == int(b.nodes) and same_cost(float(a.cost), float(b.cost), rtol=1e-12)


def _plain_dynamics(z, u, k, p):
    n, m = p["B"].shape
    return jnp.concatenate([p["A"] @ z[:n] + p["B"] @ u + p["d"][k], u, u - z[n:n + m]])


def _plain_stage_cost(z, u, k, p):
    n, m = p["B"].shape
    e, du = p["y_ref"][k] - p["C"] @ z[:n], z[n + m:]
    return jnp.maximum(e @ p["Q"] @ e, 0.0) + p["lambda_u"] * (du @ du)


def _plain_max_step(z, u, k, p):
    return jnp.all(jnp.abs(z[p["B"].shape[0] + p["B"].shape[1]:]) <= 1.0)


@SETTINGS
@given(cases)
def test_plain_sorted_search_in_the_original_coordinates_finds_the_same_optimum(case):
    """The problem written directly (state [x, u, u - u_prev], step index, params), without the bound."""
    plain = fj.Problem(_plain_dynamics, case.controls, _plain_stage_cost, case.N,
                       constraint=_plain_max_step if case.max_step else None, step_index=True)
    params = {"A": case.A, "B": case.B, "C": case.C, "Q": case.Q, "lambda_u": np.float64(case.lambda_u),
              "y_ref": case.y_ref, "d": case.d}
    z0 = np.concatenate([case.x, case.u_prev, np.zeros_like(case.u_prev)])
    plain_result = fj.sdfs(plain, z0, params=params)
    check(case, plain_result, "plain sdfs")
    lt_result = case.tracker().solve(case.x, case.u_prev, case.y_ref, case.d, warm_start=NONE)
    assert same_cost(float(lt_result.cost), float(plain_result.cost))


@SETTINGS
@given(cases, st.integers(0, 2**32 - 1))
def test_warm_start_never_changes_the_optimum_and_an_infeasible_one_is_ignored(case, seed):
    lt = case.tracker()
    cold = lt.solve(case.x, case.u_prev, case.y_ref, case.d, warm_start=NONE)
    rng = np.random.default_rng(seed)
    ws = rng.integers(0, len(case.controls), case.N)
    warm = lt.solve(case.x, case.u_prev, case.y_ref, case.d, warm_start=ws)
    check(case, warm, "random warm start")
    # lt.solve starts from ws's classes: infeasible when every sequence of them is (then ignored, only its
    # N evaluations counted)
    seqs = np.array(list(itertools.product(range(len(case.controls)), repeat=case.N)))
    same_classes = np.all(lt.class_of[seqs] == lt.class_of[ws], axis=1)
    if not np.isfinite(np.min(case.J(seqs[same_classes]))):
        np.testing.assert_array_equal(np.asarray(warm.sequence), np.asarray(cold.sequence))
        assert int(warm.nodes) == int(cold.nodes) + case.N
    if bool(cold.feasible):  # the optimum as the initial radius: nothing cheaper to find
        best = lt.solve(case.x, case.u_prev, case.y_ref, case.d, warm_start=np.asarray(cold.sequence))
        check(case, best, "optimal warm start")
        assert int(best.nodes) <= int(cold.nodes) + case.N


def test_an_infeasible_warm_start_under_max_step_is_ignored():
    case = Case("mimo", True, 7)
    case.u_prev = np.array([-1.0, -1.0, -1.0])
    lt = case.tracker()
    cold = lt.solve(case.x, case.u_prev, case.y_ref, case.d, warm_start=NONE)
    jump = np.full(case.N, 26)  # u = [+1, +1, +1] right after [-1, -1, -1]: breaks max_step at k = 0
    assert not np.isfinite(case.J(jump[None])[0])
    warm = lt.solve(case.x, case.u_prev, case.y_ref, case.d, warm_start=jump)
    check(case, warm, "infeasible warm start")
    np.testing.assert_array_equal(np.asarray(warm.sequence), np.asarray(cold.sequence))


def test_new_states_references_and_disturbances_never_recompile():
    with compilations() as seen:  # the event is still reported under this name (else the check below is void)
        jax.jit(lambda a: a * 3)(np.arange(4.0))
    assert seen, "no compile event observed: jax.monitoring's event name changed"
    case = Case("mimo", True, 3)
    lt = case.tracker()
    lt.solve(case.x, case.u_prev, case.y_ref, case.d, warm_start=NONE)  # compiles
    jitted = jax.jit(lambda x, u, y, d: lt.solve(x, u, y, d).cost)
    jitted(case.x, case.u_prev, case.y_ref, case.d)
    Case("mimo", True, 4).tracker().solve(case.x, case.u_prev, case.y_ref, case.d, warm_start=NONE)
    rng = np.random.default_rng(0)
    with compilations() as seen:
        for _ in range(3):
            x, y, d = rng.normal(size=case.x.shape), rng.normal(size=case.y_ref.shape), rng.normal(size=case.d.shape)
            u = case.controls[rng.integers(len(case.controls))]
            lt.solve(x, u, y, d, warm_start=rng.integers(0, len(case.controls), case.N))
            jitted(x, u, y, d)
            # a new model of the same shapes is new params too: the same compiled search
            Case("mimo", True, int(rng.integers(100))).tracker().solve(x, u, y, d, warm_start=NONE)
    assert seen == [], seen


@settings(SETTINGS, max_examples=3)  # each example compiles its own controller (lt_b.problem) and its plant's loop
@given(st.integers(0, 2**32 - 1))
def test_one_compiled_loop_decides_for_every_tracker_of_equal_shapes(seed):
    """FIRHC(lt_a.shared_problem) with lt_b.params(..., with_model=True) decides as lt_b's own controller, for
    trackers of one plant with other weights (Q, lambda_u); neither lt_b's params nor lt_b.shared_problem traces
    anything again."""
    with compilations(TRACED) as seen:  # the event is still reported under this name (else the check is void)
        jax.jit(lambda a: a * 5)(np.arange(3.0))
    assert seen, "no trace event observed: jax.monitoring's event name changed"
    case = Case("common", True, seed)
    rng = np.random.default_rng(seed)
    lt_a = case.tracker()
    root = rng.normal(size=(2, 2))
    case.Q, case.lambda_u = root.T @ root, float(rng.uniform(0, 2))
    lt_b = case.tracker()
    steps = 5
    Y, D = rng.normal(size=(steps,) + case.y_ref.shape), 0.3 * rng.normal(size=(steps,) + case.d.shape)
    p_a, p_b = lt_a.params(Y, D, with_model=True), lt_b.params(Y, D, with_model=True)
    assert jax.tree_util.tree_structure(p_a) == jax.tree_util.tree_structure(p_b)
    assert [a.shape for a in jax.tree_util.tree_leaves(p_a)] == [b.shape for b in jax.tree_util.tree_leaves(p_b)]
    A, B = jnp.asarray(case.A), jnp.asarray(case.B)

    def shared_plant(x, u, p):
        return A @ x + B @ u + p.data.d[0]

    def own_plant(x, u, p):
        return A @ x + B @ u + p.d[0]

    u0 = case.controls[0]
    shared = fj.FIRHC(lt_a.shared_problem, observe=lt_a.observe, warm_start=True)
    run_a = shared.simulate(case.x, steps, shared_plant, params=p_a, u0=u0)
    with compilations(TRACED) as seen:
        run_b = shared.simulate(case.x, steps, shared_plant, params=p_b, u0=u0)
        again = fj.FIRHC(lt_b.shared_problem, observe=lt_b.observe, warm_start=True).simulate(
            case.x, steps, shared_plant, params=p_b, u0=u0)
    assert seen == [], seen
    own = fj.FIRHC(lt_b.problem, observe=lt_b.observe, warm_start=True).simulate(
        case.x, steps, own_plant, params=lt_b.params(Y, D), u0=u0)
    assert not np.allclose(np.asarray(run_a.predicted_costs), np.asarray(run_b.predicted_costs))  # lt_b's weights
    for field in ("inputs", "plans", "states", "predicted_costs"):
        np.testing.assert_array_equal(np.asarray(getattr(again, field)), np.asarray(getattr(run_b, field)))
    np.testing.assert_array_equal(np.asarray(run_b.inputs), np.asarray(own.inputs))
    for k in range(steps):
        assert same_cost(float(run_b.predicted_costs[k]), float(own.predicted_costs[k])), k


@settings(SETTINGS, max_examples=3)
@given(st.integers(0, 2**32 - 1))
def test_rows_of_different_trackers_in_one_batch(seed):
    """fj.solve_batch on lt.shared_problem with each row's params from another tracker (its own Q and
    lambda_u, stacked): row b is the brute-force minimum of tracker b's J."""
    case = Case("mimo", True, seed)
    rng = np.random.default_rng(seed)
    weights, trackers, rows = [], [], []
    for _ in range(3):
        root = rng.normal(size=(2, 2))
        case.Q, case.lambda_u = root.T @ root, float(rng.uniform(0, 2))
        weights.append((case.Q, case.lambda_u))
        trackers.append(case.tracker())
        rows.append((rng.normal(size=case.x.shape), case.controls[rng.integers(27)], rng.normal(size=case.y_ref.shape)))
    X, U, Y = (np.stack(a) for a in zip(*rows, strict=True))
    params = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *(t.params(y, with_model=True)
                                                              for t, y in zip(trackers, Y, strict=True)))
    out = fj.solve_batch(trackers[0].shared_problem, jax.vmap(trackers[0].observe)(X, U), params=params)
    for b in range(3):
        (case.Q, case.lambda_u), case.x, case.u_prev, case.y_ref = weights[b], X[b], U[b], Y[b]
        case.d = np.zeros_like(case.d)
        best = case.brute_force()
        assert same_cost(float(out.cost[b]), best) and bool(out.feasible[b]) == np.isfinite(best), b
        if np.isfinite(best):
            assert same_cost(best_starting_with(case, out.first_input[b]), best), b


def test_float32_search_stays_float32_and_exact_to_its_precision():
    case = Case("mimo", False, 11)
    lt = case.tracker()
    result = lt.solve(case.x.astype(np.float32), case.u_prev, case.y_ref, case.d, warm_start=NONE)
    assert result.cost.dtype == jnp.float32
    best = case.brute_force()
    assert abs(float(result.cost) - best) <= 1e-5 * max(best, 1.0)
    assert case.J(np.asarray(result.sequence)[None])[0] <= best + 1e-5 * max(best, 1.0)


@pytest.mark.parametrize("shape", ["mimo", "common"])
def test_closed_loop_with_firhc_decides_the_brute_force_optimum_at_every_step(shape):
    """Each step applies the first input of an optimal sequence: with classes of inputs (common), the member
    that ``first_input_of`` picks from the whole optimal plan."""
    case = Case(shape, True, 5)
    lt = case.tracker()
    assert lt.num_classes == (19 if shape == "common" else 27)
    steps = 6
    rng = np.random.default_rng(1)
    y_refs = rng.normal(size=(steps,) + case.y_ref.shape)
    ds = 0.3 * rng.normal(size=(steps,) + case.d.shape)
    ctrl = fj.FIRHC(lt.problem, observe=lt.observe, warm_start=True)

    def plant(x, u, p):
        return jnp.asarray(case.A) @ x + jnp.asarray(case.B) @ u + p.d[0]

    u0 = case.controls[0]
    run = ctrl.simulate(case.x, steps, plant, params=lt.params(y_refs, ds), u0=u0)
    x, u_prev = case.x, u0
    for k in range(steps):
        case.x, case.u_prev, case.y_ref, case.d = x, u_prev, y_refs[k], ds[k]
        best = case.brute_force()
        assert same_cost(float(run.predicted_costs[k]), best), k
        u_prev = np.asarray(run.inputs[k])
        assert same_cost(best_starting_with(case, u_prev), best), k
        x = case.A @ x + case.B @ u_prev + ds[k][0]
        np.testing.assert_allclose(np.asarray(run.states[k + 1]), x, rtol=1e-12, atol=1e-12)


def test_vmap_over_many_states_matches_brute_force():
    """jax.vmap of lt.solve (fj.solve_batch runs in the README test: test_readme_long_horizon_snippet_runs)."""
    case = Case("siso", True, 9)
    lt = case.tracker()
    rng = np.random.default_rng(2)
    B = 6
    X = rng.normal(size=(B,) + case.x.shape)
    U = case.controls[rng.integers(len(case.controls), size=B)]
    Y, D = rng.normal(size=(B,) + case.y_ref.shape), 0.3 * rng.normal(size=(B,) + case.d.shape)
    vmapped = jax.jit(jax.vmap(lt.solve))(X, U, Y, D)
    for b in range(B):
        case.x, case.u_prev, case.y_ref, case.d = X[b], U[b], Y[b], D[b]
        check(case, jax.tree_util.tree_map(lambda a, b=b: a[b], vmapped), f"vmap row {b}")


def unconstrained_cost_to_go(case, k, x, u_prev):
    """min over real u(k .. N-1) of the cost of steps k .. N-1 from x(k) = x after u_prev (least squares on the
    residuals of J, which are affine in the inputs)."""
    m = case.B.shape[1]
    w, vecs = np.linalg.eigh(case.Q)
    sq = np.sqrt(np.clip(w, 0, None))[:, None] * vecs.T  # sq^T sq = Q

    def residuals(U):
        out, xx, last = [], x, u_prev
        for j in range(k, case.N):
            u = U[(j - k) * m:(j - k + 1) * m]
            xx = case.A @ xx + case.B @ u + case.d[j]
            out += [sq @ (case.y_ref[j] - case.C @ xx), np.sqrt(case.lambda_u) * (u - last)]
            last = u
        return np.concatenate(out)

    size = (case.N - k) * m
    r0 = residuals(np.zeros(size))
    jac = np.stack([residuals(e) - r0 for e in np.eye(size)], axis=1)
    best = np.linalg.lstsq(jac, -r0, rcond=None)[0]
    return float(np.sum(residuals(best) ** 2))


@SETTINGS
@given(st.builds(Case, st.sampled_from(["mimo", "long"]), st.booleans(), st.integers(0, 2**32 - 1)))
def test_the_bound_is_the_unconstrained_cost_to_go(case):
    """W_k (the lower bound at a node k steps deep) is the minimum over real inputs of the steps left, from the
    node's state: admissible, since the real inputs include the finite ones, and no looser."""
    lt = case.tracker()
    params = lt.params(case.y_ref, case.d)
    rng = np.random.default_rng(int(case.x[0] * 1e6) % 2**32)
    child = jax.jit(lt.problem.dynamics)
    for k in range(1, case.N):  # a child k steps deep: from a random node at depth k - 1 with a random input
        parent = lt.observe(rng.normal(size=case.x.shape), case.controls[rng.integers(len(case.controls))])
        u = case.controls[rng.integers(len(case.controls))]
        z = child(parent, u, np.int32(k - 1), params)
        if not bool(lt.problem.allowed(parent, z, u, k - 1, params)):  # max_step: no child, its bound unused
            continue
        node = Node.unpack(np.asarray(z), lt.class_size, lt.m)
        true = unconstrained_cost_to_go(case, k, np.asarray(node.x), members_of(lt, node)[0])
        w = float(lt.problem.lower_bound(z, np.int32(case.N - k), params))
        assert abs(w - true) <= 1e-9 * max(true, 1.0), (k, w, true)  # both exact up to rounding
    # In float32 W is rounded down by a bound on its own rounding: never above the true cost-to-go.
    f32 = np.float32
    case.y_ref, case.d = case.y_ref.astype(f32).astype(float), case.d.astype(f32).astype(float)
    params = lt.params(case.y_ref.astype(f32), case.d.astype(f32))
    for k in range(1, case.N):
        parent = lt.observe(rng.normal(size=case.x.shape).astype(f32), case.controls[rng.integers(len(case.controls))])
        u = case.controls[rng.integers(len(case.controls))].astype(f32)
        z = child(parent, u, np.int32(k - 1), params)
        if not bool(lt.problem.allowed(parent, z, u, k - 1, params)):
            continue
        node = Node.unpack(np.asarray(z, float), lt.class_size, lt.m)
        true = unconstrained_cost_to_go(case, k, np.asarray(node.x), members_of(lt, node)[0])
        w = float(lt.problem.lower_bound(z, np.int32(case.N - k), params))
        # (1e-12: the float64 reference's own rounding; float32's is 1e-7 relative)
        assert true - 1e-3 * max(true, 1.0) <= w <= true + 1e-12 * max(true, 1.0), (k, w, true)


@pytest.mark.parametrize("kwargs, match", [
    ({"Q": [[1.0, 0.5], [0.0, 1.0]]}, "weight Q must be a symmetric"),
    ({"Q": [[1.0, 2.0], [2.0, 1.0]]}, "weight Q must be positive semidefinite"),
    ({"Q": np.eye(3)}, r"Q must be \[p, p\]"),
    ({"C": np.ones((2, 3))}, "C must be"),
    ({"lambda_u": -1.0}, "lambda_u must be a finite number >= 0"),
    ({"norm": "l1"}, r"norm must be one of \('squared', 'abs'\), got 'l1'"),
    ({"max_step": float("nan")}, "max_step must be a finite number"),
    ({"A": np.ones((2, 3))}, "A must be square"),
    ({"A": [[np.nan, 0], [0, 1]]}, "A contains NaN"),
    ({"B": np.ones((3, 1))}, "B must be"),
    ({"controls": np.ones((4, 2))}, "controls must have m = 1"),
    ({"horizon": 0}, "horizon"),
])
def test_bad_arguments_are_refused_by_name(kwargs, match):
    args = {"A": np.eye(2) * 0.5, "B": np.ones((2, 1)), "controls": [-1.0, 0.0, 1.0], "horizon": 3,
            "C": np.ones((2, 2))}
    args.update(kwargs)
    with pytest.raises((ValueError, TypeError), match=match):
        fj.LinearTracking(args.pop("A"), args.pop("B"), args.pop("controls"), args.pop("horizon"), **args)


@pytest.mark.parametrize("which, value, match", [
    ("x", np.zeros(3), r"x must be \[n\]"), ("u_prev", np.zeros(2), "u_prev must have shape"),
    ("y_ref", np.zeros((2, 1)), "y_ref must have shape"), ("d", np.zeros((4, 1)), "d must have shape"),
    ("y_ref", np.full((4, 1), np.nan), "y_ref contains NaN")])
def test_bad_decision_data_is_refused_by_name(which, value, match):
    lt = fj.LinearTracking(np.eye(2) * 0.5, np.ones((2, 1)), [-1.0, 0.0, 1.0], 4, C=np.ones((1, 2)))
    args = {"x": np.zeros(2), "u_prev": np.zeros(1), "y_ref": np.zeros((4, 1)), "d": np.zeros((4, 2))}
    args[which] = value
    with pytest.raises(ValueError, match=match):
        lt.solve(**args)


def test_three_level_inverter_model():
    A, B = three_level.model()
    assert three_level.SWITCH_STATES.shape == (27, 3)
    np.testing.assert_allclose(B @ np.ones(3), 0.0, atol=1e-15)  # the common mode applies no voltage
    assert len({tuple(np.round(B @ u, 12)) for u in three_level.SWITCH_STATES}) == 19
    # one sample of +Vdc/2 on leg a from zero current: about Vdc/2 * 2/3 * Ts / L
    np.testing.assert_allclose(B @ np.array([1.0, 0.0, 0.0]), [400 / 3 * 25e-6 / 2e-3, 0.0], rtol=2e-2)


def test_the_inverter_switch_states_form_19_classes_of_equal_voltage():
    lt = three_level.make_problem(2)
    A, B = three_level.model()
    assert (lt.num_classes, lt.class_size) == (19, 3)
    sizes = np.bincount(lt.class_of)
    assert sorted(sizes) == [1] * 12 + [2] * 6 + [3]  # large and medium vectors, small vectors, zero
    for j in range(19):  # members of a class apply the same voltage; different classes do not
        volts = B @ lt.controls[lt.class_of == j].T
        np.testing.assert_allclose(volts, np.broadcast_to(volts[:, :1], volts.shape), atol=1e-12)
    reps = B @ lt.problem.controls.T  # [2, 19]
    assert np.min(np.linalg.norm(reps[:, :, None] - reps[:, None, :], axis=0) + 10 * np.eye(19)) > 1.0
    np.testing.assert_array_equal(lt.problem.controls, lt.controls[[np.flatnonzero(lt.class_of == j)[0]
                                                                    for j in range(19)]])


def test_first_input_of_must_return_one_input():
    problem = fj.Problem(lambda x, u: x + u, [-1.0, 1.0], lambda x, u: x @ x, 2,
                         first_input_of=lambda x0, seq: jnp.zeros(2))
    with pytest.raises(ValueError, match=r"first_input_of must return one input of shape \[m\] = \[1\]"):
        fj.sdfs(problem, np.ones(1))
    with pytest.raises(TypeError, match="first_input_of must be callable"):
        fj.Problem(lambda x, u: x + u, [-1.0, 1.0], lambda x, u: x @ x, 2, first_input_of=3)


def test_solve_batch_applies_the_optimal_member_of_each_row():
    """fj.solve_batch on lt.problem (the work pool, vmap, exhaustive): each row's first_input starts an optimal
    sequence, on a plant whose inputs form classes."""
    rng = np.random.default_rng(4)
    cases = [Case("common", True, int(s)) for s in rng.integers(0, 2**31, 5)]
    case = cases[0]
    lt = case.tracker()
    X = np.stack([c.x for c in cases])
    U = np.stack([c.controls[rng.integers(27)] for c in cases])
    Y, D = np.stack([c.y_ref for c in cases]), np.stack([c.d for c in cases])
    for solver in ("sdfs", "sdfs-vmap", "exhaustive"):
        out = fj.solve_batch(lt.problem, jax.vmap(lt.observe)(X, U), params=lt.params(Y, D), solver=solver)
        for b in range(len(cases)):
            case.x, case.u_prev, case.y_ref, case.d = X[b], U[b], Y[b], D[b]
            best = case.brute_force()
            assert same_cost(float(out.cost[b]), best), (solver, b)
            if np.isfinite(best):
                assert same_cost(best_starting_with(case, out.first_input[b]), best), (solver, b)


def test_thermal_model_steady_state_and_calm_states():
    A, B, d = thermal.model()
    x = np.full(4, thermal.ThermalParams().ambient)
    np.testing.assert_allclose(A @ x + d, x, atol=1e-12)  # ambient is an equilibrium with the heaters off
    X, U = thermal.calm_states(5, np.random.default_rng(0))
    np.testing.assert_allclose(X @ thermal.OUTPUTS.T, np.broadcast_to(thermal.ThermalParams().set_point, (5, 2)),
                               atol=0.05)
    assert set(map(tuple, U)) <= set(map(tuple, thermal.HEATERS))


@pytest.mark.slow
def test_the_long_horizon_guide_runs_and_agrees():
    """The first block of docs/guide/long-horizons.md, after the tour's imports, as written."""
    import re

    from repository import DOCS

    tour = re.findall(r"```python\n(.*?)```", (DOCS / "getting-started.md").read_text(), re.S)[0]
    block = re.findall(r"```python\n(.*?)```", (DOCS / "guide" / "long-horizons.md").read_text(), re.S)[0]
    namespace = {}
    exec(compile(tour.split("\n\n", 1)[0], "getting-started.md tour imports", "exec"), namespace)
    exec(compile(block, "long-horizons.md", "exec"), namespace)
    res, loop, many, lt = namespace["res"], namespace["loop"], namespace["many"], namespace["lt"]
    assert bool(res.feasible) and not np.any(np.isnan(np.asarray(loop.inputs))) and loop.states.shape == (41, 2)
    assert same_cost(float(loop.predicted_costs[0]), float(res.cost))  # the loop's first decision is res's
    for b, x in enumerate(namespace["X"]):  # fj.solve_batch: each row is lt.solve's optimum
        one = lt.solve(x, np.zeros(3), namespace["reference"](0))
        assert same_cost(float(many.cost[b]), float(one.cost)) and bool(many.feasible[b])


@pytest.mark.slow
def test_cli_three_level_inverter_writes_summary_and_figure(tmp_path, capsys):
    import json

    from firhc_jax import cli

    argv = ["inverter", "--levels", "3", "--horizon", "3", "--cycles", "0.1", "--out", str(tmp_path), "--no-progress"]
    assert cli.main(argv) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["levels"] == 3 and summary["horizon"] == 3 and summary["lambda_u"] == 0.1 and summary["steps"] == 80
    assert 0 < summary["thd"] < 0.2 and 0 < summary["switching_frequency_hz"] < 20_000
    assert summary["nodes_max"] <= 27 + 27**2 + 27**3 + 3
    assert (tmp_path / "inverter3_N3.png").stat().st_size > 10_000
    with pytest.raises(SystemExit, match="apply to --levels 2 only"):
        cli.main(["inverter", "--levels", "3", "--solver", "exhaustive", "--out", str(tmp_path)])
    with pytest.raises(SystemExit) as e:  # argparse's one-line error, before any work
        cli.main(["inverter", "--horizon", "10", "--out", str(tmp_path)])
    assert e.value.code == 2 and "with --levels 2" in capsys.readouterr().err


def test_an_input_outside_the_controls_has_no_child():
    """The problem's dynamics on an input of no class: discarded (constraint False), never read as class 0."""
    lt = three_level.make_problem(2)
    p = lt.params(np.zeros((2, 2)))
    z = lt.observe(np.zeros(2), np.zeros(3))
    stray = np.array([0.5, 0.0, 0.0])
    assert not bool(lt.problem.allowed(z, lt.problem.next_state(z, stray, 0, p), stray, 0, p))
    rep = lt.problem.controls[0]
    assert bool(lt.problem.allowed(z, lt.problem.next_state(z, rep, 0, p), rep, 0, p))


@pytest.mark.parametrize("norm, max_step", [("abs", 1.0), ("squared", None)])
def test_switchings_from_the_members_search_as_the_table(monkeypatch, norm, max_step):
    """Classes too many for the switching table (beyond MAX_TABLE_BYTES) compute the switchings between members
    from the members: the same nodes, cost and plan as the table, from roots after a control and after an input
    that is none (the five-level inverter's 61 classes of up to 5, N = 3)."""
    A, B = three_level.model()
    controls = fj.product_controls([-2.0, -1.0, 0.0, 1.0, 2.0], repeat=3)
    make = lambda: fj.LinearTracking(A, B / 2, controls, 3, lambda_u=0.5, norm=norm, max_step=max_step)  # noqa: E731
    table = make()
    monkeypatch.setattr(tracking, "MAX_TABLE_BYTES", 0)
    members = make()
    assert table._classes.switch is not None and members._classes.switch is None
    rng = np.random.default_rng(3)
    for u_prev in (controls[17], controls[90], np.array([0.5, -0.25, 0.0])):
        x, y_ref = rng.normal(scale=10.0, size=2), rng.normal(scale=20.0, size=(3, 2))
        out = [fj.sdfs(lt.problem, lt.observe(x, u_prev), params=lt.params(y_ref)) for lt in (table, members)]
        assert bool(out[0].feasible)
        assert int(out[0].nodes) == int(out[1].nodes) and float(out[0].cost) == float(out[1].cost)
        np.testing.assert_array_equal(out[0].first_input, out[1].first_input)
        plans = [lt.sequence(lt.observe(x, u_prev), o.sequence, lt.params(y_ref)) for lt, o in zip(
            (table, members), out, strict=True)]
        np.testing.assert_array_equal(plans[0], plans[1])


@pytest.mark.parametrize("which", ["five-level, shuffled", "random reals"])
def test_every_control_reaches_the_node_of_its_class(which):
    """The dynamics finds the class of any control it is given (the searches give it each class's first member, a
    closed loop without a plant applies any member): its node is of that class (whose members ``lt.classes``
    lists) with the state A x + B u, and an input that is no control has no child."""
    rng = np.random.default_rng(1)
    if which == "random reals":  # 37 inputs, some sharing a component: ties decided by the next one
        controls = np.round(rng.normal(size=(37, 2)), 1)
        controls = controls[np.unique(controls, axis=0, return_index=True)[1]]
        A, B = np.eye(2) * 0.9, rng.normal(size=(2, 2))
    else:  # 125 inputs in 61 classes of up to 5
        controls = rng.permutation(fj.product_controls([-2.0, -1.0, 0.0, 1.0, 2.0], repeat=3))
        A, B = three_level.model()
    lt = fj.LinearTracking(A, B, controls, 1)
    p, x = lt.params(np.zeros((1, 2))), np.array([0.3, -0.2])
    z = lt.observe(x, controls[0])
    child = jax.jit(lambda u: lt.problem.next_state(z, u, 0, p))
    for i, u in enumerate(controls):
        node = Node.unpack(child(u), lt.class_size, controls.shape[1])
        members = controls[lt.class_of == lt.class_of[i]]
        assert int(node.j) == lt.class_of[i], i
        assert {tuple(v) for v in members_of(lt, node)} == {tuple(v) for v in members}, i
        np.testing.assert_allclose(node.x, A @ x + B @ u, rtol=1e-12, atol=1e-12)
    for stray in (controls[0] + 0.05, controls.max(axis=0) + 1.0, controls.min(axis=0) - 1.0):
        assert not bool(lt.problem.allowed(z, child(stray), stray, 0, p)), stray


def test_the_search_state_is_a_packed_node():
    """observe packs the root Node; a child's x is the plant's next state and its stage cost is the tracking
    error plus the cheapest switching onto a member of its class (three-level inverter: C = Q = I, max_step 1)."""
    lt = three_level.make_problem(2, lambda_u=0.3)
    A, B = three_level.model()
    x, u_prev = np.array([1.0, -2.0]), np.array([1.0, 0.0, -1.0])
    z = lt.observe(x, u_prev)
    root = Node.unpack(z, lt.class_size, lt.m)
    assert z.shape == (2 + 3 + 3 + 3,)
    np.testing.assert_array_equal(root.x, x)
    np.testing.assert_array_equal(root.u_prev, u_prev)
    assert float(root.j) == -1.0
    np.testing.assert_array_equal(root.o, [0.0, -1.0, -1.0])
    assert float(root.stage) == 0.0 and float(root.W) == 0.0
    np.testing.assert_array_equal(root.pack(), z)
    y_ref = np.array([[3.0, 1.0], [0.0, 0.0]])
    params = lt.params(y_ref)
    for j, rep in enumerate(lt.problem.controls):
        child = Node.unpack(lt.problem.next_state(z, rep, 0, params), lt.class_size, lt.m)
        x_next = A @ x + B @ rep
        np.testing.assert_allclose(child.x, x_next, rtol=1e-12, atol=1e-12)
        assert int(child.j) == j
        members = lt.controls[lt.class_of == j]
        steps = np.abs(members - u_prev)
        switching = np.where(np.all(steps <= 1, axis=1), 0.3 * np.sum(steps**2, axis=1), np.inf)
        if np.isfinite(switching.min()):
            expected = np.sum((y_ref[0] - x_next) ** 2) + switching.min()
            np.testing.assert_allclose(float(child.stage), expected, rtol=1e-12)
        reached = np.zeros(lt.class_size, bool)  # padding (classes of fewer members) is never reached
        reached[:len(members)] = np.isfinite(switching)
        np.testing.assert_array_equal(np.asarray(child.o) >= 0, reached)


def test_params_of_the_other_problem_are_refused_by_name():
    """lt.problem takes lt.params(...) (or a mapping of its fields, as an .npz reads back), lt.shared_problem
    lt.params(..., with_model=True): the same child either way; the wrong one is a TypeError that names the
    right one. p["d"] still reads p.d, with a DeprecationWarning."""
    lt = three_level.make_problem(2)
    z, rep = lt.observe(np.array([1.0, -2.0]), np.zeros(3)), lt.problem.controls[4]
    y_ref = np.array([[3.0, 1.0], [0.0, 0.0]])
    data, shared = lt.params(y_ref), lt.params(y_ref, with_model=True)
    child = np.asarray(lt.problem.next_state(z, rep, 0, data))
    np.testing.assert_array_equal(lt.shared_problem.next_state(z, rep, 0, shared), child)
    np.testing.assert_array_equal(lt.problem.next_state(z, rep, 0, data._asdict()), child)
    assert float(lt.problem.first_input(z, np.zeros(2, np.int32), data)[0]) == \
        float(lt.shared_problem.first_input(z, np.zeros(2, np.int32), shared)[0])
    with pytest.raises(TypeError, match=r"params=lt.params\(y_ref, d\) \(a TrackingParams\) \(lt.shared_problem "
                                        r"takes the params with the model\), got SharedParams"):
        lt.problem.next_state(z, rep, 0, shared)
    with pytest.raises(TypeError, match=r"shared_problem reads the model from its params: pass "
                                        r"params=lt.params\(y_ref, d, with_model=True\)"):
        lt.shared_problem.next_state(z, rep, 0, data)
    with pytest.raises(TypeError, match=r"problem reads each decision's data from its params"):
        fj.sdfs(lt.problem, z)
    with pytest.warns(DeprecationWarning, match=r'read p.d, not p\["d"\]'):
        assert data["d"] is data.d
    assert data[-1] is data.d
    with pytest.raises(KeyError, match="fields"):
        data["D"]


def test_params_first_made_inside_a_jit_serve_later_calls():
    """The tracker keeps its model on the device per dtype: made first inside a trace, it must still be
    concrete arrays, not the trace's values leaking into later calls."""
    from firhc_jax.models import three_level

    lt = three_level.make_problem(3)
    y = np.zeros((3, 2))
    assert float(jax.jit(lambda y: lt.params(y).off.sum())(y)) == 0.0
    x, u = np.zeros(2), np.zeros(3)
    assert float(jax.jit(lt.solve)(x, u, y).cost) == float(lt.solve(x, u, y).cost)
