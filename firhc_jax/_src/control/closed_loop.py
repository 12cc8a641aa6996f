"""What a closed-loop run returns (``FIRHC.simulate``), and how it is kept and looked at.

``ClosedLoop`` holds per-step records: the fields of each step's ``StepInfo``
stacked over T steps, with the plant states and the applied inputs.
``run.save(path)`` writes them to one ``.npz`` (``numpy.load`` reads it, one
array per field); ``ClosedLoop.load(path)`` reads it back. ``run.plot()``
draws it into a new matplotlib ``Figure`` (``plot.py``) without touching
pyplot, so the caller's backend and open figures are left as they are.
"""
from __future__ import annotations

import math
import os
import zipfile
import zlib
from typing import TYPE_CHECKING, NamedTuple, Optional, Sequence

import jax
import numpy as np
from numpy.lib import format as npy

from ..annotations import PyTree
from . import plot, realised

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from ..problem.problem import Problem

# Each field's layout in a saved run: (length of the leading axis, number of axes, dtype kinds).
_LAYOUT = {"states": ("T+1", 2, "f"), "inputs": ("T", 2, "f"), "input_indices": ("T", 1, "iu"),
           "stage_costs": ("T", 1, "f"), "predicted_costs": ("T", 1, "f"), "nodes": ("T", 1, "iu"),
           "fallback_nodes": ("T", 1, "iu"), "feasible": ("T", 1, "b"), "used_fallback": ("T", 1, "b"),
           "complete": ("T", 1, "b"), "held": ("T", 1, "b"), "plans": ("T", 2, "iu"), "solve_times": ("T", 1, "f"),
           "times": ("T+1", 1, "f")}


class ClosedLoop(NamedTuple):
    """A closed-loop run of T steps (one ``StepInfo`` per step, stacked). A run of B loops
    (``FIRHC.simulate_batch``) has a leading axis B on every field but ``times``."""

    states: jax.Array  # [T+1, n] plant states x(0) .. x(T)
    inputs: jax.Array  # [T, m'] inputs applied to the plant (after actuate); the safe input where held
    input_indices: jax.Array  # [T] int32 index into controls of the searched input (-1: held, none found)
    stage_costs: jax.Array  # [T] model stage cost of the applied step, stage_cost(dynamics(x_model, u), u); NaN held
    predicted_costs: jax.Array  # [T] optimal cost of each step's deciding search (+inf: none found)
    nodes: jax.Array  # [T] int32 nodes of the terminal-constrained search
    fallback_nodes: jax.Array  # [T] int32 nodes of the fallback search (0 when not used)
    feasible: jax.Array  # [T] bool the terminal-constrained search found a sequence
    used_fallback: jax.Array  # [T] bool the input came from the fallback search
    complete: jax.Array  # [T] bool every search behind the decision ran to the end (not stopped by max_nodes)
    held: jax.Array  # [T] bool no input found: the safe input (u_safe, else the last input) was applied
    plans: jax.Array  # [T, N] int32 the sequence chosen at each step (all -1 where held)
    solve_times: jax.Array  # [T] seconds per decision (compiled=False only; NaN in a compiled scan)
    times: Optional[np.ndarray] = None  # [T+1] float64 seconds of each state, k * dt (simulate(..., dt=)); None

    @property
    def decision_nodes(self) -> jax.Array:
        """[T] int32 nodes of each whole decision, both searches: at most ``max_nodes``."""
        return self.nodes + self.fallback_nodes

    @property
    def batched(self) -> bool:
        """A run of B loops (``simulate_batch``): every field but ``times`` has a leading axis B."""
        return np.ndim(self.inputs) == 3

    @property
    def first_infeasible_step(self) -> Optional[int]:
        """Index of the first step whose terminal-constrained search found no sequence (in any loop of a
        batched run), or None."""
        bad = np.flatnonzero(~np.asarray(self.feasible).reshape(-1, np.shape(self.feasible)[-1]).all(axis=0))
        return int(bad[0]) if bad.size else None

    def realised_cost(self, problem: "Problem", params: PyTree = None, *,
                      terminal_cost: bool = False) -> float | np.ndarray:
        """What the plant paid: the sum over the run of ``problem``'s stage cost of each plant state reached
        and the input applied to reach it, ``stage_cost(states[k+1], inputs[k][, 0][, params[k]])`` (step
        index 0, the step each decision applies), plus, with ``terminal_cost``, ``problem``'s terminal cost
        of the last state (``params[T-1]``). A float; ``[B]`` for a batched run.

        ``problem``'s state and input must be the plant's and the applied ones (``states`` ``[n]``,
        ``inputs`` ``[m']``): with ``with_input_memory``, price the run with the problem it was built from
        (switching costs apart). ``params``: per step as ``simulate``'s (leading axis T; B, T for a batch).
        Unlike ``stage_costs`` (each decision's model prediction of its first step), this is evaluated on
        the plant's own states, so a plant that is not the model pays what it really paid."""
        return realised.realised_cost(self, problem, params, terminal_cost)

    def save(self, path: str | os.PathLike) -> str:
        """Write every field to ``path`` as an uncompressed ``.npz`` (``.npz``
        appended if missing, as ``numpy.savez`` does); returns the path written.
        ``numpy.load(path)["states"]`` reads one field; ``ClosedLoop.load`` all."""
        path = os.fspath(path)
        if not path.endswith(".npz"):
            path += ".npz"
        fields = {name: np.asarray(value) for name, value in self._asdict().items() if value is not None}
        np.savez(path, **fields)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "ClosedLoop":
        """A ``ClosedLoop`` of NumPy arrays from a file written by ``save``.

        Every array's declared shape and dtype is read from its ``.npy``
        header first, without reading data: a file whose fields disagree
        (``states`` not ``[T+1, n]`` for ``inputs`` ``[T, m']``, ...), whose
        headers declare more data than the file holds (``save`` writes
        uncompressed arrays), or that is not an ``.npz`` at all is refused
        with a ``ValueError`` before anything is allocated; so is a damaged
        archive (a member whose data fail their checksum). No pickles."""
        path = os.fspath(path)
        try:
            return cls._load(path)
        except (zipfile.BadZipFile, zlib.error, EOFError) as e:
            raise ValueError(f"{path} is a damaged .npz archive ({e}); save the run again") from None

    @classmethod
    def _load(cls, path: str) -> "ClosedLoop":
        declared = _declared_arrays(path)
        names = set(declared)
        required = [f for f in cls._fields if f not in cls._field_defaults]
        missing = [f for f in required if f not in names]
        if missing:
            raise ValueError(f"{path} is not a saved ClosedLoop: it lacks {missing}")
        unknown = sorted(names - set(cls._fields))
        if unknown:
            raise ValueError(f"{path} has arrays a ClosedLoop does not: {unknown}")
        _check_layout(path, declared)
        with np.load(path, allow_pickle=False) as data:
            return cls(**{name: data[name] for name in names})

    def plot(self, title: str = "", state_names: Sequence[str] | None = None,
             input_names: Sequence[str] | None = None) -> "Figure":
        """A new matplotlib ``Figure`` of the run, one row of axes per quantity.

        The states; each input on its own axes (held steps marked with red
        crosses); the nodes of each decision; and the solve times when the
        run was timed (``simulate(..., compiled=False)``). The time axis is in
        seconds when the run has ``times`` (``simulate(..., dt=)``), else in
        steps. An input of at most 8 levels is a step line while its switches
        can be told apart; where one loop switches more often, and in a
        batched run (``simulate_batch``), it is a map of how often each level
        is used over time. A batched run draws, per step, the median over the
        loops and the band between the 10th and 90th percentiles (extremes
        dotted) of every state, every other input and the nodes.
        ``state_names`` ``[n]`` and ``input_names`` ``[m']`` (e.g.
        ``"i_a [A]"``, units included) label them; default ``x[0]``,
        ``u[0]``, ... Built without pyplot: the backend is never switched;
        show it with ``fig.savefig`` or display it in a notebook."""
        return plot.draw(self, title, state_names, input_names)


def _declared_arrays(path: str) -> dict:
    """``{name: (shape, dtype)}`` of every array of the ``.npz`` at ``path``, from the ``.npy`` headers alone;
    a ``ValueError`` for anything but an archive of plain arrays whose data fit in the file."""
    with open(path, "rb") as f:
        head = f.read(6)
    if head == b"\x93NUMPY":
        raise ValueError(f"{path} is a .npy file (one array); ClosedLoop.load reads the .npz archive that "
                         "ClosedLoop.save writes, one array per field")
    if not zipfile.is_zipfile(path):
        raise ValueError(f"{path} is not an .npz archive; ClosedLoop.load reads the .npz that ClosedLoop.save writes")
    size, out, total = os.path.getsize(path), {}, 0
    with zipfile.ZipFile(path) as archive:
        for member in archive.infolist():
            name = member.filename
            if not name.endswith(".npy"):
                raise ValueError(f"{path}: {name!r} is not an array (.npy) of a saved ClosedLoop")
            with archive.open(member) as f:
                try:
                    version = npy.read_magic(f)
                    readers = {(1, 0): npy.read_array_header_1_0, (2, 0): npy.read_array_header_2_0}
                    if version not in readers:
                        raise ValueError(f"unsupported .npy version {version}")
                    shape, _, dtype = readers[version](f)
                except ValueError as e:
                    raise ValueError(f"{path}: {name!r} has no valid .npy header: {e}") from None
                header = f.tell()
            if dtype.hasobject:
                raise ValueError(f"{path}: {name!r} holds Python objects (a pickle), which are never loaded")
            nbytes = math.prod(shape) * dtype.itemsize
            if nbytes != member.file_size - header:
                raise ValueError(f"{path}: {name!r} declares shape {shape} of {dtype} ({nbytes:,} bytes) but holds "
                                 f"{member.file_size - header:,} bytes of data")
            total += nbytes
            out[name[:-4]] = (shape, dtype)
    if total > size:
        raise ValueError(f"{path}: its arrays declare {total:,} bytes of data, more than the file's {size:,} bytes "
                         "(compressed); ClosedLoop.save writes them uncompressed")
    return out


def _check_layout(path: str, declared: dict) -> None:
    """The fields' declared shapes and dtypes agree with one run of T steps (``inputs`` ``[T, m']``), or
    with B runs of T steps (``inputs`` ``[B, T, m']``: every field but ``times`` then leads with B)."""
    inputs = declared["inputs"][0]
    if len(inputs) not in (2, 3):
        raise ValueError(f"{path} is not a consistent ClosedLoop: inputs has shape {inputs}, expected [T, m'] "
                         "(one run) or [B, T, m'] (B runs)")
    batch = tuple(inputs[:1]) if len(inputs) == 3 else ()
    T = inputs[len(batch)]
    for name, (shape, dtype) in declared.items():
        lead, ndim, kinds = _LAYOUT[name]
        length = T + (lead == "T+1")
        first = () if name == "times" else batch
        if len(shape) != ndim + len(first) or tuple(shape[:len(first)]) != first \
                or shape[len(first)] != length or dtype.kind not in kinds:
            want = {"f": "floating", "iu": "integer", "b": "boolean"}[kinds]
            axes = f"leading axes B = {first[0]}, {lead} = {length}" if first else f"leading axis {lead} = {length}"
            raise ValueError(f"{path} is not a consistent ClosedLoop: {name} has shape {shape} dtype {dtype}, "
                             f"expected {ndim + len(first)} axes with {axes} (T from inputs "
                             f"{inputs}) and a {want} dtype")
