"""Quick start: a pendulum with three torque levels brought into a terminal set, solved exactly by the sorted
depth-first search and by exhaustive search, then controlled in a closed loop.

    python examples/quickstart.py [--quick] [--out DIR]
"""
import jax.numpy as jnp
from _common import arguments, say

import firhc_jax as fj

args = arguments(__doc__)


def pendulum(x, u):  # x [2] (angle rad, rate rad/s), u [1] (torque) -> x one 50 ms step later
    omega = x[1] + 0.05 * (-9.81 * jnp.sin(x[0]) - 0.5 * x[1] + 2.0 * u[0])
    return jnp.stack([x[0] + 0.05 * omega, omega])


problem = fj.Problem(
    dynamics=pendulum,
    controls=jnp.array([-1.0, 0.0, 1.0]),  # the finite input set
    stage_cost=fj.quadratic_cost(lam=jnp.array([10.0, 1.0]), x_s=jnp.zeros(2), beta=0.1),
    horizon=12,  # 3^12 input sequences
    terminal=lambda x: jnp.abs(x[0]) + 0.3 * jnp.abs(x[1]) < 0.6,  # a diamond around the origin
)
x0 = jnp.array([0.6, 0.0])
say(f"quickstart: N = {problem.horizon}, {problem.tree_size():,} nodes in the tree; sDFS, then exhaustive search")
best = fj.sdfs(problem, x0)
ref = fj.exhaustive(problem, x0)
print(f"sDFS: cost {float(best.cost):.6f} with {int(best.nodes):,} nodes; exhaustive: cost {float(ref.cost):.6f} "
      f"with {int(ref.nodes):,} nodes (sDFS computed {int(best.nodes) / int(ref.nodes):.1%} of them)")
assert float(best.cost) == float(ref.cost)

ctrl = fj.FIRHC(problem, fallback="unconstrained")
say("compiling and running the closed loop")
run = ctrl.simulate(x0, steps=30 if args.quick else 80, dt=0.05)
final = [round(float(v), 4) for v in run.states[-1]]
print(f"closed loop: final state {final}, at most {int(run.decision_nodes.max()):,} nodes a decision, "
      f"{int(run.held.sum())} held steps")
fig = run.plot(title="pendulum under FIRHC", state_names=["angle (rad)", "rate (rad/s)"],
               input_names=["torque (N m)"])
fig.savefig(args.out / "quickstart.png", dpi=100)
print(f"wrote {args.out / 'quickstart.png'}")
