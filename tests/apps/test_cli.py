"""The command lines check their arguments before any work: an output folder that cannot be written, a horizon
too long for the example, a negative or NaN node budget end in argparse's one-line error (exit status 2)."""
import os
import re
import subprocess
import sys

import numpy as np
import pytest
from repository import ROOT

import firhc_jax as fj
from firhc_jax import cli
from firhc_jax.apps import batch, bench, example, hopper, inverter, tanks
from firhc_jax.apps import export as export_app
from firhc_jax.apps import profile as profile_app

# Each command line with the function that starts its work, replaced in the tests below by one that fails: an
# argument refused after the work started fails the test even where the work would end in an error of its own.
COMMANDS = {
    "example": (["example"], example, "make_problem"),
    "hopper": (["hopper"], hopper, "simulate"),
    "tanks": (["tanks"], tanks, "simulate"),
    "inverter": (["inverter"], inverter, "closed_loop"),
    "bench tables": (["bench", "tables", "--quick", "--plants", "tanks"], bench, "tanks_case"),
    "bench throughput": (["bench", "throughput", "--quick"], bench, "synthetic_case"),
    "export": (["export", "tanks"], export_app, "controller"),
}


# Commands whose --out is not a folder, checked the same way otherwise.
OTHER_COMMANDS = {
    "batch": (["batch", "--states", "X0.npz", "--out", "r.npz"], batch, "_solve"),
    "profile": (["profile", "no_such_module:case"], profile_app, "load_case"),
}


@pytest.fixture
def no_work(monkeypatch):
    """``run(command, *args)``: ``cli.main`` of the command with its work replaced by a failure."""
    def run(command, *args):
        argv, module, work = {**COMMANDS, **OTHER_COMMANDS}[command]

        def started(*a, **k):
            raise AssertionError(f"{command}: the work started before the arguments were checked")

        monkeypatch.setattr(module, work, started)
        return cli.main([*argv, *args])

    return run


def _refused(capsys, run, *args) -> str:
    """argparse's error message of a refused command line (exit status 2)."""
    with pytest.raises(SystemExit) as e:
        run(*args)
    assert e.value.code == 2
    return capsys.readouterr().err.strip().splitlines()[-1]


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_an_output_folder_that_cannot_be_written_is_refused_before_any_work(command, no_work, tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    for out, reason in ((a_file, "exists and is not a folder"), (a_file / "sub", "is not a folder"),
                        ("/proc/firhc-nope/out", "cannot write into")):
        if str(out).startswith("/proc") and not os.path.isdir("/proc"):
            continue
        message = _refused(capsys, no_work, command, "--out", str(out))
        assert "error: argument --out:" in message and reason in message, message
    assert a_file.read_text() == "" and not (a_file.parent / "sub").exists()


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0, reason="root writes into any folder")
def test_a_read_only_output_folder_is_refused(no_work, tmp_path, capsys):
    folder = tmp_path / "read-only"
    folder.mkdir(mode=0o500)
    message = _refused(capsys, no_work, "tanks", "--out", str(folder / "run"))
    assert "cannot write into" in message


def test_an_output_folder_is_created_only_by_a_run(no_work, tmp_path, capsys):
    """A command refused on another argument leaves no output folder behind (the check writes nothing)."""
    out = tmp_path / "new" / "run"
    _refused(capsys, no_work, "tanks", "--out", str(out), "--horizon", "0")
    assert not (tmp_path / "new").exists()


@pytest.mark.parametrize("horizon", ["30", "100000", "13"])
def test_example_refuses_a_horizon_its_exhaustive_check_cannot_run(horizon, no_work, capsys):
    message = _refused(capsys, no_work, "example", "--horizon", horizon)
    assert f"--horizon: must be an integer between 1 and {example.MAX_HORIZON}, got '{horizon}'" in message


@pytest.mark.parametrize("command", ["bench tables", "bench throughput"])
@pytest.mark.parametrize("value", ["-1", "nan", "inf", "many"])
def test_bench_refuses_a_node_budget_that_is_not_a_count(command, value, no_work, capsys):
    message = _refused(capsys, no_work, command, "--max-es-nodes", value)
    assert "--max-es-nodes: must be a number" in message and repr(value) in message


@pytest.mark.slow
def test_a_refused_output_folder_ends_the_process_with_one_line_and_no_traceback(tmp_path):
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    proc = subprocess.run([sys.executable, "-m", "firhc_jax", "tanks", "--out", str(a_file)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and proc.stdout == ""
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == (f"python -m firhc_jax tanks: error: argument --out: "
                                                    f"{str(a_file)!r} exists and is not a folder")


# Every numeric option that sizes work or memory has a bound, and options that size work together (an exhaustive
# search's nodes over a run) are refused together, all before any work and with argparse's one line.
@pytest.mark.parametrize("command, args, message", [
    ("inverter", ["--cycles", "1e9"], "argument --cycles: must be a number > 0 and <= 100.0, got '1e9'"),
    ("inverter", ["--cycles", "0.001"], "--cycles must cover at least two samples, got 0.001"),
    ("inverter", ["--horizon", "9"], "--horizon must be between 1 and 8 with --levels 2, got 9"),
    ("inverter", ["--solver", "exhaustive", "--horizon", "8"], "exhaustive search at N = 8 visits 19,173,960 nodes"),
    ("tanks", ["--seconds", "1e9"], "argument --seconds: must be a number > 0 and <= 3600.0"),
    ("tanks", ["--seconds", "1"], "--seconds must be at least one sample (2 s), got 1"),
    ("tanks", ["--solver", "exhaustive", "-N", "6"], "25,646,166 nodes per step, 2,564,616,600 over 100 steps"),
    ("hopper", ["--solver", "exhaustive", "--horizon", "12"], "use --solver sdfs"),
    ("hopper", ["--solver", "exhaustive", "--warm"], "--warm needs --solver sdfs"),
    ("example", ["--steps", "10000000"], "argument --steps: must be an integer between 1 and 100000"),
    ("example", ["--horizon", "12", "--steps", "200"], "159,432,000 over 200 steps"),
    ("bench tables", ["--repeats", "1000"], "argument --repeats: must be an integer between 1 and 100"),
    ("bench throughput", ["--max-es-nodes", "1e12"], "argument --max-es-nodes: must be a number between 0 and"),
    ("batch", ["--lanes", "1000000"], "argument --lanes: must be an integer between 1 and 4096"),
    ("batch", ["--pop-width", "1000"], "argument --pop-width: must be an integer between 1 and 64"),
    ("batch", ["--max-memory", str(2 ** 70)], "argument --max-memory: must be an integer between 1 and"),
    ("batch", ["--repeats", "1000000"], "argument --repeats: must be an integer between 1 and 1000"),
    ("batch", ["--launch-local", "1000"], "argument --launch-local: must be an integer between 1 and 64"),
    ("batch", ["--num-processes", "100000"], "argument --num-processes: must be an integer between 1 and 1024"),
    ("profile", ["--lanes", "100000"], "argument --lanes: must be an integer between 1 and 4096"),
    ("profile", ["--repeats", "1000"], "argument --repeats: must be an integer between 1 and 100"),
    ("profile", ["--max-exhaustive-nodes", "1000000000000"], "argument --max-exhaustive-nodes: must be an integer"),
])
def test_options_that_size_work_or_memory_are_bounded_before_any_work(command, args, message, no_work, capsys):
    refused = _refused(capsys, no_work, command, *args)
    assert message in refused and refused.count("\n") == 0, refused


def test_the_bounds_leave_the_documented_runs_alone(no_work, tmp_path):
    """The default runs, and the heaviest ones the docs report, pass the checks (and reach the work)."""
    for command, args in (("inverter", ["--solver", "exhaustive", "--horizon", "5"]),
                          ("tanks", ["--solver", "exhaustive", "-N", "5"]),
                          ("hopper", ["--solver", "exhaustive", "--horizon", "8"]), ("example", ["--horizon", "12"]),
                          ("inverter", []), ("tanks", []), ("hopper", []), ("example", [])):
        with pytest.raises(AssertionError, match="the work started"):
            no_work(command, *args, "--out", str(tmp_path / command))


def test_table_3_shows_the_papers_mean_as_a_mean():
    """The paper's 595 at N = 3 is a mean of nodes per step (docs/applications/tanks.md), 2,516 the maximum."""
    row = {"plant": "tanks", "N": 3, "A": 5219, "B_max": 3145, "B_min": 51, "B_mean": 181.4, "C_dfs_pct": 10.0,
           "C_levels_pct": 9.0, "sdfs_ms": 0.6, "dfs_ms": 5.0, "levels_ms": 5.1, "us_per_iteration": 3.0,
           "warm_nodes_mean": 100.0, "warm_ms": 0.5, "best_pop_width": 1, "best_pop_width_ms": 0.6, "es_steps": 100,
           "steps": 100}
    text = bench.tables_markdown([row, {**row, "plant": "hopper", "N": 5, "A": 363, "B_max": 300, "B_min": 15}])
    tanks_table = text.split("### Table 3")[1]
    assert "| B max/mean ours (paper) | B min |" in tanks_table and "| 3,145/181 (2,516/595) | 51 |" in tanks_table
    hopper_table = text.split("### Table 2")[1].split("### Table 3")[0]
    assert "| B max/min ours (paper) | B mean |" in hopper_table and "| 300/15 (363/15) | 181 |" in hopper_table


def _help_rows(capsys) -> dict:
    """``{plant: (n, example row)}`` as ``batch --help`` states them."""
    with pytest.raises(SystemExit):
        cli.main(["batch", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    found = re.findall(r"--plant (\w+): n = (\d+)(?:(?!--plant).)*?e\.g\. a row ((?:-?[\d.]+ ?)+)", text)
    return {plant: (int(n), [float(v) for v in row.split()]) for plant, n, row in found}


@pytest.mark.slow
def test_batch_runs_the_states_its_help_gives_for_every_built_in_plant(tmp_path, capsys):
    """Each built-in plant's n and example row, as the help states them: a batch of that row is solved."""
    from firhc_jax import distributed

    rows = _help_rows(capsys)
    assert sorted(rows) == sorted(batch.PLANTS)
    for plant, (n, row) in rows.items():
        assert len(row) == n, (plant, n, row)
        np.save(tmp_path / f"{plant}.npy", np.array([row, row]))
        out = tmp_path / f"{plant}.npz"
        assert cli.main(["batch", "--plant", plant, "-N", "2", "--states", str(tmp_path / f"{plant}.npy"),
                         "--out", str(out)]) == 0
        result, _ = distributed.load_result(out)
        assert result.feasible.all() and result.sequence.shape == (2, 2) and (result.sequence >= 0).all()


def test_batch_help_gives_each_built_in_plants_state(capsys):
    """The help's n for each plant is the one its problem takes (the tanks' 5-entry controller state)."""
    from firhc_jax.models import synthetic, tanks

    rows = _help_rows(capsys)
    assert rows["tanks"][0] == len(tanks.initial_state()) == 5
    assert rows["synthetic"][0] == len(synthetic.benchmark_state()) == 3


# A mistake in the user's module: one line naming the module and the error; --debug: the exception itself.
MISTAKES = {
    "syntax": ("def case(:\n    pass\n", SyntaxError, r"SyntaxError: .* line 1"),
    "at_import": ("x = 1 / 0\ndef case():\n    pass\n", ZeroDivisionError,
                  r"ZeroDivisionError: division by zero \(at .*_at_import_\w+\.py:1\)"),
    "in_function": ("def case():\n    raise KeyError('no plant today')\n", KeyError,
                    r"raised KeyError: 'no plant today' \(at .*_in_function_\w+\.py:2\)"),
}


def _user_module(tmp_path, monkeypatch, kind: str, command: str) -> str:
    name = f"fj_user_{kind}_{command}"
    (tmp_path / f"{name}.py").write_text(MISTAKES[kind][0])
    monkeypatch.syspath_prepend(str(tmp_path))
    return name


@pytest.mark.parametrize("kind", sorted(MISTAKES))
@pytest.mark.parametrize("command", ["batch", "profile"])
def test_a_mistake_in_the_users_module_is_one_line_and_the_traceback_needs_debug(kind, command, tmp_path,
                                                                                   monkeypatch):
    from firhc_jax import distributed

    monkeypatch.setattr(fj, "solve_batch", lambda *a, **k: pytest.fail("solved"))
    module = _user_module(tmp_path, monkeypatch, kind, command)
    distributed.save_states(tmp_path / "X0.npz", np.zeros((2, 1)))
    argv = (["batch", "--problem", f"{module}:case", "--states", str(tmp_path / "X0.npz"), "--out",
             str(tmp_path / "r.npz")] if command == "batch" else ["profile", f"{module}:case", "--out",
                                                                  str(tmp_path / "prof")])
    _, error, pattern = MISTAKES[kind]
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    message = str(e.value.code)
    assert message.startswith(f"{command}: ") and module in message and "\n" not in message, message
    assert __import__("re").search(pattern, message) and message.endswith("--debug shows the traceback"), message
    import sys
    sys.modules.pop(module, None)
    with pytest.raises(error):
        cli.main([*argv, "--debug"])


BATCH_USER = """
import jax.numpy as jnp
import firhc_jax as fj


def tracking():
    return fj.Problem(lambda x, u, p: 0.9 * x + u, jnp.array([-1.0, 0.0, 1.0]),
                      lambda x, u, p: jnp.sum((x - p["ref"]["x"]) ** 2) + p["w"] * u[0] ** 2, 3)
"""


def test_batch_solves_per_row_params_and_times_the_compiled_calls_only(tmp_path, monkeypatch):
    """``--params`` (an .npz of per-row leaves, 'a/b' nested) reaches solve_batch; meta_seconds and nodes/s come
    from the calls after the first, compiling one (meta_first_seconds)."""
    import firhc_jax as fj
    from firhc_jax import distributed

    (tmp_path / "fj_batch_user.py").write_text(BATCH_USER)
    monkeypatch.syspath_prepend(str(tmp_path))
    X0 = np.array([[0.0], [1.0], [-2.0], [0.5]])
    rows = {"ref": {"x": np.array([[1.0], [0.0], [0.0], [-1.0]])}, "w": np.array([0.1, 0.2, 0.0, 1.0])}
    np.savez(tmp_path / "p.npz", **{"ref/x": rows["ref"]["x"], "w": rows["w"]})
    distributed.save_states(tmp_path / "X0.npz", X0)
    argv = ["batch", "--problem", "fj_batch_user:tracking", "--states", str(tmp_path / "X0.npz"), "--params",
            str(tmp_path / "p.npz"), "--out", str(tmp_path / "r.npz"), "--lanes", "2"]
    assert cli.main(argv) == 0
    result, meta = distributed.load_result(tmp_path / "r.npz")
    import fj_batch_user

    expected = fj.solve_batch(fj_batch_user.tracking(), X0, params=rows, lanes=2)
    np.testing.assert_array_equal(result.cost, np.asarray(expected.cost))
    np.testing.assert_array_equal(result.sequence, np.asarray(expected.sequence))
    assert meta["times"].shape == (1,) and meta["seconds"] == meta["times"][0]
    assert meta["nodes_per_second"] == pytest.approx(result.nodes.sum() / meta["seconds"])
    np.savez(tmp_path / "short.npz", **{"ref/x": rows["ref"]["x"][:3], "w": rows["w"][:3]})
    with pytest.raises(SystemExit, match=r"batch: --params: every array needs leading axis B = 4 \(the rows of "
                                         r"--states\); \['ref'\]\['x'\] has shape \(3, 1\)"):
        cli.main([*argv[:6], str(tmp_path / "short.npz"), *argv[7:]])


BATCH_ARRAY_USER = """
import jax.numpy as jnp
import firhc_jax as fj


def tracking():
    return fj.Problem(lambda x, u, p: 0.9 * x + u, jnp.array([-1.0, 0.0, 1.0]),
                      lambda x, u, p: jnp.sum((x - p) ** 2) + 0.1 * u[0] ** 2, 3)
"""


def test_batch_reads_npy_files_and_shows_its_progress_and_the_time_left(tmp_path, monkeypatch, capsys):
    """``--states X0.npy`` (the [B, n] array) and ``--params P.npy`` (one array, leading axis B); a batch of at
    least two chunks' rows is solved in calls of equal size (the last filled up), with a bar of rows and the time
    left after each on stderr, and the costs and sequences of one call. (Chunks of 2 rows here, 256 in use.)"""
    from firhc_jax import distributed

    assert [batch.chunks(b) for b in (1, 511, 512, 601, 10_000, 10 ** 6)] == [1, 1, 2, 2, 20, 20]
    monkeypatch.setattr(batch, "MIN_CHUNK_ROWS", 2)
    (tmp_path / "fj_batch_array_user.py").write_text(BATCH_ARRAY_USER)
    monkeypatch.syspath_prepend(str(tmp_path))
    X0, refs = np.array([[0.0], [1.0], [-2.0], [2.5], [-0.5]]), np.array([[1.0], [0.0], [-1.0], [0.5], [0.0]])
    np.save(tmp_path / "X0.npy", X0)
    np.save(tmp_path / "P.npy", refs)
    assert cli.main(["batch", "--problem", "fj_batch_array_user:tracking", "--states", str(tmp_path / "X0.npy"),
                     "--params", str(tmp_path / "P.npy"), "--out", str(tmp_path / "r.npz")]) == 0
    err = capsys.readouterr().err
    for label in ("first call (compiles)", "timed call 1/1"):
        assert re.search(re.escape(label) + r": +60%.*\| 3/5 \[\d\d:\d\d<\d\d:\d\d", err), err
        assert re.search(re.escape(label) + r": +100%.*\| 5/5 \[", err), err
    result, _ = distributed.load_result(tmp_path / "r.npz")
    import fj_batch_array_user

    expected = fj.solve_batch(fj_batch_array_user.tracking(), X0, params=refs)
    np.testing.assert_array_equal(result.sequence, np.asarray(expected.sequence))
    np.testing.assert_array_equal(result.cost, np.asarray(expected.cost))
    np.testing.assert_array_equal(result.feasible, np.asarray(expected.feasible))


def _unreadable(tmp_path) -> dict:
    """Files ``batch`` cannot read, each with what its one line must say."""
    from firhc_jax import distributed

    distributed.save_states(tmp_path / "whole.npz", np.zeros((4, 5)))
    whole = (tmp_path / "whole.npz").read_bytes()
    np.save(tmp_path / "whole.npy", np.zeros((4, 5)))
    files = {"truncated.npz": (whole[: len(whole) // 2], r"cannot read .*truncated\.npz \(BadZipFile: "),
             "cut.npz": (whole[:-30], r"cannot read .*cut\.npz \("),
             "damaged.npz": (whole[:200] + b"\xff" + whole[201:], r"cannot read .*damaged\.npz \(BadZipFile: Bad CRC"),
             "truncated.npy": ((tmp_path / "whole.npy").read_bytes()[:-8], r"cannot read .*truncated\.npy \("),
             "notes.txt": (b"h1 h2 h3\n0.2 0.18 0.1\n", r"notes\.txt is neither an \.npy nor an \.npz file"),
             "empty.npz": (b"", r"empty\.npz is neither an \.npy nor an \.npz file")}
    for name, (data, _) in files.items():
        (tmp_path / name).write_bytes(data)
    np.save(tmp_path / "objects.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    cases = {tmp_path / name: message for name, (_, message) in files.items()}
    cases[tmp_path / "objects.npy"] = r"cannot read .*objects\.npy \(ValueError: Object arrays cannot be loaded"
    cases[tmp_path / "missing.npz"] = r"cannot read --FLAG .*missing\.npz: No such file or directory"
    cases[tmp_path] = r"cannot read --FLAG .*: Is a directory"
    return cases


@pytest.mark.parametrize("flag", ["--states", "--params"])
def test_batch_names_every_file_it_cannot_read_in_one_line(flag, tmp_path, monkeypatch):
    from firhc_jax import distributed

    monkeypatch.setattr(fj, "solve_batch", lambda *a, **k: pytest.fail("solved"))
    good = tmp_path / "good"
    good.mkdir()
    distributed.save_states(good / "X0.npz", np.zeros((4, 5)))
    np.save(good / "P.npy", np.zeros(4))
    for path, message in _unreadable(tmp_path).items():
        files = {"--states": good / "X0.npz", "--params": good / "P.npy", flag: path}
        with pytest.raises(SystemExit) as e:
            cli.main(["batch", "--states", str(files["--states"]), "--params", str(files["--params"]),
                      "--out", str(tmp_path / "r.npz")])
        text = str(e.value.code)
        assert text.startswith("batch: ") and "\n" not in text and flag in text, text
        assert re.search(message.replace("--FLAG", flag), text), (message, text)


def test_example_says_how_much_faster_sdfs_is_and_defaults_to_a_horizon_where_it_shows(tmp_path, capsys):
    """The worked example prints sDFS's time against exhaustive search's; its default horizon is the one its
    docstring reports measured (N = 10: sDFS several times faster; at N = 8 and below they can be close)."""
    import json

    assert cli.build_parser().parse_args(["example"]).horizon == 10 and "N = 10" in example.__doc__
    assert cli.main(["example", "--horizon", "3", "--steps", "3", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    summary = json.loads((tmp_path / "summary.json").read_text())
    ratio = summary["exhaustive"]["time_per_step_s"] / summary["sdfs"]["time_per_step_s"]
    assert summary["exhaustive_over_sdfs_time"] == pytest.approx(ratio)
    assert f"sDFS: {ratio:.1f}x as fast as exhaustive search" in out and "its lead grows with N" in out


def _kept_file(path, label: str, **changed) -> None:
    """A kept decision's file at ``path`` whose key has this installation's lines, some ``changed``."""
    import json

    from firhc_jax.apps import _exported

    lines = {**_exported.installation(), **changed, "setting": repr(label)}
    header = {"key": "\n".join(f"{k}={v}" for k, v in lines.items()), "sha256": "0" * 64, "label": label}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(_exported.FORMAT + json.dumps(header).encode() + b"\n" + bytes(5000))


def _xla(name: str, digit: str, what: str) -> str:
    """The name JAX gives an entry of its compilation cache: ``<module>-<SHA-256 in hex>-cache`` (or ``-atime``)."""
    return f"{name}-{digit * 64}-{what}"


def _cache(folder, *args) -> None:
    """``python -m firhc_jax cache *args`` with ``folder`` as the cache's folder."""
    import jax

    before = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", str(folder))  # as JAX_COMPILATION_CACHE_DIR sets it
    try:
        assert cli.main(["cache", *args]) == 0
    finally:
        jax.config.update("jax_compilation_cache_dir", before)


def test_cache_lists_the_kept_files_with_their_sizes_and_clears_them(tmp_path, capsys):
    """A folder with four kept decisions (one of this installation, one of another JAX, one of another format,
    one with a damaged header), XLA's entries and files of the user's, some named like XLA's or like kept
    decisions: each decision listed with its application, size and whether it is ever read again, XLA's
    entries counted, the user's files counted apart; ``--clear`` removes the decisions and XLA's entries, and
    leaves every file of the user's."""
    from firhc_jax.apps import _exported

    folder = tmp_path / "cache"
    kept = folder / _exported.FOLDER
    _kept_file(kept / f"{'a' * 64}.jaxexport", "hopper")
    _kept_file(kept / f"{'b' * 64}.jaxexport", "tanks", jax="0.4.1")
    (kept / f"{'c' * 64}.jaxexport").write_bytes(b"firhc_jax kept decision 0\n{}\n" + bytes(100))
    (kept / f"{'e' * 64}.jaxexport").write_bytes(_exported.FORMAT + b"[" * 100_000 + b"\n")
    for name, size in ((_xla("jit_step", "1", "cache"), 250_000), (_xla("jit_step", "1", "atime"), 8),
                       (_xla("jit_loop", "2", "cache"), 50_000)):
        (folder / name).write_bytes(bytes(size))
    users = {folder / "notes.txt": b"mine", folder / "build-cache": b"x" * 7000, folder / "meeting-atime": b"8",
             folder / _xla("jit_step", "1", "cached"): b"y", kept / f"{'d' * 64}.jaxexport": b"my own program",
             kept / "mine.jaxexport": b"firhc_jax kept decision 1\n"}
    for path, data in users.items():
        path.write_bytes(data)
    kept_bytes = sum(p.stat().st_size for p in kept.iterdir() if p not in users)
    _cache(folder)
    listed = capsys.readouterr().out.splitlines()
    _cache(folder, "--clear")
    cleared = capsys.readouterr().out
    assert listed[:2] == [f"folder: {folder}",
                          f"kept decisions ({_exported.FOLDER}/): 4 files, {kept_bytes / 1e6:.1f} MB"]
    rows = {line.split()[0]: line for line in listed[2:6]}
    assert re.fullmatch(r" +a{12} +hopper +5\.\d kB +\d{4}-\d\d-\d\d \d\d:\d\d", rows["a" * 12])
    assert re.search(r" tanks +5\.\d kB .*\(never read: written by another jax\)$", rows["b" * 12])
    assert rows["c" * 12].endswith("(never read: was written in another format)")
    assert rows["e" * 12].endswith("(never read: has a damaged header)")
    assert listed[6:] == ["XLA's compilations: 2 entries, 0.3 MB",
                          f"other files, which --clear leaves: {len(users)}"]
    assert cleared.strip() == (f"removed 4 kept decisions and 3 files of XLA's compilations (0.4 MB) from "
                               f"{folder}")
    assert sorted(p for p in folder.rglob("*") if p.is_file()) == sorted(users)
    assert all(path.read_bytes() == data for path, data in users.items())


def _vanishing(monkeypatch, *paths) -> None:
    """Directory listings that also name ``paths``, files that are gone by the time they are looked at (another
    ``cache --clear``, JAX's own eviction)."""
    import pathlib

    iterdir, glob = pathlib.Path.iterdir, pathlib.Path.glob

    def ghosts(folder):
        return [p for p in paths if p.parent == folder]

    monkeypatch.setattr(pathlib.Path, "iterdir", lambda self: iter([*iterdir(self), *ghosts(self)]))
    monkeypatch.setattr(pathlib.Path, "glob", lambda self, pattern: iter([*glob(self, pattern), *ghosts(self)]))


def test_cache_passes_over_files_that_leave_the_folder_while_it_lists_them(tmp_path, monkeypatch, capsys):
    from firhc_jax.apps import _exported

    folder = tmp_path / "cache"
    kept = folder / _exported.FOLDER
    _kept_file(kept / f"{'a' * 64}.jaxexport", "hopper")
    (folder / _xla("jit_step", "1", "cache")).write_bytes(bytes(100))
    _vanishing(monkeypatch, kept / f"{'b' * 64}.jaxexport", folder / _xla("jit_gone", "2", "cache"),
               kept / ".tmp-abcdefgh.jaxexport")
    _cache(folder)
    listed = capsys.readouterr().out.splitlines()
    assert listed[1].startswith(f"kept decisions ({_exported.FOLDER}/): 1 files") and "hopper" in listed[2]
    assert listed[3:] == ["XLA's compilations: 1 entries, 0.1 kB"]
    _cache(folder, "--clear")
    assert capsys.readouterr().out.startswith("removed 1 kept decisions and 1 files of XLA's compilations")
    assert os.listdir(kept) == [] and os.listdir(folder) == [_exported.FOLDER]


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no named pipes here")
def test_cache_reads_only_regular_files(tmp_path, capsys):
    """A named pipe under a kept decision's name (or XLA's, or an unfinished write's) is another file of the
    user's: never opened (reading one waits for a writer for ever), never removed."""
    import threading

    from firhc_jax.apps import _exported

    folder = tmp_path / "cache"
    kept = folder / _exported.FOLDER
    _kept_file(kept / f"{'a' * 64}.jaxexport", "hopper")
    pipes = [kept / f"{'b' * 64}.jaxexport", kept / ".tmp-abcdefgh.jaxexport", folder / _xla("jit_x", "3", "cache")]
    for pipe in pipes:
        os.mkfifo(pipe)
    listing = threading.Thread(target=_cache, args=(folder,), daemon=True)
    listing.start()
    listing.join(timeout=10)
    hung = listing.is_alive()
    while listing.is_alive():  # let the reader go: a writer opens the pipe it waits on, and closes it
        for pipe in pipes:
            try:
                os.close(os.open(pipe, os.O_WRONLY | os.O_NONBLOCK))
            except OSError:  # no reader on this one
                pass
        listing.join(timeout=1)
    assert not hung, "cache waited on a named pipe"
    listed = capsys.readouterr().out.splitlines()
    assert listed[1].startswith(f"kept decisions ({_exported.FOLDER}/): 1 files") and "hopper" in listed[2]
    assert listed[3:] == ["XLA's compilations: 0 entries, 0.0 kB", "other files, which --clear leaves: 3"]
    _cache(folder, "--clear")
    assert all(pipe.exists() for pipe in pipes) and not (kept / f"{'a' * 64}.jaxexport").exists()


def test_cache_lists_and_clears_the_file_of_a_run_stopped_while_writing_its_decision(tmp_path, monkeypatch,
                                                                                    capsys):
    """A run killed between writing its decision's temporary file and renaming it (here: the rename interrupted,
    the clean-up skipped, as a kill skips it) leaves that file; ``cache`` lists it and ``--clear`` removes it."""
    from firhc_jax.apps import _exported

    folder = tmp_path / "cache"
    kept = folder / _exported.FOLDER
    kept.mkdir(parents=True)

    def killed(*args):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(_exported.os, "replace", killed)
        m.setattr(_exported.os, "unlink", lambda path: None)
        with pytest.raises(KeyboardInterrupt):
            _exported._write(kept / f"{'a' * 64}.jaxexport", _exported.FORMAT + bytes(3000))
    left, = kept.iterdir()
    _cache(folder)
    listed = capsys.readouterr().out.splitlines()
    assert listed[1:] == [f"kept decisions ({_exported.FOLDER}/): 0 files, 0.0 kB",
                          "unfinished kept decisions (a run stopped while writing them): 1 files, 3.0 kB",
                          "XLA's compilations: 0 entries, 0.0 kB"]
    _cache(folder, "--clear")
    assert "and 1 unfinished" in capsys.readouterr().out and not left.exists()


def test_a_tilde_in_the_cache_folder_names_one_folder_for_the_runs_and_for_cache(tmp_path, monkeypatch, capsys):
    """``JAX_COMPILATION_CACHE_DIR="~/jc"`` (quoted, or from an env file: the shell left the ``~``): the runs' cache
    setup hands JAX the home folder's ``jc``, where ``cache`` lists and clears; no folder named ``~`` appears."""
    import jax
    from jax.experimental.compilation_cache import compilation_cache

    home, work = tmp_path / "home", tmp_path / "work"
    home.mkdir()
    work.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.chdir(work)
    before = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", "~/jc")  # as JAX_COMPILATION_CACHE_DIR sets it
    try:
        cli._use_compilation_cache()  # what a run does before its work
        used = jax.config.jax_compilation_cache_dir
        assert cli.main(["cache"]) == 0
    finally:
        jax.config.update("jax_compilation_cache_dir", before)
        compilation_cache.reset_cache()
    assert used == str(home / "jc")
    assert capsys.readouterr().out.splitlines()[0] == f"folder: {home / 'jc'}"
    assert not (work / "~").exists()


def test_cache_takes_no_no_cache_and_keeps_no_compilation(monkeypatch, capsys):
    monkeypatch.setattr(cli, "_use_compilation_cache", lambda: pytest.fail("the cache command enabled the cache"))
    message = _refused(capsys, cli.main, ["cache", "--no-cache"])
    assert "unrecognized arguments: --no-cache" in message


def test_the_profile_chart_says_what_its_red_bar_means(tmp_path, monkeypatch):
    from matplotlib.colors import to_rgba

    from firhc_jax._src.tools.profile import Profile

    rows = [{"setting": f"sdfs pop_width={k}", "solver": "sdfs", "solves_per_second": 100.0 * k, "states": 3,
             "seconds": 0.03 / k, "seconds_min": 0.03 / k, "seconds_max": 0.03 / k, "nodes": 300,
             "nodes_per_second": 1e4 * k, "fastest": k == 4, "default": k == 1, "within_noise": k == 4}
            for k in (1, 2, 4)]
    costs = [{"callable": "dynamics", "ns": 500.0, "ns_min": 450.0, "ns_max": 550.0, "children": 1024,
              "compile_s": 0.1}]
    fig = profile_app.figure(Profile(rows, costs, 3, 1.0, 2.0), "case")
    fig.savefig(tmp_path / "profile.png")
    fastest = {bar.get_facecolor() for bar in fig.axes[0].patches if bar.get_width() == 400.0}
    legends = fig.legends + [ax.get_legend() for ax in fig.axes if ax.get_legend()]
    assert len(legends) == 1
    entries = {t.get_text(): h.get_facecolor() for t, h in zip(legends[0].get_texts(), legends[0].legend_handles,
                                                                strict=True)}
    meaning = [text for text, color in entries.items() if to_rgba(color) in fastest]
    assert len(meaning) == 1 and "fastest" in meaning[0], entries


@pytest.mark.slow
def test_batch_float32_refuses_a_parameter_beyond_float32_in_one_line(tmp_path):
    """``batch --float32 --params`` with a finite float64 value float32 cannot hold: one line naming the
    parameters and the value, exit status not 0, nothing written (it was searched as inf and exited 0).
    A subprocess: ``--float32`` turns x64 off for the process."""
    (tmp_path / "fj_batch_array_user.py").write_text(BATCH_ARRAY_USER)
    np.save(tmp_path / "X0.npy", np.array([[0.0], [1.0]]))
    np.save(tmp_path / "P.npy", np.array([[1.0], [1e39]]))
    proc = subprocess.run([sys.executable, "-m", "firhc_jax", "batch", "--problem", "fj_batch_array_user:tracking",
                           "--states", "X0.npy", "--params", "P.npy", "--float32", "--out", "r.npz"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=600,
                          env=dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(ROOT)])))
    last = proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else ""
    assert proc.returncode != 0 and not (tmp_path / "r.npz").exists(), proc.stderr[-2000:]
    assert "1e+39" in last and "float32" in last and "params" in last and "Traceback" not in proc.stderr, proc.stderr
