"""Progress bars for long runs (closed loops, sweeps), drawn by tqdm.

``with Progress(total, "label") as bar: bar.update(k)`` from Python loops.
Inside a compiled loop call ``tick(step, total)`` (only when progress is on):
it reports through ``jax.debug.callback`` to the innermost active bar, so a
cached compiled function reports to whichever bar is open when it runs (no
retracing). A host callback costs about 20 times a small decision
(benchmarks/RESULTS.md, issue 24), so a run reports at most ``TICKS`` times:
every ``interval(total)`` steps and at its last step (``due``).

The bar reads "compiling" until the first step is done and its clock starts
then, so rates and ETAs exclude compilation. tqdm picks the notebook or
terminal rendering and keeps non-TTY logs readable.
"""
from __future__ import annotations

import sys

import jax
from tqdm.auto import tqdm

_active: list = []
TICKS = 100  # most updates a run of any length sends to its bar


def interval(total: int) -> int:
    """Steps between two reports in a run of ``total`` steps (at most ``TICKS`` reports)."""
    return max(1, -(-int(total) // TICKS))


def due(step, total: int):
    """Whether step ``step`` (0-based) reports: every ``interval(total)`` steps and the last one.
    Works on Python ints and on traced steps."""
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


def tick(step, total: int) -> None:
    """Inside a jitted loop body of ``total`` steps: report that step ``step``
    (0-based, traced) is done, when it is ``due`` (a host callback only then)."""
    if interval(total) == 1:
        jax.debug.callback(tick_python, step)
    else:
        jax.lax.cond(due(step, total), lambda k: jax.debug.callback(tick_python, k), lambda k: None, step)
