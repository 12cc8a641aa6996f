"""Three-tank system (paper Sec. IV.2): plant physics, exactness of the closed loop, settling, CLI."""
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compiles import compiles_inside
from scipy.integrate import solve_ivp

import firhc_jax as fj
from firhc_jax import cli
from firhc_jax.apps import tanks as app
from firhc_jax.apps._timing import compile_events as compilations
from firhc_jax.apps._timing import timed_closed_loop
from firhc_jax.models import tanks as model

P = model.TankParams()
PLANT = jax.jit(jax.vmap(model.make_plant(P)))  # ([B, 3], [B]) -> ([B, 3], [B])
ALL_MODES = np.arange(model.NUM_MODES)


def _grid(levels):
    """Every level triple in ``levels`` [L, 3] with every mode: ([L*17, 3], [L*17])."""
    levels = np.asarray(levels, dtype=float)
    return np.repeat(levels, model.NUM_MODES, axis=0), np.tile(ALL_MODES, len(levels))


@pytest.fixture(scope="module")
def problems():
    """One problem per horizon, shared so that each search compiles once."""
    return {n: model.make_problem(n, P) for n in (3, 4)}


STEPS = 30  # 60 s: the whole transient into the 5 mm band, and the settled levels after it (the CLI test's run)


@pytest.fixture(scope="module")
def sdfs_n3(problems):
    """``(loop, compile_s)`` of the N = 3 sDFS closed loop for STEPS samples, run once for every test that
    looks at it (one compiled loop)."""
    return app.simulate(problems[3], "sdfs", STEPS)


def test_volume_change_is_pump_inflow_minus_drain_outflow():
    rng = np.random.default_rng(0)
    h, modes = _grid(rng.uniform(0.05, 0.5, (40, 3)))  # interior: no clipping within one sample
    h_next, drained = PLANT(jnp.asarray(h), jnp.asarray(modes))
    volume_change = P.area * np.sum(np.asarray(h_next) - h, axis=1)  # [B] m^3
    pumped = np.array([model.pump_volume(m, P) for m in modes])  # [B] m^3
    np.testing.assert_allclose(volume_change, pumped - np.asarray(drained), rtol=0, atol=1e-15)
    assert np.all(np.asarray(drained)[[model.MODES[m].trans3 == 0 for m in modes]] == 0)


def test_levels_stay_within_tank_limits():
    edges = [0.0, 1e-6, 0.01, 0.3, P.height - 0.005, P.height]
    h, modes = _grid(np.array(np.meshgrid(edges, edges, edges)).reshape(3, -1).T)
    for _ in range(30):  # every mode held for 60 s from every corner of the tank
        h, _ = PLANT(jnp.asarray(h), jnp.asarray(modes))
        assert np.all((np.asarray(h) >= 0.0) & (np.asarray(h) <= P.height))


def _rhs(_, y, c):
    h1, h2, h3 = y
    f13 = c[2] * np.sign(h1 - h3) * np.sqrt(abs(h1 - h3))
    f32 = c[3] * np.sign(h3 - h2) * np.sqrt(abs(h3 - h2))
    f30 = c[4] * np.sqrt(max(h3, 0.0))
    return [c[0] - f13, c[1] + f32, f13 - f32 - f30]


def test_rk4_sample_matches_a_tight_ode_solve():
    rng = np.random.default_rng(1)
    h, modes = _grid(np.vstack([rng.uniform(0.0, 0.55, (6, 3)), [model.SET_POINT, model.INITIAL_LEVELS]]))
    h_next, _ = PLANT(jnp.asarray(h), jnp.asarray(modes))
    coeffs = model.mode_coefficients(P)
    for h0, m, got in zip(h, modes, np.asarray(h_next), strict=True):
        ref = solve_ivp(_rhs, (0.0, P.ts), h0, args=(coeffs[m],), method="LSODA", rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(got, np.clip(ref.y[:, -1], 0.0, P.height), rtol=0, atol=1e-5)


def test_paper_example_mode_follows_eq_25():
    mode = model.MODES[model.PAPER_EXAMPLE_MODE]
    # u = {V_Fill1=0, V_Fill2=1, V_trans1=1, V_trans2=0, V_trans3=1, pump=low}
    assert (mode.fill1, mode.fill2, mode.trans1, mode.trans2, mode.trans3, mode.pump) == (0, 1, 1, 0, 1, 1)
    root = P.pipe * np.sqrt(2 * P.g)

    def eq25(h, dt):  # eq. (25) with its state-dependent time constants, at step dt
        h1, h2, h3 = h
        tau12 = P.area * np.sqrt(abs(h1 - h3)) / (P.az13 * root)  # tau_1 = tau_2: the same pipe
        tau3 = P.area * np.sqrt(h3) / (P.az30 * root)
        return np.array([h1 + dt * (h3 - h1) / tau12, h2 + dt * P.q_low / P.area,
                         h3 + dt * ((h1 - h3) / tau12 - h3 / tau3)])

    for h0 in ([0.3, 0.25, 0.15], [0.1, 0.2, 0.4]):  # T1 above, then below T3
        ref = np.asarray(h0)
        for _ in range(20000):
            ref = eq25(ref, P.ts / 20000)
        got, _ = PLANT(jnp.asarray([h0]), jnp.asarray([model.PAPER_EXAMPLE_MODE]))
        got = np.asarray(got)[0]
        np.testing.assert_allclose(got, ref, rtol=0, atol=2e-6)
        assert np.sign(got[0] - h0[0]) == np.sign(h0[2] - h0[0])  # T1 moves towards T3
        assert got[1] - h0[1] == pytest.approx(P.ts * P.q_low / P.area, abs=1e-15)  # Flow_low / A


def test_modes_are_distinct_and_pump_never_dead_heads():
    patterns = {m[1:7] for m in model.MODES}
    assert len(patterns) == model.NUM_MODES == 17
    for m in model.MODES:
        assert (m.pump > 0) == (m.fill1 + m.fill2 > 0), m.name


def test_switch_penalty_counts_toggled_actuators():
    problem = model.make_problem(3, P, switch_penalty=2.0)
    x0 = jnp.asarray(model.initial_state())  # after hold
    u = problem.controls[model.PAPER_EXAMPLE_MODE]
    x1 = problem.dynamics(x0, u)
    assert float(x1[3]) == model.PAPER_EXAMPLE_MODE and float(x1[4]) == 4.0  # V_Fill2, V_trans1, V_trans3, pump
    plain = model.make_problem(3, P).stage_cost(x1, u)
    assert float(problem.stage_cost(x1, u)) == pytest.approx(float(plain) + 8.0)


# N = 4: 12 steps, 24 s, the transient into the band
@pytest.mark.parametrize("horizon, steps", [(3, STEPS), pytest.param(4, 12, marks=pytest.mark.slow)])
def test_sdfs_and_exhaustive_closed_loops_are_identical(problems, sdfs_n3, horizon, steps):
    sdfs = sdfs_n3[0] if horizon == 3 else app.simulate(problems[horizon], "sdfs", steps)[0]
    runs = {"sdfs": sdfs, "exhaustive": app.simulate(problems[horizon], "exhaustive", steps)[0]}
    np.testing.assert_array_equal(runs["sdfs"].states, runs["exhaustive"].states)
    np.testing.assert_array_equal(runs["sdfs"].input_indices, runs["exhaustive"].input_indices)
    assert np.all(np.asarray(runs["exhaustive"].nodes) == problems[horizon].tree_size())
    assert np.all(np.asarray(runs["sdfs"].nodes) < problems[horizon].tree_size())


def test_compile_time_is_a_fresh_compilation_of_the_decision_even_when_cached():
    """Where this process compiled an equal controller's step already, the helper compiles the decision once more
    to time it (tiny problem: one compile costs little), so compile_s is never a cached call's time."""
    problem = fj.Problem(lambda x, u: 0.5 * x + u, np.array([[-1.0], [0.0], [1.0]]),
                         lambda x, u: jnp.sum(x * x), horizon=2)
    x0 = np.array([2.0])
    _, fresh_s = timed_closed_loop(fj.FIRHC(problem), x0, 2)
    with compilations() as seen:
        loop, cached_s = timed_closed_loop(fj.FIRHC(problem), x0, 2)  # an equal controller: its step is cached
    assert seen and cached_s >= max(d for _, d in seen)  # the ahead-of-time compilation, timed
    assert fresh_s > 0 and np.all(np.isfinite(loop.solve_times))


# summary.json of `tanks --horizon 3 --seconds 60` before the applications moved onto step/simulate with one timing
# helper (commit 4d3fbf9): the port changes no result.
BEFORE_PORT = {"final_levels": [0.3018917870083893, 0.2487039973569028, 0.15018343641392878],
               "max_abs_error_last_20s": 0.001891787008389323, "settling_time_s": 22.0, "nodes_min": 51,
               "nodes_max": 3145, "nodes_mean": 484.5, "fallback_steps": 0, "mode_changes": 8,
               "modes": [9, 9, 12, 12, 16, 16, 12, 16, 16, 12, 16, 11] + [0] * 18}


@pytest.mark.slow
def test_cli_runs_the_timed_loop_of_the_compiled_one_and_writes_its_results(sdfs_n3, tmp_path, monkeypatch, capsys):
    """The CLI's timed closed loop (a Python loop of the compiled step) is the compiled scan's, bit for bit; every
    decision is timed; compile_time_s is the decision's tracing and compilation (at least XLA's compile of it),
    done before the timed loop, which compiles no decision; the summary is the one recorded before the port."""
    with compilations() as seen:  # the event is still reported under this name (else the checks below are void)
        jax.jit(lambda a: a * 2)(np.arange(3.0))
    assert seen, "no compile event observed: jax.monitoring's event name changed"
    argv = ["tanks", "--horizon", "3", "--seconds", "60", "--out", str(tmp_path), "--no-progress"]
    code, seen, in_loop = compiles_inside(monkeypatch, fj.FIRHC, "simulate", lambda: cli.main(argv))
    assert code == 0
    said = capsys.readouterr().err  # every stage of the run is announced, then timed
    stages = [line[:-4] for line in said.splitlines() if line.endswith(" ...")]
    assert stages[0] == "compiling the decision" and stages[-1].startswith("writing summary.json"), said
    assert all(f"{stage}: done in" in said for stage in stages), said
    decision = max((c for c in seen if c not in in_loop), key=lambda c: c[1])  # (name, s) the longest before
    assert decision[0] not in {name for name, _ in in_loop}
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["compile_time_s"] >= decision[1]
    for key, value in BEFORE_PORT.items():
        assert summary[key] == pytest.approx(value, rel=1e-12), key
    assert summary["horizon"] == 3 and summary["solver"] == "sdfs" and summary["seconds"] == 60.0
    assert 0 < summary["solve_time_median_s"] <= summary["solve_time_max_s"]
    assert (tmp_path / "tanks_N3_sdfs.png").stat().st_size > 10_000
    timed, loop = fj.ClosedLoop.load(tmp_path / "closed_loop.npz"), sdfs_n3[0]
    for field in ("states", "input_indices", "nodes", "plans"):
        np.testing.assert_array_equal(getattr(timed, field), getattr(loop, field), err_msg=field)
    assert sdfs_n3[1] is None and np.all(np.isnan(np.asarray(loop.solve_times)))
    assert np.all(np.isfinite(timed.solve_times) & (timed.solve_times > 0))
    np.testing.assert_array_equal(timed.times, np.arange(STEPS + 1) * P.ts)


def test_levels_settle_within_5_mm_and_stay(sdfs_n3):
    loop, _ = sdfs_n3
    errors = np.asarray(loop.states)[:, :3] - np.asarray(model.SET_POINT)  # [STEPS + 1, 3]
    settled = app.settling_time(errors, P.ts, 0.005)
    assert settled is not None and settled <= 30.0
    assert np.max(np.abs(errors[int(settled / P.ts):])) <= 0.005


def test_terminal_box_is_tested_on_levels():
    problem = model.make_problem(3, P, terminal_tol=0.002)
    assert bool(problem.terminal(jnp.asarray(model.initial_state(model.SET_POINT))))
    assert not bool(problem.terminal(jnp.asarray(model.initial_state((0.3, 0.25, 0.153)))))


@pytest.mark.parametrize("argv, message", [
    (["--horizon", "0"], "between 1 and"),
    (["--horizon", "three"], "must be an integer"),
    (["--solver", "bfs"], "invalid choice"),
    (["--seconds", "-5"], "--seconds: must be a number > 0"),
    (["--switch-penalty", "-1"], ">= 0"),
])
def test_cli_rejects_bad_input(argv, message, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["tanks", *argv])
    assert e.value.code == 2
    assert message in capsys.readouterr().err


def test_cli_rejects_run_shorter_than_a_sample(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["tanks", "--seconds", "1", "--out", str(tmp_path)])
    assert e.value.code == 2 and "at least one sample" in capsys.readouterr().err


@pytest.mark.slow
def test_bound_is_admissible_and_keeps_the_closed_loop(sdfs_n3):
    """The level-rate bound passes the exhaustive check, 10x it is caught, and the bounded closed loop (with and
    without a terminal box) is the unbounded one."""
    from firhc_jax._src.tools.diagnostics import check_lower_bound

    for tol in (None, 0.01):
        # Without a box the unbounded loop is the shared one (problems[3] is make_problem(3) with P's defaults).
        plain = sdfs_n3[0] if tol is None else app.simulate(model.make_problem(3, terminal_tol=tol), steps=STEPS)[0]
        bounded, _ = app.simulate(model.make_problem(3, terminal_tol=tol, bound=True), steps=STEPS)
        np.testing.assert_allclose(np.asarray(bounded.stage_costs), np.asarray(plain.stage_costs), rtol=1e-9)
        assert np.asarray(bounded.nodes).sum() < np.asarray(plain.nodes).sum()
    problem = model.make_problem(2, bound=True)
    states = np.asarray(plain.states[:-1])[::3]
    assert check_lower_bound(problem, states) == []
    inflated = problem.replace(lower_bound=lambda x, s: 10 * problem.lower_bound(x, s))
    assert check_lower_bound(inflated, states)
