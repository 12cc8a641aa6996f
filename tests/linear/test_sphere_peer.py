"""The scalar Python sphere decoder of benchmarks/sphere_peer.py (the peer of ``lt.solve``) finds the
brute-force minimum of J, max_step and the disturbance included."""
import itertools
import sys

import numpy as np
from repository import BENCHMARKS

sys.path.insert(0, str(BENCHMARKS))
from sphere_peer import SphereDecoder  # noqa: E402

from firhc_jax.models import three_level  # noqa: E402


def brute_force(A, B, levels, N, lambda_u, max_step, x, u_prev, y_ref, d):
    """Every sequence of the input set: ``(J, U)`` of the cheapest that meets max_step."""
    inputs = [np.array(u) for u in itertools.product(levels, repeat=B.shape[1])]
    best = (np.inf, None)
    for seq in itertools.product(inputs, repeat=N):
        J, xk, prev = 0.0, x, u_prev
        if max_step is not None and any(np.max(np.abs(u - p)) > max_step for u, p in zip(seq, (u_prev,) + seq[:-1],
                                                                                          strict=True)):
            continue
        for k, u in enumerate(seq):
            xk = A @ xk + B @ u + d[k]
            e, du = y_ref[k] - xk, u - prev
            J += e @ e + lambda_u * (du @ du)
            prev = u
        if J < best[0]:
            best = (J, np.array(seq))
    return best


def test_decoder_finds_the_brute_force_minimum():
    A, B = three_level.model()
    N, lam = 2, 0.1
    levels = (-1.0, 0.0, 1.0)
    peer = SphereDecoder(A, B, np.eye(2), np.eye(2), levels, N, lam, max_step=1.0)
    rng = np.random.default_rng(3)
    for trial in range(6):
        x, y_ref = rng.normal(size=2) * 10, rng.normal(size=(N, 2)) * 10
        u_prev = rng.choice(levels, size=3)
        d = rng.normal(size=(N, 2)) * 5 if trial >= 2 else None
        J, U = peer.solve(x, u_prev, y_ref, first=None if trial % 2 else np.tile(u_prev, (N, 1)), d=d)
        J_ref, _ = brute_force(A, B, levels, N, lam, 1.0, x, u_prev, y_ref, np.zeros((N, 2)) if d is None else d)
        assert np.isclose(J, J_ref, rtol=1e-9), (trial, J, J_ref)
        assert np.max(np.abs(np.diff(np.vstack([u_prev, U]), axis=0))) <= 1.0
