"""Where the benchmarks' figures go: each script prints its tables, and with ``--publish`` the same text is
written to ``benchmarks/results/<name>.md`` under a header naming the machine, the load, the versions and the
date. The documentation's performance page includes those files, so every measured figure it shows comes from
one run of one script."""
from __future__ import annotations

import contextlib
import io
import os
import sys
import time
from pathlib import Path

from firhc_jax.apps._machine import machine

RESULTS = Path(__file__).parent / "results"


def _load() -> str:
    try:
        return ", ".join(f"{x:.1f}" for x in os.getloadavg())
    except OSError:
        return "unknown"


class _Tee(io.TextIOBase):
    def __init__(self, *streams):
        self.streams = streams

    def write(self, text):
        for s in self.streams:
            s.write(text)
        return len(text)

    def flush(self):
        for s in self.streams:
            s.flush()


@contextlib.contextmanager
def published(name: str, publish: bool, command: str):
    """Print as usual; with ``publish`` also keep what was printed in ``benchmarks/results/<name>.md``."""
    if not publish:
        yield
        return
    kept, start, load = io.StringIO(), time.strftime("%Y-%m-%d %H:%M"), _load()
    out = sys.stdout
    sys.stdout = _Tee(out, kept)
    try:
        yield
    finally:
        sys.stdout = out  # a run that fails publishes nothing: the exception passes on from here
    RESULTS.mkdir(parents=True, exist_ok=True)
    header = (f"*Measured by `{command}` on {start}: {machine()}; load average (1, 5, 15 min) {load} at the start, "
              f"{_load()} at the end.*\n\n")
    (RESULTS / f"{name}.md").write_text(header + kept.getvalue())
    print(f"wrote {RESULTS / f'{name}.md'}", file=sys.stderr)
