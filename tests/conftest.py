"""How the suite runs: three commands (README, "Tests"; .ci/run runs all three).

* ``pytest`` (the quick suite): every test not marked ``slow``, float64 (x64 enabled here explicitly; the
  library never flips it), with XLA's optimizations off (``jax_disable_most_optimizations``): compiling is
  most of the suite's time and takes about half as long without them.
* ``pytest --float32``: only the tests marked ``float32``, with x64 left off (the library's default float32
  path), optimizations off as above.
* ``pytest --full``: every test, ``slow`` ones too (subprocesses, soaks, multi-process runs, sweeps, the
  applications' summaries), compiled as users compile (optimizations on). The tests marked ``optimized``
  (two compiled programs equal bit for bit, which rests on XLA's optimizations making them the same code) run
  only here.

``-m EXPR`` picks its own tests, as usual. The suite keeps XLA's compilations in JAX's persistent compilation
cache (``fj.enable_compilation_cache``), in ``$FIRHC_JAX_TEST_CACHE`` or else ``.jax_cache/`` at the
repository's root: the workers of one run and later runs compile each search once.
``FIRHC_JAX_TEST_CACHE=off`` compiles everything afresh.
"""
import os
from pathlib import Path

import jax


def pytest_addoption(parser):
    parser.addoption("--float32", action="store_true",
                     help="run the tests marked float32, with x64 off (the library's default path)")
    parser.addoption("--full", action="store_true",
                     help="the full suite: the slow tests too, compiled with XLA's optimizations on")


def pytest_configure(config):
    if not config.getoption("--float32"):
        jax.config.update("jax_enable_x64", True)
    if not config.getoption("--full"):
        jax.config.update("jax_disable_most_optimizations", True)
    folder = os.environ.get("FIRHC_JAX_TEST_CACHE", str(Path(config.rootpath) / ".jax_cache"))
    if folder != "off":
        import firhc_jax as fj

        fj.enable_compilation_cache(folder)


def pytest_collection_modifyitems(config, items):
    if config.getoption("--float32"):
        keep = [item for item in items if item.get_closest_marker("float32")]
    elif not (config.getoption("--full") or config.getoption("markexpr")):
        keep = [item for item in items
                if not (item.get_closest_marker("slow") or item.get_closest_marker("optimized"))]
    else:
        return
    config.hook.pytest_deselected(items=[item for item in items if item not in keep])
    items[:] = keep
