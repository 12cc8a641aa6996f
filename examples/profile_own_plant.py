"""Your own plant: write the problem, then let ``fj.profile`` time every search setting on states from your
own closed loop and name the fastest. The plant here is a buck converter with a diode (inductor current and
capacitor voltage, a switch on or off) whose output follows a ramp; any traceable plant works the same way.

    python examples/profile_own_plant.py [--quick] [--out DIR]
"""
import jax.numpy as jnp
import numpy as np
from _common import arguments, say

import firhc_jax as fj

args = arguments(__doc__)
L, C, R, VIN, TS = 100e-6, 47e-6, 5.0, 24.0, 10e-6  # H, F, ohm, V, s


def buck(x, u, k, p):  # x = [i_L (A), v_C (V)], u = [switch 0/1]; forward Euler, inductor current >= 0 (diode)
    i, v = x[0], x[1]
    i_next = jnp.maximum(i + TS / L * (VIN * u[0] - v), 0.0)
    v_next = v + TS / C * (i - v / R)
    return jnp.stack([i_next, v_next])


def cost(x_next, u, k, p):  # the output voltage against the ramp's value at that step of the horizon
    return (x_next[1] - p["v_ref"][k]) ** 2 + 1e-3 * x_next[0] ** 2


N, T = (4, 60) if args.quick else (6, 400)
problem = fj.Problem(buck, jnp.array([0.0, 1.0]), cost, N, step_index=True)
ramp = np.linspace(0.0, 12.0, T + N + 1)
params = {"v_ref": fj.horizon_windows(ramp, T, N)}  # [T, N]
say(f"buck converter: N = {N}, compiling and running a closed loop of {T} steps")
run = fj.FIRHC(problem).simulate(np.zeros(2), T, params=params, dt=TS)
print(f"closed loop: final output {float(run.states[-1, 1]):.2f} V against {ramp[T]:.2f} V")

say(f"profiling every search setting on the loop's {T} states (compiles each setting)")
rows = fj.profile(problem, run.states[:-1], params, pop_widths=(1, 2) if args.quick else (1, 2, 4),
                  lanes=(8,) if args.quick else (8, 64), repeats=1 if args.quick else 3)
for row in rows:
    print(f"{row['setting']:28s} {row['solves_per_second']:12,.0f} solves/s {row['nodes_per_second']:14,.0f} nodes/s"
          + ("  <- fastest" if row["fastest"] else ""))
