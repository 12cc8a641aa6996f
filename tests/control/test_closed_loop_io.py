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
    assert isinstance(fig, Figure) and len(fig.axes) == 3  # states, the input, nodes: no untimed panel
    assert matplotlib.get_backend() == before and plt.get_fignums() == figures  # nothing opened in pyplot
    fig.savefig(tmp_path / "run.png")
    assert (tmp_path / "run.png").stat().st_size > 0
    held = fj.FIRHC(PROBLEM.replace(terminal=lambda x: x[0] > 50.0)).simulate
    with pytest.warns(RuntimeWarning, match="held"):
        assert isinstance(held(jnp.array([1.0, 0.0]), 3, compiled=False).plot(), Figure)  # held steps, timed


def _loop(states, inputs, times=None, timed=False, held=None):
    """A ``ClosedLoop`` of given states ``[(B,) T+1, n]`` and inputs ``[(B,) T, m']`` (the rest filler)."""
    lead = inputs.shape[:-1]
    return fj.ClosedLoop(states=states, inputs=inputs, input_indices=np.zeros(lead, np.int32),
                         stage_costs=np.ones(lead), predicted_costs=np.ones(lead),
                         nodes=np.arange(np.prod(lead), dtype=np.int32).reshape(lead) % 7,
                         fallback_nodes=np.zeros(lead, np.int32), feasible=np.ones(lead, bool),
                         used_fallback=np.zeros(lead, bool), complete=np.ones(lead, bool),
                         held=np.zeros(lead, bool) if held is None else held, plans=np.zeros(lead + (3,), np.int32),
                         solve_times=np.full(lead, 2e-4 if timed else np.nan), times=times)


def test_plot_draws_only_the_panels_it_has_and_names_the_time_axis():
    matplotlib.use("Agg")
    rng = np.random.default_rng(0)
    x, u = rng.normal(size=(11, 2)), rng.integers(0, 2, (10, 1)).astype(float)
    untimed = _loop(x, u).plot()
    assert [a.get_ylabel() for a in untimed.axes] == ["states", "u[0]", "nodes"]  # no empty "not timed" panel
    assert untimed.axes[-1].get_xlabel().startswith("step k (no dt")
    timed = _loop(x, u, times=0.5 * np.arange(11), timed=True).plot()
    assert [a.get_ylabel() for a in timed.axes] == ["states", "u[0]", "nodes", "solve time [ms]"]
    assert timed.axes[-1].get_xlabel() == "time [s]"
    np.testing.assert_allclose(timed.axes[-1].lines[0].get_ydata(), 0.2)  # ms


def test_plot_gives_each_input_its_own_axes_and_keeps_legends_off_the_data(tmp_path):
    """Two binary inputs, one of them held once: neither hides the other, each axis shows its levels."""
    matplotlib.use("Agg")
    rng = np.random.default_rng(1)
    u = rng.integers(0, 2, (30, 2)).astype(float)
    held = np.zeros(30, bool)
    held[4] = True
    fig = _loop(rng.normal(size=(31, 3)), u, held=held).plot(input_names=["valve a", "valve b"])
    a, b = fig.axes[1], fig.axes[2]
    assert (a.get_ylabel(), b.get_ylabel()) == ("valve a", "valve b")
    np.testing.assert_array_equal(a.lines[0].get_ydata(), u[:, 0])
    np.testing.assert_array_equal(b.lines[0].get_ydata(), u[:, 1])
    assert [t.get_text() for t in a.get_yticklabels()] == ["0", "1"]
    assert [t.get_text() for t in a.get_legend().get_texts()] == ["held (no input found)"]
    np.testing.assert_array_equal(a.lines[1].get_xdata(), [4])
    fig.savefig(tmp_path / "valves.png")  # lays the figure out
    for ax in (fig.axes[0], a):
        legend = ax.get_legend().get_window_extent()
        assert legend.x0 >= ax.get_window_extent().x1  # beside the axes, not on the data


def _mesh_shares(ax):
    from matplotlib.collections import QuadMesh

    (mesh,) = [c for c in ax.collections if isinstance(c, QuadMesh)]
    return np.asarray(mesh.get_array()).reshape(len(ax.get_yticks()), -1)  # [levels, windows]


def test_plot_maps_the_levels_of_an_input_that_switches_too_often_for_a_line():
    """2,000 steps of three five-level inputs: each is a map of its levels' shares per window of 10 steps."""
    matplotlib.use("Agg")
    rng = np.random.default_rng(2)
    u = rng.integers(-2, 3, (2000, 3)).astype(float)
    fig = _loop(rng.normal(size=(2001, 2)), u).plot()
    assert [a.get_ylabel() for a in fig.axes[1:4]] == ["u[0]", "u[1]", "u[2]"]
    for j in range(3):
        shares = _mesh_shares(fig.axes[1 + j])
        assert [t.get_text() for t in fig.axes[1 + j].get_yticklabels()] == ["-2", "-1", "0", "1", "2"]
        assert shares.shape == (5, 200)
        np.testing.assert_allclose(shares[:, 7], [np.mean(u[70:80, j] == v) for v in range(-2, 3)])
    slow = _loop(rng.normal(size=(2001, 2)), np.repeat([[0.0], [1.0]], 1000, axis=0)).plot()
    assert slow.axes[1].lines and not slow.axes[1].collections  # one switch: a step line is clear


def test_batched_plot_shows_how_often_each_input_level_is_used():
    """A {-1, 0, 1} input over 5 loops: per step, the share of the loops at each level, not a median band."""
    matplotlib.use("Agg")
    rng = np.random.default_rng(3)
    u = rng.choice([-1.0, 0.0, 1.0], (5, 12, 1))
    held = np.zeros((5, 12), bool)
    held[2, 7] = True
    fig = _loop(rng.normal(size=(5, 13, 2)), u, times=0.1 * np.arange(13), held=held).plot()
    shares = _mesh_shares(fig.axes[1])
    np.testing.assert_allclose(shares, [np.mean(u[:, :, 0] == v, axis=0) for v in (-1.0, 0.0, 1.0)])
    assert fig.axes[-1].get_xlabel() == "time [s]"
    fig.canvas.draw()  # the legend of the held step sits beside the colour scale, not on it
    (scale,) = fig.axes[1].child_axes
    assert fig.axes[1].get_legend().get_window_extent().x0 > scale.get_tightbbox().x1
