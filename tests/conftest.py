"""How the suite runs: three commands (README, "Tests"; .ci/run runs all three).

* ``pytest`` (the quick suite): every test not marked ``slow``, float64 (x64 enabled here explicitly; the
  library never flips it), with XLA's optimizations off (``jax_disable_most_optimizations``) and XLA:CPU's
  older fusion emitters (``--xla_cpu_use_fusion_emitters=false``, added to ``XLA_FLAGS``, which the tests'
  subprocesses inherit): compiling is most of the suite's time, and each of the two roughly halves it
  (docs/guide/caching.md).
* ``pytest --float32``: only the tests marked ``float32``, with x64 left off (the library's default float32
  path), compiled as the quick suite.
* ``pytest --full``: the tests the quick suite leaves out, compiled as users compile (optimizations on): the
  ``slow`` ones (subprocesses, soaks, multi-process runs, sweeps, the applications, the examples and the
  documents' code) and the ones marked ``optimized`` (two compiled programs equal bit for bit, which rests on
  XLA's optimizations making them the same code). The quick suite and this one together run every test.

``-m EXPR`` picks its own tests, as usual: ``pytest --full -m "slow or not slow"`` runs every test compiled
with optimizations on (about twice the time of the two suites).

The suite keeps XLA's compilations in JAX's persistent compilation cache (``fj.enable_compilation_cache``), in
``$FIRHC_JAX_TEST_CACHE`` or else ``.jax_cache/`` at the repository's root: the workers of one run and later
runs compile each search once. ``FIRHC_JAX_TEST_CACHE=off`` compiles everything afresh.
"""
import os
from pathlib import Path

import jax


def pytest_addoption(parser):
    parser.addoption("--float32", action="store_true",
                     help="run the tests marked float32, with x64 off (the library's default path)")
    parser.addoption("--full", action="store_true",
                     help="the long checks the quick suite leaves out (slow, optimized), compiled with XLA's "
                          "optimizations on")


QUICK_XLA_FLAGS = "--xla_cpu_use_fusion_emitters=false"


def pytest_configure(config):
    if not config.getoption("--float32"):
        jax.config.update("jax_enable_x64", True)
    if not config.getoption("--full"):
        jax.config.update("jax_disable_most_optimizations", True)
        if QUICK_XLA_FLAGS not in os.environ.get("XLA_FLAGS", ""):  # XLA reads it as the CPU backend starts
            os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {QUICK_XLA_FLAGS}".strip()
    folder = os.environ.get("FIRHC_JAX_TEST_CACHE", str(Path(config.rootpath) / ".jax_cache"))
    if folder != "off":
        import firhc_jax as fj

        fj.enable_compilation_cache(folder)


def pytest_collection_modifyitems(config, items):
    if config.getoption("--float32"):
        keep = [item for item in items if item.get_closest_marker("float32")]
    elif config.getoption("markexpr"):
        return
    else:
        long = [bool(item.get_closest_marker("slow") or item.get_closest_marker("optimized")) for item in items]
        keep = [item for item, is_long in zip(items, long, strict=True) if is_long == config.getoption("--full")]
    config.hook.pytest_deselected(items=[item for item in items if item not in keep])
    items[:] = keep
