"""A controller that runs for days (issue 14): rebuilt problems and long closed
loops keep memory flat. Each soak runs in a fresh subprocess so that the
suite's own caches do not blur the counts."""
import json
import subprocess
import sys
import textwrap

import pytest

COMMON = """
import gc, json
import jax, jax.numpy as jnp, numpy as np, firhc_jax as fj

def usage():
    gc.collect()
    maps = sum(1 for _ in open("/proc/self/maps"))
    rss = int(open("/proc/self/statm").read().split()[1]) * 4096
    return maps, rss
"""


def _run(body: str) -> dict:
    code = COMMON + textwrap.dedent(body)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_rebuilt_problems_do_not_pile_up():
    """19 rebuilt problems through a cache of 2: the 12 compiled after the first 7 (by then the cache has
    evicted, and the allocator has warmed up) leave maps and memory flat. Unbounded (checked with
    ``set_cache_size(10**6)``), those 12 added about 970 maps and 43 MB."""
    r = _run("""
        fj.set_cache_size(2)
        counts = {}
        for i in range(19):
            p = fj.Problem(lambda x, u: 0.5 * x + u, [-1.0, 0.0, 1.0], fj.quadratic_cost(1.0, 0.001 * i), 2)
            fj.sdfs(p, jnp.ones(1))
            if i in (6, 18):
                counts[i] = usage()
        print(json.dumps({"maps": [counts[6][0], counts[18][0]], "rss": [counts[6][1], counts[18][1]],
                          "cache": fj.cache_info()["size"]}))
    """)
    assert r["maps"][1] - r["maps"][0] < 200, r
    assert r["rss"][1] - r["rss"][0] < 20 * 2**20, r
    assert r["cache"] <= 2


@pytest.mark.slow
def test_a_long_closed_loop_keeps_memory_flat():
    r = _run("""
        prob = fj.Problem(lambda x, u: jnp.stack([x[0] + 0.1 * x[1], 0.9 * x[1] + 0.1 * u[0]]),
                          jnp.array([-1.0, 0.0, 1.0]), fj.quadratic_cost(jnp.array([1.0, 0.1]), jnp.zeros(2)), 3)
        ctrl = fj.FIRHC(prob)
        x, seen = jnp.array([1.0, 0.0]), []
        for chunk in range(100):  # 10^5 steps in chunks of 1,000
            run = ctrl.simulate(x, 1000)
            x = run.states[-1]
            if chunk in (10, 99):
                seen.append(usage())
        print(json.dumps({"maps": [s[0] for s in seen], "rss": [s[1] for s in seen]}))
    """)
    assert r["maps"][1] - r["maps"][0] < 50, r
    assert r["rss"][1] - r["rss"][0] < 20 * 2**20, r
