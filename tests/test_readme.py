"""The README's API tour runs as written."""
import re
from pathlib import Path

import jax.numpy as jnp
import pytest


def _blocks():
    text = (Path(__file__).parent.parent / "README.md").read_text()
    return re.findall(r"```python\n(.*?)```", text, re.S)


@pytest.fixture(scope="module")
def tour():
    """The names the tour (the first block) defines, run once for both tests."""
    namespace = {}
    exec(compile(_blocks()[0], "README.md", "exec"), namespace)
    return namespace


def test_readme_api_tour_runs(tour):
    best, ref, run = tour["best"], tour["ref"], tour["run"]
    assert float(best.cost) == float(ref.cost)
    assert int(ref.nodes) == tour["problem"].tree_size()
    assert run.states.shape == (81, 2)
    rt = tour["rt"]  # the budgeted search: complete exactly when the full search fits the budget
    assert int(rt.nodes) <= 500 and bool(rt.complete) == (int(best.nodes) <= 500)


def test_readme_parameter_and_switching_snippets_run(tour):
    """The tour's names, then the parameter and switching-penalty snippets, as written."""
    namespace = dict(tour)
    for i, block in enumerate(_blocks()[1:3], 1):
        exec(compile(block, f"README.md block {i}", "exec"), namespace)
    run = namespace["run"]  # the switching-penalty closed loop
    assert run.states.shape == (81, 2) and run.inputs.shape == (80, 1)
    assert not bool(jnp.any(jnp.isnan(run.inputs)))
