"""Tracking a reference along the horizon: the stage cost reads the target of each predicted state from the
parameters (``step_index=True``), a speed limit is a hard constraint, and one compiled closed loop serves any
reference of the same shape (``fj.horizon_windows`` cuts the windows every decision sees).

    python examples/tracking_reference.py [--quick] [--out DIR]
"""
import jax.numpy as jnp
import numpy as np
from _common import arguments, say

import firhc_jax as fj

args = arguments(__doc__)
N, T = (5, 60) if args.quick else (8, 200)


def pendulum(x, u, k, p):  # the step index k and parameters p are unused by the plant itself
    omega = x[1] + 0.05 * (-9.81 * jnp.sin(x[0]) - 0.5 * x[1] + 2.0 * u[0])
    return jnp.stack([x[0] + 0.05 * omega, omega])


def track(x_next, u, k, p):  # p["ref"] [N, 2]: the target of each predicted state
    return jnp.sum((x_next - p["ref"][k]) ** 2) + p["w"] * jnp.sum(u**2)


problem = fj.Problem(pendulum, jnp.array([-1.0, 0.0, 1.0]), track, N, step_index=True,
                     terminal_cost=lambda x, p: 10.0 * jnp.sum((x - p["ref"][-1]) ** 2),
                     constraint=lambda x, u, k, p: jnp.abs(x[1]) <= 1.5)  # a speed limit (rad/s)
t = np.arange(T + N)
signal = np.stack([0.3 * np.sin(0.05 * t), 0.3 * np.cos(0.05 * t)], 1)  # angle (rad), rate (rad/s), 50 ms steps
params = {"ref": fj.horizon_windows(signal, T, N), "w": np.full(T, 0.1)}  # [T, N, 2]: signal[t+1 .. t+N]
say(f"tracking a sine: N = {N}, compiling and running a closed loop of {T} steps")
run = fj.FIRHC(problem).simulate(np.zeros(2), T, params=params, dt=0.05)
error = np.asarray(run.states[1:, 0]) - signal[1:T + 1, 0]
print(f"rms angle error {np.sqrt(np.mean(error**2)):.4f} rad over {T} steps, most nodes a decision "
      f"{int(run.decision_nodes.max()):,}, fastest rate {float(np.abs(run.states[:, 1]).max()):.3f} rad/s")
assert float(np.abs(run.states[:, 1]).max()) <= 1.5 + 1e-9  # the constraint held along the run
fig = run.plot(title="tracking a sine along the horizon", state_names=["angle (rad)", "rate (rad/s)"],
               input_names=["torque (N m)"])
fig.axes[0].plot(np.asarray(run.times), signal[:T + 1, 0], "k--", label="reference angle (rad)")
fig.axes[0].legend(loc="upper right", fontsize="small")
fig.savefig(args.out / "tracking_reference.png", dpi=100)
print(f"wrote {args.out / 'tracking_reference.png'}")
