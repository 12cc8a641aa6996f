"""Random ``LinearTracking`` problems of fixed shapes, with the cost J of the tracking problem written out
term by term and its brute-force minimum."""
import itertools

import numpy as np

import firhc_jax as fj

# Fixed shapes, so that one compiled search serves every example: (n, m, p, N, levels per input). lt.solve
# passes the model as an argument: a new random problem of the same shapes does not recompile it (lt.problem
# holds its model as constants, so each tracker's problem compiles its own search).
# mimo has more inputs than outputs: with lambda_u = 0 its stacked F is rank deficient.
# long: a horizon long enough that part of the cost-to-go is out of every input's reach (W's data-only term).
# common: B 1 = 0, so inputs that differ by a step on every component have the same effect (the inverter's
# common mode): 27 inputs in 19 classes, which the search merges.
SHAPES = {"siso": (2, 1, 1, 4, (-1.0, 0.0, 1.0)), "mimo": (3, 3, 2, 3, (-1.0, 0.0, 1.0)),
          "long": (1, 1, 1, 6, (-1.0, 0.0, 1.0)), "common": (2, 3, 2, 3, (-1.0, 0.0, 1.0))}
NONE = np.full(3, -1)  # mimo's "no warm start": the same compiled search as a warm-started call


class Case:
    """A random LinearTracking problem and one decision's data (NumPy, float64)."""

    def __init__(self, shape, max_step, seed, norm="squared"):
        n, m, p, N, levels = SHAPES[shape]
        self.norm = norm
        rng = np.random.default_rng(seed)
        A = rng.normal(size=(n, n))
        self.A = A * rng.uniform(0.3, 0.95) / max(np.max(np.abs(np.linalg.eigvals(A))), 1e-9)
        self.B, self.C = rng.normal(size=(n, m)), rng.normal(size=(p, n))
        if shape == "common":
            self.B -= self.B.mean(axis=1, keepdims=True)
        root = rng.normal(size=(rng.integers(1, p + 1), p))  # Q = L^T L, possibly singular
        self.Q = root.T @ root
        self.lambda_u = 0.0 if rng.random() < 0.25 else float(rng.uniform(0, 2))
        self.max_step = 1.0 if max_step else None
        self.controls = np.array(list(itertools.product(levels, repeat=m)))
        self.N = N
        self.x = rng.normal(size=n)
        # u_prev: a control, or (1 in 5) a real vector that max_step may leave no way out of
        self.u_prev = self.controls[rng.integers(len(self.controls))] * (1.0 if rng.random() < 0.8 else 2.5)
        self.y_ref, self.d = rng.normal(size=(N, p)), 0.3 * rng.normal(size=(N, n))

    def tracker(self):
        controls = self.controls[:, 0] if self.controls.shape[1] == 1 else self.controls  # [M] means m = 1
        return fj.LinearTracking(self.A, self.B, controls, self.N, C=self.C, Q=self.Q, lambda_u=self.lambda_u,
                                 norm=self.norm, max_step=self.max_step)

    def J(self, sequences):
        """J of index sequences ``[S, N]`` (+inf where max_step is broken), the issue's definition term by term."""
        U = self.controls[np.asarray(sequences)]  # [S, N, m]
        x = np.broadcast_to(self.x, U.shape[:1] + self.x.shape)
        u_last = np.broadcast_to(self.u_prev, U.shape[:1] + self.u_prev.shape)
        cost, ok = np.zeros(U.shape[0]), np.ones(U.shape[0], bool)
        for k in range(self.N):
            x = x @ self.A.T + U[:, k] @ self.B.T + self.d[k]
            e = self.y_ref[k] - x @ self.C.T
            du = U[:, k] - u_last
            change = np.abs(du) if self.norm == "abs" else du * du
            cost += np.einsum("si,ij,sj->s", e, self.Q, e) + self.lambda_u * np.sum(change, axis=1)
            if self.max_step is not None:
                ok &= np.all(np.abs(du) <= self.max_step, axis=1)
            u_last = U[:, k]
        return np.where(ok, cost, np.inf)

    def brute_force(self):
        seqs = np.array(list(itertools.product(range(len(self.controls)), repeat=self.N)))
        return float(np.min(self.J(seqs)))
