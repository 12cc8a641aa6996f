"""The machine a measurement ran on, named one way by every command and benchmark that prints figures."""
from __future__ import annotations

import platform

import jax

from ..distributed import usable_cores


def machine() -> str:
    """The processor's model name, the cores this process may use, JAX's version and platform."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return f"{cpu}, {usable_cores()} usable cores, jax {jax.__version__} on {jax.devices()[0].platform}"
