"""A scalar Python sphere decoder: the peer of ``fj.LinearTracking.solve`` at short horizons.

The decoder of Geyer and Quevedo (IEEE TPEL 29(12), 2014) for the linear
tracking problem of ``firhc_jax.linear_tracking`` (the same J, max_step
and the disturbance d included), written as well as plain Python allows: J(U) = c +
||V U - h||^2 with V lower triangular (a QR factorisation of the stacked
problem with its columns reversed, done once per problem); per decision h
and c are one matrix-vector product each (NumPy); the search is a recursive
depth-first walk over the N m input components in Python floats, children
in Schnorr-Euchner order (nearest the unconstrained centre first, so the
first child too far ends the level), the shifted previous sequence as the
first radius. Only component values that keep |u_i(k) - u_i(k-1)| <=
max_step are children.

``python benchmarks/sphere_peer.py [--horizon 5] [--steps 100] [--rounds 3]`` runs the three-level
inverter closed loop (``firhc_jax.models.three_level``) with ``lt.solve`` deciding, checks that the
decoder finds the same J at every step (relative 1e-9), and prints both total times over the decisions.
"""
from __future__ import annotations

import argparse
import platform
import statistics
import time

import numpy as np


class SphereDecoder:
    """The decoder for ``x(k+1) = A x(k) + B u(k)``, ``y = C x``, every leg of u in ``levels``, and
    J = sum_k ||y_ref[k] - C x(k+1)||_Q^2 + lambda_u ||u(k) - u(k-1)||^2 over N steps."""

    def __init__(self, A, B, C, Q, levels, horizon, lambda_u, max_step=None):
        """The stacked problem of ``x(k+1) = A x(k) + B u(k) + d(k)`` (``solve``'s ``d``, default 0)."""
        A, B, C, Q = (np.asarray(a, float) for a in (A, B, C, Q))
        n, m = B.shape
        p, N = C.shape[0], horizon
        sq = np.linalg.cholesky(Q).T  # Q = sq^T sq
        # Stacked rows sqrt(Q) (y_ref[k] - C x(k+1)) and sqrt(lambda_u) (u(k) - u(k-1)):
        # F U - g, g = G [x; u_prev; y_ref; d].
        F = np.zeros((N * (p + m), N * m))
        G = np.zeros((N * (p + m), n + m + N * p + N * n))
        powers = [np.linalg.matrix_power(A, k) for k in range(N + 1)]
        for k in range(N):
            rows = slice(k * p, (k + 1) * p)
            for j in range(k + 1):  # x(k+1) = A^(k+1) x + sum_j A^(k-j) (B u(j) + d(j))
                F[rows, j * m:(j + 1) * m] = -sq @ C @ powers[k - j] @ B
                G[rows, n + m + N * p + j * n:n + m + N * p + (j + 1) * n] = sq @ C @ powers[k - j]
            G[rows, :n] = sq @ C @ powers[k + 1]
            G[rows, n + m + k * p:n + m + (k + 1) * p] = -sq
            srows = slice(N * p + k * m, N * p + (k + 1) * m)
            F[srows, k * m:(k + 1) * m] = np.sqrt(lambda_u) * np.eye(m)
            if k == 0:
                G[srows, n:n + m] = np.sqrt(lambda_u) * np.eye(m)
            else:
                F[srows, (k - 1) * m:k * m] = -np.sqrt(lambda_u) * np.eye(m)
        Qf, Rf = np.linalg.qr(F[:, ::-1])  # reversed columns: V lower triangular in U's own order
        self.V = [list(row) for row in Rf[::-1, ::-1]]
        self.H = Qf[:, ::-1].T @ G  # h = H [x; u_prev; y_ref]
        self.G = G
        self.levels, self.max_step = [float(v) for v in levels], max_step
        self.n, self.m, self.N = n, m, N

    def solve(self, x, u_prev, y_ref, first=None, d=None):
        """``(J, U [N, m])`` the optimum from ``x`` after ``u_prev`` for ``y_ref`` ``[N, p]`` and ``d``
        ``[N, n]`` (default 0); ``first``: a candidate ``[N, m]`` (the shifted previous optimum) whose J is
        the first radius. ``(inf, None)`` when no sequence meets max_step."""
        d = np.zeros(self.N * self.n) if d is None else np.asarray(d, float).ravel()
        s = np.concatenate([np.asarray(x, float), np.asarray(u_prev, float), np.asarray(y_ref, float).ravel(), d])
        g, h = self.G @ s, self.H @ s
        c = float(g @ g - h @ h)
        h = h.tolist()
        V, levels, step, m = self.V, self.levels, self.max_step, self.m
        L = len(h)
        prev0 = [float(v) for v in u_prev]
        best = [np.inf, None]
        if first is not None:
            cand = [float(v) for v in np.asarray(first, float).ravel()]
            if step is None or all(abs(a - b) <= step for a, b in zip(cand, prev0 + cand[:-m], strict=True)):
                best[0] = _distance(V, h, cand)
                best[1] = cand
        u = [0.0] * L

        def visit(i, dist):
            row = V[i]
            acc = h[i]
            for j in range(i):
                acc -= row[j] * u[j]
            vii = row[i]
            centre = acc / vii
            before = prev0[i] if i < m else u[i - m]
            cands = levels if step is None else [v for v in levels if abs(v - before) <= step]
            for v in sorted(cands, key=lambda v: abs(v - centre)):
                e = acc - vii * v
                d = dist + e * e
                if d >= best[0]:
                    return  # Schnorr-Euchner: every later child is farther from the centre
                u[i] = v
                if i + 1 == L:
                    best[0], best[1] = d, list(u)
                else:
                    visit(i + 1, d)

        visit(0, 0.0)
        if best[1] is None:
            return np.inf, None
        return c + best[0], np.asarray(best[1]).reshape(self.N, m)


def _distance(V, h, u):
    total = 0.0
    for i, row in enumerate(V):
        e = h[i]
        for j in range(i + 1):
            e -= row[j] * u[j]
        total += e * e
    return total


def closed_loop(horizon: int, steps: int, lambda_u: float = 0.1):
    """The three-level inverter closed loop, ``lt.solve`` deciding (eager, the shifted previous optimum as
    warm start) and the decoder solving the same decisions: ``(lt seconds [T], decoder seconds [T])``;
    asserts the same J at every step. ``lt.solve`` is compiled before the first timed decision."""
    import jax

    from firhc_jax.models import inverter, three_level

    lt = three_level.make_problem(horizon, lambda_u=lambda_u)
    A, B = three_level.model()
    peer = SphereDecoder(A, B, lt.C, lt.Q, (-1.0, 0.0, 1.0), horizon, lambda_u, lt.max_step)
    refs = inverter.horizon_references(three_level.PARAMS, steps, horizon)
    x, u = inverter.reference(three_level.PARAMS, 0.0), np.zeros(3)
    jax.block_until_ready(lt.solve(x, u, refs[0], warm_start=np.full(horizon, -1, np.int32)))  # compile
    seq, plan = np.full(horizon, -1, np.int32), None
    ours, theirs = [], []
    for k in range(steps):
        ws = np.where(seq[0] >= 0, np.concatenate([seq[1:], seq[-1:]]), -1).astype(np.int32)
        t0 = time.perf_counter()
        res = jax.block_until_ready(lt.solve(x, u, refs[k], warm_start=ws))
        ours.append(time.perf_counter() - t0)
        first = None if plan is None else np.concatenate([plan[1:], plan[-1:]])
        t0 = time.perf_counter()
        J, plan = peer.solve(x, u, refs[k], first)
        theirs.append(time.perf_counter() - t0)
        assert np.isclose(J, float(res.cost), rtol=1e-9), (k, J, float(res.cost))
        seq = np.asarray(res.sequence)
        u = np.asarray(lt.controls[seq[0]])
        x = A @ x + B @ u
    return ours, theirs


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--horizon", type=int, default=5)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    import jax

    jax.config.update("jax_enable_x64", True)
    totals = {"lt.solve": [], "decoder": []}
    for _ in range(args.rounds):
        ours, theirs = closed_loop(args.horizon, args.steps)
        totals["lt.solve"].append(sum(ours))
        totals["decoder"].append(sum(theirs))
    print(f"# Three-level inverter, N = {args.horizon}, {args.steps} closed-loop decisions, float64, "
          f"{platform.machine()}, jax {jax.__version__}; median of {args.rounds} rounds (same J every step)\n")
    print("| solver | total ms | ms per decision |")
    print("|---|---:|---:|")
    for name, ts in totals.items():
        t = statistics.median(ts)
        print(f"| {name} | {1e3 * t:.1f} | {1e3 * t / args.steps:.3f} |")
    ratio = statistics.median(totals["lt.solve"]) / statistics.median(totals["decoder"])
    print(f"\nlt.solve / decoder: {ratio:.2f}x")


if __name__ == "__main__":
    main()
