"""apps._exported: an application's decision kept on disk as a traced program, read back without tracing."""
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import firhc_jax as fj
from firhc_jax.apps import _exported, _timing
from firhc_jax.models import hopper as hm

CONTROLS = np.array([[-1.0], [0.0], [1.0]])


def _step(x, u):
    return jnp.stack([x[0] + 0.1 * x[1], 0.9 * x[1] + 0.2 * u[0]])


def _controller(traces: list):
    """A small controller whose dynamics count their traces (one entry each time JAX runs the Python)."""
    def dynamics(x, u):
        traces.append(1)
        return _step(x, u)

    cost = fj.quadratic_cost(lam=np.array([1.0, 0.5]), x_s=np.array([1.0, 0.0]), beta=0.01)
    return fj.FIRHC(fj.Problem(dynamics, CONTROLS, cost, 3), fallback=None)


def _arguments(ctrl):
    x0 = jnp.asarray([0.3, -0.2], dtype=jnp.zeros(()).dtype)
    return ctrl.init(x0), x0, None


class Target(NamedTuple):
    """Parameters as a NamedTuple, as some models give them (``LinearTracking``'s ``TrackingParams``)."""

    level: jax.Array  # [2]


def _leaves(out):
    return [np.asarray(a) for a in jax.tree_util.tree_leaves(out)]


@pytest.mark.float32
def test_a_kept_decision_is_read_back_without_tracing_and_decides_as_step(tmp_path):
    """The first call traces and stores the program; an equal controller in a later run (here: a new one) reads
    it back without running the model's Python, and both decide as ``ctrl.step`` does, bit for bit, over a
    closed loop."""
    traces = []
    ctrl = _controller(traces)
    state, x, p = _arguments(ctrl)
    first = _exported.decision(ctrl, "small", tmp_path, state, x, p)
    assert traces and len(list((tmp_path / _exported.FOLDER).glob("*.jaxexport"))) == 1
    traces.clear()
    again = _exported.decision(_controller(traces), "small", tmp_path, state, x, p)
    assert traces == []  # read back: the model is not traced again
    s_ref, s1, s2, xk = state, state, state, x
    for _ in range(4):
        ref, out1, out2 = ctrl.step(s_ref, xk, p), first(s1, xk, p), again(s2, xk, p)
        for a, b, c in zip(_leaves(ref), _leaves(out1), _leaves(out2), strict=True):
            np.testing.assert_array_equal(a, b)
            np.testing.assert_array_equal(a, c)
        (u, s_ref, _), (_, s1, _), (_, s2, _) = ref, out1, out2
        xk = ctrl.problem.dynamics(xk, u)


def test_the_file_is_named_by_the_settings_the_arguments_and_the_source(tmp_path, monkeypatch):
    """Other settings (to the last bit), other shapes, or another source digest give another file: a changed line
    of the package never reads a program traced from the old one."""
    ctrl = _controller([])
    state, x, p = _arguments(ctrl)
    base = _exported.digest("small", (state, x, p))
    assert _exported.digest("small", (state, x, p)) == base
    assert _exported.digest("small N=4", (state, x, p)) != base
    settings = ("hopper", 6, hm.HopperParams(), {"max_nodes": 500}, np.array([0.1, 0.2]))
    same = ("hopper", 6, hm.HopperParams(), {"max_nodes": 500}, np.array([0.1, 0.2]))
    assert _exported.digest(settings, (state, x, p)) == _exported.digest(same, (state, x, p))
    for other in (("hopper", 6, hm.HopperParams(M=np.nextafter(0.54, 1)), {"max_nodes": 500}, np.array([0.1, 0.2])),
                  ("hopper", 6, hm.HopperParams(), {"max_nodes": 501}, np.array([0.1, 0.2])),
                  ("hopper", 6, hm.HopperParams(), {"max_nodes": 500}, np.array([0.1, np.nextafter(0.2, 1)]))):
        assert _exported.digest(other, (state, x, p)) != _exported.digest(settings, (state, x, p))
    with pytest.raises(TypeError, match="cannot name a setting of type function"):
        _exported.digest(("small", lambda x: x), (state, x, p))
    assert _exported.digest("small", (state, jnp.zeros(3, x.dtype), p)) != base
    assert _exported.digest("small", (state, x, {"ref": jnp.zeros(2)})) != base
    monkeypatch.setattr(_exported, "source_digest", lambda: "another source")
    assert _exported.digest("small", (state, x, p)) != base


def test_a_damaged_file_is_traced_and_written_again(tmp_path):
    traces = []
    ctrl = _controller(traces)
    state, x, p = _arguments(ctrl)
    path = tmp_path / _exported.FOLDER / f"{_exported.digest('small', (state, x, p))}.jaxexport"
    path.parent.mkdir()
    path.write_bytes(b"not a program")
    decide = _exported.decision(ctrl, "small", tmp_path, state, x, p)
    assert traces  # traced again
    jax.export.deserialize(bytearray(path.read_bytes()))  # and written again, whole
    np.testing.assert_array_equal(decide(state, x, p)[0], ctrl.step(state, x, p)[0])


def test_a_folder_that_cannot_be_written_is_warned_about_and_the_decision_still_runs(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    ctrl = _controller([])
    state, x, p = _arguments(ctrl)
    with pytest.warns(RuntimeWarning, match="could not be kept in .*file"):
        decide = _exported.decision(ctrl, "small", blocker, state, x, p)
    np.testing.assert_array_equal(decide(state, x, p)[0], ctrl.step(state, x, p)[0])


def test_a_timed_loop_with_settings_decides_as_the_compiled_loop_and_reads_its_decision_back():
    """``timed_closed_loop(..., settings=...)`` (what the applications run, with the suite's compilation cache
    on): the same closed loop as ``simulate``'s compiled scan, and a second run does not trace the model."""
    if not jax.config.jax_compilation_cache_dir:
        pytest.skip("the compilation cache is off (FIRHC_JAX_TEST_CACHE=off)")
    traces = []
    ctrl = _controller(traces)
    x0 = _arguments(ctrl)[1]
    settings = ("test_exported", __file__, 3)  # what built _controller: this file's code
    plant = jax.jit(_step)
    first, _ = _timing.timed_closed_loop(ctrl, x0, 6, plant, settings=settings)
    traces.clear()
    again, _ = _timing.timed_closed_loop(_controller(traces), x0, 6, plant, settings=settings)
    assert traces == []
    scan = ctrl.simulate(x0, 6, plant)
    for loop in (first, again):
        for field in ("states", "inputs", "nodes", "plans", "predicted_costs"):
            np.testing.assert_array_equal(getattr(loop, field), getattr(scan, field), err_msg=field)
        assert np.all(np.asarray(loop.solve_times) > 0)


def test_parameters_held_in_named_tuples_are_kept_and_read_back(tmp_path):
    """A model whose parameters are a NamedTuple of arrays: the program is written, read back, and decides as
    ``ctrl.step`` does."""
    cost = lambda x, u, p: jnp.sum((x - p.level) ** 2) + 0.01 * u[0] ** 2  # noqa: E731
    ctrl = fj.FIRHC(fj.Problem(lambda x, u, p: _step(x, u), CONTROLS, cost, 3), fallback=None)
    x0 = jnp.asarray([0.3, -0.2], dtype=jnp.zeros(()).dtype)
    p = Target(level=jnp.asarray([1.0, 0.0], dtype=x0.dtype))
    state = ctrl.init(x0)
    _exported.decision(ctrl, "target", tmp_path, state, x0, p)
    again = _exported.decision(ctrl, "target", tmp_path, state, x0, p)
    for a, b in zip(_leaves(again(state, x0, p)), _leaves(ctrl.step(state, x0, p)), strict=True):
        np.testing.assert_array_equal(a, b)
