"""The module paths of release 0.2 (``firhc_jax.sdfs``, ``firhc_jax.controller``, ...), importable for one
more release with a ``DeprecationWarning``.

An old path is served by a finder on ``sys.meta_path`` that answers for these names only: the module it
makes holds the names of the modules that replaced it. Importing a submodule normally binds it on its
package; the package's class refuses that for the names that are public functions (``fj.sdfs``,
``fj.exhaustive``, ``fj.profile``), so an old import never turns them into modules.
"""
from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import types
import warnings

# old module -> (the modules that hold its names now, the public place to use instead)
OLD_PATHS = {
    "batch": (("firhc_jax._src.search.batch",), "firhc_jax.solve_batch"),
    "cache": (("firhc_jax._src.runtime.memory_cache",), "firhc_jax.cache_info, clear_cache, set_cache_size"),
    "checks": (("firhc_jax._src.checks", "firhc_jax._src.problem.callables"), "firhc_jax"),
    "closed_loop": (("firhc_jax._src.control.closed_loop",), "firhc_jax.ClosedLoop"),
    "compilation_cache": (("firhc_jax._src.runtime.disk_cache",), "firhc_jax.enable_compilation_cache"),
    "controller": (("firhc_jax._src.control.controller",), "firhc_jax.FIRHC"),
    "controller_checks": (("firhc_jax._src.control.decision_checks", "firhc_jax._src.checks"), "firhc_jax.FIRHC"),
    "decision": (("firhc_jax._src.control.decision",), "firhc_jax.ControllerState, firhc_jax.StepInfo"),
    "exhaustive": (("firhc_jax._src.search.exhaustive", "firhc_jax._src.search.one_state"),
                   "firhc_jax.exhaustive, firhc_jax.solvers"),
    "linear": (("firhc_jax._src.problem.formulation",), "firhc_jax.discretize, product_controls, ..."),
    "linear_factor": (("firhc_jax._src.linear.factor",), "firhc_jax.LinearTracking"),
    "loop": (("firhc_jax._src.control.runner",), "firhc_jax.FIRHC.simulate"),
    "nodes": (("firhc_jax._src.search.nodes",), "firhc_jax.rollout_cost"),
    "pool": (("firhc_jax._src.search.pool",), "firhc_jax.solve_batch, firhc_jax.solvers"),
    "problem": (("firhc_jax._src.problem.problem", "firhc_jax._src.checks"), "firhc_jax.Problem"),
    "profile": (("firhc_jax._src.tools.profile",), "firhc_jax.profile"),
    "progress": (("firhc_jax._src.runtime.progress",), "the progress= arguments"),
    "result": (("firhc_jax._src.search.result",), "firhc_jax.SearchResult"),
    "sdfs": (("firhc_jax._src.search.sdfs", "firhc_jax._src.search.one_state"),
             "firhc_jax.sdfs, firhc_jax.solvers.stack_memory"),
    "sharding": (("firhc_jax._src.runtime.sharding",), "firhc_jax.distributed"),
    "stack": (("firhc_jax._src.search.stack",), "firhc_jax.sdfs"),
    "transforms": (("firhc_jax._src.problem.transforms",), "firhc_jax.with_input_memory"),
}


class _Finder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    def __init__(self, package: str):
        self.package = package

    def find_spec(self, fullname, path=None, target=None):
        head, _, name = fullname.rpartition(".")
        if head == self.package and name in OLD_PATHS:
            return importlib.machinery.ModuleSpec(fullname, self)
        return None

    def create_module(self, spec):
        return None

    def exec_module(self, module):
        name = module.__name__.rpartition(".")[2]
        sources, instead = OLD_PATHS[name]
        warnings.warn(f"{module.__name__} is deprecated and will be removed in the next release: use {instead}",
                      DeprecationWarning, stacklevel=2)
        for source in reversed(sources):
            module.__dict__.update({k: v for k, v in vars(importlib.import_module(source)).items()
                                    if not k.startswith("__")})


class _Package(types.ModuleType):
    """The package's module: a submodule import never rebinds a public function of the same name."""

    def __setattr__(self, name, value):
        if isinstance(value, types.ModuleType) and name in getattr(self, "__all__", ()) \
                and not isinstance(getattr(self, name, None), types.ModuleType):
            return
        super().__setattr__(name, value)


def install(package: str) -> None:
    """Serve ``package``'s old module paths, and keep its public functions bound."""
    sys.modules[package].__class__ = _Package
    if not any(isinstance(f, _Finder) and f.package == package for f in sys.meta_path):
        sys.meta_path.append(_Finder(package))
