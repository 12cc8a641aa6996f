"""What a command is doing while it works: one line on stderr when a stage starts, one with its time when it
ends, so that no wait of the command line is silent (the closed loops draw their own bars)."""
from __future__ import annotations

import contextlib
import sys
import time


@contextlib.contextmanager
def stage(what: str, stream=None):
    """Announce ``what`` (a present participle: "compiling the decision"), then its seconds when done."""
    stream = stream or sys.stderr
    print(f"{what} ...", file=stream, flush=True)
    t0 = time.perf_counter()
    yield
    print(f"{what}: done in {time.perf_counter() - t0:.1f} s", file=stream, flush=True)
