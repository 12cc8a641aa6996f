"""The suite's closed loops: a plant that is not its model (observe, actuate, per-step parameters) and
the comparison of a batched loop with its single loop."""
import jax
import jax.numpy as jnp
import numpy as np

import firhc_jax as fj

# A plant that is not the model: a cart with friction the model ignores, driven through a gain, with a
# second plant input set by a fixed law (actuate). The model state carries the input applied last (observe),
# whose change is charged. The terminal band comes from the parameters: some steps it is out of reach and the
# fallback decides; some steps' band is loose and the warm start's seed is the answer.
N = 3
CONTROLS = np.array([-1.0, 0.0, 1.0])


def plant(x, u, p):  # x [2] plant state, u [2] plant input
    return jnp.stack([x[0] + 0.1 * x[1], 0.97 * x[1] + 0.1 * p["gain"] * u[0] + 0.01 * u[1]])


def observe(x, u_prev, p):  # model state [position, velocity, input applied last, its switching cost]
    return jnp.concatenate([x, u_prev, jnp.zeros(1)])


def actuate(x, u, p):
    return jnp.concatenate([u, -jnp.sign(x[1:2])])


def dynamics(z, u, p):
    return jnp.stack([z[0] + 0.1 * z[1], z[1] + 0.1 * u[0], u[0], 0.05 * (u[0] - z[2]) ** 2])


def stage_cost(z, u, p):
    return (z[0] - p["ref"]) ** 2 + 0.1 * z[1] ** 2 + z[3]


def terminal(z, p):
    return jnp.abs(z[0] - p["ref"]) < p["band"]


PROBLEM = fj.Problem(dynamics, CONTROLS, stage_cost, N, terminal=terminal)


def counting_controller(traces: list) -> fj.FIRHC:
    """These tests' controller (fallback, observe, actuate), its dynamics appending to ``traces`` when traced."""
    def counted(z, u, p):
        if isinstance(z, jax.core.Tracer):
            traces.append(1)
        return dynamics(z, u, p)

    return fj.FIRHC(fj.Problem(counted, CONTROLS, stage_cost, N, terminal=terminal), fallback="unconstrained",
                    observe=observe, actuate=actuate)


T = 8  # steps of the batched loops


def loop_params(rng, B):
    """[B, T] parameters: a reference, a plant gain and a terminal band per loop and step; some bands are
    out of reach (the fallback decides there) and some loose."""
    k = np.arange(T)
    phase = rng.uniform(0, 2 * np.pi, (B, 1))
    return {"ref": 0.5 * np.sin(0.5 * k + phase), "gain": 1.0 + 0.1 * rng.uniform(-1, 1, (B, T)),
            "band": np.where((k + rng.integers(0, 4, (B, 1))) % 4 == 1, 1e-6, 0.6)}


def row(tree, b):
    return jax.tree_util.tree_map(lambda a: a[b], tree)


FIELDS = ("inputs", "plans", "used_fallback", "feasible", "held", "complete")
# Numbers XLA may round apart in the last bit in a batched program (its vector width is not the unbatched one's).
COSTS = ("states", "predicted_costs", "stage_costs")


def assert_same_loop(batched, one, label: str, nodes: bool = False) -> int:
    """Loop ``batched`` (one row of a batched run) makes ``one``'s decisions: equal fields (equal to the last
    bits for ``COSTS``, and node counts with ``nodes``) up to the first step whose plans differ, and there an
    exact tie (the same optimal cost from the same state), after which the loops may part. Returns the
    number of steps compared."""
    plans, ref = np.asarray(batched.plans), np.asarray(one.plans)
    differ = np.flatnonzero(np.any(plans != ref, axis=1))
    k = int(differ[0]) if differ.size else len(plans)
    for field in FIELDS + (("decision_nodes",) if nodes else ()):
        np.testing.assert_array_equal(np.asarray(getattr(batched, field))[:k], np.asarray(getattr(one, field))[:k],
                                      err_msg=f"{label}, {field}")
    for field in COSTS:  # the state decided from and the optimal cost (a tie) at step k too
        upto = k if field == "stage_costs" else k + 1
        np.testing.assert_allclose(np.asarray(getattr(batched, field))[:upto], np.asarray(getattr(one, field))[:upto],
                                   rtol=1e-12, atol=1e-15, err_msg=f"{label}, {field}")
    if k < len(plans):  # a tie: both sequences optimal from that state
        assert np.isfinite(float(one.predicted_costs[k])), f"{label}: step {k} differs without a cost"
    return k
