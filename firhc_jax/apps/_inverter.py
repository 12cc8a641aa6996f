"""What the two inverter variants of ``python -m firhc_jax inverter`` share (not a command): the run record,
the waveform metrics of its summary, and its figure."""
from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

import firhc_jax as fj
from firhc_jax.models import inverter as model


class InverterRun(NamedTuple):
    """One closed-loop run of T steps."""

    loop: fj.ClosedLoop  # the controller's record (states: alpha-beta load currents i(0) .. i(T), A)
    references: np.ndarray  # [T+1, 2] alpha-beta reference at the same instants, A
    compile_time: float  # s tracing and compilation of one decision (NaN: not timed)

    # The loop's records as NumPy arrays, in the inverter's terms.
    currents = property(lambda self: np.asarray(self.loop.states), doc="[T+1, 2] alpha-beta load currents, A")
    inputs = property(lambda self: np.asarray(self.loop.inputs), doc="[T, 3] applied leg levels")
    predicted_costs = property(lambda self: np.asarray(self.loop.predicted_costs),
                               doc="[T] optimal cost of each decision, A^2")
    nodes = property(lambda self: np.asarray(self.loop.nodes), doc="[T] nodes per decision")
    solve_times = property(lambda self: np.asarray(self.loop.solve_times),
                           doc="[T] s wall time of each decision (compiled, compilation excluded)")


def spectrum(signal: np.ndarray, ts: float) -> tuple[np.ndarray, np.ndarray]:
    """One-sided amplitude spectrum ``(f [Hz], |X| [A peak])``; free of leakage over whole fundamental cycles."""
    n = signal.shape[0]
    amp = np.abs(np.fft.rfft(signal)) * 2.0 / n
    amp[0] /= 2.0
    return np.fft.rfftfreq(n, ts), amp


def waveform_metrics(run: InverterRun, params: model.InverterParams) -> dict:
    """The phase currents' figures of a run, as both summaries report them (currents in A, frequencies in Hz).

    Switching frequency per leg and leg changes: ``model.switching_frequency`` and ``model.commutations``
    of the applied levels; THD: ``model.distortion`` of each phase over the run.
    """
    steps = run.inputs.shape[0]
    seconds = steps * params.ts
    phases = model.to_phases(run.currents[:-1])  # [T, 3], one record of whole cycles
    errors = model.to_phases(run.references - run.currents)  # [T+1, 3]
    fundamentals, thds = zip(*(model.distortion(phases[:, x], params) for x in range(3)), strict=True)
    return {
        "rms_tracking_error": float(np.sqrt(np.mean(errors**2))),
        "current_amplitude": float(np.mean(fundamentals)),
        "switching_frequency_hz": model.switching_frequency(run.inputs, params),
        "thd": float(np.mean(thds)),
        "thd_phases": list(thds),
        "current_amplitudes": list(fundamentals),
        "leg_changes": model.commutations(run.inputs).tolist(),
        "steps": steps,
        "seconds": seconds,
        "parameters": {"vdc": params.vdc, "r": params.r, "l": params.l, "ts": params.ts,
                       "amplitude": params.amplitude, "frequency": params.frequency},
    }


def plot(run: InverterRun, path: Path, params: model.InverterParams, title: str = "") -> None:
    """Phase currents against references (at most three cycles) and the spectrum of phase a with its THD."""

    from ._plot import subplots

    shown = min(run.currents.shape[0], 3 * params.steps_per_cycle + 1)
    t = np.arange(shown) * params.ts * 1e3  # ms
    currents, refs = model.to_phases(run.currents[:shown]), model.to_phases(run.references[:shown])
    fig, (ax_i, ax_s) = subplots(2, 1, figsize=(9, 7), gridspec_kw={"height_ratios": [3, 2]})
    for x, (name, c) in enumerate(zip("abc", ("tab:blue", "tab:orange", "tab:green"), strict=True)):
        ax_i.plot(t, currents[:, x], color=c, lw=0.8, label=f"$i_{name}$")
        ax_i.plot(t, refs[:, x], color="k", ls="--", lw=0.6)
    ax_i.plot([], [], color="k", ls="--", lw=0.6, label="reference")
    ax_i.set_xlabel("time [ms]")
    ax_i.set_ylabel("phase current [A]")
    ax_i.legend(loc="upper right", ncol=4, fontsize=8)
    ax_i.set_title(title)
    phase_a = model.to_phases(run.currents[:-1])[:, 0]
    whole = phase_a.shape[0] // params.steps_per_cycle * params.steps_per_cycle  # spectrum over whole cycles
    f, amp = spectrum(phase_a[:whole or None], params.ts)
    fundamental, thd = model.distortion(phase_a, params)
    ax_s.semilogy(f[1:] * 1e-3, np.maximum(amp[1:] / fundamental * 100.0, 1e-4), color="tab:blue", lw=0.7)
    ax_s.set_ylim(1e-3, 200)
    ax_s.set_xlim(0, f[-1] * 1e-3)
    ax_s.set_xlabel("frequency [kHz]")
    ax_s.set_ylabel("$|I_a(f)|$ [% of fundamental]")
    ax_s.set_title(f"phase a: fundamental {fundamental:.3f} A, THD {thd * 100:.2f} %", fontsize=10)
    for ax in (ax_i, ax_s):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def figure(run: InverterRun, out, name: str, params: model.InverterParams, title: str) -> list[Path]:
    """``plot`` into ``out / name``; the list of the one path written, as ``App.plot`` returns it."""
    path = Path(out) / name
    plot(run, path, params, title)
    return [path]


def report(head: str, summary: dict) -> str:
    """The line an inverter run prints after ``head``: amplitude, distortion, switching, work, time."""
    return (f"{head}: amplitude {summary['current_amplitude']:.4f} A, rms error "
            f"{summary['rms_tracking_error']:.4f} A, THD {summary['thd'] * 100:.2f} %, switching "
            f"{summary['switching_frequency_hz']:.0f} Hz per leg, nodes/step {summary['nodes_mean']:,.1f} mean / "
            f"{summary['nodes_max']:,} max, {summary['solve_time_median_s'] * 1e3:.3f} ms median / "
            f"{summary['solve_time_max_s'] * 1e3:.2f} ms max per decision")
