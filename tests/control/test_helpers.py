"""The small helpers of a control library: an input's index, a run's realised cost, horizon windows of many
scenarios, and the inverter's THD and switching frequency."""
import math

import jax.numpy as jnp
import numpy as np
import pytest

import firhc_jax as fj
from firhc_jax.models import inverter


def dyn(x, u):
    return jnp.stack([x[0] + 0.1 * x[1], x[1] + 0.1 * (u[0] - 0.5 * u[1])])


PROBLEM = fj.Problem(dyn, fj.product_controls([-1.0, 0.0, 1.0], [0.0, 1.0]),
                     fj.quadratic_cost(jnp.array([1.0, 0.1]), jnp.zeros(2), 0.01), 3,
                     terminal_cost=lambda x: 3.0 * x[0] ** 2)


# -- Problem.index_of ------------------------------------------------------------------------------------------
def test_index_of_finds_each_input_and_every_row_of_a_run():
    assert [PROBLEM.index_of(u) for u in PROBLEM.controls] == list(range(6))
    assert PROBLEM.index_of([1, 0]) == 4 and isinstance(PROBLEM.index_of([1, 0]), int)
    np.testing.assert_array_equal(PROBLEM.index_of([[[1.0, 1.0], [-1.0, 0.0]]]), [[5, 0]])
    run = fj.FIRHC(PROBLEM).simulate(jnp.array([1.0, 0.0]), 6)
    np.testing.assert_array_equal(PROBLEM.index_of(run.inputs), run.input_indices)
    tenths = fj.Problem(dyn, np.array([0.1, 0.2, 0.3], np.float32), lambda x, u: 0.0, 1)  # float32 set
    assert tenths.index_of(0.2) == 1 and tenths.index_of([[0.3], [0.1]]).tolist() == [2, 0]
    integers = fj.Problem(dyn, np.array([0, 1, 2]), lambda x, u: 0.0, 1)
    assert integers.index_of(2.0) == 2
    with pytest.raises(ValueError, match="not in the control set"):
        integers.index_of(1.5)  # never rounded to a neighbour


def test_index_of_refuses_inputs_it_cannot_place():
    with pytest.raises(ValueError, match=r"u\[1\] = \[0.5, 0.0\] is not in the control set"):
        PROBLEM.index_of([[0.0, 0.0], [0.5, 0.0]])
    with pytest.raises(ValueError, match=r"u must be an input \[m\] = \[2\]"):
        PROBLEM.index_of([0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="u contains NaN"):
        PROBLEM.index_of([np.nan, 0.0])
    with pytest.raises(TypeError, match="u must be a real numeric input"):
        PROBLEM.index_of(["a", "b"])


# -- ClosedLoop.realised_cost ----------------------------------------------------------------------------------
def test_realised_cost_is_what_the_plant_paid():
    x0 = jnp.array([1.0, 0.0])
    ctrl = fj.FIRHC(PROBLEM)
    run = ctrl.simulate(x0, 12)
    # The plant is the model: the plant paid each decision's first predicted step.
    assert run.realised_cost(PROBLEM) == pytest.approx(float(np.sum(run.stage_costs)), rel=1e-12)
    assert run.realised_cost(PROBLEM, terminal_cost=True) == pytest.approx(
        float(np.sum(run.stage_costs)) + 3.0 * float(run.states[-1, 0]) ** 2, rel=1e-12)
    # Another plant: priced on the plant's own states, not the model's predictions.
    def plant(x, u):
        return dyn(x, u) + jnp.array([0.02, -0.01])

    other = ctrl.simulate(x0, 12, plant=plant)
    by_hand = sum(float(PROBLEM.stage_cost(other.states[k + 1], other.inputs[k])) for k in range(12))
    assert other.realised_cost(PROBLEM) == pytest.approx(by_hand, rel=1e-12)
    assert abs(by_hand - float(np.sum(other.stage_costs))) > 1e-3


def test_realised_cost_reads_each_steps_parameters_at_step_index_zero():
    def track(x_next, u, k, p):
        return (x_next[0] - p["ref"][k]) ** 2 + p["w"] * jnp.sum(u ** 2)

    tracking = fj.Problem(lambda x, u, k, p: dyn(x, u), PROBLEM.controls, track, 3, step_index=True,
                          terminal_cost=lambda x, p: 10.0 * (x[0] - p["ref"][-1]) ** 2)
    T = 8
    params = {"ref": fj.horizon_windows(0.3 * np.sin(0.4 * np.arange(T + 3)), T, 3), "w": np.full(T, 0.05)}
    x0 = jnp.array([0.5, 0.0])
    run = fj.FIRHC(tracking).simulate(x0, T, params=params)
    paid = sum(float((run.states[k + 1, 0] - params["ref"][k, 0]) ** 2 + 0.05 * np.sum(run.inputs[k] ** 2))
               for k in range(T))
    assert run.realised_cost(tracking, params) == pytest.approx(paid, rel=1e-12)
    end = 10.0 * float(run.states[-1, 0] - params["ref"][-1, -1]) ** 2
    assert run.realised_cost(tracking, params, terminal_cost=True) == pytest.approx(paid + end, rel=1e-12)
    both = {k: np.stack([v, v]) for k, v in params.items()}  # two loops, the same parameters
    loops = fj.FIRHC(tracking).simulate_batch(np.array([[0.5, 0.0], [-0.2, 0.1]]), T, params=both)
    costs = loops.realised_cost(tracking, both, terminal_cost=True)
    assert costs.shape == (2,) and costs[0] == pytest.approx(paid + end, rel=1e-12)
    with pytest.raises(ValueError, match="leading axes T"):
        run.realised_cost(tracking, {k: v[:-1] for k, v in params.items()})


def test_realised_cost_refuses_what_cannot_price_the_run():
    run = fj.FIRHC(PROBLEM).simulate(jnp.array([1.0, 0.0]), 4)
    with pytest.raises(ValueError, match="has no terminal_cost"):
        run.realised_cost(PROBLEM.replace(terminal_cost=None), terminal_cost=True)
    with pytest.raises(ValueError, match="inputs have 2 columns"):
        run.realised_cost(fj.Problem(dyn, [0.0, 1.0], PROBLEM.stage_cost, 3))
    with pytest.raises(TypeError, match="problem must be"):
        run.realised_cost("PROBLEM")


# -- fj.horizon_windows over scenarios -------------------------------------------------------------------------
def test_horizon_windows_of_a_batch_of_scenarios():
    rng = np.random.default_rng(0)
    signals = rng.normal(size=(4, 10, 2))  # B scenarios of T + N = 10 samples of a 2-vector
    windows = fj.horizon_windows(signals, 7, 3, axis=1)
    assert windows.shape == (4, 7, 3, 2)
    for b in range(4):
        np.testing.assert_array_equal(windows[b], fj.horizon_windows(signals[b], 7, 3))
    np.testing.assert_array_equal(windows[2, 5], signals[2, 6:9])  # step t sees signal[t+1 .. t+N]
    np.testing.assert_array_equal(fj.horizon_windows(signals, 8, 3, start=0, axis=1)[1, 4], signals[1, 4:7])
    with pytest.raises(ValueError, match=r"= 11 samples along axis 1"):
        fj.horizon_windows(signals, 8, 3, axis=1)
    with pytest.raises(ValueError, match="axis 3 is not an axis of signal"):
        fj.horizon_windows(signals, 2, 3, axis=3)


# -- the inverter's THD and switching frequency ----------------------------------------------------------------
def test_inverter_switching_frequency_counts_level_changes_per_leg():
    P = inverter.InverterParams()
    T = 400
    legs = np.zeros((T, 3))
    legs[1::2, 0] = 1.0  # leg a toggles every sample: T - 1 changes
    legs[200:, 1] = 2.0  # leg b: one jump of two levels (a five-level leg), two commutations
    np.testing.assert_array_equal(inverter.commutations(legs), [T - 1, 2, 0])
    assert inverter.switching_frequency(legs, P) == pytest.approx((T + 1) / 3 / (2 * T * P.ts), rel=1e-12)
    assert inverter.switching_frequency(legs[:, :1], P) == pytest.approx(1 / (2 * P.ts) * (T - 1) / T)
    with pytest.raises(ValueError, match=r"inputs must be finite leg levels \[T, legs\]"):
        inverter.commutations(legs[:, 0])


def test_inverter_thd_of_a_run_of_five_level_legs():
    """The public measures serve a plant the model does not build: a synthetic five-level phase current."""
    P = inverter.InverterParams()
    t = np.arange(P.steps_per_cycle) * P.ts
    w = 2 * math.pi * P.frequency
    fundamental, thd = inverter.distortion(8.0 * np.cos(w * t) + 0.4 * np.cos(7 * w * t), P)
    assert fundamental == pytest.approx(8.0, rel=1e-12) and thd == pytest.approx(0.05, rel=1e-12)
    with pytest.raises(ValueError, match=r"signal must be a finite record \[T\]"):
        inverter.distortion(np.ones((4, 2)), P)
