"""Progress bars for long runs (closed loops, sweeps), drawn by tqdm.

``with Progress(total, "label") as bar: bar.update(k)`` from Python loops;
``tick_python(step)`` reports to the innermost active bar. A run reports at
most ``TICKS`` times: every ``interval(total)`` steps and at its last step
(``due``). A compiled closed loop never calls back from inside its scan (a
host callback in the loop's program costs more than cheap steps,
docs/dev/xla_notes.md): it runs as chunks of ``interval(total)`` steps, one
compiled chunk dispatched again from Python, and reports between chunks.

The bar reads "compiling" until the first step is done and its clock starts
then, so rates and ETAs exclude compilation. tqdm picks the notebook or
terminal rendering and keeps non-TTY logs readable.
"""
from __future__ import annotations

import sys

from tqdm.auto import tqdm

_active: list = []
TICKS = 25  # most updates a run of any length sends to its bar (each costs a compiled loop a dispatch)


def interval(total: int) -> int:
    """Steps between two reports in a run of ``total`` steps (at most ``TICKS`` reports)."""
    return max(1, -(-int(total) // TICKS))


def due(step, total: int):
    """Whether step ``step`` (0-based) reports: every ``interval(total)`` steps and the last one."""
    done = step + 1
    return (done % interval(total) == 0) | (done == total)


class Progress:
    """A tqdm bar of ``total`` steps labelled ``label``; nothing when disabled."""

    def __init__(self, total: int, label: str = "", enabled: bool = True, stream=None):
        self.total, self.label, self.enabled = max(int(total), 1), label, enabled
        self.stream = stream or sys.stderr
        self._bar, self._started = None, False

    def update(self, done: int):
        """Report that ``done`` steps are finished."""
        if self._bar is None:
            return
        if not self._started:  # first step: compilation is over, start the clock now
            self._started = True
            self._bar.set_description(self.label)
            self._bar.reset(total=self.total)
        if done > self._bar.n:
            self._bar.update(done - self._bar.n)

    def __enter__(self):
        _active.append(self)
        if self.enabled:
            self._bar = tqdm(total=self.total, desc=f"{self.label} (compiling)", file=self.stream,
                             mininterval=0.1, dynamic_ncols=True)
        return self

    def __exit__(self, *exc):
        _active.remove(self)
        if self._bar is not None:
            if exc[0] is None:
                self.update(self.total)
            self._bar.close()


def tick_python(step) -> None:
    """From a Python loop: report that step ``step`` (0-based) is done (call it when ``due``)."""
    if _active:
        _active[-1].update(int(step) + 1)

