"""The command lines check their arguments before any work: an output folder that cannot be written, a horizon
too long for the example, a negative or NaN node budget end in argparse's one-line error (exit status 2)."""
import os
import subprocess
import sys

import pytest

from firhc_jax import cli
from firhc_jax.apps import bench, example, hopper, inverter, tanks

# Each command line with the function that starts its work, replaced in the tests below by one that fails: an
# argument refused after the work started fails the test even where the work would end in an error of its own.
COMMANDS = {
    "example": (["example"], example, "make_problem"),
    "hopper": (["hopper"], hopper, "simulate"),
    "tanks": (["tanks"], tanks, "simulate"),
    "inverter": (["inverter"], inverter, "closed_loop"),
    "bench tables": (["bench", "tables", "--quick", "--plants", "tanks"], bench, "tanks_case"),
    "bench throughput": (["bench", "throughput", "--quick"], bench, "synthetic_case"),
}


@pytest.fixture
def no_work(monkeypatch):
    """``run(command, *args)``: ``cli.main`` of the command with its work replaced by a failure."""
    def run(command, *args):
        argv, module, work = COMMANDS[command]

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
