"""The package's layout: public names re-exported from ``firhc_jax._src``, the old module paths of release 0.2
importable with a ``DeprecationWarning``, and public functions never rebound to modules."""
import ast
import importlib
import subprocess
import sys
import types
from pathlib import Path

import pytest

import firhc_jax as fj
from firhc_jax._src.old_paths import OLD_PATHS

PACKAGE = Path(fj.__file__).parent
NAMESPACES = ("solvers", "linear_tracking", "diagnostics", "distributed")


def test_the_public_names_are_kept():
    assert len(fj.__all__) == 33
    for name in fj.__all__:
        assert hasattr(fj, name), name
    for name in ("sdfs", "exhaustive", "profile"):
        assert callable(getattr(fj, name)) and not isinstance(getattr(fj, name), types.ModuleType), name


@pytest.mark.parametrize("path", ["__init__.py"] + [f"{n}.py" for n in NAMESPACES])
def test_public_modules_only_re_export(path):
    """The root and the public namespaces hold imports, ``__all__`` and the version, nothing else."""
    tree = ast.parse((PACKAGE / path).read_text())
    for node in tree.body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            continue
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant):  # the docstring
            continue
        if isinstance(node, ast.Assign) and {t.id for t in node.targets} <= {"__all__", "__version__"}:
            continue
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Call) and path == "__init__.py":
            continue  # serving the old module paths
        pytest.fail(f"{path} line {node.lineno} defines something: {ast.unparse(node)[:80]}")


def test_every_old_module_path_imports_with_a_deprecation_warning():
    """In a fresh interpreter: each import warns, each module holds names, and ``fj.sdfs``, ``fj.exhaustive``
    and ``fj.profile`` stay functions whatever is imported, in whichever form."""
    code = f"""
import importlib, sys, types, warnings
import firhc_jax as fj
for old in {sorted(OLD_PATHS)!r}:
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        module = importlib.import_module("firhc_jax." + old)
    assert any(w.category is DeprecationWarning and f"firhc_jax.{{old}} is deprecated" in str(w.message)
               for w in seen), old
    assert [k for k in vars(module) if not k.startswith("_")], old
    exec(f"import firhc_jax.{{old}}")
    exec(f"from firhc_jax.{{old}} import *")
    for name in ("sdfs", "exhaustive", "profile"):
        assert callable(getattr(fj, name)) and not isinstance(getattr(fj, name), types.ModuleType), (old, name)
print("ok")
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0 and "ok" in done.stdout, done.stderr[-3000:]


def test_old_paths_keep_their_names():
    sys.modules.pop("firhc_jax.sdfs", None), sys.modules.pop("firhc_jax.exhaustive", None)
    with pytest.warns(DeprecationWarning):
        old = importlib.import_module("firhc_jax.sdfs")
    assert old.stack_memory is fj.solvers.stack_memory
    with pytest.warns(DeprecationWarning):
        old = importlib.import_module("firhc_jax.exhaustive")
    assert old.memory is fj.solvers.exhaustive_memory
    assert callable(fj.sdfs) and callable(fj.exhaustive)


def test_private_modules_live_under_src():
    top = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert top == sorted(["__init__.py", "__main__.py", "cli.py"] + [f"{n}.py" for n in NAMESPACES]), top


# The private areas in dependency order: a module imports from its own area and those before it, never after.
ORDER = ("runtime", "jaxpr", "problem", "search", "control", "linear", "export", "tools")


@pytest.mark.parametrize("area", ORDER)
def test_no_private_area_imports_one_above_it(area):
    above = set(ORDER[ORDER.index(area) + 1:])
    wrong = []
    for path in sorted((PACKAGE / "_src" / area).glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level == 2 and node.module:
                if node.module.split(".")[0] in above:
                    wrong.append(f"{path.name}: from ..{node.module}")
    assert not wrong, wrong
