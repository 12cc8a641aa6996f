"""The compiled closed loop with a progress bar runs as chunks of steps dispatched from Python; the chunks
carry the loop on exactly, so the run is the one-scan run to the last bit."""
import jax.numpy as jnp
import numpy as np

import firhc_jax as fj
from firhc_jax import progress

STEPS = 245  # chunks of interval(245) = 10 steps, the last one 5 steps past the end


def test_progress_chunks_are_the_one_scan_run_bit_for_bit(capsys):
    traces = []

    def dynamics(x, u, p):
        traces.append(1)
        return jnp.stack([x[0] + 0.1 * x[1], 0.95 * x[1] + 0.1 * p["gain"] * u[0]])

    def stage_cost(x, u, p):
        return (x[0] - p["ref"]) ** 2 + 0.1 * x[1] ** 2

    problem = fj.Problem(dynamics, jnp.array([[-1.0], [0.0], [1.0]]), stage_cost, 3,
                         terminal=lambda x, p: jnp.abs(x[0] - p["ref"]) < p["band"])
    ctrl = fj.FIRHC(problem, fallback="unconstrained", warm_start=True)
    k = np.arange(STEPS)
    params = {"ref": np.sin(0.05 * k), "gain": 1.0 + 0.1 * np.cos(k),
              "band": np.where(k % 7 == 3, 1e-6, 0.5)}  # some steps fall back: the carry holds the plan
    x0 = np.array([0.3, -0.2])
    assert STEPS % progress.interval(STEPS)
    one = ctrl.simulate(x0, STEPS, params=params)
    chunked = ctrl.simulate(x0, STEPS, params=params, progress=True)
    assert f"{STEPS}/{STEPS}" in capsys.readouterr().err
    assert np.any(np.asarray(one.used_fallback)) and not np.all(np.asarray(one.used_fallback))
    for name, a in one._asdict().items():
        if a is not None:
            b = getattr(chunked, name)
            assert np.shape(a) == np.shape(b), name
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=name)
    before = len(traces)  # new values, the same compiled chunk
    ctrl.simulate(-x0, STEPS, params={**params, "ref": -params["ref"]}, progress=True)
    assert len(traces) == before
