"""The documentation matches the code: the README stays a front door, every public name has an API entry, the
solver page lists the solver table, user pages cite no issue numbers, and every ```python block of the README
and the docs runs as written (the long part, in the full suite). A block that cannot run here (a job of several
hosts) is fenced ```py instead."""
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
from reference import same_cost
from repository import DOCS, ROOT

import firhc_jax as fj

USER_PAGES = sorted(p for p in DOCS.rglob("*.md") if "dev" not in p.relative_to(DOCS).parts)
NAMESPACES = {"solvers": fj.solvers, "linear_tracking": fj.linear_tracking, "diagnostics": fj.diagnostics,
              "distributed": fj.distributed}


def _blocks(path: Path) -> list:
    return re.findall(r"```python\n(.*?)```", path.read_text(), re.S)


def _api_text() -> str:
    return "\n".join(p.read_text() for p in (DOCS / "api").glob("*.md"))


def test_the_readme_is_a_front_door():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 150 and len(text.split()) <= 1200
    for heading in ("## Features", "## Installation", "## Quick example", "## Command line", "## Documentation",
                    "## The paper", "## License"):
        assert heading in text, heading
    quick = _blocks(ROOT / "README.md")
    assert len(quick) == 1 and len(quick[0].splitlines()) <= 25
    assert not re.search(r"\d+(\.\d+)? ?(ms|us|µs) ", text), "timings belong on the performance page"


def test_every_public_name_has_an_api_entry():
    api = _api_text()
    for name in fj.__all__:
        if name in NAMESPACES or name == "diagnostics":
            continue
        assert f"::: firhc_jax.{name}\n" in api, name
    for space, module in NAMESPACES.items():
        for name in module.__all__:
            assert (f"::: firhc_jax.{space}.{name}" in api or f'"{name}"' in api
                    or f"::: firhc_jax.{name}\n" in api), f"firhc_jax.{space}.{name}"


def test_every_model_has_an_api_entry():
    api = _api_text()
    for module in (Path(fj.__file__).parent / "models").glob("*.py"):
        if not module.name.startswith("_"):
            assert f"::: firhc_jax.models.{module.stem}\n" in api, module.stem


def test_every_page_is_in_the_navigation():
    nav = (ROOT / "mkdocs.yml").read_text()
    for page in DOCS.rglob("*.md"):
        rel = page.relative_to(DOCS).as_posix()
        assert rel in nav, rel


def test_the_solver_page_lists_the_solver_table():
    """docs/guide/solvers.md has one row per solver, naming each of its options (the table is the source)."""
    text = (DOCS / "guide" / "solvers.md").read_text()
    rows = {m.group(1): m.group(0) for m in re.finditer(r"^\| `([a-z-]+)` \|.*$", text, re.M)}
    assert set(rows) == set(fj.solvers.SOLVERS), sorted(rows)
    for name, solver in fj.solvers.SOLVERS.items():
        for option in solver.options:
            assert f"`{option}" in rows[name], (name, option)
        yes = lambda flag: "yes" if flag else "no"  # noqa: E731
        assert rows[name].rstrip(" |").endswith(f"{yes(solver.budgets)}, {yes(solver.warm_starts)}"), name


def test_user_pages_cite_no_issue_numbers():
    for page in USER_PAGES + [ROOT / "README.md"]:
        hits = re.findall(r"[Ii]ssues? \d+", page.read_text())
        assert not hits, (page.name, hits)


# ------------------------------------------------------------------ the code blocks, as written


# Pages that show on purpose a closed loop compiled again for a new plant object, and how many times.
RECOMPILES_SHOWN = {"guide/caching.md": 1}


def _run_page(path: Path, namespace: dict) -> list:
    """The namespace after each block of ``path``, run in order in ``namespace`` (copies: later blocks rebind).
    A closed loop compiled again for a new plant object of the same code (the controller warns) is a mistake
    in an example, unless the page shows it on purpose (``RECOMPILES_SHOWN``)."""
    snapshots = []
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        for i, block in enumerate(_blocks(path)):
            exec(compile(block, f"{path.relative_to(ROOT)} python block {i}", "exec"), namespace)
            snapshots.append(dict(namespace))
    again = [w for w in said if "compiles its closed loop again" in str(w.message)]
    page = path.relative_to(DOCS).as_posix() if path.is_relative_to(DOCS) else path.name
    assert len(again) == RECOMPILES_SHOWN.get(page, 0), (page, [str(w.message) for w in again])
    return snapshots


@pytest.fixture(scope="module")
def tour():
    """Getting started's tour, which the guide's pages build on (a reader goes through it first)."""
    return _run_page(DOCS / "getting-started.md", {})


@pytest.fixture(scope="module")
def guide(tour):
    """The namespace a reader of the guide has: the tour's, then the parameters page's problems."""
    return _run_page(DOCS / "guide" / "parameters.md", dict(tour[-1]))


@pytest.mark.slow
def test_the_readme_example_runs_and_agrees(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the example saves its figure in the working folder
    ns = _run_page(ROOT / "README.md", {})[-1]
    assert float(ns["best"].cost) == float(ns["ref"].cost)
    assert int(ns["ref"].nodes) == ns["problem"].tree_size() > 10 * int(ns["best"].nodes)  # pruning shows
    assert (tmp_path / "pendulum.png").is_file()
    assert ns["run"].states.shape == (81, 2) and not bool(ns["run"].held.any())


@pytest.mark.slow
def test_the_tour_runs_and_agrees(tour):
    ns = tour[0]
    best, ref, run = ns["best"], ns["ref"], ns["run"]
    assert float(best.cost) == float(ref.cost)
    assert int(ref.nodes) == ns["problem"].tree_size()
    assert run.states.shape == (81, 2)
    rt = ns["rt"]  # the budgeted search: complete exactly when the full search fits the budget
    assert int(rt.nodes) <= 500 and bool(rt.complete) == (int(best.nodes) <= 500)


@pytest.mark.slow
@pytest.mark.parametrize("page", [p.relative_to(DOCS).as_posix() for p in USER_PAGES
                                  if _blocks(p) and p.name not in ("getting-started.md", "parameters.md")])
def test_every_python_block_of_the_guide_runs(page, guide):
    """Each page runs in a copy of the namespace the tour and the parameters page leave."""
    _run_page(DOCS / page, dict(guide[-1]))


@pytest.mark.slow
def test_parameters_and_batches_agree_with_the_tour(tour, guide):
    params = guide
    assert params[0]["run"].states.shape == (201, 2)  # the tracking loop, one decision per reference step
    switching = params[-1]["run"]
    assert switching.states.shape == (81, 2) and not np.any(np.isnan(np.asarray(switching.inputs)))
    batches = _run_page(DOCS / "guide" / "batches.md", dict(guide[-1]))
    ns = next(n for n in batches if "tracked" in n)
    assert same_cost(float(ns["res"].cost[-1]), float(tour[-1]["best"].cost))  # the last row is the tour's x0
    runs = next(n for n in batches if "batched" in n)["batched"]
    assert runs.states.shape == (33, 41, 2) and runs.plans.shape == (33, 40, 8)
    np.testing.assert_allclose(np.asarray(runs.states[-1]), np.asarray(tour[0]["run"].states[:41]),
                               rtol=1e-12, atol=1e-15)
    ns = next(n for n in batches if "X_T" in n)  # the self-contained block: exact per row, scan agrees
    ref = fj.solve_batch(ns["problem"], ns["X0"][:4], solver="exhaustive")
    np.testing.assert_allclose(np.asarray(ns["res"].cost[:4]), np.asarray(ref.cost), rtol=1e-12)
    assert ns["costs"].shape == (10, 256) and ns["tracked"].cost.shape == (256,)
    np.testing.assert_allclose(np.asarray(ns["costs"][0]), np.asarray(ns["res"].cost), rtol=1e-12)


def test_the_caching_page_names_every_part_of_a_controllers_key():
    """The key table names every field of a controller's options (the key is derived from all of them) and the
    plant of a compiled closed loop."""
    import dataclasses

    from firhc_jax._src.control.controller import Options

    rows = {line.split("|")[1].strip(): line for line in (DOCS / "guide" / "caching.md").read_text().splitlines()
            if line.startswith("| `")}
    step, loop = rows["`ctrl.step`, `ctrl(x)`, `ctrl.solve`"], rows["`ctrl.simulate` (compiled)"]
    words = {"problem": "the problem", "solver_options": "every solver option"}
    for field in dataclasses.fields(Options):
        assert words.get(field.name, f"`{field.name}`") in step, field.name
    assert "the plant, as an object" in loop


@pytest.mark.slow
def test_the_realtime_recipe_runs_its_loop_with_the_collector_paused(guide):
    """The real-time page's recipe: every plant write of its loop happens with the cyclic collector off, and the
    collector is back on after the loop."""
    import gc

    ns, seen = dict(guide[-1]), []
    dynamics = ns["dynamics"]
    ns["dynamics"] = lambda x, u: (seen.append(gc.isenabled()), dynamics(x, u))[1]  # what the page's write calls
    exec(compile(_blocks(DOCS / "guide" / "realtime.md")[0], "realtime.md python block 0", "exec"), ns)
    assert len(seen) == 80 and not any(seen) and gc.isenabled()
