"""Progress bars for long runs (closed loops, batches, profiles), drawn by tqdm.

``with Progress(total, "label", progress) as bar: bar.update(k)`` from Python
loops; ``tick_python(step)`` reports to the innermost active bar of the
calling thread (calls in other threads have bars of their own). A run
reports at most ``TICKS`` times: every ``interval(total)`` steps and at its
last step (``due``). A compiled closed loop never calls back from inside its
scan (a host callback in the loop's program costs more than cheap steps,
docs/dev/xla_notes.md): it runs as chunks of ``interval(total)`` steps, one
compiled chunk dispatched again from Python, and reports between chunks.

``progress``: ``True`` draws the bar at once, ``False`` never, ``None``
(automatic, every long call's default) once the call has run ``AFTER_S``
seconds: a watcher thread draws it then if the call has not reported yet
(the elapsed time, where a call runs as one compiled program and cannot
report), else the first report after that does. Until then an automatic call
costs a few microseconds. A compiled loop, which can report only by running
in chunks, asks ``chunked``: from the seconds a unit of work took in the
last call of the same compiled program (``record``), chunks only when this
call is expected to run over ``AFTER_S``; a first call runs as one program.
A batch of rows chunks only with ``progress=True``, and only where its rows
are solved apart (``solve_batch``: chunks would regroup a work pool's rows,
and so change their results); otherwise its bar shows the time elapsed and
the time expected (``expected_s``).

The bar reads "compiling" until the first step is done and its clock starts
then, so rates and ETAs exclude compilation. tqdm picks the notebook or
terminal rendering and keeps non-TTY logs readable.
"""
from __future__ import annotations

import collections
import sys
import threading
import time
from typing import Hashable, Optional

from tqdm.auto import tqdm

_local = threading.local()  # .bars: each thread's active bars, innermost last
TICKS = 25  # most updates a run of any length sends to its bar (each costs a compiled loop a dispatch)
AFTER_S = 2.0  # an automatic bar appears once its call has run this long
_RATES_KEPT = 64  # compiled programs whose seconds per unit are remembered (least recently used dropped)
_rates: "collections.OrderedDict[Hashable, float]" = collections.OrderedDict()


def _active() -> list:
    """The bars of this thread's calls, innermost last: a call's steps move its own bar, whatever other threads
    run."""
    bars = getattr(_local, "bars", None)
    if bars is None:
        bars = _local.bars = []
    return bars


def current() -> Optional["Progress"]:
    """The innermost bar of this thread's calls, or None."""
    bars = _active()
    return bars[-1] if bars else None


def interval(total: int) -> int:
    """Steps between two reports in a run of ``total`` steps (at most ``TICKS`` reports)."""
    return max(1, -(-int(total) // TICKS))


def due(step, total: int):
    """Whether step ``step`` (0-based) reports: every ``interval(total)`` steps and the last one."""
    done = step + 1
    return (done % interval(total) == 0) | (done == total)


def chunked(progress: Optional[bool], key: Hashable, units: int) -> bool:
    """Whether a call of ``units`` units of the compiled program ``key`` runs in chunks that report:
    ``progress`` if given, else (automatic) when the last call of ``key`` says this one takes ``AFTER_S``
    or more."""
    if progress is not None:
        return bool(progress)
    rate = _rates.get(key)
    return rate is not None and rate * units >= AFTER_S


def expected_s(key: Hashable, units: int) -> Optional[float]:
    """The seconds a call of ``units`` units of the compiled program ``key`` should take, from its last call
    (``record``); None before its first."""
    rate = _rates.get(key)
    return None if rate is None else rate * units


def record(key: Hashable, units: int, seconds: float) -> None:
    """``key``'s last call ran ``units`` units in ``seconds`` (compilation excluded)."""
    _rates[key] = seconds / max(units, 1)
    _rates.move_to_end(key)
    while len(_rates) > _RATES_KEPT:
        _rates.popitem(last=False)


class Progress:
    """A tqdm bar of ``total`` steps labelled ``label``: drawn at once (``enabled`` True), never (False), or
    once the call has run ``AFTER_S`` seconds (None). ``counted=False``: a call that cannot report its steps
    (one compiled program); its bar shows the time elapsed, and the seconds the call should take where
    ``expected`` says (the last call of the same program: ``expected_s``), and ``uncounted``: why, or what
    would count them."""

    def __init__(self, total: int, label: str = "", enabled: Optional[bool] = True, stream=None,
                 counted: bool = True, expected: Optional[float] = None,
                 uncounted: str = "progress=True counts its steps"):
        self.total, self.label, self.enabled, self.counted = max(int(total), 1), label, enabled, counted
        self.expected, self.uncounted = expected, uncounted
        self.stream = stream or sys.stderr
        self._bar, self._started, self._since, self._done = None, False, 0.0, 0
        self._waiting = " (compiling)"  # said until the first step is done
        self._closed = False  # the call is over: the watcher draws nothing more
        self._drawn = 0.0  # seconds into the call at the watcher's last redraw
        self._tty = getattr(self.stream, "isatty", lambda: False)()
        self._lock = threading.Lock()

    def update(self, done: int):
        """Report that ``done`` steps are finished."""
        self._done = done
        if self._bar is None and (self.enabled is not None or time.monotonic() - self._since < AFTER_S):
            return
        self.show()

    def show(self):
        """Draw the bar now, at the steps reported so far (an automatic bar: its first report after ``AFTER_S``
        seconds, or the watcher then)."""
        with self._lock:
            if self._closed:
                return
            if self._bar is None and self.counted:
                self._bar = tqdm(total=self.total, desc=self.label + self._waiting, file=self.stream,
                                 mininterval=0.1, dynamic_ncols=True)
            elif self._bar is None:
                run = ("compiling, then one compiled run" if self.expected is None else
                       f"one compiled run of about {_duration(self.expected)}, as the last one")
                self._bar = tqdm(total=None, desc=f"{self.label} ({run}: not counted; {self.uncounted})",
                                 file=self.stream, dynamic_ncols=True, bar_format="{desc}: {elapsed}",
                                 delay=1e-9)  # drawn below, with the call's time
                self._bar.start_t -= time.monotonic() - self._since
                self._bar.refresh()
            if self._done and not self._started:  # first step: compilation is over, start the clock now
                self._started = True
                self._bar.set_description(self.label)
                self._bar.reset(total=self.total)
            if self._done > self._bar.n:
                self._bar.update(self._done - self._bar.n)

    def describe(self, label: str):
        """Label the bar ``label`` from now on (what the call is doing)."""
        with self._lock:
            self.label, self._waiting = label, ""
            if self._bar is not None:
                self._bar.set_description(label)

    def tick(self):
        """Redraw the elapsed time (the watcher, while the call runs): every second in a terminal, every 10 %
        of the time elapsed in a log (a file or a pipe keeps each redraw)."""
        with self._lock:
            elapsed = time.monotonic() - self._since
            if self._bar is None or elapsed < self._drawn + max(1.0, 0.0 if self._tty else 0.1 * elapsed):
                return
            self._drawn = elapsed
            self._bar.refresh()

    def __enter__(self):
        _active().append(self)
        self._since = time.monotonic()  # when the call started: a bar that cannot count shows the time since
        if self.enabled:
            self.show()
        elif self.enabled is None:
            _WATCHER.watch(self)
        return self

    def __exit__(self, *exc):
        bars = _active()
        bars.remove(self)
        if self.enabled is None:  # the enclosing automatic bar of this thread, if any, is watched again
            _WATCHER.watch(next((b for b in reversed(bars) if b.enabled is None), None))
        if self._bar is not None and exc[0] is None and self.counted:
            self.update(self.total)
        with self._lock:
            self._closed = True
            if self._bar is not None:
                self._bar.close()


def _duration(seconds: float) -> str:
    """``seconds`` as a bar says it: "40 s", "12 min", "3.5 h"."""
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


class _Watcher:
    """One daemon thread that draws an automatic bar whose call has run ``AFTER_S`` seconds, and redraws its
    elapsed time: the innermost automatic bar of each thread's calls. It looks every ``POLL_S`` seconds while
    calls come, so that a call only sets its thread's entry of ``bars`` (no thread is woken: a short call
    costs a microsecond more), and sleeps until the next call after ``IDLE_S`` seconds without one (so that
    it never wakes inside a user's real-time loop)."""

    POLL_S, IDLE_S = 0.25, 5.0

    def __init__(self):
        self._cond = threading.Condition()
        self.bars: dict[int, Progress] = {}  # the call being watched in each thread, by thread
        self._asleep, self._thread = True, None
        self._last = 0.0  # when a call was last watched

    def watch(self, bar: Optional[Progress]) -> None:
        """Watch ``bar`` for the calling thread (None: its calls are over)."""
        if bar is None:
            self.bars.pop(threading.get_ident(), None)
        else:
            self.bars[threading.get_ident()] = bar
        self._last = time.monotonic()
        if bar is not None and self._asleep:
            with self._cond:
                self._asleep = False
                if self._thread is None:
                    self._thread = threading.Thread(target=self._run, name="firhc_jax progress", daemon=True)
                    self._thread.start()
                self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: not self._asleep)
            time.sleep(self.POLL_S)
            bars, now = tuple(self.bars.values()), time.monotonic()
            if not bars:
                if now - self._last > self.IDLE_S:
                    with self._cond:
                        self._asleep = not self.bars
                continue
            for bar in bars:
                if now - bar._since >= AFTER_S:
                    if bar._bar is None:
                        bar.show()
                    else:
                        bar.tick()


_WATCHER = _Watcher()


def tick_python(step) -> None:
    """From a Python loop: report that step ``step`` (0-based) is done (call it when ``due``), to the innermost
    bar of this thread."""
    bar = current()
    if bar is not None:
        bar.update(int(step) + 1)
