"""The Numba peers (``benchmarks/numba_peer.py``) agree with ``fj.sdfs`` and ``fj.exhaustive``: the same decisions
(sequence and node count) from every state, and costs equal to ``COST_RTOL``. Not bit for bit: XLA fuses
multiply-adds differently from one program to another and with its optimizations off (the quick suite), so
costs differ in their last bits (up to 4e-16 relative here), between ``fj.sdfs`` and ``fj.exhaustive`` too.

Needs the bench extra (``pip install -e ".[test,bench]"``); without Numba it is skipped, so it is run where
Numba is installed: ``python -m pytest --full tests/project/test_numba_peer.py``. Slow (JIT-compiling the peers and
the library's searches: 20-40 s), so the quick suite leaves it out.
"""
import sys

import numpy as np
import pytest

import firhc_jax as fj
from firhc_jax.models import tanks
from firhc_jax.models.synthetic import SyntheticParams, benchmark_state, make_problem

pytest.importorskip("numba", reason="the Numba peer check needs the bench extra: pip install -e '.[test,bench]' "
                                    "(README, Tests)")
from repository import BENCHMARKS

sys.path.insert(0, str(BENCHMARKS))
import numba_peer as peer  # noqa: E402

pytestmark = pytest.mark.slow
N = 3
COST_RTOL = 1e-12  # relative: about 2,500 times the largest difference seen (4e-16)


def _cases():
    rng = np.random.default_rng(7)
    syn = make_problem(N, SyntheticParams(17), dtype=np.float64)
    x_syn = np.vstack([np.asarray(benchmark_state(np.float64)), rng.uniform(-1, 1, (3, 3))])
    x_tank = np.zeros((4, 5))
    x_tank[:, :3] = rng.uniform(0.05, 0.5, (4, 3))
    x_tank[:, 3] = rng.integers(0, tanks.NUM_MODES, 4)
    tank = tanks.make_problem(N)
    return [("synthetic", syn, peer.synthetic_children, peer.synthetic_params(syn), x_syn),
            ("linear", peer.linear_problem(N), peer.linear_children, peer.linear_plant(), rng.uniform(-2, 2, (4, 3))),
            ("tanks", tank, peer.tank_children, peer.tank_params(), x_tank),
            ("tanks simd", tank, peer.tank_children_simd, peer.tank_params(), x_tank)]


@pytest.mark.parametrize("case", _cases(), ids=lambda c: c[0])
def test_peer_matches_library(case):
    _, problem, children, params, states = case
    M = problem.num_controls
    for x in states:
        ref, es_ref = fj.sdfs(problem, x), fj.exhaustive(problem, x)
        cost, seq, nodes = peer.sdfs(children, params, x, M, N)
        es_cost, es_seq, es_nodes = peer.exhaustive(children, params, x, M, N)
        assert (nodes, seq.tolist()) == (int(ref.nodes), np.asarray(ref.sequence).tolist())
        assert (es_nodes, es_seq.tolist()) == (int(es_ref.nodes), np.asarray(es_ref.sequence).tolist())
        np.testing.assert_allclose([cost, es_cost], [float(ref.cost), float(es_ref.cost)], rtol=COST_RTOL, atol=0)


def test_batched_peer_solves_each_row():
    problem = peer.linear_problem(N)
    X = np.random.default_rng(1).uniform(-2, 2, (5, 3))
    costs, seqs, nodes = peer.sdfs_batch(peer.linear_children, peer.linear_plant(), X, 17, N)
    for b, x in enumerate(X):
        ref = fj.sdfs(problem, x)
        assert (seqs[b].tolist(), nodes[b]) == (np.asarray(ref.sequence).tolist(), int(ref.nodes))
        np.testing.assert_allclose(costs[b], float(ref.cost), rtol=COST_RTOL, atol=0)
