"""apps._exported: an application's decision kept on disk as a traced program, read back without tracing, and
only when it is verifiably the program of this setting, platform and version."""
import hashlib
import json
import os
import subprocess
import sys
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


def _name(settings, args) -> str:
    return _exported.kept_path("", _exported.key(settings, args)).name


def test_the_file_is_named_by_the_settings_the_arguments_the_source_and_the_platform(monkeypatch):
    """Other settings (to the last bit), other shapes, another source digest or another platform give another
    file: a changed line of the package never reads a program traced from the old one."""
    ctrl = _controller([])
    state, x, p = _arguments(ctrl)
    base = _name("small", (state, x, p))
    assert _name("small", (state, x, p)) == base
    assert _name("small N=4", (state, x, p)) != base
    settings = ("hopper", 6, hm.HopperParams(), {"max_nodes": 500}, np.array([0.1, 0.2]))
    same = ("hopper", 6, hm.HopperParams(), {"max_nodes": 500}, np.array([0.1, 0.2]))
    assert _name(settings, (state, x, p)) == _name(same, (state, x, p))
    for other in (("hopper", 6, hm.HopperParams(M=np.nextafter(0.54, 1)), {"max_nodes": 500}, np.array([0.1, 0.2])),
                  ("hopper", 6, hm.HopperParams(), {"max_nodes": 501}, np.array([0.1, 0.2])),
                  ("hopper", 6, hm.HopperParams(), {"max_nodes": 500}, np.array([0.1, np.nextafter(0.2, 1)]))):
        assert _name(other, (state, x, p)) != _name(settings, (state, x, p))
    with pytest.raises(TypeError, match="cannot name a setting of type function"):
        _exported.key(("small", lambda x: x), (state, x, p))
    assert _name("small", (state, jnp.zeros(3, x.dtype), p)) != base
    assert _name("small", (state, x, {"ref": jnp.zeros(2)})) != base
    here = jax.export.default_export_platform()
    assert f"platform={here}" in _exported.key("small", (state, x, p)).splitlines()
    there = _elsewhere()
    monkeypatch.setattr(jax.export, "default_export_platform", lambda: there)
    assert _name("small", (state, x, p)) != base
    monkeypatch.undo()
    monkeypatch.setattr(_exported, "source_digest", lambda: "another source")
    assert _name("small", (state, x, p)) != base


def _kept(tmp_path, ctrl, settings="small"):
    """``(path, arguments)``: ``ctrl``'s decision kept in ``tmp_path`` under ``settings``."""
    args = _arguments(ctrl)
    _exported.decision(ctrl, settings, tmp_path, *args)
    return _exported.kept_path(tmp_path, _exported.key(settings, args)), args


def _traced_again(tmp_path, path, args, message, settings="small"):
    """The decision of a fresh controller over a kept file that must not run: one warning naming the file and
    ``message``, the model traced again, the file written again (it then passes the checks), and the decision
    that of ``ctrl.step``."""
    traces = []
    ctrl = _controller(traces)
    with pytest.warns(RuntimeWarning) as warned:
        decide = _exported.decision(ctrl, settings, tmp_path, *args)
        out = decide(*args)
    assert len(warned) == 1, [str(w.message) for w in warned]
    text = str(warned[0].message)
    assert path.name in text and message in text and text.endswith("traced and written again") and "\n" not in text
    assert traces  # traced again
    for a, b in zip(_leaves(out), _leaves(ctrl.step(*args)), strict=True):
        np.testing.assert_array_equal(a, b)
    header, blob = _exported.read_header(path.read_bytes())
    assert header["key"] == _exported.key(settings, args)
    assert header["sha256"] == hashlib.sha256(blob).hexdigest()
    traces.clear()
    _exported.decision(_controller(traces), settings, tmp_path, *args)
    assert traces == []  # the file written again is read back


def test_a_damaged_file_is_traced_and_written_again(tmp_path):
    ctrl = _controller([])
    path, args = _kept(tmp_path, ctrl)
    path.write_bytes(b"not a program")
    _traced_again(tmp_path, path, args, "is not a kept decision")


def test_a_deeply_nested_header_is_traced_and_written_again(tmp_path):
    """A header of 100,000 nested JSON lists (Python's parser gives up with a ``RecursionError``): refused as
    damaged, as any header that cannot be read, and replaced."""
    path, args = _kept(tmp_path, _controller([]))
    path.write_bytes(_exported.FORMAT + b"[" * 100_000 + b"\n" + bytes(10))
    with pytest.raises(_exported.Refused, match="has a damaged header"):
        _exported.read_header(path.read_bytes())
    _traced_again(tmp_path, path, args, "has a damaged header")


def test_a_flipped_byte_in_the_program_is_traced_and_written_again(tmp_path):
    """A byte of the program's StableHLO changed (jax.export still reads it; compiling it would fail)."""
    path, args = _kept(tmp_path, _controller([]))
    data = bytearray(path.read_bytes())
    mlir = data.index(b"ML\xefR")  # MLIR bytecode's magic number
    data[mlir + 1] ^= 0xFF
    path.write_bytes(bytes(data))
    _traced_again(tmp_path, path, args, "is damaged (its program does not match the SHA-256")


def test_a_flipped_bit_in_a_model_constant_is_traced_and_written_again(tmp_path):
    """The model's 0.9 (``_step``) with a bit of its exponent flipped: a program that runs and decides for
    another model."""
    path, args = _kept(tmp_path, _controller([]))
    data = bytearray(path.read_bytes())
    constant = np.asarray(0.9, args[1].dtype).tobytes()
    assert data.count(constant) == 1
    data[data.index(constant) + len(constant) - 2] ^= 0x20
    path.write_bytes(bytes(data))
    _traced_again(tmp_path, path, args, "is damaged")


def test_another_settings_program_under_this_name_is_traced_and_written_again(tmp_path):
    """The file of the settings "other" (another model: its 0.9 is 0.5) copied to the name of "small"."""
    ctrl = _controller([])
    args = _arguments(ctrl)
    other = fj.FIRHC(ctrl.problem.replace(dynamics=lambda x, u: _step(x, u).at[1].add(-0.4 * x[1])), fallback=None)
    _exported.decision(other, "other", tmp_path, *args)
    mine = _exported.kept_path(tmp_path, _exported.key("small", args))
    _exported.kept_path(tmp_path, _exported.key("other", args)).rename(mine)
    _traced_again(tmp_path, mine, args, "was written for another setting")


def _forged(path, blob: bytes) -> None:
    """Replace the program in the kept file at ``path`` by ``blob``, with a header that vouches for it."""
    header, _ = _exported.read_header(path.read_bytes())
    header["sha256"] = hashlib.sha256(blob).hexdigest()
    path.write_bytes(_exported.FORMAT + json.dumps(header).encode() + b"\n" + blob)


def _elsewhere() -> str:
    """A platform other than this machine's: CUDA on a CPU, the CPU on a GPU."""
    return "cpu" if jax.export.default_export_platform() != "cpu" else "cuda"


def test_a_program_for_another_platform_is_traced_and_written_again(tmp_path, monkeypatch):
    """A program exported for another platform (CUDA on a CPU) under this setting's name: written by a run there
    (its key names that platform), or with a header that names this one."""
    ctrl = _controller([])
    path, args = _kept(tmp_path, ctrl)
    here, there = jax.export.default_export_platform(), _elsewhere()
    with monkeypatch.context() as m:
        m.setattr(jax.export, "default_export_platform", lambda: there)
        there_key = _exported.key("small", args)
    program = bytes(jax.export.export(jax.jit(ctrl.step), platforms=[there])(*args).serialize())
    path.write_bytes(_exported.FORMAT + json.dumps(
        {"key": there_key, "sha256": hashlib.sha256(program).hexdigest(), "label": "small"}).encode()
        + b"\n" + program)
    _traced_again(tmp_path, path, args, f"was written for another platform ({there}, not {here})")
    _forged(path, program)
    _traced_again(tmp_path, path, args, f"was exported for {there}, not {here}")


def test_a_kept_program_that_fails_when_run_is_traced_and_written_again(tmp_path):
    """A program that passes every check on disk (its header vouches for it) but does not compile: the call
    falls back to tracing, never to a traceback."""
    path, args = _kept(tmp_path, _controller([]))
    blob = bytearray(_exported.read_header(path.read_bytes())[1])
    mlir = blob.index(b"ML\xefR")
    blob[mlir:mlir + 4] = b"XXXX"
    _forged(path, bytes(blob))
    _traced_again(tmp_path, path, args, "failed when run (")


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


def test_no_decision_is_kept_with_the_compilation_cache_off(tmp_path, monkeypatch):
    """With ``jax_enable_compilation_cache`` off (``--no-cache``) a timed loop neither reads nor writes a kept
    decision, though a folder is set (as ``JAX_COMPILATION_CACHE_DIR`` sets one)."""
    from firhc_jax._src.runtime.disk_cache import compilation_cache_off

    ctrl = _controller([])
    x0 = _arguments(ctrl)[1]
    monkeypatch.setattr(_timing, "decision", lambda *a, **k: pytest.fail("a kept decision was used"))
    before = jax.config.jax_compilation_cache_dir
    with compilation_cache_off():
        jax.config.update("jax_compilation_cache_dir", str(tmp_path))
        try:
            loop, _ = _timing.timed_closed_loop(ctrl, x0, 2, jax.jit(_step), settings=("test_exported", __file__))
        finally:
            jax.config.update("jax_compilation_cache_dir", before)
    np.testing.assert_array_equal(loop.states, ctrl.simulate(x0, 2, jax.jit(_step)).states)
    assert list(tmp_path.iterdir()) == []


def _tanks(cache, out, *args):
    """``python -m firhc_jax tanks`` for two samples with ``cache`` as the compilation cache's folder:
    ``(stderr, the states and predicted costs)``; the run must exit 0 without a traceback."""
    proc = subprocess.run([sys.executable, "-m", "firhc_jax", "tanks", "--seconds", "4", "--no-progress", "--out",
                           str(out), *args], capture_output=True, text=True, timeout=600,
                          env={**os.environ, "JAX_COMPILATION_CACHE_DIR": str(cache)})
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    loop = fj.ClosedLoop.load(out / "closed_loop.npz")
    return proc.stderr, np.concatenate([loop.states.ravel(), loop.predicted_costs.ravel()])


def _kept_warnings(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if "kept decision" in line]


@pytest.mark.slow
def test_the_command_line_runs_only_the_kept_program_of_its_setting(tmp_path):
    """``tanks --switch-penalty 0``'s program under ``--switch-penalty 50``'s name, then that program with a byte
    flipped: each run warns on one line, traces again, and gives the closed loop of its own setting."""
    cache = tmp_path / "cache"
    folder = cache / _exported.FOLDER
    zero_run = _tanks(cache, tmp_path / "zero", "--switch-penalty", "0")[1]
    zero, = folder.iterdir()
    stderr, fifty = _tanks(cache, tmp_path / "fifty", "--switch-penalty", "50")
    mine, = set(folder.iterdir()) - {zero}
    assert _kept_warnings(stderr) == []
    assert not np.array_equal(zero_run, fifty)  # the two settings predict other costs
    mine.write_bytes(zero.read_bytes())
    stderr, states = _tanks(cache, tmp_path / "swapped", "--switch-penalty", "50")
    assert _kept_warnings(stderr) == [f"warning: the kept decision {str(mine)!r} was written for another setting: "
                                      "traced and written again"]
    np.testing.assert_array_equal(states, fifty)
    data = bytearray(mine.read_bytes())
    data[data.index(b"ML\xefR") + 1] ^= 0xFF
    mine.write_bytes(bytes(data))
    stderr, states = _tanks(cache, tmp_path / "flipped", "--switch-penalty", "50")
    assert [" is damaged " in line for line in _kept_warnings(stderr)] == [True]
    np.testing.assert_array_equal(states, fifty)
    stderr, states = _tanks(cache, tmp_path / "again", "--switch-penalty", "50")
    assert _kept_warnings(stderr) == []  # written again, whole
    np.testing.assert_array_equal(states, fifty)
