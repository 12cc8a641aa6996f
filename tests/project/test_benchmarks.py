"""Benchmarks that read the library's internals run end to end on a small size (a subprocess from the
repository's root, as the performance page's commands run them) and print their tables: those comparing
LinearTracking with the plain search of every input, the split of one eager decision (which finds each
call's compiled program where the lean path keeps it), the generated C against the Numba peer, and the derived
lower bound against a hand-written one (each asserts that every bound's decisions are exact). A change inside
cannot leave them broken unnoticed."""
import os
import subprocess
import sys

import pytest
from repository import BENCHMARKS, ROOT

pytestmark = pytest.mark.slow

RUNS = {  # script and a small size: what its table must show
    "classes_bench.py": (["--levels", "3", "--horizons", "1", "2", "--steps", "20", "--rounds", "1"],
                         ["19 of 3"]),
    "sphere_bench.py": (["--sections", "inverter", "thermal", "--horizons", "1", "2", "--steps", "20",
                         "--plain-until", "2", "--thermal-states", "2", "--thermal-horizon", "4",
                         "--thermal-max-nodes", "200000"],
                        ["plain sDFS", "LinearTracking"]),
    "call_bench.py": (["--calls", "20", "--rounds", "1"], ["## pinned to one core", "`lt.solve`", "compiled scan"]),
    "export_bench.py": (["--quick"], ["linear, 17 inputs", "| 1 | "]),
    "small_loops_bench.py": (["--quick"], ["| ctrl.step, inverter N = 3 (us) |", "solve_batch"]),
    "auto_bound_bench.py": (["--uc-horizon", "3", "--uc-steps", "3", "--band-horizon", "5", "--band-states", "4"],
                            ["## Unit commitment", "## Comfort band", "| auto |"]),
}


@pytest.mark.parametrize("script", sorted(RUNS))
def test_benchmark_runs_small(script):
    args, shows = RUNS[script]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    done = subprocess.run([sys.executable, str(BENCHMARKS / script), *args], capture_output=True, text=True,
                          env=env, cwd=ROOT, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    for text in shows:
        assert text in done.stdout, done.stdout
