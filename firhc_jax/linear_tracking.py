"""Exact tracking for linear plants with a finite input set at long horizons:
the sphere decoder as a lower bound of the sorted search.

The problem (``LinearTracking``): x(k+1) = A x(k) + B u(k) + d(k), y = C x,
every u(k) a row of ``controls``, and

    J(U) = sum_{k=0}^{N-1} ||y_ref[k] - C x(k+1)||_Q^2 + lambda_u ||u(k) - u(k-1)||^2,   u(-1) = u_prev,

optionally with |u_i(k) - u_i(k-1)| <= max_step for every component and step.

Why this is the sphere decoder (Geyer and Quevedo, IEEE TPEL 29(12), 2014).
Stacking the horizon, J(U) = ||F U - g||^2 with F static (A, B, C, Q,
lambda_u, N) and g linear in (x, u_prev, y_ref, d). A QR factorisation of F
with its columns reversed completes the square without inverting anything:
J(U) = c + ||V U - h||^2 with V lower triangular. The decoder's partial
distance of a prefix u(0..k) (c plus the rows of V up to u(k)) is J's minimum
over every *continuous* completion of the prefix, which is also the prefix's
own cost plus W_{k+1}(x(k+1), u(k)), the unconstrained cost-to-go of the steps
left: a quadratic in the state the prefix reaches (the plant is Markov). So
the decoder is the sorted search on the problem in its own coordinates with
W as ``lower_bound``: the same keys, the same nodes in the same order (peers
sorted by key: the Schnorr-Euchner order), and the incumbent is the decoder's
radius, which ``warm_start`` (the shifted previous sequence) sets first. W is
at least the decoder's distance where F is rank deficient (singular Q,
lambda_u = 0, more inputs than outputs): the decoder then loses the part of
the suffix that no input reaches.

Inputs of equal effect are merged. Where B u_i = B u_j (up to rounding: the
inverter's switch states that differ by one step on every leg, its common
mode), two inputs lead to the same plant state and differ only in the
switching term. Branching on both would search the same subtree twice for
every such choice along a path, so a node branches on the C *classes* of
inputs (``input_classes``) and keeps, for each member of its class, the
cheapest switching of the steps so far that ends on that member (a min-plus
step per child: the Viterbi recursion over at most R members). Its cost is
then J's minimum over every sequence of inputs of that class sequence, and
its bound the smallest of (member's switching + W from that member). Exact:
the optimum is the cheapest class sequence with its cheapest members, which
``sequence`` recovers from the plan (forward min-plus, argmins backward), and
``first_input_of`` gives the member to apply now. On the three-level inverter
(27 inputs, 19 classes, N = 10, lambda_u = 0.1) this computes 27 times fewer
nodes than the plain sorted search (docs/inverter.md); without equal-effect
inputs (R = 1) the node is the plain one.

In this form the search state is the plant's own: ``[x, U, o, stage, W]``
with U the class's R inputs and o their switching costs above the cheapest
(n + R (m + 1) + 2 numbers instead of the decoder's N m partial sums), and
the cost a search returns is J itself, accumulated stage by stage. W_k is
kept factored, W_k(s) = ||T_k s + w_k||^2 + s_k for s = [x; u_prev]: T_k is
static, w_k and s_k are linear and quadratic in (y_ref, d) and travel as
params, so new states, references and disturbances never recompile. One node
is one step with its C classes (not one input component per level as in the
decoder), and where F is rank deficient W is strictly tighter than the
decoder's distance: both measured in docs/inverter.md.

W stays a lower bound at any scaling of Q, lambda_u and the units: which
directions inputs reach is decided on F with unit rows and columns
(``_rank``), and the factorisation's own error bound is taken off W
(``cost_to_go``): weights whose ratio nears 1/eps weaken W towards 0, and
the search towards the plain sorted search, which is still exact.
"""
from __future__ import annotations

import numpy as np

import jax
import jax.numpy as jnp

from .checks import as_state
from .problem import Problem, _check_controls, is_tracer, positive_int, weight
from .cache import compiled
from .result import SearchResult, raise_on_errors
from .sdfs import DEFAULT_MAX_MEMORY, node_budget, sdfs


class LinearTracking:
    """Exact finite-input tracking MPC for a linear plant (module docstring).

    Args:
      A: ``[n, n]``, B: ``[n, m]``: the discrete-time model x+ = A x + B u + d.
      controls: ``[M, m]`` finite input set (``[M]`` when m = 1).
      horizon: N >= 1.
      C: ``[p, n]`` output matrix (default I).
      Q: ``[p, p]`` symmetric positive semidefinite output weight (default I).
      lambda_u: weight (>= 0) of ||u(k) - u(k-1)||^2, the first step against u_prev.
      max_step: optional bound (>= 0) on |u_i(k) - u_i(k-1)|, every component
        and step, the first against u_prev: a hard constraint.
      max_memory: bytes the factorisation may take (``factor_memory``, which
        grows as N^3); a larger one is refused before any work.

    Attributes:
      problem: the ``fj.Problem`` the search solves (``step_index=True``): one
        child per class of inputs (its controls ``[C, m]``: each class's first
        input), state ``[x, U, o, stage cost, W]`` ``[n + R (m + 1) + 2]``
        (``observe``), params of one decision from ``params``, ``lower_bound``
        the cost-to-go W, ``first_input_of`` the member to apply. Use it with
        any solver: ``fj.sdfs``, ``fj.solve_batch``, ``fj.FIRHC``: their
        ``first_input`` is the exact optimum's; their ``sequence`` indexes
        classes (``sequence`` maps it to inputs). Its callables hold the model
        as constants (a new tracker compiles its own search; ``solve`` passes
        the model as params and does not).
      num_classes, class_size: C classes of at most R inputs (``input_classes``).
      observe: ``observe(x, u_prev[, p])``, the search state at plant state
        ``x`` after input ``u_prev``.

    The factorisation is done once here, in float64 (NumPy); the search runs in
    the dtype of the state given to it.
    """

    def __init__(self, A, B, controls, horizon, *, C=None, Q=None, lambda_u=0.0, max_step=None,
                 max_memory: int = DEFAULT_MAX_MEMORY):
        A = _matrix("A", A)
        n = A.shape[0]
        if A.shape != (n, n):
            raise ValueError(f"A must be square [n, n], got shape {A.shape}")
        B = _matrix("B", B)
        if B.shape[0] != n:
            raise ValueError(f"B must be [n, m] with n = {n} rows like A, got shape {B.shape}")
        m = B.shape[1]
        C = np.eye(n) if C is None else _matrix("C", C)
        if C.shape[1] != n:
            raise ValueError(f"C must be [p, n] with n = {n} columns like A, got shape {C.shape}")
        p = C.shape[0]
        Q = np.eye(p) if Q is None else _matrix("Q", Q)
        if Q.shape != (p, p):
            raise ValueError(f"Q must be [p, p] = [{p}, {p}] like the rows of C, got shape {Q.shape}")
        N = positive_int("horizon", horizon)
        lambda_u = _scalar("lambda_u", lambda_u)
        max_step = None if max_step is None else _scalar("max_step", max_step)
        max_memory = positive_int("max_memory", max_memory)
        need = factor_memory(n, m, p, N)
        if need > max_memory:
            raise ValueError(f"LinearTracking's factorisation at horizon N = {N} (n = {n}, m = {m}, p = {p}) needs "
                             f"about {need:,} bytes, more than max_memory={max_memory:,} (it grows as N^3); "
                             "shorten the horizon or raise max_memory")
        self.A, self.B, self.C, self.Q = A, B, C, Q
        self.lambda_u, self.max_step, self.horizon = lambda_u, max_step, N
        self.n, self.m, self.p = n, m, p
        controls = _check_controls(controls)
        if controls.shape[1] != m:
            raise ValueError(f"controls must have m = {m} columns like B, got shape {controls.shape}")
        self._controls = controls
        members = input_classes(B, controls)  # [C, R]
        self.num_classes, self.class_size = members.shape
        self._class_of = np.zeros(len(controls), np.int32)  # [M] the class of each input
        for j, row in enumerate(members):
            self._class_of[row[row >= 0]] = j
        M, M_data, Ms, Tu, err_s, err_d = child_map(A, B, C, psd_factor("Q", Q), lambda_u, N)
        filled = np.where(members >= 0, members, members[:, :1])  # padding repeats the first member
        model = {"M": M, "M_norm": np.linalg.norm(M[:, n + p:], axis=(1, 2)), "lambda_u": np.float64(lambda_u),
                 "Tu": Tu, "Tu_norm": np.linalg.norm(Tu, axis=(1, 2)), "err_s": err_s,
                 "members": controls.astype(float)[filled],  # [C, R, m]
                 "member_index": filled.astype(float), "member_ok": (members >= 0).astype(float)}  # [C, R]
        if max_step is not None:
            model["max_step"] = np.float64(max_step)
        self._model = model  # float64, NumPy: the constants of problem's callables
        self._data_maps = {"M_data": M_data, "Ms": Ms, "err_d": err_d}  # float64: what params applies
        self._device = {}  # dtype -> the model and the data maps on the device, for solve and sequence
        reps = controls[members[:, 0]]
        self.problem = Problem(_bind(_dynamics, model), reps, _stage_cost, N, lower_bound=_lower_bound,
                               constraint=_bind(_constraint, model), step_index=True,
                               first_input_of=_bind(_first_input, model))
        # solve's: the model travels in the params, so a new model of the same shapes reuses the compiled search
        self._search_problem = Problem(_dynamics, reps, _stage_cost, N, lower_bound=_lower_bound,
                                       constraint=_constraint, step_index=True, first_input_of=_first_input)
        self.observe = _observer(self.class_size)

    @property
    def controls(self) -> np.ndarray:
        """``[M, m]`` the input set (read-only)."""
        return self._controls

    @property
    def class_of(self) -> np.ndarray:
        """``[M]`` the class (row of ``problem.controls``) of each input (read-only)."""
        return self._class_of

    def sequence(self, z0, classes, params):
        """``[N]`` int32 indices into ``controls``: the cheapest inputs of the
        optimal class sequence ``classes`` ``[N]`` (a ``SearchResult.sequence``
        of ``problem``) from the search state ``z0`` (``observe``); -1 where it
        is -1 (infeasible). Its J is the search's cost."""
        z0 = jnp.asarray(z0)
        return _sequence(z0, classes, self._with_model(params, z0.dtype))

    def params(self, y_ref, d=None) -> dict:
        """The params of ``problem`` for a reference ``y_ref`` ``[..., N, p]``
        (y_ref[k] is the target of C x(k+1)) and disturbance ``d`` ``[..., N, n]``
        (default 0), in y_ref's floating dtype. Leading axes batch: one row per
        state for ``fj.solve_batch``, one per step for ``FIRHC.simulate``.

        Only what the data decides, per step: the data part of each step's map
        (``off`` ``[..., N, 2n + p + m]``), bounds on the rounding of its
        cost-to-go rows (``off_err`` ``[..., N]``) and on the factorisation's
        own error (``g_err`` ``[..., N]``), the data-only part of the
        cost-to-go (``s`` ``[..., N]``), and the data itself (``y_ref``,
        ``d``: a closed loop's plant gets the same params, e.g.
        ``A x + B u + p["d"][0]``). The model is held by ``problem``'s
        callables. Give the state (``observe``) the same dtype."""
        y_ref = jnp.asarray(y_ref)
        if not jnp.issubdtype(y_ref.dtype, jnp.floating):
            y_ref = y_ref.astype(jax.dtypes.canonicalize_dtype(np.float64))
        lead, N = y_ref.shape[:-2], self.horizon
        if y_ref.shape[-2:] != (N, self.p):
            raise ValueError(f"y_ref must be [N, p] = [{N}, {self.p}] (with optional leading axes), "
                             f"got shape {tuple(y_ref.shape)}")
        d = jnp.zeros(lead + (N, self.n), y_ref.dtype) if d is None else jnp.asarray(d, y_ref.dtype)
        if d.shape != lead + (N, self.n):
            raise ValueError(f"d must be [N, n] = [{N}, {self.n}] with y_ref's leading axes {lead}, "
                             f"got shape {tuple(d.shape)}")
        return _params(self._factors(y_ref.dtype)["maps"], y_ref, d)

    def _factors(self, dtype) -> dict:
        """The model and the data maps on the device in ``dtype`` (made once per dtype)."""
        key = jnp.dtype(dtype)
        if key not in self._device:
            host = {"model": self._model, "maps": self._data_maps}
            self._device[key] = jax.tree_util.tree_map(lambda a: jnp.asarray(a, key), host)
        return self._device[key]

    def _with_model(self, params, dtype) -> dict:
        """``params`` with the model's arrays added: the params of the module's own callables."""
        return {**self._factors(dtype)["model"], **params}

    def solve(self, x, u_prev, y_ref, d=None, *, warm_start=None, max_nodes=None) -> SearchResult:
        """The exact minimiser of J from state ``x`` ``[n]`` after input
        ``u_prev`` ``[m]``, for ``y_ref`` ``[N, p]`` and ``d`` ``[N, n]`` (default 0).

        ``cost`` is J, ``sequence`` indexes ``controls`` (infeasible under
        ``max_step``: cost +inf, sequence -1, NaN input). ``warm_start``
        ``[N]`` is evaluated first and becomes the initial radius if feasible;
        ``max_nodes`` as in ``fj.sdfs``. Runs in ``x``'s floating dtype;
        works under ``jax.jit`` and ``jax.vmap``, and new values never
        recompile."""
        x = as_state(x, "x")
        if x.shape != (self.n,):
            raise ValueError(f"x must be [n] = [{self.n}], got shape {tuple(x.shape)}")
        u_prev = _vector("u_prev", u_prev, (self.m,), x.dtype)
        y_ref = _vector("y_ref", y_ref, (self.horizon, self.p), x.dtype)
        d = None if d is None else _vector("d", d, (self.horizon, self.n), x.dtype)
        if warm_start is not None:
            ws = warm_start if is_tracer(warm_start) else np.asarray(warm_start)
            if ws.shape != (self.horizon,) or not jnp.issubdtype(ws.dtype, jnp.integer):
                raise ValueError(f"warm_start must be [N] = [{self.horizon}] integer indices into controls, "
                                 f"got {ws.dtype} of shape {tuple(ws.shape)}")
            M = len(self._controls)
            if not is_tracer(ws) and not (bool(jnp.all((ws >= 0) & (ws < M))) or bool(jnp.all(ws == -1))):
                raise ValueError(f"warm_start indices must lie in [0, {M}) (or be all -1: none), got {ws.tolist()}")
            warm_start = ws.astype(np.int32)
        # One compiled call (observe, params, search, members), shared by trackers of equal shapes: the model
        # travels as an argument, so a new A, B, Q or lambda_u of the same shapes reuses it.
        run = compiled(_solve, self._search_problem, observe=self.observe)
        return raise_on_errors(run(self._factors(x.dtype), self._controls, self._class_of, x, u_prev, y_ref, d,
                                   warm_start, node_budget(max_nodes)))


def _solve(problem, factors, controls, class_of, x, u_prev, y_ref, d, warm_start, budget, *, observe):
    """``LinearTracking.solve`` after its checks, traced (``problem``: the one whose params carry the model)."""
    if warm_start is not None:  # indices into controls -> their classes (all -1 stays none)
        M = class_of.shape[0]
        inside = (warm_start >= 0) & (warm_start < M)
        warm_start = jnp.where(inside, class_of[jnp.clip(warm_start, 0, M - 1)],
                               jnp.where(warm_start < 0, warm_start, problem.num_controls))
    d = jnp.zeros(y_ref.shape[:-1] + x.shape, x.dtype) if d is None else d
    z0, params = observe(x, u_prev), {**factors["model"], **_params(factors["maps"], y_ref, d)}
    result = sdfs(problem, z0, params=params, warm_start=warm_start, max_nodes=budget)
    sequence = _sequence(z0, result.sequence, params)
    # the first of these inputs (first_input_of may break a tie between members the other way)
    first = controls.astype(result.first_input.dtype)[jnp.maximum(sequence[0], 0)]
    return result._replace(sequence=sequence, first_input=jnp.where(result.feasible, first, jnp.nan))


# ---------------------------------------------------------------------------
# The problem's callables: one set for every model. ``LinearTracking.problem`` binds them to its model (``_bind``:
# constants, so that a closed loop's per-step params carry only the step's data); ``solve`` passes the model in
# the params (a new A, B, Q or lambda_u of the same shapes reuses its compiled search). A child is a *class* of
# inputs with the same effect B u on the plant (the inverter's switch states of one voltage vector:
# ``input_classes``); only the switching term tells its members apart, so the child keeps all R of them: state
# z = [x (n), members' inputs U (R m), their switching costs o (R), stage cost, bound] ``[n + R (m + 1) + 2]``.
# o[e] is the cheapest switching of the steps so far that ends on member e, less that of the cheapest member
# (whose cost the stage cost carries), so o >= 0, and -1 marks a member that no allowed switching reaches (a
# marker no cost can take, and finite: the searches discard non-finite states). A min-plus step per child (the
# Viterbi recursion), so the tree branches on the C classes and never on members of one class. One affine map of
# [x; u] per child (``child_map``) gives its state, the residual of its stage cost and that of its cost-to-go
# (one matrix product instead of several: measured in docs/inverter.md).
# ---------------------------------------------------------------------------

def _bind(fn, model):
    """``fn(z, ..., p)`` with ``model`` (float64 NumPy) added to ``p`` as constants in z's dtype."""
    def bound(z, *args):
        *rest, p = args
        if not isinstance(p, dict):
            raise TypeError("LinearTracking.problem reads each decision's data from its params: pass "
                            "params=lt.params(y_ref, d)")
        return fn(z, *rest, {**{k: jnp.asarray(v, z.dtype) for k, v in model.items()}, **p})

    return bound


def _sizes(z, u, prm):
    R, m = prm["members"].shape[-2:]
    n = z.shape[0] - R * (m + 1) - 2
    return n, m, R, prm["M"].shape[1] - 2 * n - m  # n, m, R, p


def _entries(z, n, m, R):
    """The node's members ``[R, m]`` and their switching costs ``[R]`` (-1: not reached)."""
    return z[n:n + R * m].reshape(R, m), z[n + R * m:n + R * (m + 1)]


def _switch(u_from, o_from, u_to, ok_to, prm):
    """One min-plus step of the switching costs: for each member ``u_to`` ``[R', m]`` the cheapest
    o_from[e] + lambda_u ||u_to - u_from[e]||^2 over the allowed predecessors e (``[R', R]``; +inf where there
    is none), and the argmin."""
    du = u_to[:, None, :] - u_from[None, :, :]
    allowed = ok_to[:, None] & (o_from[None, :] >= 0)
    if "max_step" in prm:
        allowed &= jnp.all(jnp.abs(du) <= prm["max_step"], axis=-1)
    S = jnp.where(allowed, o_from[None, :] + prm["lambda_u"] * jnp.sum(du * du, axis=-1), jnp.inf)
    return jnp.min(S, axis=1), jnp.argmin(S, axis=1)


def _class(u, prm):
    """``(class, found)``: the first class whose members include input ``u`` ``[m]``, and whether one does."""
    hit = jnp.any(jnp.all(prm["members"] == u.astype(prm["members"].dtype), axis=-1) & (prm["member_ok"] > 0), axis=-1)
    C = hit.shape[0]
    return jnp.minimum(jnp.min(jnp.where(hit, jnp.arange(C), C)), C - 1), jnp.any(hit)


def _dynamics(z, u, k, prm):
    n, m, R, p = _sizes(z, u, prm)
    j, found = _class(u, prm)  # an input of no class (not a control) has no child
    U, ok = prm["members"][j].astype(z.dtype), (prm["member_ok"][j] > 0) & found  # [R, m], [R]
    xu = jnp.concatenate([z[:n], U[0]])
    out = prm["M"][k] @ xu + prm["off"][k]  # [x(k+1) (n), sqrt(Q) (y_ref[k] - C x(k+1)) (p), W's residual v (n + m)]
    dU = U - U[0]
    v = out[n + p:] + dU @ prm["Tu"][k].T  # [R, n + m] the residual of W_{k+1}(x(k+1), member)
    # W = ||v||^2 + s, rounded down by a bound on the rounding of v (its terms nearly cancel, and W must stay
    # admissible): ||v_true|| >= ||v|| - ||v - v_true||, with ||v - v_true|| <= gamma (||M_v|| ||[x; u]|| + ||off_v||
    # + ||Tu|| ||du||) + the rounding of off_v.
    off_v = prm["off"][k][n + p:]
    g = _gamma(z.dtype, n + 2 * m)
    err = g * (prm["M_norm"][k] * jnp.sqrt(xu @ xu) + jnp.sqrt(off_v @ off_v)
               + prm["Tu_norm"][k] * jnp.sqrt(jnp.sum(dU * dU, axis=1))) + prm["off_err"][k]
    W = jnp.maximum(jnp.sqrt(jnp.sum(v * v, axis=1)) - err, 0) ** 2 * (1 - g) + prm["s"][k]
    # and by the factorisation's own error (``cost_to_go``): sqrt(W) is off by at most
    # err_s ||[x(k+1); u]|| + g_err
    x_next = out[:n]
    off_by = prm["err_s"][k] * jnp.sqrt(x_next @ x_next + jnp.sum(U * U, axis=1)) + prm["g_err"][k]
    W = jnp.maximum(jnp.sqrt(W) - off_by, 0) ** 2 * (1 - g)
    cost, _ = _switch(*_entries(z, n, m, R), U, ok, prm)
    reached = jnp.isfinite(cost)
    switching = jnp.min(cost)  # +inf where no member is reached: the constraint discards that child
    o = jnp.where(reached, cost - switching, -1)
    # o + W: one more rounding of each sum, taken off the bound too
    bound = jnp.min(jnp.where(reached, (o + W) * (1 - g), jnp.inf))
    e = out[n:n + p]
    return jnp.concatenate([x_next, U.reshape(-1), o, (e @ e + switching)[None], bound[None]])


def _stage_cost(z, u, k, prm):
    return z[-2]


def _lower_bound(z, steps_left, prm):
    return z[-1]


def _constraint(z, u, k, prm):
    """Some member of the class can follow the node's (max_step). Decided on the switching costs alone, so a
    NaN state or reference reaches the searches' own check of non-finite nodes (``nan_encountered``)."""
    n, m, R, _ = _sizes(z, u, prm)
    return jnp.any(_entries(z, n, m, R)[1] >= 0)


def _members(z0, classes, prm):
    """``[N]`` the member (0 .. R-1) of each class of ``classes`` on the cheapest switching path from the
    root ``z0``: the min-plus recursion of ``_dynamics`` forward, then its argmins backward."""
    R, m = prm["members"].shape[-2:]
    n = z0.shape[0] - R * (m + 1) - 2
    j = jnp.maximum(classes, 0)

    def forward(carry, jk):
        U_from, o_from = carry
        U, ok = prm["members"][jk].astype(z0.dtype), prm["member_ok"][jk] > 0
        cost, came_from = _switch(U_from, o_from, U, ok, prm)
        return (U, cost), came_from

    (_, last), came_from = jax.lax.scan(forward, _entries(z0, n, m, R), j)  # came_from [N, R]

    def backward(e, came):
        return came[e], e

    _, picked = jax.lax.scan(backward, jnp.argmin(last).astype(came_from.dtype), came_from, reverse=True)
    return picked


@jax.jit
def _sequence(z0, classes, prm):
    picked = _members(z0, classes, prm)
    return jnp.where(classes >= 0, prm["member_index"][jnp.maximum(classes, 0), picked].astype(jnp.int32), -1)


def _first_input(z0, classes, prm):
    """``first_input_of``: the first member on the cheapest switching path of ``classes`` from ``z0``.

    This runs in every decision, so without a loop: the switching costs between the members of consecutive
    classes are R x R matrices, all built at once, and their min-plus product (associative) is reduced
    pairwise, log2(N) vectorised levels (a scan costs several microseconds a step on XLA:CPU, and an
    unrolled recursion made the work pool's compile time grow steeply with N: 340 s at N = 10)."""
    R, m = prm["members"].shape[-2:]
    n = z0.shape[0] - R * (m + 1) - 2
    j = jnp.maximum(classes, 0)
    U, ok = prm["members"][j].astype(z0.dtype), prm["member_ok"][j] > 0  # [N, R, m], [N, R]
    first, _ = _switch(*_entries(z0, n, m, R), U[0], ok[0], prm)  # [R] the root to each first member
    du = U[1:, None, :, :] - U[:-1, :, None, :]  # [N-1, R (from), R (to), m]
    allowed = ok[:-1, :, None] & ok[1:, None, :]
    if "max_step" in prm:
        allowed &= jnp.all(jnp.abs(du) <= prm["max_step"], axis=-1)
    chain = jnp.where(allowed, prm["lambda_u"] * jnp.sum(du * du, axis=-1), jnp.inf)  # [N-1, R, R]
    while chain.shape[0] > 1:  # min-plus products of neighbours; an odd one out waits a level
        pairs = chain.shape[0] // 2 * 2
        product = jnp.min(chain[:pairs:2, :, :, None] + chain[1:pairs:2, None, :, :], axis=2)
        chain = jnp.concatenate([product, chain[pairs:]])
    rest = jnp.min(chain[0], axis=1) if chain.shape[0] else jnp.zeros((R,), z0.dtype)
    return U[0][jnp.argmin(first + rest)]


_OBSERVERS = {}


def _observer(R: int):
    """``observe`` for trackers whose classes have R members: one function per R, so that controllers of
    equal shapes share their compiled loop."""
    if R not in _OBSERVERS:
        def observe(x, u_prev, p=None):
            """The search state ``[x, u_prev (R times), o = [0, -1, ...], 0, 0]`` ``[n + R (m + 1) + 2]``
            from the plant state ``x`` ``[n]`` and the input applied last ``u_prev`` ``[m]``. The signature
            of ``fj.FIRHC``'s ``observe`` (``p`` unused)."""
            x = jnp.asarray(x)
            u_prev = jnp.asarray(u_prev, x.dtype)
            o = jnp.full((R,), -1, x.dtype).at[0].set(0)
            return jnp.concatenate([x, jnp.tile(u_prev, R), o, jnp.zeros(2, x.dtype)])

        _OBSERVERS[R] = observe
    return _OBSERVERS[R]


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


@jax.jit
def _params(maps, y_ref, d):
    dtype = y_ref.dtype
    lead = y_ref.shape[:-2]
    data = jnp.concatenate([y_ref.reshape(lead + (-1,)), d.reshape(lead + (-1,))], axis=-1)  # [..., N(p + n)]
    gamma = _gamma(dtype, data.shape[-1])

    def apply(M):  # M data and a bound on its rounding error
        return (jnp.einsum("kid,...d->...ki", M, data),
                gamma * jnp.einsum("kid,...d->...ki", jnp.abs(M), jnp.abs(data)))

    off, off_err = apply(maps["M_data"])
    e, e_err = apply(maps["Ms"])
    n_w = off.shape[-1] - d.shape[-1] - y_ref.shape[-1]  # n + m rows of W's residual, the last of off
    data_norm = jnp.sqrt(jnp.sum(data * data, axis=-1))
    return {"off": off, "off_err": jnp.sqrt(jnp.sum(off_err[..., -n_w:] ** 2, axis=-1)),
            "s": _norm2_below(e, e_err), "g_err": maps["err_d"] * (data_norm * (1 + gamma))[..., None],
            "y_ref": y_ref, "d": d}


# ---------------------------------------------------------------------------
# The static factorisation (NumPy, float64).
# ---------------------------------------------------------------------------

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


def _gamma(dtype, terms: int):
    """Relative rounding bound of a dot product of ``terms`` terms (with margin)."""
    return jnp.finfo(dtype).eps * (terms + 2)


def _norm2_below(v, err):
    """A lower bound of ||v_true||^2 over the last axis, given |v - v_true| <= err
    elementwise: W must never exceed the true cost-to-go (T s and w nearly
    cancel, so their rounding matters in float32)."""
    sq = jnp.sum(jnp.maximum(jnp.abs(v) - err, 0) ** 2, axis=-1)
    return sq * (1 - _gamma(v.dtype, v.shape[-1]))


def psd_factor(name: str, Q) -> np.ndarray:
    """``L`` ``[p, p]`` with L^T L = Q, for a symmetric positive semidefinite
    ``Q`` (checked by ``fj.problem.weight``: else a ``ValueError`` naming ``name``)."""
    w, vecs = np.linalg.eigh(weight(name, Q))
    return np.sqrt(np.clip(w, 0, None))[:, None] * vecs.T


def _matrix(name, a) -> np.ndarray:
    if is_tracer(a):
        raise TypeError(f"{name} must be concrete values, not a traced array: the model is factorised once, "
                        "in NumPy, when LinearTracking is built")
    try:
        given = np.asarray(a)
        if given.dtype.kind == "c":
            raise TypeError(f"{name} must be real, got complex dtype {given.dtype}")
        arr = given.astype(float)
    except ValueError as e:
        raise TypeError(f"{name} must be a real 2-D array: {e}") from None
    if arr.ndim != 2 or 0 in arr.shape:
        raise ValueError(f"{name} must be a non-empty 2-D array, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf")
    return arr


def _scalar(name, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a real number, got {value!r}") from None
    if not np.isfinite(v) or v < 0:
        raise ValueError(f"{name} must be finite and >= 0, got {value!r}")
    return v


def _vector(name, a, shape, dtype):
    if not is_tracer(a):
        arr = np.asarray(a)
        if arr.dtype.kind not in "biuf":
            raise TypeError(f"{name} must be a real array {list(shape)}, got dtype {arr.dtype}")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} contains NaN or inf")
        a = arr
    if tuple(a.shape) != shape:
        raise ValueError(f"{name} must have shape {list(shape)}, got {tuple(a.shape)}")
    return a.astype(dtype) if is_tracer(a) else np.asarray(a, dtype)  # a jitted call takes NumPy as it is
