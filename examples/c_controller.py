"""A controller that leaves Python: the pendulum's FIRHC exported as C99 (``fj.export_c``), compiled with a small C
main loop that reads a state a line from stdin and writes the input to apply, and run against a simulated plant.
The same loop with ``ctrl.step`` gives the same inputs; the example checks that and prints the C decision's
time.

    python examples/c_controller.py [--quick] [--out DIR]
"""
import shutil
import subprocess
import time

import jax
import jax.numpy as jnp
import numpy as np
from _common import arguments, say

import firhc_jax as fj

MAIN = r"""
#include <stdio.h>
#include "pendulum.h"

/* One decision a line: read the measured state "theta omega", write the input to apply and the return code. */
int main(void) {
    pendulum_state s;
    double x[PENDULUM_PLANT_NX], u[PENDULUM_PLANT_NU];
    pendulum_init(&s, NULL, NULL);
    while (scanf("%lf %lf", &x[0], &x[1]) == 2) {
        int code = pendulum_step(&s, x, NULL, u);
        printf("%.17g %d\n", u[0], code);
        fflush(stdout);
    }
    return 0;
}
"""

args = arguments(__doc__)
STEPS = 40 if args.quick else 200
if shutil.which("cc") is None:
    raise SystemExit("this example needs a C compiler (cc) on the PATH")


def pendulum(x, u):
    omega = x[1] + 0.05 * (-9.81 * jnp.sin(x[0]) - 0.5 * x[1] + 2.0 * u[0])
    return jnp.stack([x[0] + 0.05 * omega, omega])


problem = fj.Problem(pendulum, jnp.array([-1.0, 0.0, 1.0]),
                     fj.quadratic_cost(lam=jnp.array([10.0, 1.0]), x_s=jnp.zeros(2), beta=0.1), 8,
                     terminal=lambda x: jnp.abs(x[0]) + 0.3 * jnp.abs(x[1]) < 0.6)
ctrl = fj.FIRHC(problem, fallback="unconstrained", warm_start=True)
folder = args.out / "c_controller"
say(f"exporting the controller to {folder}")
exported = fj.export_c(ctrl, folder, name="pendulum", x0=np.zeros(2))
(folder / "main.c").write_text(MAIN)
binary = folder / "pendulum"
subprocess.run(["cc", "-std=c99", "-O2", "-o", str(binary), str(folder / "main.c"), str(exported.source), "-lm"],
               check=True)
say(f"compiled {binary}; running {STEPS} decisions through it and through ctrl.step")

step = jax.jit(pendulum)
controller = subprocess.Popen([str(binary)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
x, state, differ = np.array([0.6, 0.0]), ctrl.init(np.array([0.6, 0.0])), 0
for _ in range(STEPS):
    controller.stdin.write(f"{float(x[0])!r} {float(x[1])!r}\n")
    controller.stdin.flush()
    u_c, code = controller.stdout.readline().split()
    u, state, info = ctrl.step(state, x)
    differ += float(u_c) != float(u[0])
    x = np.asarray(step(jnp.asarray(x), jnp.asarray([float(u_c)])))
controller.stdin.close()
controller.wait()

lib = exported.compile()  # the same code called from Python, to time one decision
c_state = lib.init(np.zeros(2))
t0 = time.perf_counter()
for _ in range(200):
    lib.step(c_state, np.array([0.6, 0.0]))
per_call = (time.perf_counter() - t0) / 200
print(f"{STEPS} decisions through the C loop: {differ} differ from ctrl.step; final angle {x[0]:+.4f} rad")
print(f"C decision (ctypes call included): {1e6 * per_call:.1f} us; memory: {exported.work_bytes:,} bytes of stack "
      f"a call, a {exported.state_bytes}-byte controller state")
if differ:
    raise SystemExit(1)
