"""Reliability at the controller's and the files' edges: a non-finite input found is never applied, saved runs
are read only when their declared shapes agree, messages name what the user wrote, helpers take what they say."""
import io
import zipfile

import jax.numpy as jnp
import numpy as np
import pytest

import firhc_jax as fj

CONTROLS = jnp.array([-1.0, 0.0, 1.0])


def _nan_first_input(x0, sequence):
    """The optimal sequence's first input, except NaN from states beyond 0.5."""
    return jnp.where(x0[0] > 0.5, jnp.nan, CONTROLS[jnp.maximum(sequence[0], 0)]).reshape(1)


NAN_INPUT = fj.Problem(lambda x, u: 0.5 * x + u, CONTROLS, fj.quadratic_cost(1.0, 0.0), 2,
                       first_input_of=_nan_first_input)


@pytest.mark.parametrize("compiled", [True, False])
def test_a_non_finite_first_input_of_is_held_never_applied(compiled):
    ctrl = fj.FIRHC(NAN_INPUT)
    x0, u0 = jnp.array([1.0]), jnp.array([-0.25])
    with pytest.warns(RuntimeWarning, match="held"):
        run = ctrl.simulate(x0, 3, u0=u0, compiled=compiled)
    assert np.isfinite(np.asarray(run.inputs)).all() and np.isfinite(np.asarray(run.states)).all()
    np.testing.assert_array_equal(np.asarray(run.held), [True, False, False])
    assert float(run.inputs[0, 0]) == -0.25  # u0 held at step 0; from x = 0.25 an input is found again
    assert (np.asarray(run.plans[0]) == -1).all() and int(run.input_indices[0]) == -1
    assert np.isnan(float(run.stage_costs[0]))


def test_step_holds_the_safe_input_and_the_one_shot_call_raises_on_a_non_finite_input():
    x0 = jnp.array([1.0])
    ctrl = fj.FIRHC(NAN_INPUT, u_safe=jnp.array([0.0]))
    u, state, info = ctrl.step(ctrl.init(x0, jnp.array([1.0])), x0)
    assert float(u[0]) == 0.0 and bool(info.held) and (np.asarray(state.plan) == -1).all()
    with pytest.raises(fj.InfeasibleError, match=r"first_input_of returned a non-finite input \[nan\]"):
        ctrl(x0)
    u, _ = ctrl(jnp.array([0.2]))  # where first_input_of is finite the decision stands
    assert np.isfinite(float(u[0]))
