"""Two-level inverter with RL load: discretisation, reference plumbing, exactness of the closed loop, CLI."""
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from reference import rollout, same_cost
from scipy.linalg import expm

import firhc_jax as fj
from firhc_jax import cli
from firhc_jax.apps import inverter as app
from firhc_jax.apps._timing import compile_events
from firhc_jax.models import inverter as model

P = model.InverterParams()


def test_switch_states_give_the_hexagon_and_two_zero_vectors():
    v_alpha, v_beta = model.voltage(model.SWITCH_STATES, P.vdc)
    radius = np.hypot(v_alpha, v_beta)
    np.testing.assert_allclose(radius[[0, 7]], 0.0, atol=1e-12)
    np.testing.assert_allclose(radius[1:7], 2.0 * P.vdc / 3.0, rtol=1e-14)
    angles = np.degrees(np.arctan2(v_beta[1:7], v_alpha[1:7])) % 360.0
    np.testing.assert_allclose(angles, [0, 60, 120, 180, 240, 300], atol=1e-9)
    assert len({tuple(s) for s in model.SWITCH_STATES}) == 8


def test_exact_discretisation_matches_the_matrix_exponential():
    # continuous alpha-beta model d/dt i = A i + B v with v held over T_s
    A, B = -P.r / P.l * np.eye(2), np.eye(2) / P.l
    aug = expm(np.block([[A, B], [np.zeros((2, 4))]]) * P.ts)
    Ad, Bd = aug[:2, :2], aug[:2, 2:]
    plant = jax.jit(model.make_plant(P, "exact"))
    rng = np.random.default_rng(0)
    for u in model.SWITCH_STATES:
        i = rng.uniform(-15.0, 15.0, 2)
        v = np.array(model.voltage(u, P.vdc))
        np.testing.assert_allclose(np.asarray(plant(jnp.asarray(i), jnp.asarray(u))), Ad @ i + Bd @ v,
                                   rtol=1e-12, atol=1e-12)


def test_euler_is_first_order_close_to_exact():
    a_exact, b_exact = model.discretise(P, "exact")
    a_euler, b_euler = model.discretise(P, "euler")
    x = P.r * P.ts / P.l
    assert a_euler == 1.0 - x and b_euler == P.ts / P.l
    assert a_exact - a_euler == pytest.approx(x * x / 2.0 - x**3 / 6.0, rel=1e-3)  # exp(-x) = 1 - x + x^2/2 - ...
    assert (b_euler - b_exact) / b_euler == pytest.approx(x / 2.0, rel=2e-2)
    with pytest.raises(ValueError, match="method"):
        model.discretise(P, "rk4")


def test_problem_tracks_each_predicted_step_against_its_own_reference():
    """The stage cost of the input with step index j compares the currents after it with p["ref"][j], and the
    model state is the currents alone (with the input memory): no step counter."""
    horizon = 3
    mem = model.make_problem(horizon, P)
    assert mem.problem.step_index
    refs = model.horizon_references(P, 1, horizon)[0]  # [3, 2]: references at steps 1, 2, 3
    p = {"ref": jnp.asarray(refs), "lambda_u": jnp.asarray(2.0)}
    i0 = jnp.asarray(model.initial_currents(P))
    z = mem.observe(i0, jnp.zeros(3), p)
    assert z.shape == (2 + 3 + 1,)  # [i_alpha, i_beta, u_prev (3), switching cost]
    plant = model.make_plant(P)
    total = 0.0
    for j, u in enumerate(model.SWITCH_STATES[[1, 1, 7]]):  # V1, V1, V7: 1 change, 0, then 2 legs change
        z = mem.problem.dynamics(z, jnp.asarray(u), jnp.int32(j), p)
        total += float(mem.problem.stage_cost(z, jnp.asarray(u), jnp.int32(j), p))

    def step(i, u, t):  # the plant's currents against the reference of their own step
        i = np.asarray(plant(jnp.asarray(i), jnp.asarray(u)))
        return i, np.sum((refs[t] - i) ** 2)

    tracking, i3 = rollout(step, i0, model.SWITCH_STATES[[1, 1, 7]])
    assert same_cost(total, tracking + 2.0 * (1 + 0 + 2), rtol=1e-12)
    np.testing.assert_array_equal(z[:2], i3)


@pytest.mark.parametrize("lambda_u", [0.0, 1.0])
def test_sdfs_and_exhaustive_closed_loops_agree(lambda_u):
    # Compiled scans, one per solver for both values of lambda_u (a parameter: no recompile).
    runs = {s: app.closed_loop(3, s, steps=100, lambda_u=lambda_u, timed=False) for s in ("sdfs", "exhaustive")}
    np.testing.assert_array_equal(runs["sdfs"].predicted_costs, runs["exhaustive"].predicted_costs)
    np.testing.assert_array_equal(runs["sdfs"].currents, runs["exhaustive"].currents)
    assert np.all(runs["exhaustive"].nodes == 8 + 64 + 512)
    assert runs["sdfs"].nodes.mean() < 0.25 * (8 + 64 + 512)


def test_switching_penalty_lowers_switching_frequency():
    steps = model.InverterParams().steps_per_cycle // 4  # a quarter cycle (free: ~7.2 kHz, penalised: ~2.1 kHz)
    summaries = [app.summarize(app.closed_loop(2, "sdfs", steps, lam, timed=False), 2, "sdfs", lam, P)
                 for lam in (0.0, 2.0)]
    free, penalised = summaries
    assert penalised["switching_frequency_hz"] < 0.6 * free["switching_frequency_hz"]
    assert penalised["rms_tracking_error"] > free["rms_tracking_error"]  # the price: a larger ripple
    assert free["rms_tracking_error"] < 0.3


def test_distortion_of_a_pure_sine_and_of_a_known_harmonic():
    t = np.arange(P.steps_per_cycle * 2) * P.ts
    w = 2 * math.pi * P.frequency
    fundamental, thd = model.distortion(3.0 * np.cos(w * t + 0.3), P)
    assert fundamental == pytest.approx(3.0, rel=1e-12) and thd < 1e-12
    fundamental, thd = model.distortion(3.0 * np.cos(w * t) + 0.15 * np.sin(5 * w * t) + 0.5, P)
    assert fundamental == pytest.approx(3.0, rel=1e-12) and thd == pytest.approx(0.05, rel=1e-12)
    f, amp = app.spectrum(3.0 * np.cos(w * t) + 0.15 * np.sin(5 * w * t), P.ts)  # the DFT agrees over whole cycles
    assert amp[np.argmin(abs(f - P.frequency))] == pytest.approx(3.0, rel=1e-12)
    fundamental, thd = model.distortion(3.0 * np.cos(w * t[:300] - 1.0) + 0.5, P)  # 3/8 of a cycle
    assert fundamental == pytest.approx(3.0, rel=1e-9) and thd < 1e-9


# summary.json of `inverter --horizon 2 --cycles 0.25` before the port to step_index and to one timing helper
# (commit 4d3fbf9, when the model state carried a step counter): the port changes no result.
BEFORE_PORT = {"rms_tracking_error": 0.3808262952794588, "current_amplitude": 10.073239385415711,
               "switching_frequency_hz": 3333.3333333333335, "thd": 0.044181480300264565,
               "thd_phases": [0.043874676616242086, 0.044776898998980186, 0.04389286528557142],
               "current_amplitudes": [10.061015127786998, 9.717331037697962, 10.441371990762173],
               "leg_changes": [26, 24, 50], "nodes_mean": 24.16, "nodes_max": 40, "nodes_min": 16,
               "predicted_cost_mean": 1.4220101336570423, "steps": 200}


@pytest.mark.slow
def test_cli_writes_the_summary_recorded_before_the_port_and_its_files(tmp_path):
    argv = ["inverter", "--horizon", "2", "--cycles", "0.25", "--out", str(tmp_path), "--no-progress"]
    with compile_events() as seen:
        assert cli.main(argv) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    for key, value in BEFORE_PORT.items():
        assert summary[key] == pytest.approx(value, rel=1e-12), key
    assert summary["horizon"] == 2 and summary["solver"] == "sdfs" and summary["levels"] == 2
    assert 0 < summary["solve_time_median_s"] <= summary["solve_time_max_s"]
    assert summary["compile_time_s"] >= max(d for _, d in seen)  # the decision's compilation, the longest one
    assert (tmp_path / "inverter_N2_sdfs.png").stat().st_size > 10_000
    loop = fj.ClosedLoop.load(tmp_path / "closed_loop.npz")
    assert loop.states.shape == (201, 2) and np.all(np.isfinite(loop.solve_times))


@pytest.mark.parametrize("argv, message", [
    (["--horizon", "0"], "between 1 and"),
    (["--solver", "bfs"], "invalid choice"),
    (["--cycles", "0"], "--cycles: must be a number > 0"),
    (["--lambda-u", "-1"], ">= 0"),
    (["--model", "rk4"], "invalid choice"),
])
def test_cli_rejects_bad_input(argv, message, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["inverter", *argv])
    assert e.value.code == 2
    assert message in capsys.readouterr().err


def test_cli_rejects_run_shorter_than_two_samples(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:  # argparse's one-line error, before any work
        cli.main(["inverter", "--cycles", "0.001", "--out", str(tmp_path)])
    assert e.value.code == 2 and "at least two samples" in capsys.readouterr().err


@pytest.mark.slow
def test_bound_is_admissible_and_keeps_the_closed_loop():
    """The reachable-hexagon bound passes the exhaustive check on closed-loop states away from the reference,
    10x it is caught, and the bounded closed loop is the unbounded one."""
    from firhc_jax._src.tools.diagnostics import check_lower_bound

    plain = app.closed_loop(2, steps=40, lambda_u=1.0, timed=False)
    bounded = app.closed_loop(2, steps=40, lambda_u=1.0, bound=True, timed=False)
    np.testing.assert_allclose(bounded.predicted_costs, plain.predicted_costs, rtol=1e-9)
    np.testing.assert_array_equal(bounded.inputs, plain.inputs)
    mem = model.make_problem(2, bound=True)
    inflated = mem.problem.replace(lower_bound=lambda z, s, p: 10 * mem.problem.lower_bound(z, s, p))
    # One check of five closed-loop states, 1.5 A off (bound > 0), against the reference of step 16 (each
    # check call compiles its own searches, so the states share one call).
    p = {"ref": jnp.asarray(model.horizon_references(P, 17, 2)[16]), "lambda_u": jnp.asarray(1.0)}
    z = jnp.stack([mem.observe(jnp.asarray(plain.currents[k]) + 1.5, jnp.zeros(3), p) for k in range(0, 40, 8)])
    assert check_lower_bound(mem.problem, z, params=p) == []
    assert check_lower_bound(inflated, z, params=p)
