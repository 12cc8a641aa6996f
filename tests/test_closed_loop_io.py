"""A closed loop keeps its plans and time axis, saves, loads and plots."""
import jax.numpy as jnp
import matplotlib
import numpy as np
import pytest

import firhc_jax as fj


def dyn(x, u):
    return jnp.stack([x[0] + 0.1 * x[1], x[1] + 0.1 * u[0]])


PROBLEM = fj.Problem(dyn, jnp.array([-1.0, 0.0, 1.0]), fj.quadratic_cost(jnp.array([1.0, 0.1]), jnp.zeros(2), 0.01),
                     3, terminal=lambda x: jnp.abs(x[0]) < 0.9)


CTRL = fj.FIRHC(PROBLEM, fallback="unconstrained")


@pytest.fixture(scope="module")
def run():
    return CTRL.simulate(jnp.array([1.0, 0.0]), 8, dt=0.05)


def test_plans_and_time_axis(run):
    assert run.plans.shape == (8, 3) and run.plans.dtype == jnp.int32
    np.testing.assert_array_equal(np.asarray(run.plans[:, 0]), np.asarray(run.input_indices))
    np.testing.assert_allclose(run.times, 0.05 * np.arange(9))
    assert CTRL.simulate(jnp.array([1.0, 0.0]), 8).times is None
    for bad in (0.0, -1.0, np.nan, "0.1", True):
        with pytest.raises(ValueError, match="dt"):
            CTRL.simulate(jnp.array([1.0, 0.0]), 8, dt=bad)


def test_save_load_round_trip(run, tmp_path):
    path = run.save(tmp_path / "run")
    assert path.endswith("run.npz")
    with np.load(path) as data:  # plain NumPy reads it
        np.testing.assert_array_equal(data["states"], np.asarray(run.states))
        np.testing.assert_array_equal(data["inputs"], np.asarray(run.inputs))
    back = fj.ClosedLoop.load(path)
    for name in fj.ClosedLoop._fields:
        a, b = getattr(run, name), getattr(back, name)
        np.testing.assert_array_equal(np.asarray(a), b, err_msg=name)
        assert np.asarray(a).dtype == b.dtype, name
    untimed = CTRL.simulate(jnp.array([1.0, 0.0]), 8)
    assert fj.ClosedLoop.load(untimed.save(tmp_path / "untimed.npz")).times is None
    np.savez(tmp_path / "other.npz", states=np.zeros((2, 2)))
    with pytest.raises(ValueError, match="not a saved ClosedLoop"):
        fj.ClosedLoop.load(tmp_path / "other.npz")


def test_plot_returns_a_figure_and_leaves_the_backend_alone(run, tmp_path):
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.figure import Figure

    before, figures = matplotlib.get_backend(), plt.get_fignums()
    fig = run.plot(title="cart")
    assert isinstance(fig, Figure) and len(fig.axes) == 4
    assert matplotlib.get_backend() == before and plt.get_fignums() == figures  # nothing opened in pyplot
    fig.savefig(tmp_path / "run.png")
    assert (tmp_path / "run.png").stat().st_size > 0
    held = fj.FIRHC(PROBLEM.replace(terminal=lambda x: x[0] > 50.0)).simulate
    with pytest.warns(RuntimeWarning, match="held"):
        assert isinstance(held(jnp.array([1.0, 0.0]), 3, compiled=False).plot(), Figure)  # held steps, timed
