"""The compiled closed loop with a progress bar runs as chunks of steps dispatched from Python; the chunks
carry the loop on exactly: the run makes the one-scan run's decisions, and with XLA's optimizations on (the
full suite) it is that run to the last bit."""
import jax.numpy as jnp
import numpy as np
import pytest
from compiles import compile_count

import firhc_jax as fj
from firhc_jax._src.runtime import progress

STEPS = 245  # chunks of interval(245) = 10 steps, the last one 5 steps past the end


def _loop(traces: list):
    """``(ctrl, params [T], x0)``: a closed loop whose dynamics count their traces in ``traces``."""

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
    return ctrl, params, np.array([0.3, -0.2])


def _close(pairs):
    """Every decision equal, every value equal up to rounding (a chunk and the whole scan are two programs)."""
    for name, a, b in pairs:
        assert a.shape == b.shape, name
        if np.issubdtype(a.dtype, np.floating):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15, err_msg=name)
        else:
            np.testing.assert_array_equal(a, b, err_msg=name)


def _fields(one, other):
    return [(name, np.asarray(a), np.asarray(getattr(other, name))) for name, a in one._asdict().items()
            if a is not None]


def _one_scan_and_chunked(capsys):
    """The same closed loop as one scan and as chunks with a bar; then new values, counted."""
    traces = []
    ctrl, params, x0 = _loop(traces)
    assert STEPS % progress.interval(STEPS)
    one = ctrl.simulate(x0, STEPS, params=params)
    chunked = ctrl.simulate(x0, STEPS, params=params, progress=True)
    assert f"{STEPS}/{STEPS}" in capsys.readouterr().err
    assert np.any(np.asarray(one.used_fallback)) and not np.all(np.asarray(one.used_fallback))
    before, compiled = len(traces), compile_count()  # new values, the same compiled chunk
    ctrl.simulate(-x0, STEPS, params={**params, "ref": -params["ref"]}, progress=True)
    assert len(traces) == before and compile_count() == compiled
    return _fields(one, chunked)


def test_progress_chunks_make_the_one_scan_runs_decisions(capsys):
    _close(_one_scan_and_chunked(capsys))


def test_a_batch_of_loops_with_a_bar_makes_the_same_decisions():
    """simulate_batch with a bar: each part of the loops runs its chunks into its own records."""
    ctrl, params, x0 = _loop([])
    X0 = np.stack([x0, -x0, 0.5 * x0, np.array([0.1, 0.4])])
    P = {k: np.stack([np.asarray(v)] * len(X0)) for k, v in params.items()}
    _close(_fields(ctrl.simulate_batch(X0, STEPS, params=P),
                   ctrl.simulate_batch(X0, STEPS, params=P, progress=True)))


@pytest.mark.optimized
def test_progress_chunks_are_the_one_scan_run_bit_for_bit(capsys):
    for name, a, b in _one_scan_and_chunked(capsys):
        np.testing.assert_array_equal(a, b, err_msg=name)


def test_the_python_loop_runs_with_the_collector_paused_and_restores_it():
    """simulate(compiled=False) keeps Python's cyclic garbage collector out of its loop (a collection walks
    every object of the process inside one decision); fj.collector_paused restores whatever was set."""
    import gc

    seen = []

    def plant(x, u):  # called from the loop, as it is
        seen.append(gc.isenabled())
        return np.asarray(x) + 0.1 * np.asarray(u)

    ctrl = fj.FIRHC(fj.Problem(lambda x, u: x + 0.1 * u, jnp.array([-1.0, 0.0, 1.0]), fj.quadratic_cost(1.0, 0.0), 2))
    assert gc.isenabled()
    run = ctrl.simulate(np.array([1.0]), 4, plant, compiled=False)
    assert seen == [False] * 4 and gc.isenabled() and np.isfinite(np.asarray(run.solve_times)).all()
    with pytest.raises(KeyError):
        with fj.collector_paused():
            assert not gc.isenabled()
            raise KeyError("an error inside the loop")
    assert gc.isenabled()
    gc.disable()
    try:
        with fj.collector_paused():
            pass
        assert not gc.isenabled()  # left as the caller set it
    finally:
        gc.enable()
