"""The ``"c"`` engine: a controller's eager decisions (``ctrl.step``, ``ctrl(x)``) in generated C.

On the first eager decision for a signature of arguments the controller is exported (``export_c``, with these
parameters' shapes), compiled with the system's C compiler (``$CC``, else ``cc``) into a shared library in a
folder of this process, and called through ``ctypes`` from then on: one C call a decision, no XLA program.
The arguments are written into buffers of fixed address (one set per thread: the C code is reentrant) and the
outputs read back from the controller state's report (``export.STATE_FIELDS``) in one structured cast, as
NumPy arrays of the dtypes the XLA decision returns. The C code computes in float64 and rounds as the C
compiler does (no contraction into fused multiply-adds, ISO C), so costs can differ from XLA's in the last
bits, and an exact tie can be broken towards another optimal sequence.
"""
from __future__ import annotations

import atexit
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
from ..control.engines import ENGINES
from ..search.result import SearchResult
from .export import _check_controller, compile_shared, export_c, state_dtype

FLAGS = (("-O3", "-march=native"), ("-O3",))  # the first set the compiler takes
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


class CEngine:
    name = "c"

    def check(self, ctrl) -> None:
        _check_controller(ctrl)
        if shutil.which(compiler()) is None:
            raise RuntimeError(f"engine='c' compiles generated C with {compiler()!r} (set $CC), which is not on "
                               "this machine's PATH; use engine='xla'")

    def build(self, ctrl, state, x, params):
        return CStep(ctrl, state, x, params)


class CStep:
    """One controller's decision in C for one signature of ``(state, x, params)`` (checked arguments)."""

    def __init__(self, ctrl, state, x, params):
        opts = ctrl.options
        out = jax.eval_shape(functools.partial(decide_checked, opts), state, x, params)  # the callables' checks
        with _lock:
            name = f"fj{next(_names)}"
        exported = export_c(ctrl, _build_folder(), name=name, params=params, x0=np.asarray(x))
        for flags in FLAGS:
            try:
                self.lib = compile_shared(exported, cc=compiler(), flags=flags)
                break
            except RuntimeError:
                if flags is FLAGS[-1]:
                    raise
        self._fn = self.lib._step
        self._n_x, self._n_u = exported.plant_state_size, exported.plant_input_size
        self._n_p = exported.num_params
        self._record = state_dtype(exported.input_size, exported.horizon)
        u_plant, next_state, info = out
        floats = {"u": next_state.u, "cost": info.result.cost, "stage_cost": info.stage_cost,
                  "first_input": info.result.first_input}  # the session's floating dtypes (float32 without x64)
        self._casts = tuple((field, np.dtype(a.dtype)) for field, a in floats.items()
                            if np.dtype(a.dtype) != self._record[field].base)
        self._u_dtype = np.dtype(u_plant.dtype)
        self._local = threading.local()

    def _buffers(self):
        """This thread's ``(state record, its bytes, x, params, u)`` buffers and their addresses."""
        b = getattr(self._local, "buffers", None)
        if b is None:
            record, x, p, u = (np.zeros((), self._record), np.zeros(self._n_x), np.zeros(self._n_p),
                               np.zeros(self._n_u))
            address = lambda a: a.__array_interface__["data"][0]  # noqa: E731
            b = self._local.buffers = (record, record.reshape(1).view(np.uint8), x, p, u, address(record),
                                       address(x), address(p) if self._n_p else None, address(u))
        return b

    def __call__(self, state: ControllerState, x, params):
        record, raw, xb, pb, ub, ra, xa, pa, ua = self._buffers()
        record["u"], record["plan"], record["budget"] = state.u, state.plan, state.budget
        xb[:] = x
        if self._n_p:
            start = 0
            for leaf in jax.tree_util.tree_leaves(params):
                leaf = np.ravel(leaf)
                pb[start:start + leaf.size] = leaf
                start += leaf.size
        self._fn(ra, xa, pa, ua)
        r = raw.copy().view(self._record).reshape(())  # a structured copy is several times slower
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
