"""Compiled scalar peers of ``fj.sdfs`` and ``fj.exhaustive``, written in Numba, so that engine timings
can be read as ratios to the best plain loop code (``benchmarks/engine_bench.py``). Batches run row after
row on one core (``sdfs_batch``) or over every core with ``prange`` (``sdfs_batch_parallel``), the peer of
``fj.solve_batch``'s default.

The searches follow the library rule for rule (Table 1 at ``pop_width=1``; exhaustive search keeps the
lexicographically first optimum) and count nodes the same way, so cost, sequence and node count can be
compared exactly. Problems without a terminal constraint only: every plant here is unconstrained.

Bit-for-bit agreement: XLA's CPU backend always lets LLVM fuse ``a * b + c`` into one fused multiply-add
(no fast-math otherwise), so plain scalar code rounds differently in about one child in four. The plant
kernels below are written with explicit ``fma`` where XLA fuses, fastmath off. That reproduces the
synthetic and linear plants exactly. On the tank plant, XLA recomputes each RK4 stage in several kernels
and, in a pipe-difference ``k13 m13 - k32 m32`` (modes 6 and 16 only), LLVM picks which product to fuse by
its use count in that kernel; the peer fuses the first, as LLVM does by default, and differs in the last
bit on a few children of those two modes. Inside the search loop XLA also fuses the synthetic plant's cost
differently from a lone expansion, and with XLA's optimizations off (the quick test suite) the linear
plant's too, so the peer's costs can differ in the last bits (4e-16 relative seen). Sequences and node
counts agree, and costs to 1e-12 relative (checked by ``tests/project/test_numba_peer.py`` and ``engine_bench.py``).
"""
from __future__ import annotations

import math

import numba
import numpy as np
from numba.core import types
from numba.extending import intrinsic

from firhc_jax.models import tanks


@intrinsic
def fma(typingctx, a, b, c):
    """``a * b + c`` rounded once (LLVM's ``llvm.fma.f64``), as XLA's fused multiply-adds."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        return builder.fma(*args)

    return sig, codegen


# ---------------------------------------------------------------------------------------------------------
# Plants. ``children(P, x, out_x, out_stage)`` writes the M children of state ``x`` and their stage costs.
# ---------------------------------------------------------------------------------------------------------

@numba.njit
def synthetic_children(P, x, out_x, out_stage):
    """``firhc_jax.models.synthetic`` (work 0); ``P = (controls [M, 2], 0.2 * controls[:, 1], input cost [M],
    lam [3])``."""
    U, c1, ucost, lam = P
    x0, x1, x2 = x[0], x[1], x[2]
    sin0, cos0 = math.sin(x0), math.cos(x0)
    y0, damp = fma(x1, 0.2, x0), 0.1 * x1  # XLA hoists 0.1 x1 out of the loop over inputs: no fma
    for m in range(U.shape[0]):
        y1 = fma(U[m, 0] - sin0 - damp, 0.2, x1)
        y2 = fma(c1[m], cos0, x2 * 0.9)
        out_x[m, 0], out_x[m, 1], out_x[m, 2] = y0, y1, y2
        acc = (lam[0] * (y0 * y0) + lam[2] * (y2 * y2)) + lam[1] * (y1 * y1)  # XLA's order (a reassoc reduce)
        out_stage[m] = acc + ucost[m]


def synthetic_params(problem):
    """Peer parameters of ``synthetic.make_problem(N, SyntheticParams(M))`` (work 0), input cost summed as XLA
    folds it."""
    U = np.asarray(problem.controls, np.float64)
    return U, 0.2 * U[:, 1], (0.0 + 0.5 * (U[:, 0] * U[:, 0])) + 0.5 * (U[:, 1] * U[:, 1]), np.array([1.0, 0.1, 1.0])


@numba.njit
def linear_children(P, x, out_x, out_stage):
    """``x_next = B[u] + A[u] @ x`` summed left to right, stage cost ``|x_next|^2``; ``P = (A, B)``."""
    A, B = P
    for m in range(A.shape[0]):
        y0 = fma(A[m, 0, 2], x[2], fma(A[m, 0, 1], x[1], fma(A[m, 0, 0], x[0], B[m, 0])))
        y1 = fma(A[m, 1, 2], x[2], fma(A[m, 1, 1], x[1], fma(A[m, 1, 0], x[0], B[m, 1])))
        y2 = fma(A[m, 2, 2], x[2], fma(A[m, 2, 1], x[1], fma(A[m, 2, 0], x[0], B[m, 2])))
        out_x[m, 0], out_x[m, 1], out_x[m, 2] = y0, y1, y2
        out_stage[m] = fma(y2, y2, fma(y0, y0, y1 * y1))


def linear_plant(num_controls: int = 17, seed: int = 0):
    """The linear benchmark plant ``(A [M, 3, 3], B [M, 3])``: stable, slightly rotating modes (fixed seed)."""
    rng = np.random.default_rng(seed)
    A = 0.9 * np.eye(3)[None] + 0.15 * rng.standard_normal((num_controls, 3, 3))
    return A, 0.2 * rng.standard_normal((num_controls, 3))


def linear_problem(horizon: int, num_controls: int = 17, seed: int = 0):
    """``linear_plant`` as an ``fj.Problem`` (controls: mode indices), elementwise so every search rounds alike."""
    import jax.numpy as jnp

    import firhc_jax as fj

    A_np, B_np = linear_plant(num_controls, seed)

    def dynamics(x, u):
        k = u[0].astype(jnp.int32)
        a, b = jnp.asarray(A_np, x.dtype)[k], jnp.asarray(B_np, x.dtype)[k]
        return jnp.stack([b[i] + a[i, 0] * x[0] + a[i, 1] * x[1] + a[i, 2] * x[2] for i in range(3)])

    def stage_cost(x_next, u):
        return x_next[0] * x_next[0] + x_next[1] * x_next[1] + x_next[2] * x_next[2]

    return fj.Problem(dynamics, np.arange(num_controls, dtype=float)[:, None], stage_cost, horizon)


def tank_params(params: tanks.TankParams | None = None, set_point=tanks.SET_POINT,
                switch_penalty: float = 0.0):
    """Peer parameters of ``tanks.make_problem``: ``(coefficients [17, 5], toggles [17, 17], set point [3],
    [dt, height, substeps, switch_penalty])``: arrays only, so that ``prange`` can share them out."""
    params = params or tanks.TankParams()
    dt = params.ts / params.substeps
    return (tanks.mode_coefficients(params), tanks._TOGGLES, np.asarray(set_point, float),
            np.array([dt, params.height, params.substeps, switch_penalty], float))


@numba.njit(inline="always")
def _signed_root(d):
    return (d if d == 0.0 else math.copysign(1.0, d)) * math.sqrt(abs(d))


@numba.njit(inline="always")
def _rates(h1, h2, h3, in1, in2, k13, k32, k30):
    m13, m32 = _signed_root(h1 - h3), _signed_root(h3 - h2)
    f30 = math.sqrt(max(h3, 0.0))
    return fma(-k13, m13, in1), fma(k32, m32, in2), fma(-k30, f30, fma(k13, m13, -(k32 * m32)))


@numba.njit(inline="always")
def _substep(h1, h2, h3, in1, in2, k13, k32, k30, dt, top):
    """One classical RK4 step of ``tanks.make_plant``, then the clip to ``[0, top]``."""
    half, sixth = 0.5 * dt, dt / 6.0
    a0, a1, a2 = _rates(h1, h2, h3, in1, in2, k13, k32, k30)
    b0, b1, b2 = _rates(fma(a0, half, h1), fma(a1, half, h2), fma(a2, half, h3), in1, in2, k13, k32, k30)
    d0, d1, d2 = _rates(fma(b0, half, h1), fma(b1, half, h2), fma(b2, half, h3), in1, in2, k13, k32, k30)
    e0, e1, e2 = _rates(fma(d0, dt, h1), fma(d1, dt, h2), fma(d2, dt, h3), in1, in2, k13, k32, k30)
    return (min(max(fma(a0 + 2.0 * b0 + 2.0 * d0 + e0, sixth, h1), 0.0), top),
            min(max(fma(a1 + 2.0 * b1 + 2.0 * d1 + e1, sixth, h2), 0.0), top),
            min(max(fma(a2 + 2.0 * b2 + 2.0 * d2 + e2, sixth, h3), 0.0), top))


@numba.njit(inline="always")
def _tank_cost(h1, h2, h3, toggles, hs, penalty):
    e0, e1, e2 = (h1 - hs[0]) * 1e3, (h2 - hs[1]) * 1e3, (h3 - hs[2]) * 1e3
    return fma(penalty, toggles, fma(e2, e2, fma(e0, e0, e1 * e1)))


@numba.njit
def tank_children(P, x, out_x, out_stage):
    """Three-tank plant, one child after another (all RK4 sub-steps of a mode, then the next mode)."""
    coeffs, toggles, hs, scalars = P
    dt, top, substeps, penalty = scalars[0], scalars[1], int(scalars[2]), scalars[3]
    prev = int(x[3])
    for m in range(coeffs.shape[0]):
        in1, in2, k13, k32, k30 = coeffs[m, 0], coeffs[m, 1], coeffs[m, 2], coeffs[m, 3], coeffs[m, 4]
        h1, h2, h3 = x[0], x[1], x[2]
        for _ in range(substeps):
            h1, h2, h3 = _substep(h1, h2, h3, in1, in2, k13, k32, k30, dt, top)
        out_x[m, 0], out_x[m, 1], out_x[m, 2], out_x[m, 3] = h1, h2, h3, float(m)
        out_x[m, 4] = toggles[prev, m]
        out_stage[m] = _tank_cost(h1, h2, h3, toggles[prev, m], hs, penalty)


@numba.njit
def tank_children_simd(P, x, out_x, out_stage):
    """Three-tank plant, all modes in one loop per sub-step (branch-free body: LLVM vectorises it)."""
    coeffs, toggles, hs, scalars = P
    dt, top, substeps, penalty = scalars[0], scalars[1], int(scalars[2]), scalars[3]
    M, prev = coeffs.shape[0], int(x[3])
    for m in range(M):
        out_x[m, 0], out_x[m, 1], out_x[m, 2] = x[0], x[1], x[2]
    for _ in range(substeps):
        for m in range(M):
            out_x[m, 0], out_x[m, 1], out_x[m, 2] = _substep(out_x[m, 0], out_x[m, 1], out_x[m, 2], coeffs[m, 0],
                                                             coeffs[m, 1], coeffs[m, 2], coeffs[m, 3], coeffs[m, 4],
                                                             dt, top)
    for m in range(M):
        out_x[m, 3], out_x[m, 4] = float(m), toggles[prev, m]
        out_stage[m] = _tank_cost(out_x[m, 0], out_x[m, 1], out_x[m, 2], toggles[prev, m], hs, penalty)


# ---------------------------------------------------------------------------------------------------------
# Searches, generic over the plant (``children`` is compiled into each specialisation).
# ---------------------------------------------------------------------------------------------------------

@numba.njit
def sdfs(children, P, x0, M, N):
    """Table 1: pop the top node; if it is not cheaper than the incumbent, prune it; else compute its M
    children: at depth N the cheapest (lowest input among equals) improves a strictly dearer incumbent,
    above it those cheaper than the incumbent are pushed, the cheapest (lowest input) on top.
    Returns ``(cost, sequence [N], nodes)``."""
    n = x0.shape[0]
    cap = (N - 1) * (M - 1) + 1
    sx, sc = np.empty((cap, n)), np.empty(cap)
    sd, su = np.empty(cap, np.int64), np.empty(cap, np.int64)
    cx, stage, cost = np.empty((M, n)), np.empty(M), np.empty(M)
    order, path, best_path = np.empty(M, np.int64), np.empty(N, np.int64), np.full(N, -1, np.int64)
    best, nodes = np.inf, 0
    sx[0, :], sc[0], sd[0], su[0], size = x0, 0.0, 0, -1, 1
    while size > 0:
        size -= 1
        c, d = sc[size], sd[size]
        if d > 0:
            path[d - 1] = su[size]  # the parent is the last node popped at depth d - 1
        if not c < best:
            continue
        children(P, sx[size], cx, stage)
        nodes += M
        if d + 1 == N:
            for i in range(M):
                if c + stage[i] < best:
                    best = c + stage[i]
                    best_path[:N - 1] = path[:N - 1]
                    best_path[N - 1] = i
            continue
        k = 0
        for i in range(M):  # kept children by ascending cost, lower input first among equals
            cost[i] = c + stage[i]
            if cost[i] < best:
                j = k
                while j > 0 and cost[order[j - 1]] > cost[i]:
                    order[j] = order[j - 1]
                    j -= 1
                order[j] = i
                k += 1
        for j in range(k - 1, -1, -1):
            i = order[j]
            sx[size, :], sc[size], sd[size], su[size] = cx[i], cost[i], d + 1, i
            size += 1
    return best, best_path, nodes


@numba.njit
def exhaustive(children, P, x0, M, N):
    """Every node, depth first in lexicographic order; the first of equal-cost leaves wins.
    Returns ``(cost, sequence [N], nodes)``."""
    n = x0.shape[0]
    lx, lc, stage = np.empty((N, M, n)), np.empty((N, M)), np.empty(M)
    idx, best_path = np.zeros(N, np.int64), np.full(N, -1, np.int64)
    children(P, x0, lx[0], stage)
    for i in range(M):
        lc[0, i] = 0.0 + stage[i]
    best, nodes, level = np.inf, M, 0
    while level >= 0:
        if level == N - 1:  # leaves
            for i in range(M):
                if lc[level, i] < best:
                    best = lc[level, i]
                    best_path[:N - 1] = idx[:N - 1]
                    best_path[N - 1] = i
            level -= 1
            if level >= 0:
                idx[level] += 1
        elif idx[level] == M:
            level -= 1
            if level >= 0:
                idx[level] += 1
        else:
            i = idx[level]
            children(P, lx[level, i], lx[level + 1], stage)
            for j in range(M):
                lc[level + 1, j] = lc[level, i] + stage[j]
            nodes += M
            level += 1
            idx[level] = 0
    return best, best_path, nodes


@numba.njit
def sdfs_batch(children, P, X0, M, N):
    """``sdfs`` on each row of ``X0`` ``[B, n]``, one after another on one core.
    Returns ``(costs [B], sequences [B, N], nodes [B])``."""
    B = X0.shape[0]
    costs, seqs, nodes = np.empty(B), np.empty((B, N), np.int64), np.empty(B, np.int64)
    for b in range(B):
        costs[b], seqs[b], nodes[b] = sdfs(children, P, X0[b], M, N)
    return costs, seqs, nodes


@numba.njit(parallel=True)
def sdfs_batch_parallel(children, P, X0, M, N):
    """``sdfs`` on each row of ``X0`` ``[B, n]``, the rows spread over every core (``prange``, Numba's
    default schedule: equal blocks of rows per thread). Returns ``(costs [B], sequences [B, N], nodes [B])``."""
    B = X0.shape[0]
    costs, seqs, nodes = np.empty(B), np.empty((B, N), np.int64), np.empty(B, np.int64)
    for b in numba.prange(B):
        costs[b], seqs[b], nodes[b] = sdfs(children, P, X0[b], M, N)
    return costs, seqs, nodes
