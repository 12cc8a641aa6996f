"""A real-time loop: one decision per sampling period from your own loop, as a hardware interface, a ROS node
or a co-simulation would call it. ``ctrl.init`` gives the state before the first decision; ``ctrl.step`` is one
compiled decision (observe, search with a warm start, fallback, actuate) and never hands the plant a NaN. Where a
C compiler is on the PATH, the same loop runs again with ``engine="c"`` (each decision one call of generated C)
and gives the same inputs.

    python examples/realtime_loop.py [--quick] [--out DIR]
"""
import os
import shutil
import time

import jax
import jax.numpy as jnp
import numpy as np
from _common import arguments, say

import firhc_jax as fj

args = arguments(__doc__)
STEPS = 60 if args.quick else 400


@jax.jit
def pendulum(x, u):
    omega = x[1] + 0.05 * (-9.81 * jnp.sin(x[0]) - 0.5 * x[1] + 2.0 * u[0])
    return jnp.stack([x[0] + 0.05 * omega, omega])


class Hardware:
    """Stands in for the plant's interface: read the measured state, write the input for one period."""

    def __init__(self, x):
        self.x = x

    def read(self):
        return self.x

    def write(self, u):
        self.x = pendulum(self.x, u)


problem = fj.Problem(pendulum, jnp.array([-1.0, 0.0, 1.0]),
                     fj.quadratic_cost(lam=jnp.array([10.0, 1.0]), x_s=jnp.zeros(2), beta=0.1), 8,
                     terminal=lambda x: jnp.abs(x[0]) + 0.3 * jnp.abs(x[1]) < 0.6)


def run(ctrl, label):
    """The loop: ``STEPS`` decisions from the same initial state; returns the inputs applied."""
    hardware = Hardware(jnp.array([0.6, 0.0]))
    state = ctrl.init(hardware.read(), u0=jnp.zeros(1))
    say(f"real-time loop ({label}): compiling one decision before the loop starts")
    jax.block_until_ready(ctrl.step(state, hardware.read()))  # compile before the loop starts
    say(f"running {STEPS} decisions, one per period")
    times, held, inputs = [], 0, []
    for _ in range(STEPS):
        t0 = time.perf_counter()
        u, state, info = ctrl.step(state, np.asarray(hardware.read()))
        u = jax.block_until_ready(u)
        times.append(time.perf_counter() - t0)
        hardware.write(u)
        held += bool(info.held)
        inputs.append(np.asarray(u))
    us = np.asarray(times) * 1e6
    print(f"{label}: {STEPS} decisions: median {np.median(us):.0f} us, 99th percentile {np.percentile(us, 99):.0f} "
          f"us, slowest {us.max():.0f} us; {held} held; final state "
          f"{np.asarray(hardware.read()).round(4).tolist()}")
    assert held == 0 and float(jnp.abs(hardware.read()[0])) < 0.6
    return np.asarray(inputs)


options = dict(fallback="unconstrained", warm_start=True)
inputs = run(fj.FIRHC(problem, **options), "XLA")
if shutil.which(os.environ.get("CC") or "cc"):
    np.testing.assert_allclose(run(fj.FIRHC(problem, engine="c", **options), 'engine="c"'), inputs)
else:
    say('no C compiler on the PATH: the engine="c" loop is skipped')
