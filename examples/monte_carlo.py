"""A Monte Carlo of closed loops with ``simulate_batch``: spacecraft attitude control with three pairs of
on/off thrusters (27 torque patterns), B loops from random attitudes with random inertias and fuel prices,
one compiled run over every CPU core. Loop b makes the decisions ``simulate`` would make from ``X0[b]``.

    python examples/monte_carlo.py [--quick] [--out DIR]
"""
import numpy as np
from _common import arguments, say

import firhc_jax as fj
from firhc_jax.models import spacecraft

args = arguments(__doc__)
B, T, N = (8, 15, 2) if args.quick else (128, 60, 3)
rng = np.random.default_rng(0)

X0, inertia = spacecraft.random_loops(B, rng)  # [B, 6] attitudes and rates, [B, 3] principal moments
fuel = rng.uniform(1.0, 5.0, B)  # deg^2 per firing thruster pair and sample, one price per loop
params = spacecraft.step_params(inertia, fuel, T)  # leaves [B, T, ...]: loop b, step k
ctrl = fj.FIRHC(spacecraft.make_problem(N))
say(f"Monte Carlo: {B} spacecraft loops of {T} steps, N = {N}; compiling and running them in one batch")
runs = ctrl.simulate_batch(X0, T, plant=spacecraft.make_plant(), params=params, dt=spacecraft.PARAMS.ts,
                           progress=not args.quick)
start, final = spacecraft.pointing_error(X0), spacecraft.pointing_error(np.asarray(runs.states[:, -1]))
print(f"{B} loops of {T} steps: pointing error median {np.median(start):.2f} -> {np.median(final):.3f} deg, "
      f"worst {final.max():.3f} deg; nodes a decision at most {int(runs.decision_nodes.max()):,}")
assert np.median(final) < np.median(start)
fig = runs.plot(title=f"{B} spacecraft loops", state_names=[f"MRP {a}" for a in "123"]
                + [f"rate {a} (rad/s)" for a in "xyz"], input_names=[f"thrusters {a}" for a in "xyz"])
fig.savefig(args.out / "monte_carlo.png", dpi=100)
print(f"wrote {args.out / 'monte_carlo.png'}")
