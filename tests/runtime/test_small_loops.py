"""``fj.enable_small_loop_kernels``: an explicit, process-wide opt-in, refused once JAX has started, and the
same decisions with it (each case in a fresh process: the setting is the process's; a cost may differ in its
last bit, the loop compiled as one kernel rounding its multiply-adds apart)."""
import os
import subprocess
import sys

import pytest
from repository import ROOT

SEARCH = """
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
import firhc_jax as fj
def pendulum(x, u):
    omega = x[1] + 0.05 * (-9.81 * jnp.sin(x[0]) - 0.5 * x[1] + 2.0 * u[0])
    return jnp.stack([x[0] + 0.05 * omega, omega])
cost = fj.quadratic_cost(jnp.array([10.0, 1.0]), jnp.zeros(2), 0.1)
problem = fj.Problem(pendulum, jnp.array([-1.0, 0.0, 1.0]), cost, 5)
r = fj.sdfs(problem, np.array([0.6, 0.0]))
print("RESULT", repr(float(r.cost)), int(r.nodes), np.asarray(r.sequence).tolist())
"""


def run(code: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("XLA_FLAGS", None)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)


def test_the_opt_in_sets_both_flags_and_searches_alike():
    plain = run(SEARCH)
    opted = run("import os, firhc_jax as fj\nflags = fj.enable_small_loop_kernels()\n"
                "assert os.environ['XLA_FLAGS'] == flags and 'small_while_loop_byte_threshold=1000000000' in flags\n"
                "assert 'ynn_fusion_type' in flags\n" + SEARCH)
    assert plain.returncode == 0 and opted.returncode == 0, plain.stderr[-2000:] + opted.stderr[-2000:]
    (a,), (b,) = ([line.split(maxsplit=2)[1:] for line in out.stdout.splitlines() if line.startswith("RESULT")]
                  for out in (plain, opted))
    assert a[1] == b[1]  # nodes and sequence
    assert abs(float(a[0]) - float(b[0])) <= 1e-12 * abs(float(a[0]))  # one kernel may round the last bit apart


def test_the_opt_in_is_refused_once_jax_has_started():
    done = run("import jax.numpy as jnp, firhc_jax as fj\njnp.ones(2).block_until_ready()\n"
               "try:\n    fj.enable_small_loop_kernels()\nexcept RuntimeError as e:\n    print('REFUSED', e)\n")
    assert done.returncode == 0, done.stderr[-2000:]
    assert "REFUSED" in done.stdout and "XLA_FLAGS" in done.stdout


@pytest.mark.parametrize("value", [0, -1, 1.5, True])
def test_a_threshold_that_is_not_a_positive_int_is_refused(value):
    import firhc_jax as fj

    with pytest.raises(ValueError, match="byte_threshold"):
        fj.enable_small_loop_kernels(value)
