"""The ``"c"`` engine: eager searches (``fj.sdfs``, ``lt.solve``) and a controller's eager decisions
(``ctrl.step``, ``ctrl(x)``) in generated C.

On the first eager call for a signature of arguments the problem, tracker or controller is exported (``export_c``,
with these parameters' shapes), compiled with the system's C compiler (``$CC``, else ``cc``) into a shared library
in a folder of this process, and called through ``ctypes`` from then on: one C call a decision, no XLA program.
The arguments are written into buffers of fixed address (one set per thread: the C code is reentrant) and the
outputs read back in place from the record the C code fills (``export.RESULT_FIELDS``, the controller state's
report ``export.STATE_FIELDS``), as NumPy arrays of the dtypes the XLA program returns. The C code computes the
callables in the session's float, as the export does, and rounds as the C compiler does (no contraction into fused
multiply-adds: ``FLAGS``), so costs can differ from XLA's in the last bits, and an exact tie can be broken towards
another optimal sequence.
"""
from __future__ import annotations

import atexit
import ctypes
import functools
import itertools
import os
import shutil
import tempfile
import threading
from typing import Optional

import jax
import numpy as np

from ..control.decision import ControllerState, StepInfo
from ..control.decision_checks import decide_checked
from ..runtime.engines import ENGINES
from ..search.result import SearchResult
from ..search.sdfs import INT32_MAX
from ..search.sdfs import search as sdfs_search
from .export import _check_controller, compile_shared, export, result_dtype, state_dtype

# The first set the compiler takes; contraction into fused multiply-adds off, as ISO C mode gives with GCC (clang
# contracts by default).
FLAGS = (("-O3", "-march=native", "-ffp-contract=off"), ("-O3", "-ffp-contract=off"))
MAX_WORK_BYTES = 4 << 20  # the generated search's arrays live on the calling thread's stack (8 MiB by default)
_folder: Optional[str] = None
_names = itertools.count()
_lock = threading.Lock()


def compiler() -> str:
    return os.environ.get("CC") or "cc"


def _build_folder() -> str:
    """This process's folder of generated code, removed at exit."""
    global _folder
    with _lock:
        if _folder is None:
            _folder = tempfile.mkdtemp(prefix="firhc_jax_c_")
            atexit.register(shutil.rmtree, _folder, True)
        return _folder


def _have_compiler() -> None:
    if shutil.which(compiler()) is None:
        raise RuntimeError(f"engine='c' compiles generated C with {compiler()!r} (set $CC), which is not on this "
                           "machine's PATH; use engine='xla'")


def _compiled(what, params, x0, pop_width: int = 1):
    """``what`` (a problem, its search's ``pop_width``, or a controller) exported into this process's folder and
    compiled: the ``Compiled``."""
    with _lock:
        name = f"fj{next(_names)}"
    exported = export(what, _build_folder(), name=name, params=params, x0=np.asarray(x0), for_engine=True,
                      pop_width=pop_width)
    if exported.work_bytes > MAX_WORK_BYTES:
        raise ValueError(f"engine='c' keeps the search's arrays on the calling thread's stack: this one needs "
                         f"{exported.work_bytes:,} bytes, more than {MAX_WORK_BYTES:,}; lower pop_width or lanes, "
                         "shorten the horizon, or use engine='xla'")
    for flags in FLAGS:
        try:
            return compile_shared(exported, cc=compiler(), flags=flags)
        except RuntimeError:
            if flags is FLAGS[-1]:
                raise


def _address(a: np.ndarray) -> int:
    return a.__array_interface__["data"][0]


def _shapes(params) -> tuple:
    return tuple(np.shape(leaf) for leaf in jax.tree_util.tree_leaves(params))


def _param_views(buffer: np.ndarray, shapes: tuple) -> tuple:
    """Views of ``buffer``, one per parameter leaf in its shape (``_shapes``): the leaves written into them lie
    flattened as the generated code takes them."""
    views, start = [], 0
    for shape in shapes:
        size = int(np.prod(shape))
        views.append(buffer[start:start + size].reshape(shape))
        start += size
    return tuple(views)


def _write_params(views: tuple, params) -> None:
    for view, leaf in zip(views, jax.tree_util.tree_leaves(params), strict=True):
        view[...] = leaf


def _casts(record: np.dtype, floats: dict) -> tuple:
    """``(field, dtype)`` of the floating outputs whose session dtype (float32 without x64) is not the record's."""
    return tuple((field, np.dtype(a.dtype)) for field, a in floats.items() if np.dtype(a.dtype) != record[field].base)


def _result_function(lib, suffix: str, inputs: int):
    """The generated ``NAME_<suffix>(inputs..., seed, budgeted, max_nodes, result)`` of ``lib``, typed."""
    fn = getattr(lib.lib, f"{lib.exported.name}_{suffix}")
    fn.restype = ctypes.c_int
    fn.argtypes = [ctypes.c_void_p] * (inputs + 1) + [ctypes.c_int, ctypes.c_int32, ctypes.c_void_p]
    return fn


def _indices(warm_start: np.ndarray, count: int) -> bool:
    """``warm_start`` is all -1 (none) or indices in ``[0, count)``: what ``checks.as_sequence`` accepts."""
    return bool(np.all(warm_start == -1) or (np.all(warm_start >= 0) and np.all(warm_start < count)))


def _search_outputs(r: np.ndarray, casts: tuple, code: int) -> tuple:
    """``(SearchResult, alarm)`` from a filled ``NAME_result`` record ``r`` (a copy) and the call's return code:
    the alarm of the XLA search (a value the checks refuse, an error flag)."""
    f = {field: r[field].astype(dtype) for field, dtype in casts} if casts else r
    result = SearchResult(cost=f["cost"], sequence=r["sequence"], first_input=f["first_input"], nodes=r["nodes"],
                          feasible=r["feasible"], iterations=r["iterations"], negative_cost=r["negative_cost"],
                          nan_encountered=r["nan_encountered"], overflow=r["overflow"], complete=r["complete"])
    return result, code < 0 or bool(r["nan_encountered"] | r["overflow"])


class CEngine:
    name = "c"

    def check_search(self) -> None:
        _have_compiler()

    def build_search(self, problem, x0, params, budgeted: bool, pop_width: int):
        return CSearch(problem, x0, params, budgeted, pop_width)

    def check_tracking(self) -> None:
        _have_compiler()

    def build_tracking(self, lt, x, u_prev, y_ref, d, budgeted: bool):
        return CTrack(lt, x, u_prev, y_ref, d, budgeted)

    def check(self, ctrl) -> None:
        _check_controller(ctrl)
        _have_compiler()

    def build(self, ctrl, state, x, params):
        return CStep(ctrl, state, x, params)


class _Searched:
    """A generated ``NAME_search`` or ``NAME_track`` for one signature of checked arguments: its typed function,
    its result record and, per thread, the buffers it reads and writes (vectors, parameters, seed, record)."""

    def __init__(self, lib, suffix: str, sizes: tuple, params, budgeted: bool, out):
        self.lib, e = lib, lib.exported
        self._fn = _result_function(lib, suffix, len(sizes) + 1)
        self._sizes, self._shapes = sizes, _shapes(params)
        self._budgeted, self._N = int(budgeted), e.horizon
        self._record = result_dtype(e.input_size, e.horizon)
        self._casts = _casts(self._record, {"cost": out.cost, "first_input": out.first_input})
        self._local = threading.local()

    def _buffers(self) -> tuple:
        """``(record bytes, vectors, parameter views, seed, pointers)``; pointers in the function's order: the
        vectors, the parameters, the seed, the record."""
        b = getattr(self._local, "buffers", None)
        if b is None:
            record, seed = np.zeros((), self._record), np.zeros(self._N, np.int32)
            vectors = [np.zeros(size) for size in self._sizes]
            p = np.zeros(sum(int(np.prod(s)) for s in self._shapes))
            pointers = (*(_address(v) for v in vectors), _address(p) if p.size else None, _address(seed),
                        _address(record))
            b = self._local.buffers = (record.reshape(1).view(np.uint8), vectors, _param_views(p, self._shapes), seed,
                                       pointers)
        return b

    def _run(self, vectors, params, seed, max_nodes) -> tuple:
        """``(result, alarm)`` of a call on these values (``seed``: indices, or None)."""
        raw, buffers, views, seed_buffer, pointers = self._buffers()
        for buffer, value in zip(buffers, vectors, strict=True):
            buffer[...] = value
        if views:
            _write_params(views, params)
        if seed is not None:
            seed_buffer[:] = seed
        code = self._fn(*pointers[:-2], None if seed is None else pointers[-2], self._budgeted, int(max_nodes),
                        pointers[-1])
        return _search_outputs(np.ndarray((), self._record, raw.copy()), self._casts, code)


class CSearch(_Searched):
    """``fj.sdfs`` of one problem in C for one signature of ``(x0, params)`` (checked arguments)."""

    def __init__(self, problem, x0, params, budgeted: bool, pop_width: int):
        out = jax.eval_shape(lambda x, p: sdfs_search(problem, x, p, None, INT32_MAX, pop_width=pop_width,
                                                      budgeted=budgeted), x0, params)
        lib = _compiled(problem, params, x0, pop_width)
        super().__init__(lib, "search", (lib.exported.state_size,), params, budgeted, out)
        self._M = lib.exported.num_controls

    def __call__(self, x0, params, warm_start, max_nodes):
        """``(result, alarm)`` as ``fj.sdfs``'s compiled search gives them."""
        if warm_start is not None and not _indices(warm_start, self._M):
            return None, True  # refused by the checks the caller runs on an alarm, before the result is read
        return self._run((x0,), params, warm_start, max_nodes)


class CTrack(_Searched):
    """``LinearTracking.solve`` of one tracker in C for one signature of its arguments (checked)."""

    def __init__(self, lt, x, u_prev, y_ref, d, budgeted: bool):
        out = jax.eval_shape(lambda *a: lt.solve(*a, max_nodes=INT32_MAX if budgeted else None), x, u_prev, y_ref,
                             d)
        self._no_d = np.zeros((lt.horizon, lt.n))
        raw = (np.asarray(y_ref, np.float64), self._no_d if d is None else np.asarray(d, np.float64))
        lib = _compiled(lt, raw, x)
        super().__init__(lib, "track", (lib.exported.plant_state_size, lt.m), raw, budgeted, out)
        self._class_of = np.asarray(lt.class_of, np.int32)

    def __call__(self, x, u_prev, y_ref, d, warm_start, max_nodes):
        """``(result, alarm)`` as ``LinearTracking.solve``'s compiled search gives them."""
        seed = None
        if warm_start is not None:
            if not _indices(warm_start, self._class_of.shape[0]):
                return None, True  # as in CSearch
            seed = np.where(warm_start >= 0, self._class_of[np.maximum(warm_start, 0)], -1)  # inputs -> classes
        return self._run((x, u_prev), (y_ref, self._no_d if d is None else d), seed, max_nodes)


class CStep:
    """One controller's decision in C for one signature of ``(state, x, params)`` (checked arguments)."""

    def __init__(self, ctrl, state, x, params):
        opts = ctrl.options
        out = jax.eval_shape(functools.partial(decide_checked, opts), state, x, params)  # the callables' checks
        self.lib = _compiled(ctrl, params, x)
        exported = self.lib.exported
        self._fn = self.lib._step
        self._n_x, self._n_u = exported.plant_state_size, exported.plant_input_size
        self._n_p, self._shapes = exported.num_params, _shapes(params)
        self._record = state_dtype(exported.input_size, exported.horizon)
        u_plant, next_state, info = out
        self._casts = _casts(self._record, {"u": next_state.u, "cost": info.result.cost,
                                            "stage_cost": info.stage_cost, "first_input": info.result.first_input})
        self._u_dtype = np.dtype(u_plant.dtype)
        self._local = threading.local()

    def _buffers(self):
        """This thread's ``(state record, its bytes, x, params, u)`` buffers and their addresses."""
        b = getattr(self._local, "buffers", None)
        if b is None:
            record, x, p, u = (np.zeros((), self._record), np.zeros(self._n_x), np.zeros(self._n_p),
                               np.zeros(self._n_u))
            b = self._local.buffers = (record, record.reshape(1).view(np.uint8), x, _param_views(p, self._shapes), u,
                                       _address(record), _address(x), _address(p) if self._n_p else None,
                                       _address(u))
        return b

    def __call__(self, state: ControllerState, x, params):
        record, raw, xb, pb, ub, ra, xa, pa, ua = self._buffers()
        record["u"], record["plan"], record["budget"] = state.u, state.plan, state.budget
        xb[:] = x
        if self._n_p:
            _write_params(pb, params)
        self._fn(ra, xa, pa, ua)
        r = np.ndarray((), self._record, raw.copy())  # a structured copy is several times slower
        f = {field: r[field].astype(dtype) for field, dtype in self._casts} if self._casts else r
        result = SearchResult(cost=f["cost"], sequence=r["sequence"], first_input=f["first_input"],
                              nodes=r["result_nodes"], feasible=r["result_feasible"], iterations=r["iterations"],
                              negative_cost=r["negative_cost"], nan_encountered=r["nan_encountered"],
                              overflow=r["overflow"], complete=r["complete"])
        info = StepInfo(result=result, used_fallback=r["used_fallback"], complete=r["complete"], nodes=r["nodes"],
                        fallback_nodes=r["fallback_nodes"], feasible=r["feasible"], held=r["held"],
                        stage_cost=f["stage_cost"])
        return ub.astype(self._u_dtype), ControllerState(u=f["u"], plan=r["plan"], budget=r["budget"]), info


ENGINES["c"] = CEngine()
