"""The README's Python code runs as written: every ```python block, in order, in one namespace (a later block
may use what an earlier one defined, as a reader would)."""
import re
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from reference import same_cost

# One fixture runs every block of the README (about 30 s of compiling): the documents' examples are long checks.
pytestmark = pytest.mark.slow


def _blocks():
    text = (Path(__file__).parent.parent / "README.md").read_text()
    return re.findall(r"```python\n(.*?)```", text, re.S)


@pytest.fixture(scope="module")
def after():
    """The namespace after each block (copies: later blocks rebind names such as ``run``)."""
    namespace, snapshots = {}, []
    for i, block in enumerate(_blocks()):
        exec(compile(block, f"README.md python block {i}", "exec"), namespace)
        snapshots.append(dict(namespace))
    return snapshots


def test_every_python_block_runs(after):
    assert len(after) == len(_blocks()) >= 4


def test_readme_api_tour(after):
    tour = after[0]
    best, ref, run = tour["best"], tour["ref"], tour["run"]
    assert float(best.cost) == float(ref.cost)
    assert int(ref.nodes) == tour["problem"].tree_size()
    assert run.states.shape == (81, 2)
    rt = tour["rt"]  # the budgeted search: complete exactly when the full search fits the budget
    assert int(rt.nodes) <= 500 and bool(rt.complete) == (int(best.nodes) <= 500)


def test_readme_parameter_and_switching_snippets(after):
    assert after[1]["run"].states.shape == (201, 2)  # the tracking loop, one decision per reference step
    run = after[2]["run"]  # the switching-penalty closed loop
    assert run.states.shape == (81, 2) and run.inputs.shape == (80, 1)
    assert not bool(jnp.any(jnp.isnan(run.inputs)))


def test_readme_batched_closed_loops(after):
    ns = next(n for n in after if "batched" in n)
    runs, run = ns["batched"], after[0]["run"]
    assert runs.states.shape == (33, 41, 2) and runs.plans.shape == (33, 40, 8)
    # loop 32 is x0's (to the last bits: XLA vectorises the batched program its own way)
    np.testing.assert_allclose(np.asarray(runs.states[-1]), np.asarray(run.states[:41]), rtol=1e-12, atol=1e-15)


def test_readme_batched_search(after):
    ns = next(n for n in after if "tracked" in n)
    res, tracked = ns["res"], ns["tracked"]
    assert res.cost.shape == tracked.cost.shape == (16,)
    assert same_cost(float(res.cost[-1]), float(ns["best"].cost))  # the last row is the tour's x0
    assert np.all(np.isfinite(np.asarray(tracked.cost)))  # tracking has no terminal set: every row feasible
