"""Long calls show progress by default: ``simulate``, ``simulate_batch``, ``solve_batch`` and ``fj.profile`` draw
a bar once a call has run ``progress.AFTER_S`` seconds (here 0: every call is long), counted with an estimate
where a closed loop runs in chunks (the last call of the same program was long), else the time elapsed (and
for a batch, which runs as one program unless ``progress=True`` and its rows are solved apart, the time its
last call took); short calls draw nothing, and ``progress=False`` never does."""
import re

import jax.numpy as jnp
import numpy as np
import pytest

import firhc_jax as fj
from firhc_jax._src.runtime import progress
from firhc_jax.apps._timing import TRACED
from firhc_jax.apps._timing import compile_events as compilations


def _problem(N=3):
    return fj.Problem(lambda x, u: 0.9 * x + 0.2 * u, jnp.array([-1.0, 0.0, 1.0]), fj.quadratic_cost(1.0, 0.0), N)


def test_a_short_call_draws_nothing(capsys):
    problem = _problem()
    ctrl = fj.FIRHC(problem)
    for default in (False, True):  # compiled first (a first call that compiles for 2 s draws the time elapsed)
        ctrl.simulate(np.array([1.0]), 5, **({} if default else {"progress": False}))
        fj.solve_batch(problem, np.ones((3, 1)), **({} if default else {"progress": False}))
    assert capsys.readouterr().err == ""


def test_long_calls_draw_a_bar_by_default(capsys, monkeypatch):
    monkeypatch.setattr(progress, "AFTER_S", 0.0)
    monkeypatch.setattr(progress._Watcher, "POLL_S", 0.01)  # the watcher looks at once
    ctrl = fj.FIRHC(_problem(4), fallback="unconstrained")  # a controller of its own: no run of it timed yet
    x0 = np.array([1.5])
    whole = ctrl.simulate(x0, 30, progress=False)
    assert capsys.readouterr().err == ""
    ctrl.simulate(x0, 30)  # the last run was long (every run is): chunks, counted
    err = capsys.readouterr().err
    assert "FIRHC[sdfs]" in err and "30/30" in err and "100%" in err
    again = ctrl.simulate(x0, 30)
    np.testing.assert_array_equal(np.asarray(again.plans), np.asarray(whole.plans))
    capsys.readouterr()
    ctrl.simulate(x0, 7, compiled=False)
    assert "7/7" in capsys.readouterr().err
    ctrl.simulate_batch(np.array([[1.5], [-0.5]]), 4)  # a first run of this loop: one program, time elapsed
    assert "FIRHC[sdfs] x 2 loops (compiling, then one compiled run: not counted" in capsys.readouterr().err
    ctrl.simulate_batch(np.array([[1.5], [-0.5]]), 4)
    assert "8/8" in capsys.readouterr().err


def test_solve_batch_and_profile_draw_a_bar_by_default(capsys, monkeypatch):
    monkeypatch.setattr(progress, "AFTER_S", 0.0)
    problem = _problem(5)
    X = np.linspace(-2, 2, 80)[:, None]
    whole = fj.solve_batch(problem, X, progress=False, lanes=4)
    assert capsys.readouterr().err == ""
    with compilations(TRACED) as seen:  # the last call was long: still the one program (no chunk compiled)
        again = fj.solve_batch(problem, X, lanes=4)
    assert seen == [], seen
    np.testing.assert_array_equal(np.asarray(again.nodes), np.asarray(whole.nodes))
    capsys.readouterr()
    shown = fj.solve_batch(problem, X, lanes=4, progress=True)  # a pool's rows are never split: not counted
    assert re.search(r"solve_batch \(one compiled run .*: not counted; its rows share one work pool\): 00:0\d",
                     capsys.readouterr().err)
    for field in fj.SearchResult._fields:
        np.testing.assert_array_equal(np.asarray(getattr(shown, field)), np.asarray(getattr(whole, field)))
    apart = fj.solve_batch(problem, X, solver="sdfs-vmap", progress=True)  # rows solved apart: counted, in chunks
    assert "80/80" in capsys.readouterr().err
    np.testing.assert_array_equal(np.asarray(apart.cost), np.asarray(whole.cost))
    fj.profile(problem, X[:4], pop_widths=(1,), lanes=(4,), repeats=1)
    assert "profile" in capsys.readouterr().err
    with pytest.raises(TypeError, match="progress must be None, True or False"):
        fj.solve_batch(problem, X, progress="yes")


def test_a_bar_that_cannot_count_says_how_long_the_last_call_took(capsys):
    """A call run as one program (a batch after a long one) shows the time elapsed and the time its last call
    took, read from the record of that program's rate."""
    progress.record(("a test's program",), 100, 84.0)
    assert progress.expected_s(("a test's program",), 50) == 42.0
    assert progress.expected_s(("a program never run",), 50) is None
    with progress.Progress(50, "solve_batch", enabled=True, counted=False,
                           expected=progress.expected_s(("a test's program",), 50)):
        pass
    assert "solve_batch (one compiled run of about 42 s, as the last one: not counted" in capsys.readouterr().err
    with progress.Progress(50, "solve_batch", enabled=True, counted=False, expected=600.0):
        pass
    assert "of about 10 min" in capsys.readouterr().err


def _two_threads(enabled, tick: bool) -> dict:
    """Two threads, each in a call with a bar of its own (``enabled``), the second opened while the first is
    open; with ``tick``, the first reports 3 steps once both are open. ``{i: the steps thread i's bar was told,
    (i, "drawn"): whether it was drawn while both calls ran}``."""
    import io
    import threading

    streams = [io.StringIO(), io.StringIO()]
    opened, ticked, seen = [threading.Event(), threading.Event()], threading.Event(), {}

    def call(i):
        if i == 1:
            opened[0].wait(10)
        with progress.Progress(10 * (i + 1), f"call {i}", enabled=enabled, stream=streams[i],
                               counted=enabled is not None) as bar:
            opened[i].set()
            opened[1].wait(10)
            if i == 0 and tick:
                progress.tick_python(2)
            if i == 0:
                ticked.set()
            ticked.wait(10)
            seen[i] = bar._done
            for _ in range(300):  # both bars drawn (at most 3 s)
                if all(stream.getvalue() for stream in streams):
                    break
                threading.Event().wait(0.01)
            seen[i, "drawn"] = bool(streams[i].getvalue())

    threads = [threading.Thread(target=call, args=(i,)) for i in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(20)
    return seen


def test_bars_of_calls_in_other_threads_never_cross(monkeypatch):
    """The steps a thread reports move its own bar only (they moved the bar opened last, whichever thread's it
    was), and the watcher draws the automatic bars of calls in every thread (it watched only the call started
    last)."""
    monkeypatch.setattr(progress, "AFTER_S", 0.0)
    monkeypatch.setattr(progress._Watcher, "POLL_S", 0.01)
    assert _two_threads(True, tick=True) == {0: 3, 1: 0, (0, "drawn"): True, (1, "drawn"): True}
    assert _two_threads(None, tick=False) == {0: 0, 1: 0, (0, "drawn"): True, (1, "drawn"): True}
