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

import os
from typing import NamedTuple, Optional

import jax
import numpy as np


class ClosedLoop(NamedTuple):
    """A closed-loop run of T steps (one ``StepInfo`` per step, stacked)."""

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
    def first_infeasible_step(self) -> Optional[int]:
        """Index of the first step whose terminal-constrained search found no sequence, or None."""
        bad = np.flatnonzero(~np.asarray(self.feasible))
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
        """A ``ClosedLoop`` of NumPy arrays from a file written by ``save``."""
        with np.load(os.fspath(path), allow_pickle=False) as data:
            names = set(data.files)
            required = [f for f in cls._fields if f not in cls._field_defaults]
            missing = [f for f in required if f not in names]
            if missing:
                raise ValueError(f"{os.fspath(path)} is not a saved ClosedLoop: it lacks {missing}")
            unknown = sorted(names - set(cls._fields))
            if unknown:
                raise ValueError(f"{os.fspath(path)} has arrays a ClosedLoop does not: {unknown}")
            return cls(**{name: data[name] for name in names})

    def plot(self, title: str = ""):
        """A new matplotlib ``Figure``: states, applied inputs (held steps
        marked), nodes per decision and solve times, against time when the run
        has ``times`` (else the step index). Built without pyplot: the
        backend is never switched; show it with ``fig.savefig`` or display it
        in a notebook."""
        from matplotlib.figure import Figure

        states, inputs = np.asarray(self.states), np.asarray(self.inputs)
        T = inputs.shape[0]
        t = np.arange(T + 1) if self.times is None else np.asarray(self.times)
        unit = "step" if self.times is None else "t [s]"
        fig = Figure(figsize=(8, 8), layout="constrained")
        ax = fig.subplots(4, 1, sharex=True)
        ax[0].plot(t, states)
        ax[0].set_ylabel("states")
        ax[1].step(t[:-1], inputs, where="post")
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
