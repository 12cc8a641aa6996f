"""Fixtures of the controller's tests."""
import pytest

import firhc_jax as fj
from firhc_jax._src.control import runner
from firhc_jax._src.runtime import progress


@pytest.fixture
def ticks(monkeypatch) -> list:
    """The steps the progress bar is told of, in order, from the compiled loop's callback and the Python loop."""
    told = []
    original = progress.tick_python

    def counting(step):
        told.append(int(step))
        return original(step)

    monkeypatch.setattr(progress, "tick_python", counting)  # reached from the compiled loop's callback
    monkeypatch.setattr(runner, "tick_python", counting)  # called by the Python loop
    fj.clear_cache()  # a closed loop compiled earlier would hold the original callback
    return told
