"""Smoke test of ``python -m firhc_jax bench throughput --quick`` and of the tables' bookkeeping."""
import json
import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pytest
from repository import BENCHMARKS

import firhc_jax as fj
from firhc_jax.apps import bench


def _bench_quick(what: str, out) -> subprocess.CompletedProcess:
    """``python -m firhc_jax bench WHAT --quick --out OUT`` in a fresh process, checked to succeed."""
    proc = subprocess.run([sys.executable, "-m", "firhc_jax", "bench", what, "--quick", "--out", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc


@pytest.mark.slow
def test_throughput_quick_writes_tables_csv_and_plots(tmp_path):
    out = tmp_path / "bench"
    proc = _bench_quick("throughput", out)
    rows = json.loads((out / "throughput.json").read_text())
    searches = {r["search"] for r in rows}
    assert {"sdfs", "sdfs K=2", "exhaustive dfs", "exhaustive levels", "vmap sdfs"} <= searches
    profile, sweep = [r for r in rows if "nodes_per_s" in r], [r for r in rows if "ms_per_step" in r]
    assert profile and all(r["nodes_per_s"] > 0 for r in profile)
    assert {r["N"] for r in sweep} == {2, 3} and all(r["ms_per_step"] > 0 for r in sweep)
    for name in ("throughput.md", "throughput.csv", "throughput.png", "time_vs_horizon.png"):
        assert (out / name).stat().st_size > 0
    assert "synthetic(work=0) N = 3: sdfs K=2 (compiling, then 1 x 4 searches): done in" in proc.stderr
    assert (out / "throughput.md").read_text().startswith(f"**{bench.SMOKE}.**") and bench.SMOKE in proc.stdout


@pytest.mark.slow
def test_tables_quick_is_table_3_at_one_horizon_with_every_stage_announced(tmp_path):
    out = tmp_path / "tables"
    proc = _bench_quick("tables", out)
    rows = json.loads((out / "tables.json").read_text())
    assert [(r["plant"], r["N"], r["best_pop_width"]) for r in rows] == [("tanks", 3, 1)]
    text = (out / "tables.md").read_text()
    assert text.startswith(f"{bench.SMOKE}.") and "### Table 3: three tanks, 20 s closed loop" in text
    for stage in ("tanks N = 3: the closed loop that gives the states searched",
                  "tanks N = 3: sdfs warm (compiling", "tanks N = 3: exhaustive levels (compiling"):
        assert stage in proc.stderr, proc.stderr[-2000:]


def test_exhaustive_subset_respects_the_node_budget():
    case = bench.synthetic_case(3, count=40)
    rows = bench.subset(case, max_nodes=case.problem.tree_size() * 7.5)
    assert len(rows) == 7 and rows[0] == 0 and rows[-1] == 39
    assert len(bench.subset(case, max_nodes=case.problem.tree_size())) == 1
    assert len(bench.subset(case, max_nodes=case.problem.tree_size() - 1)) == 0  # one search alone is over budget


def _bounded_case(count: int) -> bench.Case:
    """A Table-2/3 row's case in miniature, like ``bench tables --bound``: a terminal set and an admissible
    bound that is +inf wherever the set is out of reach (x moves at most 1 a step), on a 39-node tree."""
    problem = fj.Problem(lambda x, u: x + u, np.array([[-1.0], [0.0], [1.0]]), lambda x, u: jnp.sum(x * x), 3,
                         terminal=lambda x: jnp.abs(x[0]) <= 0.5,
                         lower_bound=lambda x, s: jnp.where(jnp.abs(x[0]) - s > 0.5, jnp.inf, 0.0))
    return bench._case("toy", problem, np.linspace(1.0, 3.0, count)[:, None])


@pytest.mark.slow
def test_table_row_of_a_bounded_problem_times_full_exhaustive_searches():
    """The bound prunes sDFS only: both exhaustive searches visit all A nodes of every state (table_row asserts
    it, as in ``bench tables --bound``; exhaustive(method="dfs") once let a +inf bound prune)."""
    case = _bounded_case(3)
    row = bench.table_row(case, repeats=1, max_es_nodes=1e9, pop_widths=(1, 2))  # two widths: fewer compiles
    assert row["A"] == case.problem.tree_size() == 39 and row["es_steps"] == row["steps"] == 3
    assert row["B_min"] <= row["B_mean"] <= row["B_max"] < row["A"]
    assert 0 < row["C_dfs_pct"] and 0 < row["C_levels_pct"]
    assert row["best_pop_width"] in (1, 2)
    np.testing.assert_array_equal(case.reference.shape, (3, 3))


def test_table_row_without_exhaustive_searches_when_one_exceeds_the_budget():
    case = _bounded_case(2)
    row = bench.table_row(case, repeats=1, max_es_nodes=case.problem.tree_size() - 1, pop_widths=(1, 2))
    assert row["es_steps"] == 0 and row["steps"] == 2
    assert row["C_dfs_pct"] is None and row["C_levels_pct"] is None and row["dfs_ms"] is None
    assert 0 < row["sdfs_max_ms"] and row["best_pop_width"] in (1, 2)
    text = bench.tables_markdown([{**row, "plant": "tanks", "N": 9}])
    assert "| 9 | " in text and "over budget" in text


@pytest.mark.slow
def test_the_monte_carlo_bench_quick_makes_the_same_decisions_every_way():
    """``benchmarks/monte_carlo_bench.py --quick``: every way of batching closed loops runs, and each makes
    (d) simulate_batch's decisions, which fj.exhaustive confirms."""
    import re

    script = BENCHMARKS / "monte_carlo_bench.py"
    proc = subprocess.run([sys.executable, str(script), "--quick", "--repeats", "1"], capture_output=True,
                          text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = [line for line in proc.stdout.splitlines() if "against (d)" in line]
    assert len(lines) == 3 and all(" 0 of " in line for line in lines), lines
    worst = re.search(r"fj.exhaustive on \d+ decisions of \(d\): cost rel. diff. max ([0-9.e+-]+)", proc.stdout)
    assert worst and float(worst.group(1)) < 1e-9, proc.stdout[-1500:]


def _rows(plant="synthetic(work=0)"):
    """Rows of a quick throughput run, made up: every rate within one decade, as a smoke run's often are."""
    profile = [{"plant": plant, "N": 3, "search": search, "batch": b, "pop_width": k, "nodes_per_s": rate}
               for search, b, k, rate in (("sdfs", 1, 1, 1.3e5), ("sdfs K=2", 1, 2, 2.1e5),
                                          ("vmap sdfs", 1, 1, 1.1e5), ("vmap sdfs", 8, 1, 3.2e5),
                                          ("vmap exhaustive levels", 1, None, 2.5e5),
                                          ("vmap exhaustive levels", 8, None, 6.4e5))]
    sweep = [{"plant": plant, "N": n, "search": search, "ms_per_step": ms}
             for n, search, ms in ((2, "sdfs", 4.0), (3, "sdfs", 0.27), (2, "exhaustive dfs", 0.5),
                                   (3, "exhaustive dfs", 1.2), (2, "exhaustive levels", 0.3),
                                   (3, "exhaustive levels", 0.9))]
    return profile, sweep


@pytest.mark.parametrize("smoke", [False, True])
def test_throughput_figures_label_ticks_in_plain_numbers_and_smoke_runs_as_such(smoke, tmp_path, monkeypatch):
    """Counts on the x axes labelled by themselves ("2", not "2x10^0"), rates and times in plain numbers, and a
    smoke run's figures titled as one."""
    from firhc_jax.apps import _plot

    figures = []
    drawn = _plot.subplots
    monkeypatch.setattr(_plot, "subplots", lambda *a, **k: figures.append(drawn(*a, **k)) or figures[-1])
    paths = bench.plot_profile(*_rows(), tmp_path, smoke=smoke)
    assert [p.name for p in paths] == ["throughput.png", "time_vs_horizon.png"]
    labels = []
    for fig, _ in figures:
        for ax in fig.axes:
            for axis in (ax.xaxis, ax.yaxis):
                labels += [t.get_text() for t in axis.get_ticklabels(minor=False) + axis.get_ticklabels(minor=True)]
        title = fig._suptitle.get_text() if fig._suptitle else ""
        assert (bench.SMOKE in title) == smoke, title
    assert labels and not [t for t in labels if "times" in t or "^" in t or "$" in t], labels
    throughput = figures[0][0].axes
    assert [t.get_text() for t in throughput[0].xaxis.get_ticklabels()] == ["1", "2"]
    assert [t.get_text() for t in throughput[1].xaxis.get_ticklabels()] == ["1", "8"]
    assert {"200,000", "300,000"} <= set(labels)  # between the decades, in plain numbers


def test_a_quick_tables_run_is_labelled_a_smoke_run_under_its_own_length():
    row = {"plant": "tanks", "N": 3, "A": 5219, "B_max": 3145, "B_min": 51, "B_mean": 181.4, "C_dfs_pct": 10.0,
           "C_levels_pct": 9.0, "sdfs_ms": 0.6, "dfs_ms": 5.0, "levels_ms": 5.1, "us_per_iteration": 3.0,
           "warm_nodes_mean": 100.0, "warm_ms": 0.5, "best_pop_width": 1, "best_pop_width_ms": 0.6, "es_steps": 10,
           "steps": 10}
    quick = bench.tables_markdown([row], quick=True).splitlines()
    assert quick[:3] == ["### Table 3: three tanks, 20 s closed loop", "", f"**{bench.SMOKE}.**"]
    full = bench.tables_markdown([row])
    assert full.startswith("### Table 3: three tanks, 200 s closed loop\n") and "SMOKE" not in full
