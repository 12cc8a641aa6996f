"""Python's cyclic garbage collector kept out of a real-time loop.

A collection of the oldest generation walks every object the process holds
(about 128,000 once JAX and a controller are loaded): 0.07-0.4 s, inside
whichever decision allocated the object that set it off. A decision
(``FIRHC.step``) leaves no reference cycles, so its objects are freed as
they go whether the collector runs or not: pausing it for a loop of decisions
leaves nothing behind. Measured in ``benchmarks/realtime_bench.py``
(docs/guide/realtime.md).
"""
from __future__ import annotations

import contextlib
import gc


@contextlib.contextmanager
def collector_paused():
    """Python's cyclic garbage collector off inside the block, as it was after it (nothing is collected on the
    way out: a loop of decisions leaves no cycles behind). Reference counting frees objects as usual."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()
