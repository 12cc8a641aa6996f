"""The benchmarks' published tables (``benchmarks/_results.py``): what a script prints is what the performance
page includes, under a header that names the machine, the load and the command; nothing is written without
``--publish``."""
import sys

import pytest
from repository import BENCHMARKS

sys.path.insert(0, str(BENCHMARKS))
import _results  # noqa: E402


def test_published_keeps_what_was_printed_under_a_header(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(_results, "RESULTS", tmp_path / "results")
    with _results.published("demo", True, "python benchmarks/demo.py --publish"):
        print("| a | b |\n|---|---|\n| 1 | 2 |")
    text = (tmp_path / "results" / "demo.md").read_text()
    header, table = text.split("\n\n", 1)
    assert "`python benchmarks/demo.py --publish`" in header and "usable cores, jax" in header
    assert "load average" in header
    assert table == "| a | b |\n|---|---|\n| 1 | 2 |\n"
    assert "| 1 | 2 |" in capsys.readouterr().out  # still printed


def test_nothing_is_written_without_publish(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(_results, "RESULTS", tmp_path / "results")
    with _results.published("demo", False, "x"):
        print("table")
    assert not (tmp_path / "results").exists() and "table" in capsys.readouterr().out


def test_a_failed_run_publishes_nothing(tmp_path, monkeypatch):
    monkeypatch.setattr(_results, "RESULTS", tmp_path / "results")
    with pytest.raises(RuntimeError), _results.published("demo", True, "x"):
        print("half a table")
        raise RuntimeError("the benchmark broke")
    assert not (tmp_path / "results" / "demo.md").exists()
