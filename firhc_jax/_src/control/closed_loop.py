"""What a closed-loop run returns (``FIRHC.simulate``), and how it is kept and looked at.

``ClosedLoop`` holds per-step records: the fields of each step's ``StepInfo``
stacked over T steps, with the plant states and the applied inputs.
``run.save(path)`` writes them to one ``.npz`` (``numpy.load`` reads it, one
array per field); ``ClosedLoop.load(path)`` reads it back. ``run.plot()``
draws states, inputs, nodes and solve times into a new matplotlib ``Figure``
without touching pyplot, so the caller's backend and open figures are left as
they are.
"""
from __future__ import annotations

import math
import os
import zipfile
import zlib
from typing import NamedTuple, Optional

import jax
import numpy as np
from numpy.lib import format as npy

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

    def save(self, path) -> str:
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
    def load(cls, path) -> "ClosedLoop":
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

    def plot(self, title: str = "", state_names=None, input_names=None):
        """A new matplotlib ``Figure``: states, applied inputs (held steps
        marked), nodes per decision and solve times, against time in seconds
        when the run has ``times`` (``simulate(..., dt=)``), else the step
        index. ``state_names`` ``[n]`` and ``input_names`` ``[m']`` (e.g.
        ``"i_a [A]"``, units included) label the curves in legends; default
        ``x[0]``, ``u[0]``, ... Built without pyplot: the backend is never
        switched; show it with ``fig.savefig`` or display it in a notebook.
        A batched run (``simulate_batch``) draws, per step, the median over
        the loops and the band between the 10th and 90th percentiles (the
        extremes dotted) of every state and input, and the nodes' spread."""
        from matplotlib.figure import Figure

        if self.batched:
            return self._plot_batch(title, state_names, input_names)
        states, inputs = np.asarray(self.states), np.asarray(self.inputs)
        state_names = _names("state_names", state_names, states.shape[1], "x", "states [T+1, n]")
        input_names = _names("input_names", input_names, inputs.shape[1], "u", "inputs [T, m']")
        T = inputs.shape[0]
        t = np.arange(T + 1) if self.times is None else np.asarray(self.times)
        unit = "step" if self.times is None else "time [s]"
        fig = Figure(figsize=(8, 8), layout="constrained")
        ax = fig.subplots(4, 1, sharex=True)
        ax[0].plot(t, states, label=state_names)
        ax[0].set_ylabel("states")
        ax[0].legend(loc="best")
        ax[1].step(t[:-1], inputs, where="post", label=input_names)
        held = np.flatnonzero(np.asarray(self.held))
        if held.size:
            ax[1].plot(t[held], inputs[held, 0], "rx", label="held (no input found)")
        ax[1].legend(loc="best")
        ax[1].set_ylabel("inputs")
        ax[2].step(t[:-1], np.asarray(self.nodes), where="post", label="constrained search")
        if np.any(np.asarray(self.fallback_nodes)):
            ax[2].step(t[:-1], np.asarray(self.decision_nodes), where="post", label="with the fallback")
            ax[2].legend(loc="best")
        ax[2].set_ylabel("nodes")
        times = np.asarray(self.solve_times, float)
        if np.all(np.isnan(times)):
            ax[3].text(0.5, 0.5, "not timed (compiled scan; simulate(..., compiled=False) times each decision)",
                       ha="center", va="center", transform=ax[3].transAxes)
        else:
            ax[3].step(t[:-1], 1e3 * times, where="post")
        ax[3].set_ylabel("solve time [ms]")
        ax[3].set_xlabel(unit)
        if title:
            fig.suptitle(title)
        return fig


    def _plot_batch(self, title: str, state_names, input_names):
        """``plot`` of B loops: percentile bands over the loops, step by step."""
        from matplotlib.figure import Figure

        states, inputs = np.asarray(self.states), np.asarray(self.inputs)  # [B, T+1, n], [B, T, m']
        B, T = inputs.shape[:2]
        state_names = _names("state_names", state_names, states.shape[2], "x", "states [B, T+1, n]")
        input_names = _names("input_names", input_names, inputs.shape[2], "u", "inputs [B, T, m']")
        t = np.arange(T + 1) if self.times is None else np.asarray(self.times)
        fig = Figure(figsize=(8, 8), layout="constrained")
        ax = fig.subplots(3, 1, sharex=True)
        for a, values, names, x, held_over in ((ax[0], states, state_names, t, False),
                                               (ax[1], inputs, input_names, t[:-1], True)):
            for j, name in enumerate(names):
                _band(a, x, values[:, :, j], name, f"C{j % 10}", held_over)
            a.legend(loc="best", fontsize="small")
        ax[0].set_ylabel(f"states ({B} loops)")
        ax[1].set_ylabel("inputs")
        held = np.asarray(self.held).sum(axis=0)
        if held.any():
            steps = np.flatnonzero(held)
            ax[1].plot(t[steps], np.median(inputs[:, steps, 0], axis=0), "rx", label="a loop held (no input found)")
            ax[1].legend(loc="best", fontsize="small")
        _band(ax[2], t[:-1], np.asarray(self.decision_nodes, float), "nodes per decision", "C0", True)
        ax[2].set_ylabel("nodes")
        ax[2].legend(loc="best", fontsize="small")
        ax[2].set_xlabel("step" if self.times is None else "time [s]")
        fig.suptitle(title or f"{B} closed loops: median, 10-90 % band, extremes dotted")
        return fig


def _band(ax, x, values, name: str, color: str, steps: bool) -> None:
    """The median of ``values`` ``[B, len(x)]`` over the loops, its 10-90 % band and its extremes;
    ``steps``: held over each step (inputs, nodes) rather than joined (states)."""
    low, mid, high = np.percentile(values, [10, 50, 90], axis=0)
    draw = {"drawstyle": "steps-post"} if steps else {}
    ax.plot(x, mid, color=color, label=f"{name} (median)", **draw)
    ax.fill_between(x, low, high, color=color, alpha=0.25, linewidth=0, step="post" if steps else None)
    ax.plot(x, values.min(axis=0), color=color, linestyle=":", linewidth=0.8, **draw)
    ax.plot(x, values.max(axis=0), color=color, linestyle=":", linewidth=0.8, **draw)


def _names(arg: str, names, count: int, symbol: str, what: str) -> list[str]:
    """``count`` curve labels: the user's, checked, else ``symbol[i]``."""
    if names is None:
        return [f"{symbol}[{i}]" for i in range(count)]
    if isinstance(names, str) or not all(isinstance(n, str) for n in names):
        raise TypeError(f"{arg} must be a sequence of {count} strings, got {names!r}")
    names = list(names)
    if len(names) != count:
        raise ValueError(f"{arg} must name the run's {count} columns of {what}, got {len(names)}: {names}")
    return names


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
