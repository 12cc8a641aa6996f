"""The long-horizon inverter: a three-level three-phase inverter (27 switch states, no -1 to +1 jump) tracks a
sinusoidal current at N = 10 with ``fj.LinearTracking``, the sphere decoder of FCS-MPC as sDFS with an exact
cost-to-go bound. The same decision is also searched as a plain problem of the 27 switch states, to show
what the bound and the classes of inputs save.

    python examples/long_horizon_inverter.py [--quick] [--out DIR]
"""
import jax
import numpy as np
from _common import arguments, say

import firhc_jax as fj
from firhc_jax.models import inverter, three_level

args = arguments(__doc__)
N, T = (4, 40) if args.quick else (10, 400)
params = three_level.PARAMS  # R = 2 ohm, L = 2 mH, Vdc = 400 V, Ts = 25 us, 20 A at 50 Hz

lt = three_level.make_problem(N, lambda_u=0.1)  # Q = I, 0.1 A^2 per unit leg step, |du| <= 1
refs = inverter.horizon_references(params, T, N)  # [T, N, 2]: the alpha-beta reference at k+1 .. k+N
ctrl = fj.FIRHC(lt.problem, observe=lt.observe, warm_start=True, pop_width=three_level.pop_width(N))
plant = jax.jit(lambda i, u, p: three_level.make_plant()(i, u))
say(f"three-level inverter: N = {N}, compiling and running a closed loop of {T} steps")
run = ctrl.simulate(inverter.initial_currents(params), T, plant=plant, params=lt.params(refs),
                    u0=np.zeros(3), dt=params.ts)
error = np.asarray(run.states[1:]) - inverter.reference(params, np.asarray(run.times[1:]))
print(f"N = {N}, {T} steps: rms current error {np.sqrt(np.mean(error**2)):.3f} A, nodes a decision "
      f"mean {float(run.nodes.mean()):.0f}, max {int(run.nodes.max()):,}")

# One decision from the start: lt.solve gives the exact optimum J; the plain tree of 27 switch states is far larger
say("one decision from the start with lt.solve")
best = lt.solve(inverter.initial_currents(params), np.zeros(3), refs[0])
tree = sum(27**i for i in range(1, N + 1))
print(f"one decision: J = {float(best.cost):.4f} A^2 with {int(best.nodes):,} nodes, of {tree:,} in the plain tree")
fig = run.plot(title=f"three-level inverter, LinearTracking, N = {N}", state_names=["i_alpha (A)", "i_beta (A)"],
               input_names=["leg a", "leg b", "leg c"])
fig.savefig(args.out / "long_horizon_inverter.png", dpi=100)
print(f"wrote {args.out / 'long_horizon_inverter.png'}")
