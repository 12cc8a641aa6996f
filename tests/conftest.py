"""Tests run in float64 (x64 enabled here explicitly; the library never flips it).

``pytest --float32`` runs only the tests marked ``float32`` with x64 left off: the library's default
float32 path, on the exactness and budget properties.

Tests marked ``slow`` (subprocesses, soaks, multi-process runs, long sweeps, the applications' summaries) are
left out unless ``-m`` is given: ``pytest -m slow`` runs them, and with the plain run that is the full suite
(README, "Tests"; .ci/run runs every command).

The suite keeps XLA's compilations in JAX's persistent compilation cache (``fj.enable_compilation_cache``), in
``$FIRHC_JAX_TEST_CACHE`` or else ``.jax_cache/`` at the repository's root: the workers of one run and later runs
compile each search once. ``FIRHC_JAX_TEST_CACHE=off`` compiles everything afresh.
"""
import os
from pathlib import Path

import jax


def pytest_addoption(parser):
    parser.addoption("--float32", action="store_true",
                     help="run the tests marked float32, with x64 off (the library's default path)")


def pytest_configure(config):
    if not config.getoption("--float32"):
        jax.config.update("jax_enable_x64", True)
    folder = os.environ.get("FIRHC_JAX_TEST_CACHE", str(Path(config.rootpath) / ".jax_cache"))
    if folder != "off":
        import firhc_jax as fj

        fj.enable_compilation_cache(folder)


def pytest_collection_modifyitems(config, items):
    if config.getoption("--float32"):
        keep = [item for item in items if item.get_closest_marker("float32")]
    elif not config.getoption("markexpr"):
        keep = [item for item in items if not item.get_closest_marker("slow")]
    else:
        return
    config.hook.pytest_deselected(items=[item for item in items if item not in keep])
    items[:] = keep
