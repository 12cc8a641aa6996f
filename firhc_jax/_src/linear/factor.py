"""The static factorisation of ``LinearTracking`` (NumPy, float64, once per tracker): the classes of inputs of
equal effect, the cost-to-go's factors and each step's child map (``firhc_jax.linear_tracking``'s module
docstring says what they are and why they are exact). Nothing here is traced."""
from __future__ import annotations

import numpy as np

from ..problem.problem import weight


def input_classes(B, controls) -> np.ndarray:
    """``[C, R]`` indices into ``controls`` ``[M, m]`` grouped by their effect
    B u on the plant, classes in the order of their first input, padded with -1.

    Effects are equal up to rounding: per state component, 64 eps of the
    largest sum of |B_ij u_j| over the inputs, the scale of that component's
    own rounding (so the grouping does not depend on the units of B)."""
    effect = controls @ B.T  # [M, n]
    tol = 64 * np.finfo(float).eps * np.max(np.abs(controls) @ np.abs(B).T, axis=0, initial=0.0)  # [n]
    classes = []
    for i in range(len(controls)):
        for c in classes:
            if np.all(np.abs(effect[i] - effect[c[0]]) <= tol):
                c.append(i)
                break
        else:
            classes.append([i])
    out = np.full((len(classes), max(len(c) for c in classes)), -1)
    for j, c in enumerate(classes):
        out[j, :len(c)] = c
    return out


def factor_memory(n: int, m: int, p: int, N: int) -> int:
    """Bytes that ``LinearTracking`` holds for its factorisation at its peak, about: the data-only factor
    ``Ms`` ``[N, N(p + m), N(p + n)]`` (float64) four times over (per step, stacked, shifted, on the device),
    the decomposition of the longest stacked problem and the child maps. It grows as N^3."""
    rows, data = N * (p + m), N * (p + n)
    return 8 * (4 * N * rows * data + 2 * rows * rows + 2 * N * (2 * n + p + m) * data)


def cost_to_go(A, B, C, sqrt_q, lambda_u, N):
    """Factors of the unconstrained cost-to-go of the last N - k steps, k = 0 .. N-1.

    W_k(x, u_prev) = min over real u(k .. N-1) of the cost of those steps from
    x(k) = x after input u_prev; with s = [x; u_prev] and data = [vec(y_ref);
    vec(d)]: W_k = ||T[k] s + Mw[k] data||^2 + ||Ms[k] data||^2.

    Returns ``T`` ``[N, n+m, n+m]``, ``Mw`` ``[N, n+m, N(p+n)]``, ``Ms``
    ``[N, N(p+m), N(p+n)]`` (rows padded with zeros), ``err_s``, ``err_d``
    ``[N]``. W_k = ||P (G_s s + G_d data)||^2 where F U - (G_s s + G_d data) is
    the stacked residual of the steps left and P projects onto the complement
    of F's range (from its SVD); a QR factorisation of P G_s splits it into
    the square part T and the rest. The computed P is off by at most delta
    (Wedin: the SVD's backward error over the smallest singular value kept),
    so sqrt(W_k) is off by at most ``err_s[k] ||s|| + err_d[k] ||data||``
    (delta ||G_s||_F, delta ||G_d||_F): the search takes that off to keep W a lower
    bound at any conditioning of Q (delta >= 1 leaves no bound).
    """
    n, m = B.shape
    p = sqrt_q.shape[0]
    eps = np.finfo(float).eps
    powers = [np.eye(n)]
    for _ in range(N):
        powers.append(A @ powers[-1])
    q_c = sqrt_q @ C
    nd, ns = N * (p + n), n + m
    T, Mw, rests = np.zeros((N, ns, ns)), np.zeros((N, ns, nd)), []
    err_s, err_d = np.zeros(N), np.zeros(N)
    for k in range(N):
        S = N - k
        F = np.zeros((S * (p + m), S * m))
        Gs, Gd = np.zeros((S * (p + m), ns)), np.zeros((S * (p + m), nd))
        for j in range(S):  # step k + j: tracking rows, then switching rows
            r = slice(j * p, (j + 1) * p)
            for i in range(j + 1):
                F[r, i * m:(i + 1) * m] = q_c @ powers[j - i] @ B
                Gd[r, N * p + (k + i) * n:N * p + (k + i + 1) * n] = -q_c @ powers[j - i]
            Gs[r, :n] = -q_c @ powers[j + 1]
            Gd[r, (k + j) * p:(k + j + 1) * p] = sqrt_q
            r = slice(S * p + j * m, S * p + (j + 1) * m)
            F[r, j * m:(j + 1) * m] = np.sqrt(lambda_u) * np.eye(m)
            if j:
                F[r, (j - 1) * m:j * m] = -np.sqrt(lambda_u) * np.eye(m)
            else:
                Gs[r, n:] = np.sqrt(lambda_u) * np.eye(m)
        U, sv, _ = np.linalg.svd(F)
        rank = _rank(F)
        perp = U[:, rank:].T  # [R - rank, R]
        Ue, Te = np.linalg.qr(perp @ Gs, mode="complete")
        rows = min(ns, Te.shape[0])
        T[k, :rows] = Te[:rows]
        Mw[k, :rows] = Ue[:, :rows].T @ perp @ Gd
        rests.append(Ue[:, rows:].T @ perp @ Gd)
        # delta >= 1 already leaves no bound (||P g|| <= ||g||): capped there, so that it stays finite
        ratio = sv[0] / sv[rank - 1] if rank and sv[rank - 1] > 0 else (np.inf if rank else 0.0)
        delta = min(8 * eps * (max(F.shape) + ns) * (1 + ratio), 2.0)
        err_s[k], err_d[k] = delta * np.linalg.norm(Gs), delta * np.linalg.norm(Gd)  # Frobenius >= spectral
    Ms = np.zeros((N, N * (p + m), nd))  # rows for every rank: a new model of the same sizes has the same shapes
    for k, rest in enumerate(rests):
        Ms[k, :rest.shape[0]] = rest
    return T, Mw, Ms, err_s, err_d


def _rank(F) -> int:
    """The number of directions of F's range that inputs reach, decided on F with its rows and columns scaled
    to unit norm (zero ones dropped): the same rank in exact arithmetic, whatever the weights Q and lambda_u
    and the inputs' units do to the scale of F's rows and columns. (A tolerance relative to F's own largest
    singular value would count a light output's directions under a heavy one, Q = diag(1e30, 1), as out of
    reach, and W would exceed the cost-to-go.) The rest, at the rounding level of the scaled F, are
    unreachable: the usual numerical rank."""
    rows = np.linalg.norm(F, axis=1)
    G = F[rows > 0] / rows[rows > 0, None]
    cols = np.linalg.norm(G, axis=0)
    G = G[:, cols > 0] / cols[cols > 0]
    if G.size == 0:
        return 0
    sv = np.linalg.svd(G, compute_uv=False)
    return int(np.sum(sv > np.finfo(float).eps * max(G.shape) * sv[0]))


def child_map(A, B, C, sqrt_q, lambda_u, N):
    """The affine map from a node to a child, per input index k.

    For the child of input u(k) from state x(k) after u(k-1):
    ``M[k] [x; u] + M_data[k] data`` = [x(k+1); sqrt(Q) (y_ref[k] - C x(k+1));
    T_{k+1} [x(k+1); u] + w_{k+1}], whose last part's squared norm plus
    ``||Ms[k] data||^2`` is W_{k+1}(x(k+1), u(k)) (``cost_to_go``; 0 at k = N-1).

    Returns ``M`` ``[N, n + p + n + m, n + m]``, ``M_data``
    ``[N, n + p + n + m, N(p + n)]``, ``Ms`` ``[N, N(p + m), N(p + n)]``,
    ``Tu`` ``[N, n + m, m]``, the columns of u(k) in T_{k+1} (0 at k = N-1):
    how W's residual moves with the child's input, for the other members
    of its class, and ``err_s``, ``err_d`` ``[N]``: those of W_{k+1}
    (``cost_to_go``; 0 at k = N-1)."""
    n, m = B.shape
    p = sqrt_q.shape[0]
    T, Mw, Ms, err_s, err_d = cost_to_go(A, B, C, sqrt_q, lambda_u, N)
    nd, q_c = N * (p + n), sqrt_q @ C
    M, M_data = np.zeros((N, 2 * n + p + m, n + m)), np.zeros((N, 2 * n + p + m, nd))
    for k in range(N):
        d_k = np.zeros((n, nd))
        d_k[:, N * p + k * n:N * p + (k + 1) * n] = np.eye(n)  # selects d[k] from data
        M[k, :n] = np.hstack([A, B])
        M_data[k, :n] = d_k
        M[k, n:n + p] = -q_c @ M[k, :n]
        M_data[k, n:n + p] = -q_c @ d_k
        M_data[k, n:n + p, k * p:(k + 1) * p] += sqrt_q  # y_ref[k]
        if k + 1 < N:
            Tx, Tu = T[k + 1][:, :n], T[k + 1][:, n:]
            M[k, n + p:] = Tx @ M[k, :n] + np.hstack([np.zeros((n + m, n)), Tu])
            M_data[k, n + p:] = Tx @ d_k + Mw[k + 1]
    Ms_next = np.concatenate([Ms[1:], np.zeros_like(Ms[:1])])
    Tu = np.concatenate([T[1:, :, n:], np.zeros((1, n + m, m))])
    return M, M_data, Ms_next, Tu, np.append(err_s[1:], 0.0), np.append(err_d[1:], 0.0)


def psd_factor(name: str, Q) -> np.ndarray:
    """``L`` ``[p, p]`` with L^T L = Q, for a symmetric positive semidefinite
    ``Q`` (checked by ``fj.problem.weight``: else a ``ValueError`` naming ``name``)."""
    w, vecs = np.linalg.eigh(weight(name, Q))
    return np.sqrt(np.clip(w, 0, None))[:, None] * vecs.T
