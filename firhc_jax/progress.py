"""A dependency-free text progress bar for long runs (closed loops, sweeps).

``with Progress(total, "label") as bar: bar.update(k)`` from Python loops.
Inside a compiled loop call ``tick(step)``: it reports through
``jax.debug.callback`` to the innermost active bar, so a cached compiled
function reports to whichever bar is open when it runs (no retracing).
"""
from __future__ import annotations

import sys
import time

import jax

_active: list = []


class Progress:
    """Prints ``label [#####.....] k/total  elapsed  eta`` on stderr; silent when disabled."""

    def __init__(self, total: int, label: str = "", enabled: bool = True, stream=None):
        self.total, self.label, self.enabled = max(int(total), 1), label, enabled
        self.stream = stream or sys.stderr
        self.start = time.perf_counter()
        self._last, self._shown = -1.0, -1

    def update(self, done: int):
        if not self.enabled or done == self._shown:
            return
        now = time.perf_counter()
        if done < self.total and now - self._last < 0.1:
            return
        self._last, self._shown = now, done
        frac = min(done / self.total, 1.0)
        elapsed = now - self.start
        eta = f"{elapsed / frac - elapsed:6.1f}s" if frac > 0 else "     ?"
        bar = "#" * int(30 * frac) + "." * (30 - int(30 * frac))
        self.stream.write(f"\r{self.label} [{bar}] {done}/{self.total}  {elapsed:6.1f}s  eta {eta}")
        self.stream.flush()

    def __enter__(self):
        _active.append(self)
        self.start = time.perf_counter()
        self.update(0)
        return self

    def __exit__(self, *exc):
        _active.remove(self)
        if self.enabled:
            self.update(self.total)
            self.stream.write("\n")
            self.stream.flush()


def tick_python(step) -> None:
    """From a Python loop: report that step ``step`` (0-based) is done."""
    if _active:
        _active[-1].update(int(step) + 1)


def tick(step) -> None:
    """Inside a jitted loop body: report that step ``step`` (0-based) is done."""
    jax.debug.callback(tick_python, step)
