"""Progress bars for long runs (closed loops, sweeps), drawn by tqdm.

``with Progress(total, "label") as bar: bar.update(k)`` from Python loops.
Inside a compiled loop call ``tick(step)`` (only when progress is on: it is a
host callback per step): it reports through ``jax.debug.callback`` to the
innermost active bar, so a cached compiled function reports to whichever bar
is open when it runs (no retracing).

The bar reads "compiling" until the first step is done and its clock starts
then, so rates and ETAs exclude compilation. tqdm picks the notebook or
terminal rendering and keeps non-TTY logs readable.
"""
from __future__ import annotations

import sys

import jax
from tqdm.auto import tqdm

_active: list = []


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
    """From a Python loop: report that step ``step`` (0-based) is done."""
    if _active:
        _active[-1].update(int(step) + 1)


def tick(step) -> None:
    """Inside a jitted loop body: report that step ``step`` (0-based) is done."""
    jax.debug.callback(tick_python, step)
