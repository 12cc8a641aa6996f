"""Spacecraft attitude model: the search is exact on it, and the plant conserves angular momentum."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import firhc_jax as fj
from firhc_jax.models import spacecraft as sc

N = 2
PROBLEM = sc.make_problem(N)  # one problem for the module: each search compiles once


@pytest.mark.float32
@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), fuel=st.floats(0.0, 20.0))
def test_sdfs_cost_equals_exhaustive(seed, fuel):
    x0, inertia = sc.random_loops(1, np.random.default_rng(seed), max_angle=40.0, max_rate=2.0, spread=0.5)
    x = jnp.asarray(x0[0])  # the dtype the test runs in (float32 with --float32)
    p = {"inertia": jnp.asarray(inertia[0], x.dtype), "fuel": jnp.asarray(fuel, x.dtype)}
    best, ref = fj.sdfs(PROBLEM, x, params=p), fj.exhaustive(PROBLEM, x, params=p)
    assert bool(best.feasible) and bool(best.complete)
    np.testing.assert_allclose(float(best.cost), float(ref.cost), rtol=8 * N * jnp.finfo(x.dtype).eps)
    assert int(ref.nodes) == 27 + 27**2


def test_dcm_of_a_rotation_about_one_axis():
    phi = np.radians(130.0)
    c, s = np.cos(phi), np.sin(phi)
    expected = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # target frame -> body frame, about z
    np.testing.assert_allclose(sc.dcm(np.array([0.0, 0.0, np.tan(phi / 4)])), expected, atol=1e-14)
    assert sc.pointing_error(np.array([0.0, 0.0, np.tan(phi / 4), 0.0, 0.0, 0.0])) == pytest.approx(130.0)


def test_plant_conserves_angular_momentum_without_torque():
    """Torque-free tumbling through several turns (past the shadow-set switch): the angular momentum in the
    target frame and the kinetic energy stay what they were, to RK4's accuracy."""
    x0, inertia = sc.random_loops(8, np.random.default_rng(1), max_angle=170.0, max_rate=3.0, spread=0.5)
    plant = sc.make_plant()

    def tumble(x, j):
        def body(x, _):
            x_next = plant(x, jnp.zeros(3), {"inertia": j, "fuel": jnp.zeros(())})
            return x_next, x_next
        return jax.lax.scan(body, x, None, length=200)[1]

    xs = np.asarray(jax.jit(jax.vmap(tumble))(jnp.asarray(x0), jnp.asarray(inertia)))  # [8, 200, 6]
    assert np.any(np.abs(np.diff(np.sign(xs[:, :, :3]), axis=1)) == 2)  # sigma jumped: the shadow set
    assert np.all(np.linalg.norm(xs[:, :, :3], axis=-1) <= 1.0)
    h0, h = sc.angular_momentum(x0, inertia), sc.angular_momentum(xs, inertia[:, None])
    np.testing.assert_allclose(h, np.broadcast_to(h0[:, None], h.shape), rtol=0,
                               atol=1e-7 * np.linalg.norm(h0, axis=-1).min())
    energy = np.sum(inertia[:, None] * xs[..., 3:] ** 2, axis=-1)
    np.testing.assert_allclose(energy, np.broadcast_to(np.sum(inertia * x0[:, 3:] ** 2, -1)[:, None], energy.shape),
                               rtol=1e-9)


def test_step_params_broadcast_loops_over_steps():
    p = sc.step_params(np.ones((4, 3)), np.arange(4.0), 5)
    assert p["inertia"].shape == (4, 5, 3) and p["fuel"].shape == (4, 5)
    np.testing.assert_array_equal(p["fuel"][:, 3], np.arange(4.0))
    with pytest.raises(ValueError, match="inertia must be"):
        sc.step_params(np.ones((4, 2)), np.arange(4.0), 5)


def test_closed_loop_with_per_step_params_fuel_weight_steers_firing():
    """``simulate`` with params of leading axis ``steps``: free fuel fires the thrusters and brings the
    attitude closer; a fuel weight above any pointing gain never fires, and the attitude drifts freely."""
    ctrl, plant, steps = fj.FIRHC(PROBLEM), sc.make_plant(), 6
    x0, inertia = sc.random_loops(1, np.random.default_rng(3), max_angle=15.0, max_rate=0.2)
    free = ctrl.simulate(x0[0], steps, plant, params=sc.step_params(inertia[0], 0.0, steps))
    dear = ctrl.simulate(x0[0], steps, plant, params=sc.step_params(inertia[0], 1e6, steps))
    assert np.abs(np.asarray(free.inputs)).sum() > 0 and not np.asarray(dear.inputs).any()
    assert sc.pointing_error(np.asarray(free.states[-1])) < sc.pointing_error(np.asarray(dear.states[-1]))
    coast, step = x0[0], jax.jit(plant)
    for _ in range(steps):
        coast = step(coast, jnp.zeros(3), {"inertia": inertia[0], "fuel": 0.0})
    np.testing.assert_allclose(np.asarray(dear.states[-1]), np.asarray(coast), rtol=1e-12)
