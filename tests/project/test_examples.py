"""Every script of ``examples/`` runs with ``--quick`` as a user runs it (a subprocess from the repository's
root), exits 0, prints its figures and writes the figure it promises."""
import os
import shutil
import subprocess
import sys

import pytest
from repository import ROOT

EXAMPLES = sorted(p.name for p in (ROOT / "examples").glob("*.py") if not p.name.startswith("_"))
PRINTS = {  # what each example reports, checked in its output
    "quickstart.py": "sDFS: cost", "tracking_reference.py": "rms angle error", "realtime_loop.py": "decisions: median",
    "monte_carlo.py": "pointing error median", "long_horizon_inverter.py": "one decision: J =",
    "profile_own_plant.py": "<- fastest", "c_controller.py": "differ from ctrl.step",
}
pytestmark = pytest.mark.slow


def test_every_example_is_listed():
    assert len(EXAMPLES) >= 5 and set(EXAMPLES) == set(PRINTS)


@pytest.mark.parametrize("name", EXAMPLES)
def test_example_runs_quick(name, tmp_path):
    if name == "c_controller.py" and shutil.which("cc") is None:
        pytest.skip("no C compiler (cc) on this machine: the example compiles a generated controller")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    done = subprocess.run([sys.executable, str(ROOT / "examples" / name), "--quick", "--out", str(tmp_path)],
                          capture_output=True, text=True, env=env, cwd=ROOT, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    assert PRINTS[name] in done.stdout, done.stdout
    if "wrote" in done.stdout:
        assert list(tmp_path.glob("*.png")), "the figure it reports is missing"
