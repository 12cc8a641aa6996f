"""``fj.export_c``: a problem's search, or a controller's decision, as plain C99 with no Python and no XLA.

The callables are translated from their jaxprs (``c_code``); the search is the template ``search.c``, the
library's searches of one state (the solvers' ``search``) rule for rule. The callables are traced in the
session's types (float64 with x64 enabled, else float32) and computed in them; the generated functions take and
return ``double`` states, parameters and inputs. No JAX setting is changed: a trace under a temporary x64
setting would leave JAX's caches of the user's jitted functions with constants of the wrong type
(docs/dev/xla_notes.md).
Memory is sized at export: ``NAME_solve`` and ``NAME_step`` keep their work arrays on the C stack
(``NAME_work_bytes()``), allocate nothing and need only libm.
"""
from __future__ import annotations

import ctypes
import dataclasses
import math
from pathlib import Path
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from ..checks import check_params
from ..control.controller import FIRHC
from ..control.decision import budget_of
from ..linear.tracking import LinearTracking
from ..problem.callables import check_state
from ..problem.problem import Problem, call, input_dtype
from ..search import exhaustive, solvers
from ..search.nodes import one_child
from ..search.sdfs import INT32_MAX, node_budget
from .c_code import PRELUDE, c_type, literal, primitives, translate, translate_children

TYPES, SEARCH = (Path(__file__).parent / "search.c").read_text().split(
    "/* @functions: the generated callables go above this line */")
MAX_STATE_SEARCH = 256  # state sizes tried when the state size is inferred from the callables

# Return codes of NAME_solve and NAME_step (documented in the header and docs/guide/deploy.md).
CODES = {"FOUND": 1, "FALLBACK": 2, "NONE": 0, "BAD_STATE": -1, "BAD_PARAMS": -2, "NEGATIVE_COST": -3}

# NAME_state, field by field: (name, C type, length (0: a scalar, "m" or "N"), comment). What the next
# decision needs, then the last decision's report: FIRHC.step's StepInfo and the deciding SearchResult, in their
# types (int32 counts, one-byte flags), so that NumPy reads them in place.
STATE_FIELDS = (
    ("u", "double", "m", "the searched input applied last"),
    ("plan", "int32_t", "N", "the last decision's sequence, -1: none"),
    ("budget", "int32_t", 0, "node budget of a decision (2^31 - 1: none)"),
    ("nodes", "int32_t", 0, "last decision: nodes of the terminal-constrained search"),
    ("fallback_nodes", "int32_t", 0, "last decision: nodes of the fallback search"),
    ("iterations", "int32_t", 0, "last decision: nodes expanded, both searches"),
    ("result_nodes", "int32_t", 0, "last decision: nodes of the deciding search"),
    ("cost", "double", 0, "last decision: the deciding search's cost (+inf: none)"),
    ("stage_cost", "double", 0, "last decision: the model's stage cost of the applied step (NaN: held)"),
    ("first_input", "double", "m", "last decision: the deciding search's input (NaN: none)"),
    ("sequence", "int32_t", "N", "last decision: the deciding search's sequence (-1: none)"),
    ("complete", "unsigned char", 0, "last decision: every search ran to the end"),
    ("used_fallback", "unsigned char", 0, "last decision: the input came from the fallback search"),
    ("feasible", "unsigned char", 0, "last decision: the terminal-constrained search found a sequence"),
    ("result_feasible", "unsigned char", 0, "last decision: the deciding search found a sequence"),
    ("held", "unsigned char", 0, "last decision: no input found, the safe input was applied"),
    ("negative_cost", "unsigned char", 0, "last decision: a negative stage or terminal cost was computed"),
    ("nan_encountered", "unsigned char", 0, "last decision: a non-finite state or NaN cost was met (discarded)"),
    ("overflow", "unsigned char", 0, "last decision: a finite cost plus a finite stage cost overflowed"),
)
# NAME_result, field by field (as STATE_FIELDS): fj.sdfs's SearchResult, what NAME_search writes.
RESULT_FIELDS = (
    ("cost", "double", 0, "the optimal cost (+inf: none)"),
    ("first_input", "double", "m", "the input to apply (NaN: none)"),
    ("sequence", "int32_t", "N", "the optimal input indices (-1: none)"),
    ("nodes", "int32_t", 0, "nodes computed (a seed's included)"),
    ("iterations", "int32_t", 0, "nodes expanded"),
    ("feasible", "unsigned char", 0, "a sequence meets the terminal set and the constraints"),
    ("complete", "unsigned char", 0, "the search ran to the end (not stopped by the budget): optimal"),
    ("negative_cost", "unsigned char", 0, "a negative stage or terminal cost was computed"),
    ("nan_encountered", "unsigned char", 0, "a non-finite state or NaN cost was met (discarded)"),
    ("overflow", "unsigned char", 0, "a finite cost plus a finite stage cost overflowed"),
)
_CTYPES = {"double": ctypes.c_double, "int32_t": ctypes.c_int32, "unsigned char": ctypes.c_ubyte}
_NUMPY = {"double": np.float64, "int32_t": np.int32, "unsigned char": np.bool_}


def _struct(fields, m: int, N: int) -> type:
    """A ``ctypes.Structure`` of ``fields`` (``STATE_FIELDS``, ``RESULT_FIELDS``): the C compiler's layout."""
    size = {"m": m, "N": N}
    return type("Struct", (ctypes.Structure,), {"_fields_": [
        (name, _CTYPES[kind] * size[length] if length else _CTYPES[kind]) for name, kind, length, _ in fields]})


def _record(fields, m: int, N: int) -> np.dtype:
    """The NumPy record of the same layout as ``_struct``, its flags as ``bool``."""
    struct, size = _struct(fields, m, N), {"m": m, "N": N}
    return np.dtype({"names": [f[0] for f in fields],
                     "formats": [(_NUMPY[kind], (size[length],)) if length else _NUMPY[kind]
                                 for _, kind, length, _ in fields],
                     "offsets": [getattr(struct, f[0]).offset for f in fields],
                     "itemsize": ctypes.sizeof(struct)})


def state_struct(m: int, N: int) -> type:
    """``NAME_state`` as a ``ctypes.Structure``."""
    return _struct(STATE_FIELDS, m, N)


def state_dtype(m: int, N: int) -> np.dtype:
    """``NAME_state`` as a NumPy record (``FIRHC(engine="c")`` reads its outputs from it in place)."""
    return _record(STATE_FIELDS, m, N)


def result_dtype(m: int, N: int) -> np.dtype:
    """``NAME_result`` as a NumPy record (``fj.sdfs(engine="c")`` reads its result from it in place)."""
    return _record(RESULT_FIELDS, m, N)


def typedef(fields, name: str, m: int, N: int) -> str:
    """The C typedef ``name`` of ``fields``."""
    size = {"m": m, "N": N}
    lines = [f"    {kind} {field}{f'[{size[length]}]' if length else ''};  /* {comment} */"
             for field, kind, length, comment in fields]
    return "typedef struct {\n" + "\n".join(lines) + f"\n}} {name};\n\n"


@dataclasses.dataclass
class Exported:
    """What ``export_c`` wrote: the paths, the sizes, and the bytes the generated functions need."""

    header: Path
    source: Path
    name: str
    state_size: int  # n, the model's state
    plant_state_size: int  # the state NAME_step takes (observe's input)
    input_size: int  # m, an input of the control set
    plant_input_size: int  # the input NAME_step writes (actuate's output)
    horizon: int
    num_controls: int
    num_params: int  # doubles in the flat params vector
    work_bytes: int  # NAME_work_bytes(): the search's arrays on the C stack
    state_bytes: int  # sizeof(NAME_state), 0 for a problem

    def compile(self, *, cc: str = "cc", flags=("-O2",)) -> "Compiled":
        """Compile the two files into a shared library beside them and load it through ``ctypes``: the
        generated functions called from Python, for checks and timings. A ``RuntimeError`` carries the
        compiler's message."""
        return compile_shared(self, cc=cc, flags=flags)


def export_c(problem_or_controller, directory, *, name: str = "firhc", params=None, x0=None,
             max_nodes: Optional[int] = None) -> Exported:
    """Write ``name.h`` and ``name.c``: C99 for the exact search of a ``Problem`` or the decision of a
    ``FIRHC``, equal to ``fj.sdfs`` (and ``ctrl.step``, whatever its solver).

    Args:
      problem_or_controller: an ``fj.Problem`` (generates ``NAME_solve`` and ``NAME_search``, ``fj.sdfs`` at
        ``pop_width=1``), an ``fj.FIRHC`` (also ``NAME_init`` and ``NAME_step``, its solver and options), or an
        ``fj.LinearTracking``: its controller ``FIRHC(lt.problem, observe=lt.observe, warm_start=True)``
        (with ``max_nodes``), whose parameters are the raw data ``(y_ref [N, p], d [N, n])``, mapped in the
        generated code as ``lt.params`` maps them (``params``: that pair, default zeros), and ``NAME_track``,
        ``lt.solve``.
      directory: where the two files go (created if missing).
      name: the C prefix of every public symbol, a C identifier.
      params: an example of the problem's parameter pytree (shapes and dtypes are compiled in; the C code
        takes its values flattened as ``jax.flatten_util.ravel_pytree`` flattens them); None without.
      x0: an example state ``[n]`` (of the plant, for a controller with ``observe``); default: the size is
        found from the callables, and a ``ValueError`` asks for ``x0`` where several sizes fit.
      max_nodes: a node budget for ``NAME_solve`` (a ``Problem`` only; a controller's is its own).

    Returns an ``Exported`` with the paths and the memory the generated functions need. Refused with a
    ``ValueError`` naming the cause: a primitive the C translation does not cover (named, with the callable
    it is in), a callable ``warm_start``.
    """
    return export(problem_or_controller, directory, name=name, params=params, x0=x0, max_nodes=max_nodes)


def export(problem_or_controller, directory, *, name: str = "firhc", params=None, x0=None,
           max_nodes: Optional[int] = None, for_engine: bool = False, pop_width: int = 1) -> Exported:
    """``export_c``; ``pop_width``: a problem's search's (``fj.sdfs``'s). ``for_engine``: the children in the forms
    of the ``"c"`` engine, which compiles with
    ``-O3`` and the target's vector instructions for this process: a problem whose child is a loop (its plant's
    sub-steps) computes its children operation by operation across the control set
    (``translate_children(across=True)``, slower at ``-O2``); any other computes what a child derives from its
    input alone at export, into tables (``translate_children(rows=)``: static data a small target may not
    want)."""
    if not (isinstance(name, str) and name.isidentifier() and name.isascii()):
        raise ValueError(f"name must be a C identifier (letters, digits, _), got {name!r}")
    prepare = tracker = None
    if isinstance(problem_or_controller, LinearTracking):
        tracker = problem_or_controller
        x0 = np.zeros(tracker.n) if x0 is None else x0
        problem_or_controller, params, prepare = _tracking(tracker, params, max_nodes)
        max_nodes = None
    controller = problem_or_controller if isinstance(problem_or_controller, FIRHC) else None
    problem = controller.problem if controller else problem_or_controller
    if not isinstance(problem, Problem):
        raise TypeError(f"export_c takes a firhc_jax.Problem or FIRHC, got {type(problem_or_controller).__name__}")
    if controller is not None:
        _check_controller(controller)
        if max_nodes is not None:
            raise TypeError("max_nodes is the controller's own (FIRHC(..., max_nodes=)); give it for a Problem only")
    solver = (controller.options.solver, controller.options.search_options) if controller else \
        ("sdfs", {"pop_width": pop_width})
    return _write(problem, controller, Path(directory).expanduser(), name, params, x0, max_nodes, prepare,
                  for_engine, tracker, solver)


def _tracking(lt: LinearTracking, data, max_nodes):
    """``(controller, raw data, map)`` of a ``LinearTracking`` export: the data ``(y_ref, d)``."""
    N, p_out, n = lt.horizon, lt.C.shape[0], lt.n
    if data is None:
        data = (np.zeros((N, p_out)), np.zeros((N, n)))
    if not (isinstance(data, tuple) and len(data) == 2):
        raise TypeError("params of a LinearTracking export is the pair (y_ref [N, p], d [N, n])")
    y_ref, d = (np.asarray(a, np.float64) for a in data)
    if y_ref.shape != (N, p_out) or d.shape != (N, n):
        raise ValueError(f"params must be (y_ref [N, p] = [{N}, {p_out}], d [N, n] = [{N}, {n}]), got shapes "
                         f"{y_ref.shape} and {d.shape}")
    budget = {} if max_nodes is None else {"max_nodes": max_nodes}
    ctrl = FIRHC(lt.problem, observe=lt.observe, warm_start=True, **budget)
    return ctrl, (y_ref, d), lambda raw: lt.params(raw[0], raw[1])


def _check_controller(ctrl: FIRHC) -> None:
    if callable(ctrl.options.warm_start):
        raise ValueError("a callable warm_start is Python; the C export takes warm_start=True or False")


class _Unit:
    """The translation unit being written: tables, functions, and the params' layout."""

    def __init__(self, problem: Problem, params, n: int):
        self.tables: dict = {}
        self.functions: list[str] = []
        self.n, self.m = n, problem.input_dim
        leaves, self.treedef = jax.tree_util.tree_flatten(params)
        self.leaves = [jnp.asarray(leaf) for leaf in leaves]
        self.specs = [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in self.leaves]
        self.has_params = params is not None
        self.controller = False
        self.raw_specs = None  # the parameters the C code takes, when a map fills the callables' (prepare)
        self.for_engine = False  # the "c" engine's forms of the children (export)
        self.solver: tuple = ("sdfs", {"pop_width": 1})  # the solver's name and its search options (export)

    def p(self, leaves):
        return jax.tree_util.tree_unflatten(self.treedef, leaves) if self.has_params else None

    @property
    def p_names(self) -> list[str]:
        return [f"p{i}" for i in range(len(self.specs))]

    def p_args(self, prefix: str = "p->") -> str:
        return "".join(f", {prefix}{n}" for n in self.p_names)

    def prepare(self, fn, raw) -> None:
        """The C code takes ``raw`` (flattened) and fills the callables' parameters with ``fn(raw)``."""
        leaves, tree = jax.tree_util.tree_flatten(raw)
        self.raw_specs = [jax.ShapeDtypeStruct(np.shape(a), jnp.result_type(a)) for a in leaves]
        names = [f"r{i}" for i in range(len(leaves))]
        self.functions.append(translate(
            "fj_prepare", lambda *r: jax.tree_util.tree_leaves(fn(jax.tree_util.tree_unflatten(tree, r))),
            self.raw_specs, names, [c_type(s.dtype) for s in self.specs], self.tables, "the parameter map"))

    def add(self, fn_name, fn, specs, names, out_types, where):
        self.functions.append(translate(fn_name, fn, list(specs) + self.specs, list(names) + self.p_names,
                                        out_types, self.tables, where))


def _real():
    """The session's float: the generated code computes the callables in it (float64 with x64 enabled)."""
    return jax.dtypes.canonicalize_dtype(np.float64)


def _x(n):
    return jax.ShapeDtypeStruct((n,), _real())


def _variant(unit: _Unit, problem: Problem, tag: str, controls: str, drop=()) -> str:
    """The C functions of one problem (the main one or a fallback) and its ``fj_problem``; returns its name."""
    n, m, N = unit.n, problem.input_dim, problem.horizon
    u_spec = jax.ShapeDtypeStruct((m,), problem.controls.dtype)
    k_spec = jax.ShapeDtypeStruct((), jnp.int32)
    forms = f"of the problem{'' if tag == 'main' else ' ' + tag}"

    def child(x, u, k, *leaves):
        x_next, stage, allowed = one_child(problem, x, u, k, unit.p(leaves))
        return x_next, stage, allowed

    def culprit(primitive: str) -> str:
        parts = {"dynamics": lambda x, u, k, p: problem.next_state(x, u, k, p),
                 "stage_cost": lambda x, u, k, p: problem.cost_of_step(x, problem.next_state(x, u, k, p), u, k, p),
                 "constraint": lambda x, u, k, p: problem.allowed(x, problem.next_state(x, u, k, p), u, k, p)}
        args = (_x(n), u_spec, k_spec, unit.p(unit.specs))
        for field, fn in parts.items():
            if primitive in primitives(jax.make_jaxpr(fn)(*args)):
                return f"{field} {forms}"
        return f"dynamics, stage_cost or constraint {forms}"

    unit.add(f"fj_{tag}_child_raw", child, [_x(n), u_spec, k_spec], ["x", "u", "k"],
             ["double", "double", "unsigned char"], culprit)
    specs = [_x(n), u_spec, k_spec] + unit.specs
    across = unit.for_engine and bool({"while", "scan"} & primitives(jax.make_jaxpr(child)(*specs)))
    unit.functions.append(translate_children(
        f"fj_{tag}_children_raw", child, specs, ["x", "u", "k"] + unit.p_names, controls, problem.num_controls,
        ["double", "double", "unsigned char"], unit.tables, culprit, across=across,
        rows=np.asarray(problem.controls) if unit.for_engine and not across else None))
    unit.functions.append(
        f"static void fj_{tag}_child(const double *x, int input, int32_t k, const fj_params *p, double *x_next, "
        f"double *stage, unsigned char *allowed) {{\n"
        f"    fj_{tag}_child_raw(x, &{controls}[input * {m}], &k{unit.p_args()}, x_next, stage, allowed);\n}}\n"
        f"static void fj_{tag}_children(const double *x, int32_t k, const fj_params *p, double *xs, "
        f"double *stage, unsigned char *allowed) {{\n"
        f"    fj_{tag}_children_raw(x, &k{unit.p_args()}, xs, stage, allowed);\n}}\n")
    fields = {"terminal": "NULL", "terminal_cost": "NULL", "lower_bound": "NULL"}
    scalar = {"terminal": "unsigned char", "terminal_cost": "double", "lower_bound": "double"}
    for field in fields:
        fn = getattr(problem, field)
        if fn is None or field in drop:
            continue
        if field == "lower_bound":
            unit.add(f"fj_{tag}_{field}_raw", lambda x, s, *leaves, fn=fn: call(fn, unit.p(leaves), x, s),
                     [_x(n), k_spec], ["x", "s"], [scalar[field]], f"{field} {forms}")
            unit.functions.append(
                f"static double fj_{tag}_{field}(const double *x, int32_t s, const fj_params *p) {{\n"
                f"    double r; fj_{tag}_{field}_raw(x, &s{unit.p_args()}, &r); return r;\n}}\n")
        else:
            unit.add(f"fj_{tag}_{field}_raw", lambda x, *leaves, fn=fn: call(fn, unit.p(leaves), x),
                     [_x(n)], ["x"], [scalar[field]], f"{field} {forms}")
            unit.functions.append(
                f"static {scalar[field]} fj_{tag}_{field}(const double *x, const fj_params *p) {{\n"
                f"    {scalar[field]} r; fj_{tag}_{field}_raw(x{unit.p_args()}, &r); return r;\n}}\n")
        fields[field] = f"fj_{tag}_{field}"
    # The input to apply for a sequence: first_input_of, or the sequence's first row of the control set.
    if problem.first_input_of is not None:
        def first(x0, seq, *leaves):
            return problem.first_input(x0, seq, unit.p(leaves))
        unit.add(f"fj_{tag}_first_input_raw", first, [_x(n), jax.ShapeDtypeStruct((N,), jnp.int32)],
                 ["x0", "seq"], ["double"], f"first_input_of {forms}")
        body = f"fj_{tag}_first_input_raw(x0, seq{unit.p_args()}, u);"
    else:
        body = f"for (int j = 0; j < {m}; j++) u[j] = (double){controls}[seq[0] * {m} + j];"
    unit.functions.append(f"static void fj_{tag}_first_input(const double *x0, const int32_t *seq, "
                          f"const fj_params *p, double *u) {{\n    {body}\n}}\n")
    constrained = int(problem.constraint is not None)
    unit.functions.append(
        f"static const fj_problem fj_{tag} = {{fj_{tag}_children, fj_{tag}_child, {fields['terminal']}, "
        f"{fields['terminal_cost']}, {fields['lower_bound']}, {constrained}, {_exhaustive(unit, problem)}}};\n")
    return f"fj_{tag}"


def _exhaustive(unit: _Unit, problem: Problem) -> str:
    """``fj_problem``'s ``exhaustive, level_iterations`` for the unit's solver: which search ``solvers``'s
    ``"exhaustive"`` runs on ``problem`` (the level search, or where XLA:CPU cannot compile it the sDFS with
    pruning off) and the level search's batched calls."""
    name, options = unit.solver
    if name != "exhaustive":
        return "0, 0"
    x = jax.ShapeDtypeStruct((unit.n,), _real())
    if options["method"] == "dfs" or exhaustive.levels_executable(problem, x, unit.p(unit.specs),
                                                                   options["chunk_nodes"]) is None:
        return "2, 0"
    split, _, chunks = exhaustive.plan(problem, options["chunk_nodes"])
    return f"1, {split + chunks * (problem.horizon - split)}"


def _controls_table(unit: _Unit, problem: Problem, tag: str) -> str:
    c = problem.controls
    items = ", ".join(literal(v, c.dtype) for v in c.reshape(-1))
    unit.functions.append(f"static const {c_type(c.dtype)} fj_{tag}_controls[{c.size}] = {{{items}}};\n")
    return f"fj_{tag}_controls"


def state_size(problem: Problem, params, x0, observe=None) -> tuple[int, int]:
    """``(n, n_plant)``: the model's state size and the plant's (what ``observe`` takes): ``x0``'s, or the
    sizes at which the callables trace and keep the state's shape."""
    u = jnp.zeros((problem.input_dim,), input_dtype(problem))

    def model_fits(n):
        try:
            x = _x(n)
            out = jax.eval_shape(lambda x: problem.next_state(x, problem.controls[0], 0, params), x)
            jax.eval_shape(lambda x: problem.cost_of_step(x, x, problem.controls[0], 0, params), x)
            for fn in (problem.terminal, problem.terminal_cost):
                if fn is not None:
                    jax.eval_shape(lambda x, fn=fn: call(fn, params, x), x)
            return out.shape == (n,)
        except Exception:  # noqa: BLE001 - a size the callables reject
            return False

    def observed(n_plant):
        try:
            return jax.eval_shape(lambda x: call(observe, params, x, u), _x(n_plant)).shape
        except Exception:  # noqa: BLE001
            return None

    if x0 is not None:
        x0 = np.asarray(x0, np.float64)
        if x0.ndim != 1:
            raise ValueError(f"x0 must be a state [n], got shape {x0.shape}")
        if observe is None:
            return x0.shape[0], x0.shape[0]
        shape = observed(x0.shape[0])
        if shape is None or len(shape) != 1:
            raise ValueError(f"observe does not map a plant state of shape {x0.shape} to a state [n]")
        return shape[0], x0.shape[0]
    if observe is None:
        fits = [n for n in range(1, MAX_STATE_SEARCH + 1) if model_fits(n)]
    else:
        fits = [n for n in range(1, MAX_STATE_SEARCH + 1)
                if (s := observed(n)) is not None and len(s) == 1 and model_fits(s[0])]
    if len(fits) != 1:
        found = "no size" if not fits else f"several sizes ({', '.join(map(str, fits[:5]))}, ...)"
        raise ValueError(f"the state size could not be found from the callables ({found} of 1..{MAX_STATE_SEARCH} "
                         "fit): pass an example state, export_c(..., x0=...)")
    if observe is None:
        return fits[0], fits[0]
    return observed(fits[0])[0], fits[0]


def _write(problem: Problem, ctrl: Optional[FIRHC], directory: Path, name: str, params, x0, max_nodes,
           prepare=None, for_engine: bool = False, tracker: Optional[LinearTracking] = None,
           solver: tuple = ("sdfs", {"pop_width": 1})) -> Exported:
    """Write the two files. ``prepare``: the map from the parameters the C code takes (``params``) to those the
    callables take, translated too (None: the same); ``tracker``: the ``LinearTracking`` exported (its
    ``NAME_track``); ``solver``: the search's solver and its search options."""
    raw = params
    if prepare is not None:
        params = prepare(jax.tree_util.tree_map(jnp.asarray, raw))
    params = check_params(params)
    opts = ctrl.options if ctrl else None
    observe = opts.observe if opts else None
    n, n_plant = state_size(problem, params, x0, observe)
    check_state(problem, jnp.zeros((n,), _real()), params)
    unit = _Unit(problem, params, n)
    unit.for_engine, unit.solver = for_engine, solver
    N, M, m = problem.horizon, problem.num_controls, problem.input_dim
    flat, _ = ravel_pytree(raw) if raw is not None else (np.zeros(0), None)
    num_params = int(np.size(flat))
    if prepare is not None:
        unit.prepare(prepare, raw)

    unused = ("lower_bound",) if solver[0] == "exhaustive" else ()  # the reference search takes no bound
    variants = {"main": _variant(unit, problem, "main", _controls_table(unit, problem, "main"), unused)}
    relaxed = opts.relaxed if opts else None
    if relaxed is not None:
        if relaxed.horizon != N or relaxed.num_controls != M or relaxed.input_dim != m:
            raise ValueError("the fallback problem must have the same horizon and control set size")
        same = relaxed.replace(terminal=problem.terminal, lower_bound=problem.lower_bound).key == problem.key
        if same and relaxed.terminal is None and relaxed.lower_bound is None:
            unit.functions.append(f"static const fj_problem fj_fallback = {{fj_main_children, fj_main_child, NULL, "
                                  f"{'fj_main_terminal_cost' if problem.terminal_cost else 'NULL'}, NULL, "
                                  f"{int(problem.constraint is not None)}, {_exhaustive(unit, relaxed)}}};\n"
                                  "#define fj_fallback_first_input fj_main_first_input\n")
            variants["fallback"] = "fj_fallback"
        else:
            variants["fallback"] = _variant(unit, relaxed, "fallback", _controls_table(unit, relaxed, "fallback"),
                                            unused)
    plant_m = m
    if ctrl is not None:
        _controller_functions(unit, opts, n_plant)
        unit.controller = True
        unit.has_fallback = "fallback" in variants
        if opts.actuate:
            plant_m = int(np.prod(jax.eval_shape(lambda x, u: call(opts.actuate, params, x, u), _x(n_plant),
                                                 jax.ShapeDtypeStruct((m,), _real())).shape))

    if tracker is not None:
        unit.add("fj_members", lambda x, seq, *leaves: tracker.sequence(x, seq, unit.p(leaves)),
                 [_x(n), jax.ShapeDtypeStruct((N,), jnp.int32)], ["x", "seq"], ["int32_t"],
                 "LinearTracking.sequence")
        unit.tables["fj_inputs"] = ("fj_inputs", "static const double fj_inputs[] = {"
                                    + ", ".join(literal(v, np.float64) for v in np.ravel(tracker.controls)) + "};")
    budget = node_budget(max_nodes) if ctrl is None else budget_of(opts)
    header, source = _assemble(unit, problem, ctrl, name, n, n_plant, plant_m, num_params, int(budget),
                               tracker is not None)
    directory.mkdir(parents=True, exist_ok=True)
    (directory / f"{name}.h").write_text(header)
    (directory / f"{name}.c").write_text(source)
    K, lanes = _pop_width(unit), _lanes(unit)
    work = work_bytes(N, M, n, searches=2 if ctrl is not None else 1, pop_width=K, lanes=lanes)
    state_bytes = 0 if ctrl is None else ctypes.sizeof(state_struct(m, N))
    return Exported(header=directory / f"{name}.h", source=directory / f"{name}.c", name=name, state_size=n,
                    plant_state_size=n_plant, input_size=m, plant_input_size=plant_m, horizon=N, num_controls=M,
                    num_params=num_params, work_bytes=work, state_bytes=state_bytes)


def _align(size: int, to: int) -> int:
    return -(-size // to) * to


def work_bytes(N: int, M: int, n: int, searches: int = 1, pop_width: int = 1, lanes: int = 0) -> int:
    """Bytes of the search's arrays on the C stack: ``fj_work`` and one ``fj_incumbent`` a search, laid out as
    a C compiler lays out ``search.c``'s structures (``NAME_work_bytes()`` returns the same)."""
    K = pop_width
    L = K * M
    children = _align(_align(8 * (M * n + 2 * M) + M, 4) + 4 * M + M, 8)
    stack = _align(8 * ((N + 1) * L * n + 2 * (N + 1) * L + (N + 1)) + 4 * (N + 1) * K * N, 8)
    incumbent = _align(_align(8 + 4 * N, 8) + 8 + 8 + 4, 8)
    return max(1, lanes) * stack + K * children + searches * incumbent


def _pop_width(unit: _Unit) -> int:
    return unit.solver[1].get("pop_width", 1)


def _lanes(unit: _Unit) -> int:
    """``FJ_LANES``: a decision's pool slots (0: not the pool)."""
    name, options = unit.solver
    if name != "pool":
        return 0
    return solvers.DECISION_LANES if options.get("lanes") is None else options["lanes"]


def _controller_functions(unit: _Unit, opts, n_plant: int) -> None:
    m = unit.m
    u_spec = jax.ShapeDtypeStruct((m,), input_dtype(opts.problem))  # the state's input (double in C)
    if opts.observe:
        unit.add("fj_observe", lambda x, u, *leaves: call(opts.observe, unit.p(leaves), x, u),
                 [_x(n_plant), u_spec], ["x", "u_in"], ["double"], "observe")
    if opts.actuate:
        unit.add("fj_actuate", lambda x, u, *leaves: call(opts.actuate, unit.p(leaves), x, u),
                 [_x(n_plant), u_spec], ["x", "u_in"], ["double"], "actuate")


def _params_struct(unit: _Unit) -> str:
    if not unit.specs:
        return "typedef struct { char unused; } fj_params;\n"
    fields = "".join(f"    {c_type(s.dtype)} p{i}[{max(1, math.prod(s.shape))}];\n" for i, s in enumerate(unit.specs))
    return "typedef struct {\n" + fields + "} fj_params;\n"


def _unpack(unit: _Unit) -> str:
    """C statements that fill ``fj_params pr`` from ``params`` (through the parameter map, if any) and return -2
    on a non-finite value."""
    lines, offset = ["    fj_params pr;"], 0
    specs, target = (unit.specs, "pr.p") if unit.raw_specs is None else (unit.raw_specs, "raw")
    for i, s in enumerate(specs):
        size = math.prod(s.shape)
        if unit.raw_specs is not None:
            lines.append(f"    {c_type(s.dtype)} raw{i}[{max(size, 1)}];")
        lines.append(f"    for (int j = 0; j < {size}; j++) {{ if (!isfinite(params[{offset} + j])) return "
                     f"{CODES['BAD_PARAMS']}; {target}{i}[j] = ({c_type(s.dtype)})params[{offset} + j]; }}")
        offset += size
    if unit.raw_specs is not None:
        args = [f"raw{i}" for i in range(len(unit.raw_specs))] + [f"pr.p{i}" for i in range(len(unit.specs))]
        lines.append(f"    fj_prepare({', '.join(args)});")
    return "\n".join(lines)


def _assemble(unit: _Unit, problem: Problem, ctrl, name: str, n: int, n_plant: int, plant_m: int,
              num_params: int, budget: int, tracking: bool = False) -> tuple[str, str]:
    N, M, m = problem.horizon, problem.num_controls, problem.input_dim
    up = name.upper()
    api = [f"int {name}_solve(const double *x0, const double *params, int *sequence, double *cost, "
           "long long *nodes);",
           f"int {name}_search(const double *x0, const double *params, const int32_t *seed, int budgeted, "
           f"int32_t max_nodes, {name}_result *result);", f"size_t {name}_work_bytes(void);"]
    state = typedef(RESULT_FIELDS, f"{name}_result", m, N)
    if ctrl is not None:
        state += typedef(STATE_FIELDS, f"{name}_state", m, N)
        api += [f"void {name}_init({name}_state *s, const double *x0, const double *u0);",
                f"int {name}_step({name}_state *s, const double *x, const double *params, double *u);"]
    if tracking:
        api.append(f"int {name}_track(const double *x, const double *u_prev, const double *params, "
                   f"const int32_t *seed, int budgeted, int32_t max_nodes, {name}_result *result);")
    header = f"""/* Generated by firhc_jax.export_c: the exact finite-input search{' and controller' if ctrl else ''} \
{name}. C99, libm only, no allocation.

   Sizes: state n = {name.upper()}_NX, inputs M = {up}_M of dimension {up}_NU, horizon N = {up}_N, parameters
   {up}_NP doubles (flattened as jax.flatten_util.ravel_pytree flattens the example params; pass NULL when 0).

   {name}_solve(x0, params, sequence, cost, nodes): the optimal input indices [N] (rows of the control set), their
   cost and the nodes computed, as fj.sdfs returns them. Returns
     1  a sequence meets the terminal set and the constraints (cost finite);
     0  none does (cost +inf, sequence all -1), or a node budget stopped the search before it found one;
    -1  x0 is not finite;  -2  a parameter is not finite;
    -3  a negative stage or terminal cost was computed: pruning is not exact (fj.sdfs raises ValueError).

   {name}_search(x0, params, seed, budgeted, max_nodes, result): the same search with fj.sdfs's whole result
   ({name}_result); seed: NULL, or [N] indices evaluated first as fj.sdfs's warm_start (all -1: none); budgeted:
   0, or 1 to search within max_nodes as fj.sdfs(max_nodes=) does. Returns the codes of {name}_solve.
*/
#ifndef {up}_H
#define {up}_H
#include <stddef.h>
#include <stdint.h>
#define {up}_NX {n}
#define {up}_PLANT_NX {n_plant}
#define {up}_M {M}
#define {up}_NU {m}
#define {up}_PLANT_NU {plant_m}
#define {up}_N {N}
#define {up}_NP {num_params}
#define {up}_MAX_NODES {budget}LL
#ifdef __cplusplus
extern "C" {{
#endif
{state}{chr(10).join(api)}
#ifdef __cplusplus
}}
#endif
#endif
"""
    tables = "\n".join(definition for _, definition in unit.tables.values())
    source = [f"/* Generated by firhc_jax.export_c. */\n#include <stdint.h>\n#include <stddef.h>\n#include <tgmath.h>\n"
              f'#include "{name}.h"\n\n#define FJ_N {N}\n#define FJ_M {M}\n#define FJ_NX {n}\n#define FJ_NU {m}\n'
              f'#define FJ_K {_pop_width(unit)}\n#define FJ_LANES {_lanes(unit)}\n'
              f'#define FJ_EXHAUSTIVE {int(unit.solver[0] == "exhaustive")}\n',
              PRELUDE, _params_struct(unit), TYPES, tables, *unit.functions, SEARCH,
              _solve(unit, name, budget)]
    if ctrl is not None:
        source.append(_step(unit, ctrl.options, name, n_plant, plant_m))
    if tracking:
        source.append(_track(unit, name, n_plant))
    return header, "\n".join(source)


def _track(unit: _Unit, name: str, n_plant: int) -> str:
    """``NAME_track``: ``LinearTracking.solve`` (observe, the parameter map, the search over classes, the
    cheapest members of the optimal classes)."""
    return f"""
int {name}_track(const double *x, const double *u_prev, const double *params, const int32_t *seed, int budgeted,
                 int32_t max_nodes, {name}_result *r) {{
    if (!fj_all_finite(x, {n_plant}) || !fj_all_finite(u_prev, FJ_NU)) return {CODES['BAD_STATE']};
{_unpack(unit)}
    double z0[FJ_NX];
    fj_observe(x, u_prev{unit.p_args('pr.')}, z0);
    fj_work w;
    fj_incumbent out;
    int count = seed != NULL && seed[0] >= 0;
    int complete = fj_search(&fj_main, &pr, z0, seed, count, max_nodes, budgeted, 0, &out, &w);
    int found = fj_result(r, &out, complete);
    if (found) fj_members(z0, out.path{unit.p_args('pr.')}, r->sequence);
    else for (int j = 0; j < FJ_N; j++) r->sequence[j] = -1;
    for (int j = 0; j < FJ_NU; j++) r->first_input[j] = found ? fj_inputs[r->sequence[0] * FJ_NU + j] : NAN;
    if (out.flags & FJ_NEGATIVE) return {CODES['NEGATIVE_COST']};
    return found ? {CODES['FOUND']} : {CODES['NONE']};
}}
"""


def _solve(unit: _Unit, name: str, budget: int) -> str:
    budgeted = int(budget != INT32_MAX)
    return f"""
size_t {name}_work_bytes(void) {{ return sizeof(fj_work) + {2 if unit.controller else 1} * sizeof(fj_incumbent); }}

/* A search's outcome in NAME_result but its sequence and input; returns whether it found a sequence. */
static int fj_result({name}_result *r, const fj_incumbent *out, int complete) {{
    int found = isfinite(out->cost);
    r->cost = out->cost;
    r->nodes = (int32_t)out->nodes;
    r->iterations = (int32_t)out->iterations;
    r->feasible = found;
    r->complete = complete;
    r->negative_cost = (out->flags & FJ_NEGATIVE) != 0;
    r->nan_encountered = (out->flags & FJ_NONFINITE) != 0;
    r->overflow = (out->flags & FJ_OVERFLOW) != 0;
    return found;
}}

int {name}_solve(const double *x0, const double *params, int *sequence, double *cost, long long *nodes) {{
    if (!fj_all_finite(x0, FJ_NX)) return {CODES['BAD_STATE']};
{_unpack(unit)}
    fj_work w;
    fj_incumbent out;
    fj_search(&fj_main, &pr, x0, NULL, 0, {budget}LL, {budgeted}, 0, &out, &w);
    for (int j = 0; j < FJ_N; j++) sequence[j] = out.path[j];
    *cost = out.cost;
    *nodes = out.nodes;
    if (out.flags & FJ_NEGATIVE) return {CODES['NEGATIVE_COST']};
    return isfinite(out.cost) ? {CODES['FOUND']} : {CODES['NONE']};
}}

int {name}_search(const double *x0, const double *params, const int32_t *seed, int budgeted, int32_t max_nodes,
                  {name}_result *r) {{
    if (!fj_all_finite(x0, FJ_NX)) return {CODES['BAD_STATE']};
{_unpack(unit)}
    fj_work w;
    fj_incumbent out;
    int count = seed != NULL && seed[0] >= 0;
    int complete = fj_search(&fj_main, &pr, x0, seed, count, max_nodes, budgeted, 0, &out, &w);
    int found = fj_result(r, &out, complete);
    for (int j = 0; j < FJ_N; j++) r->sequence[j] = found ? out.path[j] : -1;
    if (found) fj_main_first_input(x0, out.path, &pr, r->first_input);
    else for (int j = 0; j < FJ_NU; j++) r->first_input[j] = NAN;
    if (out.flags & FJ_NEGATIVE) return {CODES['NEGATIVE_COST']};
    return found ? {CODES['FOUND']} : {CODES['NONE']};
}}
"""


def _step(unit: _Unit, opts, name: str, n_plant: int, plant_m: int) -> str:
    budgeted = int(opts.budgeted)
    has_fallback = unit.has_fallback
    previous = bool(opts.warm_start) or opts.budgeted
    safe = ("for (int j = 0; j < FJ_NU; j++) s->u[j] = s->u[j];" if opts.u_safe is None else
            "{ static const double safe[FJ_NU] = {" + ", ".join(literal(v, np.float64) for v in opts.u_safe)
            + "}; for (int j = 0; j < FJ_NU; j++) s->u[j] = safe[j]; }")
    observe = f"fj_observe(x, s->u{unit.p_args('pr.')}, xm);" if opts.observe else \
        "for (int j = 0; j < FJ_NX; j++) xm[j] = x[j];"
    actuate = f"fj_actuate(x, s->u{unit.p_args('pr.')}, u);" if opts.actuate else \
        "for (int j = 0; j < FJ_NU; j++) u[j] = s->u[j];"
    candidates = ""
    if previous:
        candidates = "    if (s->plan[0] >= 0) {\n"
        if opts.budgeted:
            candidates += ("        for (int j = 0; j < FJ_N - 1; j++) cand[count * FJ_N + j] = s->plan[j + 1];\n"
                           "        cand[count * FJ_N + FJ_N - 1] = -1;\n        count++;\n")
        elif opts.warm_start:
            candidates += ("        for (int j = 0; j < FJ_N - 1; j++) cand[count * FJ_N + j] = s->plan[j + 1];\n"
                           "        cand[count * FJ_N + FJ_N - 1] = s->plan[FJ_N - 1];\n        count++;\n")
        candidates += "    }\n"
    fallback = ""
    if has_fallback:
        fallback = f"""
    if (!isfinite(res.cost)) {{
        long long left = {budgeted} ? (s->budget - res.nodes > 0 ? s->budget - res.nodes : 0) : (long long)s->budget;
        fj_incumbent second;
        int done2 = fj_search(&fj_fallback, &pr, xm, cand, count, left, {budgeted}, 0, &second, &w);
        second.flags |= res.flags;
        second.iterations += res.iterations;
        complete = complete && done2;
        s->fallback_nodes = (int32_t)second.nodes;
        res = second;
        used = 1;
    }}"""
    first = "fj_fallback_first_input" if has_fallback else "fj_main_first_input"
    pick = (f"if (used) {first}(xm, res.path, &pr, found); else fj_main_first_input(xm, res.path, &pr, found);"
            if has_fallback else f"{first}(xm, res.path, &pr, found);")
    unpack = _unpack(unit).replace(f"return {CODES['BAD_PARAMS']};", "{ bad = " + str(CODES['BAD_PARAMS'])
                                   + "; break; }")
    return f"""
/* The last decision's report in the state (StepInfo's fields): res NULL for a decision that searched nothing. */
static void fj_report({name}_state *s, const fj_incumbent *res, int used, int complete, int held, int flags) {{
    int found = res && isfinite(res->cost);
    s->result_feasible = found;
    s->result_nodes = res ? (int32_t)res->nodes : 0;
    s->complete = complete;
    s->used_fallback = used;
    s->feasible = found && !used;
    s->held = held;
    s->negative_cost = (flags & FJ_NEGATIVE) != 0;
    s->nan_encountered = (flags & FJ_NONFINITE) != 0;
    s->overflow = (flags & FJ_OVERFLOW) != 0;
    s->iterations = res ? (int32_t)res->iterations : 0;
    s->cost = res ? res->cost : INFINITY;
    s->stage_cost = NAN;
    for (int j = 0; j < FJ_N; j++) s->sequence[j] = found ? res->path[j] : -1;
    for (int j = 0; j < FJ_NU; j++) s->first_input[j] = NAN;
}}

void {name}_init({name}_state *s, const double *x0, const double *u0) {{
    (void)x0;
    for (int j = 0; j < FJ_NU; j++) s->u[j] = u0 ? u0[j] : 0.0;
    for (int j = 0; j < FJ_N; j++) s->plan[j] = -1;
    s->budget = {int(budget_of(opts))};
    s->nodes = 0;
    s->fallback_nodes = 0;
    fj_report(s, NULL, 0, 1, 0, 0);
}}

int {name}_step({name}_state *s, const double *x, const double *params, double *u) {{
    int bad = 0;
{unpack}
    if (!fj_all_finite(x, {n_plant})) bad = {CODES['BAD_STATE']};
    if (bad) {{
        {safe}
        for (int j = 0; j < FJ_N; j++) s->plan[j] = -1;
        s->nodes = 0;
        s->fallback_nodes = 0;
        fj_report(s, NULL, 0, 1, 1, FJ_NONFINITE);
        for (int j = 0; j < FJ_NU; j++) u[j] = s->u[j];
        return bad;
    }}
    double xm[FJ_NX];
    {observe}
    int32_t cand[2 * FJ_N];
    int count = 0;
{candidates}    long long reserve = {budgeted} && {int(opts.relaxed is not None)} ? s->budget / 2 : 0;
    fj_work w;
    fj_incumbent res;
    int complete = fj_search(&fj_main, &pr, xm, cand, count, s->budget, {budgeted}, reserve, &res, &w);
    int used = 0;
    s->nodes = (int32_t)res.nodes;
    s->fallback_nodes = 0;{fallback}
    double found[FJ_NU];
    int held = !isfinite(res.cost);
    if (!held) {{
        {pick}
        held = !fj_all_finite(found, FJ_NU);
    }}
    fj_report(s, &res, used, complete, held, res.flags);
    if (isfinite(res.cost))
        for (int j = 0; j < FJ_NU; j++) s->first_input[j] = found[j];
    if (held) {{
        {safe}
        for (int j = 0; j < FJ_N; j++) s->plan[j] = -1;
    }} else {{
        double x_next[FJ_NX];
        unsigned char allowed;
        fj_main.child(xm, res.path[0], 0, &pr, x_next, &s->stage_cost, &allowed);
        for (int j = 0; j < FJ_NU; j++) s->u[j] = found[j];
        for (int j = 0; j < FJ_N; j++) s->plan[j] = res.path[j];
    }}
    {actuate}
    if (res.flags & FJ_NEGATIVE) return {CODES['NEGATIVE_COST']};
    return held ? {CODES['NONE']} : used ? {CODES['FALLBACK']} : {CODES['FOUND']};
}}
"""


class Compiled:
    """A generated search or controller compiled into a shared library and called through ``ctypes``
    (``Exported.compile``): for checks and timing from Python; a deployment compiles the two files itself."""

    def __init__(self, exported: Exported, path: Path, params_example=None):
        import ctypes

        self.exported, self.path = exported, path
        self.lib = ctypes.CDLL(str(path))
        e, name = exported, exported.name
        vp, dp = ctypes.c_void_p, ctypes.POINTER(ctypes.c_double)
        self._solve = getattr(self.lib, f"{name}_solve")
        self._solve.restype = ctypes.c_int
        self._solve.argtypes = [vp, vp, vp, dp, ctypes.POINTER(ctypes.c_longlong)]
        self._cost, self._nodes = ctypes.c_double(), ctypes.c_longlong()
        self._sequence = np.zeros(e.horizon, np.intc)
        self._outputs = (_address(self._sequence), ctypes.byref(self._cost), ctypes.byref(self._nodes))
        # Inputs are copied into buffers of fixed address: cheaper than taking a new array's pointer a call.
        self._x = np.zeros(max(e.state_size, e.plant_state_size))
        self._p = np.zeros(e.num_params)
        self._inputs = (_address(self._x), _address(self._p) if e.num_params else None)
        if e.state_bytes:
            self.State = state_struct(e.input_size, e.horizon)
            self._init, self._step = getattr(self.lib, f"{name}_init"), getattr(self.lib, f"{name}_step")
            self._init.argtypes, self._init.restype = [vp, vp, vp], None
            self._step.argtypes, self._step.restype = [vp, vp, vp, vp], ctypes.c_int
            self._u = np.zeros(e.plant_input_size)
            self._u_address = _address(self._u)

    @staticmethod
    def flat_params(params) -> Optional[np.ndarray]:
        """``params`` as the C code takes them: ``ravel_pytree``'s order in one float64 vector (None: no
        parameters). A float64 vector passes as it is."""
        if params is None:
            return None
        if isinstance(params, np.ndarray) and params.dtype == np.float64 and params.ndim == 1:
            return params
        leaves = jax.tree_util.tree_leaves(params)
        return np.concatenate([np.ravel(np.asarray(leaf, np.float64)) for leaf in leaves]) if leaves else None

    def solve(self, x0, params=None) -> tuple[int, np.ndarray, float, int]:
        """``NAME_solve``: ``(code, sequence [N], cost, nodes)``."""
        self._load(x0, self.exported.state_size, params)
        code = self._solve(*self._inputs, *self._outputs)
        return code, self._sequence.copy(), self._cost.value, self._nodes.value

    def init(self, x0, u0=None):
        """``NAME_init``: a new controller state."""
        import ctypes

        state = self.State()
        x0 = np.ascontiguousarray(x0, np.float64)
        u0 = None if u0 is None else np.ascontiguousarray(u0, np.float64)
        self._init(ctypes.addressof(state), x0.ctypes.data, None if u0 is None else u0.ctypes.data)
        return state

    def step(self, state, x, params=None) -> tuple[int, np.ndarray]:
        """``NAME_step``: ``(code, u)``; ``state`` is updated in place."""
        import ctypes

        self._load(x, self.exported.plant_state_size, params)
        code = self._step(ctypes.addressof(state), *self._inputs, self._u_address)
        return code, self._u.copy()

    def _load(self, x, n: int, params) -> None:
        x = np.asarray(x, np.float64)
        if x.shape != (n,):
            raise ValueError(f"the state must have shape ({n},), got {x.shape}")
        self._x[:n] = x
        if self.exported.num_params:
            if params is None:
                raise TypeError(f"this code takes {self.exported.num_params} parameters: pass params")
            p = self.flat_params(params)
            if p.shape != self._p.shape:
                raise ValueError(f"params flatten to {p.size} numbers, the code takes {self._p.size}")
            self._p[:] = p


def _address(array: np.ndarray) -> int:
    """The data pointer of a NumPy array (``array.ctypes.data`` builds an object on every call)."""
    return array.__array_interface__["data"][0]


def compile_shared(exported: Exported, *, cc: str = "cc", flags=("-O2",)) -> Compiled:
    """``Exported.compile``."""
    import hashlib
    import subprocess

    source = exported.source.read_bytes()
    tag = hashlib.sha1(source + " ".join(flags).encode()).hexdigest()[:12]
    path = exported.source.with_name(f"{exported.name}-{tag}.so")
    if not path.exists():
        cmd = [cc, "-std=c99", *flags, "-fPIC", "-shared", "-o", str(path), str(exported.source), "-lm"]
        done = subprocess.run(cmd, capture_output=True, text=True)
        if done.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed:\n{done.stderr[-4000:]}")
    return Compiled(exported, path)
