"""Exact tracking for linear plants with a finite input set at long horizons:
the sphere decoder as a lower bound of the sorted search.

The problem (``LinearTracking``): x(k+1) = A x(k) + B u(k) + d(k), y = C x,
every u(k) a row of ``controls``, and

    J(U) = sum_{k=0}^{N-1} ||y_ref[k] - C x(k+1)||_Q^2 + lambda_u ||u(k) - u(k-1)||^2,   u(-1) = u_prev,

or with the switching term lambda_u ||u(k) - u(k-1)||_1 (``norm="abs"``: for unit steps the count of switch
changes, FCS-MPC's usual term), optionally with |u_i(k) - u_i(k-1)| <= max_step for every component and step.

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
step: the Viterbi recursion over at most R members, once per node for all its
children, from a table of the switchings between members). Its cost is
then J's minimum over every sequence of inputs of that class sequence, and
its bound the smallest of (member's switching + W from that member). Exact:
the optimum is the cheapest class sequence with its cheapest members, which
``sequence`` recovers from the plan (forward min-plus, argmins backward), and
``first_input_of`` gives the member to apply now. On the three-level inverter
(27 inputs, 19 classes, N = 10, lambda_u = 0.1) this computes 27 times fewer
nodes than the plain sorted search (docs/applications/inverter.md); without equal-effect
inputs (R = 1) the node is the plain one.

In this form the search state is the plant's own: a ``Node`` (x, the root's
u_prev, the class, its members' switching costs o above the cheapest, the stage
cost and the bound W; n + m + R + 3 numbers instead of the decoder's N m
partial sums), and the cost a search returns is J itself, accumulated stage by
stage. W_k is kept factored, W_k(s) = ||T_k s + w_k||^2 + s_k for
s = [x; u_prev]: T_k is static (a ``TrackingModel``), w_k and s_k are linear
and quadratic in (y_ref, d) and travel as params (``TrackingParams``), so new
states, references and disturbances never recompile. One node is one step with
its C classes (not one input component per level as in the decoder), and where
F is rank deficient W is strictly tighter than the decoder's distance: both
measured in docs/applications/inverter.md.

W stays a lower bound at any scaling of Q, lambda_u and the units: which
directions inputs reach is decided on F with unit rows and columns
(``linear_factor._rank``), and the factorisation's own error bound is taken off W
(``linear_factor.cost_to_go``): weights whose ratio nears 1/eps weaken W towards 0, and
the search towards the plain sorted search, which is still exact.

The factorisation is NumPy, float64, done once per tracker (``firhc_jax._src.linear.factor``); this module holds the
named structures and the traced callables.
"""
from __future__ import annotations

import functools
import warnings
from collections.abc import Mapping
from typing import Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from ..annotations import ArrayLike
from ..checks import as_sequence, as_state, finite, is_tracer, matrix, non_negative, numeric, positive_int
from ..problem.problem import Problem, _check_controls
from ..runtime import engines, lean
from ..runtime.memory_cache import cached, compiled
from ..runtime.packed import compile_packed
from ..search.one_state import sdfs
from ..search.result import SearchResult, alarms, raise_on_errors
from ..search.sdfs import DEFAULT_MAX_MEMORY, node_budget
from .factor import child_map, factor_memory, input_classes, psd_factor

NORMS = ("squared", "abs")  # the switching term: lambda_u ||du||^2 or lambda_u ||du||_1

# ---------------------------------------------------------------------------
# Named structures. Shapes are one decision's: n states, m inputs, p outputs, N steps, C classes of at most R
# inputs; params and a batch of nodes take leading axes (one per row, step or loop) in front.
# ---------------------------------------------------------------------------

class Node(NamedTuple):
    """A node of the search: the plant state that a class of inputs of equal effect reached, the cheapest
    switching that ends on each of the class's members, the step's stage cost and the bound.

    ``j`` is the class of the step into the node (its members: ``lt.classes[j]``, in the order of ``o``); the
    root has none (-1) and switches from ``u_prev``, the input applied last, which its children read (the
    other nodes carry the root's). ``o[e]`` is the cheapest switching of the steps so far that ends on member e,
    less that of the cheapest member (whose cost ``stage`` carries), so o >= 0; -1 marks a member that no
    allowed switching reaches (a marker no cost can take, and finite: the searches discard non-finite states).
    ``fj.Problem`` states are vectors that every search stacks ``[..., n]``, so the searches hold a node packed,
    ``[n + m + R + 3]`` (``pack``; ``LinearTracking.observe`` packs the root), and the callables read it back
    (``unpack``)."""
    x: jax.Array       # [n] the plant state
    u_prev: jax.Array  # [m] the input applied before the root
    j: jax.Array       # [] the class of the step into the node, as a number of the node's dtype; -1: the root
    o: jax.Array       # [R] each member's switching so far above the cheapest member's; -1: not reached
    stage: jax.Array   # [] the stage cost of the step into the node: tracking error plus the cheapest switching
    W: jax.Array       # [] the bound on the cost to go: the least o[e] + W_k(x, member e) over the members

    def pack(self) -> jax.Array:
        """``[n + m + R + 3]``: the node as the searches hold it."""
        return jnp.concatenate([self.x, self.u_prev, self.j[None], self.o, self.stage[None], self.W[None]])

    @classmethod
    def unpack(cls, z, R: int, m: int) -> Node:
        """The node packed in ``z`` ``[n + m + R + 3]``, its classes of ``R`` members of ``m`` inputs."""
        n = z.shape[0] - m - R - 3
        return cls(z[:n], z[n:n + m], z[n + m], z[n + m + 1:n + m + 1 + R], z[-2], z[-1])


class TrackingModel(NamedTuple):
    """What the callables read of a tracker's weights and plant: its factorisation (``linear_factor.child_map``)
    and lambda_u. Trackers of equal shapes (A, B, C and Q shapes, horizon) have models of equal shapes,
    whatever their values; the classes of inputs and the switching term's norm and ``max_step`` are the
    callables' own (``shared_problem``: one set per controls, norm and max_step)."""
    M: jax.Array             # [N, 2n + p + m, n + m] step k's map of [x; u]: x(k+1), -sqrt(Q) C x(k+1), W's residual
    M_norm: jax.Array        # [N] Frobenius norm of M's rows of W's residual: a bound on their rounding
    lambda_u: jax.Array      # [] the weight of the switching term
    Tu: jax.Array            # [N, n + m, m] how W's residual moves with the child's input (the other members)
    Tu_norm: jax.Array       # [N] Frobenius norm of Tu
    err_s: jax.Array         # [N] the factorisation's error in sqrt(W_{k+1}) per unit of ||[x(k+1); u]||


class _Classes(NamedTuple):
    """The classes of inputs of equal effect and the switching between their members: what depends on the
    controls, the norm and max_step only, held by the callables as constants (float64 NumPy)."""
    members: np.ndarray       # [C, R, m] each class's inputs (padding repeats the first)
    member_index: np.ndarray  # [C, R] their indices into controls, as numbers
    member_ok: np.ndarray     # [C, R] 1 for a member, 0 for padding
    du_norm: np.ndarray       # [C, R] ||member e - member 0||: how far W's residual moves from member 0's
    l1: np.ndarray            # [] 1: the switching term is lambda_u ||u(k) - u(k-1)||_1; 0: lambda_u ||...||^2
    max_step: Optional[np.ndarray]  # [] the bound on |u_i(k) - u_i(k-1)|; None: no bound
    switch: Optional[np.ndarray]    # [C, R, C, R] switching per unit lambda_u from member (i, e) to (j, f), -1
    #                                 where not allowed (max_step, padding); None: computed from the members


class _DataMaps(NamedTuple):
    """The linear maps from a decision's data [vec(y_ref); vec(d)] ``[N (p + n)]`` to its params."""
    M_data: jax.Array  # [N, 2n + p + m, N (p + n)] the data's part of each step's child map
    Ms: jax.Array      # [N, N (p + m), N (p + n)] the data-only part of W_{k+1}'s residual
    err_d: jax.Array   # [N] the factorisation's error in sqrt(W_{k+1}) per unit of ||data||


class TrackingParams(NamedTuple):
    """One decision's params of ``LinearTracking.problem`` (``lt.params(y_ref, d)``): what its data decides.
    A closed loop's plant gets them too: ``A x + B u + p.d[0]``."""
    off: jax.Array      # [N, 2n + p + m] the data's part of each step's child map (M_data data)
    off_err: jax.Array  # [N] a bound on the rounding of off's rows of W's residual
    s: jax.Array        # [N] the data-only part of W_{k+1}, rounded down
    g_err: jax.Array    # [N] the factorisation's error in sqrt(W_{k+1}) from the data
    y_ref: jax.Array    # [N, p] the reference: y_ref[k] is the target of C x(k+1)
    d: jax.Array        # [N, n] the disturbance: x(k+1) = A x(k) + B u(k) + d[k]

    def __getitem__(self, key):
        """``p[i]`` as for any tuple; ``p["d"]`` (the params were a dict) warns and reads ``p.d``."""
        if isinstance(key, str):
            if key not in self._fields:
                raise KeyError(f"{key!r}: LinearTracking's params have the fields {self._fields}")
            warnings.warn(f'LinearTracking\'s params are a TrackingParams: read p.{key}, not p["{key}"] (the '
                          "dict access goes in the next release)", DeprecationWarning, stacklevel=2)
            return getattr(self, key)
        return tuple.__getitem__(self, key)


class SharedParams(NamedTuple):
    """One decision's params of ``LinearTracking.shared_problem`` (``lt.params(y_ref, d, with_model=True)``):
    the data and the tracker's model, so that one compiled search serves every tracker of equal shapes."""
    data: TrackingParams  # the decision's data (the plant reads p.data.d)
    model: TrackingModel  # the tracker's model in the data's dtype, with the data's leading axes


class LinearTracking:
    """Exact finite-input tracking MPC for a linear plant (module docstring).

    The model must be linear, x+ = A x + B u + d. A bilinear one (a
    flying-capacitor converter: the switch state times the state) is out of
    scope: solve it as a plain ``fj.Problem`` with that model as its
    ``dynamics`` (and a ``lower_bound`` if you have one), or linearise it per
    operating point (docs/guide/long-horizons.md, "Models that are not
    linear").

    Args:
      A: ``[n, n]``, B: ``[n, m]``: the discrete-time model x+ = A x + B u + d.
      controls: ``[M, m]`` finite input set (``[M]`` when m = 1).
      horizon: N >= 1.
      C: ``[p, n]`` output matrix (default I).
      Q: ``[p, p]`` symmetric positive semidefinite output weight (default I).
      lambda_u: weight (>= 0) of the switching term, the first step against u_prev.
      norm: the switching term: ``"squared"`` (default), lambda_u ||u(k) - u(k-1)||^2, or ``"abs"``,
        lambda_u ||u(k) - u(k-1)||_1 (for unit steps, the count of switch changes), as
        ``fj.input_change_cost``'s ``norm``.
      max_step: optional bound (>= 0) on |u_i(k) - u_i(k-1)|, every component
        and step, the first against u_prev: a hard constraint.
      max_memory: bytes the factorisation may take (``factor_memory``, which
        grows as N^3); a larger one is refused before any work.

    Attributes:
      problem: the ``fj.Problem`` the search solves (``step_index=True``): one
        child per class of inputs (its controls ``[C, m]``: each class's first
        input), state a packed ``Node`` ``[n + m + R + 3]`` (``observe``),
        params of one decision from ``params``, ``lower_bound`` the
        cost-to-go W, ``first_input_of`` the member to apply. Use it with any
        solver: ``fj.sdfs``, ``fj.solve_batch``, ``fj.FIRHC``: their
        ``first_input`` is the exact optimum's; their ``sequence`` indexes
        classes (``sequence`` maps it to inputs). Its callables hold the model
        as constants, so each step's params are its data only, and a new
        tracker compiles its own search.
      shared_problem: the same problem with callables that read the model
        from the params (``params(..., with_model=True)``): one compiled
        search for every tracker of equal shapes (see below); ``solve`` uses it.
      num_classes, class_size: C classes of at most R inputs (``input_classes``).
      observe: ``observe(x, u_prev[, p])``, the search state at plant state
        ``x`` after input ``u_prev``.

    Weights per closed loop or per row, without recompiling: trackers of equal
    shapes (A, B, C and Q shapes, the same ``controls`` and classes, horizon,
    ``norm`` and ``max_step``) differ only in their ``TrackingModel``'s values. So
    ``fj.FIRHC(lt.shared_problem, observe=lt.observe)`` with
    ``other.params(y_ref, d, with_model=True)`` decides as ``other``'s own
    controller, and a batch whose rows (or loops) carry params of different
    trackers, stacked, solves each with its own weights in one compiled call.

    The factorisation is done once here, in float64 (NumPy); the search runs in
    the dtype of the state given to it.
    """

    def __init__(self, A: ArrayLike, B: ArrayLike, controls: ArrayLike, horizon: int, *, C: ArrayLike | None = None,
                 Q: ArrayLike | None = None, lambda_u: float = 0.0, norm: str = "squared",
                 max_step: float | None = None, max_memory: int = DEFAULT_MAX_MEMORY):
        A = matrix("A", A)
        n = A.shape[0]
        if A.shape != (n, n):
            raise ValueError(f"A must be square [n, n], got shape {A.shape}")
        B = matrix("B", B)
        if B.shape[0] != n:
            raise ValueError(f"B must be [n, m] with n = {n} rows like A, got shape {B.shape}")
        m = B.shape[1]
        C = np.eye(n) if C is None else matrix("C", C)
        if C.shape[1] != n:
            raise ValueError(f"C must be [p, n] with n = {n} columns like A, got shape {C.shape}")
        p = C.shape[0]
        Q = np.eye(p) if Q is None else matrix("Q", Q)
        if Q.shape != (p, p):
            raise ValueError(f"Q must be [p, p] = [{p}, {p}] like the rows of C, got shape {Q.shape}")
        N = positive_int("horizon", horizon)
        lambda_u = non_negative("lambda_u", lambda_u)
        if norm not in NORMS:
            raise ValueError(f"norm must be one of {NORMS}, got {norm!r}")
        max_step = None if max_step is None else non_negative("max_step", max_step)
        max_memory = positive_int("max_memory", max_memory)
        need = factor_memory(n, m, p, N)
        if need > max_memory:
            raise ValueError(f"LinearTracking's factorisation at horizon N = {N} (n = {n}, m = {m}, p = {p}) needs "
                             f"about {need:,} bytes, more than max_memory={max_memory:,} (it grows as N^3); "
                             "shorten the horizon or raise max_memory")
        self.A, self.B, self.C, self.Q = A, B, C, Q
        self.lambda_u, self.norm, self.max_step, self.horizon = lambda_u, norm, max_step, N
        self.n, self.m, self.p = n, m, p
        controls = _check_controls(controls)
        if controls.shape[1] != m:
            raise ValueError(f"controls must have m = {m} columns like B, got shape {controls.shape}")
        self._controls = controls
        members = input_classes(B, controls)  # [C, R]
        self._members = members
        self.num_classes, self.class_size = members.shape
        self._class_of = np.zeros(len(controls), np.int32)  # [M] the class of each input
        for j, row in enumerate(members):
            self._class_of[row[row >= 0]] = j
        M, M_data, Ms, Tu, err_s, err_d = child_map(A, B, C, psd_factor("Q", Q), _squared_weight(
            lambda_u, norm, controls, max_step), N)
        # float64, NumPy: the constants of problem's callables, and what params applies to the data
        self._model = TrackingModel(
            M=M, M_norm=np.linalg.norm(M[:, n + p:], axis=(1, 2)), lambda_u=np.float64(lambda_u), Tu=Tu,
            Tu_norm=np.linalg.norm(Tu, axis=(1, 2)), err_s=err_s)
        self._maps = _DataMaps(M_data, Ms, err_d)
        self._device = {}  # dtype -> the model, the data maps and the classes on the device
        classes = _classes_of(controls, members, norm, max_step)
        reps = controls[members[:, 0]]
        self.problem = Problem(controls=reps, horizon=N, step_index=True, **_callables(classes, self._model))
        self.shared_problem = Problem(controls=reps, horizon=N, step_index=True,
                                      **_shared_callables(classes, controls, members, norm, max_step))
        self._classes = classes
        self.observe = _observer(self.class_size)

    @property
    def controls(self) -> np.ndarray:
        """``[M, m]`` the input set (read-only)."""
        return self._controls

    @property
    def class_of(self) -> np.ndarray:
        """``[M]`` the class (row of ``problem.controls``) of each input (read-only)."""
        return self._class_of

    @property
    def classes(self) -> np.ndarray:
        """``[C, R]`` each class's members, indices into ``controls`` in the order of a ``Node``'s ``o``, -1
        padding a class of fewer than R (read-only)."""
        return self._members

    def sequence(self, z0: ArrayLike, classes: ArrayLike, params: TrackingParams | SharedParams) -> jax.Array:
        """``[N]`` int32 indices into ``controls``: the cheapest inputs of the
        optimal class sequence ``classes`` ``[N]`` (a ``SearchResult.sequence``
        of ``problem`` or ``shared_problem``) from the search state ``z0``
        (``observe``), with the model of ``params`` (a ``SharedParams``) or
        this tracker's; -1 where it is -1 (infeasible). Its J is the search's cost."""
        z0 = jnp.asarray(z0)
        model, _, tables = self._on_device(z0.dtype)
        model = params.model if isinstance(params, SharedParams) else model
        return _sequence(z0, classes, _in_dtype(model, z0.dtype), tables)

    def params(self, y_ref: ArrayLike, d: ArrayLike | None = None, *,
               with_model: bool = False) -> TrackingParams | SharedParams:
        """The params of ``problem`` for a reference ``y_ref`` ``[..., N, p]``
        (y_ref[k] is the target of C x(k+1)) and disturbance ``d`` ``[..., N, n]``
        (default 0), in y_ref's floating dtype. Leading axes batch: one row per
        state for ``fj.solve_batch``, one per step for ``FIRHC.simulate``.

        A ``TrackingParams``: what the data decides, per step (its fields), the
        data itself included (``p.y_ref``, ``p.d``: a closed loop's plant gets
        the same params, e.g. ``A x + B u + p.d[0]``). The model is held by
        ``problem``'s callables. With ``with_model=True``, the params of
        ``shared_problem``: a ``SharedParams`` of that data and this tracker's
        model (``TrackingModel``), every leaf with y_ref's leading axes, so
        that rows, steps or loops of different trackers stack. Give the state
        (``observe``) the same dtype."""
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
        model, maps, _ = self._on_device(y_ref.dtype)
        data = _params(maps, y_ref, d)
        if not with_model:
            return data
        return SharedParams(data, jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, lead + a.shape), model))

    def _on_device(self, dtype) -> tuple[TrackingModel, _DataMaps, _Classes]:
        """The model, the data maps and the classes on the device in ``dtype`` (made once per dtype)."""
        key = jnp.dtype(dtype)
        if key not in self._device:
            with jax.ensure_compile_time_eval():  # concrete arrays even when first asked for inside a trace
                self._device[key] = _in_dtype((self._model, self._maps, self._classes), key)
        return self._device[key]

    def solve(self, x: ArrayLike, u_prev: ArrayLike, y_ref: ArrayLike, d: ArrayLike | None = None, *,
              warm_start: ArrayLike | None = None, max_nodes: int | ArrayLike | None = None,
              engine: str = "xla") -> SearchResult:
        """The exact minimiser of J from state ``x`` ``[n]`` after input
        ``u_prev`` ``[m]``, for ``y_ref`` ``[N, p]`` and ``d`` ``[N, n]`` (default 0).

        ``cost`` is J, ``sequence`` indexes ``controls`` (infeasible under
        ``max_step``: cost +inf, sequence -1, NaN input). ``warm_start``
        ``[N]`` is evaluated first and becomes the initial radius if feasible;
        ``max_nodes`` as in ``fj.sdfs``. Runs in ``x``'s floating dtype;
        works under ``jax.jit`` and ``jax.vmap``, and new values never
        recompile. ``engine="c"`` runs an eager call in C as ``fj.sdfs``'s
        does (``export_c``'s ``NAME_track``, compiled on the first call for
        each argument shape); a traced call runs in XLA either way."""
        args = (x, u_prev, y_ref, d, warm_start)
        entry = ("lt.solve", self, max_nodes is None, engine)
        run = None if is_tracer(max_nodes) else lean.recall(entry, args)
        if run is None:  # the first call of this signature (or a traced one): every check
            x, u_prev, y_ref, d, warm_start = self._checked(*args)
            # No budget is no budget (None): fj.sdfs seeds a budgeted search first, which costs nodes
            budget = None if max_nodes is None else node_budget(max_nodes)
            checked = (x, u_prev, y_ref, d, warm_start)
            if any(map(is_tracer, (*checked, budget))):
                # One compiled call (observe, params, search, members), shared by trackers of equal shapes: the
                # model travels as an argument, so a new A, B, Q or lambda_u of the same shapes reuses it.
                run = compiled(_solve, self.shared_problem, observe=self.observe)
                return raise_on_errors(run(*self._on_device(x.dtype), self._controls, self._class_of, *checked,
                                           budget))
            outside = engines.engine(engine)
            if outside is not None:
                outside.check_tracking()
                run = lean.first_call(entry, args, lambda: outside.build_tracking(
                    self, *checked[:4], max_nodes is not None))
            else:
                run = lean.first_call(entry, args, lambda: self._eager(checked, max_nodes))
            args = checked
        x, u_prev, y_ref, d, warm_start = args
        result, alarm = run(x, u_prev, y_ref, d, None if warm_start is None else np.asarray(warm_start, np.int32),
                            node_budget(max_nodes))
        if alarm:  # the value checks of the first call on these values (each raises with its own message), then
            self._checked(x, u_prev, y_ref, d, warm_start)  # the search's error flags
            raise_on_errors(result)
        return result

    def _eager(self, checked: tuple, max_nodes) -> Callable:
        """``run(x, u_prev, y_ref, d, warm_start, max_nodes) -> (result, alarm)``: the compiled eager call for the
        checked arguments' shapes and dtypes, shared by trackers of equal shapes (the model travels as an
        argument)."""
        program = cached(
            ("lt.solve", "eager", self.shared_problem.key, self.observe, max_nodes is None, lean.spec(checked)),
            lambda: compile_packed(functools.partial(_solve_eager, self.shared_problem, observe=self.observe,
                                                     budgeted=max_nodes is not None),
                                   *self._on_device(checked[0].dtype), self._controls, self._class_of, *checked,
                                   node_budget(max_nodes)))

        def run(x, u_prev, y_ref, d, warm_start, budget):
            return program(*self._on_device(jax.dtypes.canonicalize_dtype(x.dtype)), self._controls,
                           self._class_of, x, u_prev, y_ref, d, warm_start, budget)
        return run

    def _checked(self, x, u_prev, y_ref, d, warm_start) -> tuple:
        """``solve``'s arguments, checked: ``x`` a finite state [n] (``as_state``), the vectors of their shapes
        in its dtype, ``warm_start`` indices into ``controls`` (``as_sequence``)."""
        x = as_state(x, "x")
        if x.shape != (self.n,):
            raise ValueError(f"x must be [n] = [{self.n}], got shape {tuple(x.shape)}")
        u_prev = _vector("u_prev", u_prev, (self.m,), x.dtype)
        y_ref = _vector("y_ref", y_ref, (self.horizon, self.p), x.dtype)
        d = None if d is None else _vector("d", d, (self.horizon, self.n), x.dtype)
        return x, u_prev, y_ref, d, as_sequence(warm_start, self.horizon, len(self._controls))


def _solve_eager(problem, model, maps, classes, controls, class_of, x, u_prev, y_ref, d, warm_start, budget, *,
                 observe, budgeted: bool):
    """An eager ``LinearTracking.solve`` (``lean``): ``(result, alarm)``; ``alarm``: a value fails the checks
    (a non-finite vector, a warm-start index out of range) or the search raised an error flag."""
    u_prev, y_ref = u_prev.astype(x.dtype), y_ref.astype(x.dtype)
    d = None if d is None else d.astype(x.dtype)
    alarm = lean.non_finite(x, u_prev, y_ref, d) | lean.bad_sequence(warm_start, class_of.shape[0])
    result = _solve(problem, model, maps, classes, controls, class_of, x, u_prev, y_ref, d, warm_start,
                    budget if budgeted else None, observe=observe)
    return result, alarm | alarms(result)


def _solve(problem, model, maps, classes, controls, class_of, x, u_prev, y_ref, d, warm_start, budget, *, observe):
    """``LinearTracking.solve`` after its checks, traced (``problem``: ``shared_problem``)."""
    if warm_start is not None:  # indices into controls -> their classes (all -1 stays none)
        M = class_of.shape[0]
        inside = (warm_start >= 0) & (warm_start < M)
        warm_start = jnp.where(inside, class_of[jnp.clip(warm_start, 0, M - 1)],
                               jnp.where(warm_start < 0, warm_start, problem.num_controls))
    d = jnp.zeros(y_ref.shape[:-1] + x.shape, x.dtype) if d is None else d
    z0 = observe(x, u_prev)
    result = sdfs(problem, z0, params=SharedParams(_params(maps, y_ref, d), model), warm_start=warm_start,
                  max_nodes=budget)
    sequence = _sequence(z0, result.sequence, model, classes)
    # the first of these inputs (first_input_of may break a tie between members the other way)
    first = controls.astype(result.first_input.dtype)[jnp.maximum(sequence[0], 0)]
    return result._replace(sequence=sequence, first_input=jnp.where(result.feasible, first, jnp.nan))


# ---------------------------------------------------------------------------
# The problem's callables: one set per classes of inputs, ``fn(z, ..., data, model, classes)``. ``problem`` binds
# its model as constants (``_callables(classes, model)``: a closed loop's per-step params carry only the step's
# data); ``shared_problem`` reads it from the params (``_shared_callables``: a new A, B, Q or lambda_u of the same
# shapes reuses its compiled search). A child is a *class* of inputs with the same effect B u on the plant (the
# inverter's switch states of one voltage vector: ``input_classes``); only the switching term tells its members
# apart, so the child keeps the cheapest switching to each of its R members (``Node``), and the tree branches on
# the C classes and never on members of one class. The min-plus step from a node's members to every class's is
# computed once per node (it depends on the node alone: ``vmap`` over the children leaves it unbatched), from a
# table of the switchings between members (``_Classes.switch``), and each child reads its row. One affine map of
# [x; u] per child (``child_map``) gives its state, the residual of its stage cost and that of its cost-to-go.
# ---------------------------------------------------------------------------

def _callables(classes: _Classes, model: Optional[TrackingModel] = None) -> dict:
    """The ``fj.Problem`` callables, each ``(z, ..., p)``, with ``classes`` (float64 NumPy) held as constants and
    ``model`` too (``problem``), or, for None, the model read from the params (``shared_problem``)."""
    def reading(fn):
        def call(z, *args):
            *rest, p = args
            if model is None:
                if not isinstance(p, SharedParams):
                    raise TypeError("LinearTracking.shared_problem reads the model from its params: pass "
                                    f"params=lt.params(y_ref, d, with_model=True) (a SharedParams), got "
                                    f"{type(p).__name__}")
                data, held = p.data, p.model
            else:
                data, held = _tracking_params(p), model
            return fn(z, *rest, data, *_in_dtype((held, classes), z.dtype))

        return call

    return {"dynamics": reading(_dynamics), "stage_cost": reading(_stage_cost),
            "lower_bound": reading(_lower_bound), "constraint": reading(_constraint),
            "first_input_of": reading(_first_input)}


_SHARED = {}  # (controls, classes, norm, max_step) -> shared_problem's callables


def _shared_callables(classes: _Classes, controls, members, norm: str, max_step) -> dict:
    """``shared_problem``'s callables: one set per controls, classes (``members``), norm and max_step, so that
    trackers of equal shapes that differ in A, B, C, Q or lambda_u share its compiled searches."""
    key = (controls.shape, controls.tobytes(), members.shape, members.tobytes(), norm, max_step,
           classes.switch is None)
    if key not in _SHARED:
        _SHARED[key] = _callables(classes)
    return _SHARED[key]


def _tracking_params(p) -> TrackingParams:
    """``problem``'s params: a ``TrackingParams``, or a mapping of its fields (``python -m firhc_jax batch
    --params`` reads an ``.npz`` of ``lt.params(Y)._asdict()`` as one); else a ``TypeError``."""
    if isinstance(p, Mapping) and set(p) == set(TrackingParams._fields):
        p = TrackingParams(**p)
    if not isinstance(p, TrackingParams):
        hint = " (lt.shared_problem takes the params with the model)" if isinstance(p, SharedParams) else ""
        raise TypeError("LinearTracking.problem reads each decision's data from its params: pass "
                        f"params=lt.params(y_ref, d) (a TrackingParams){hint}, got {type(p).__name__}")
    return p


def _in_dtype(tree, dtype):
    """Every array of ``tree`` in ``dtype`` (NumPy constants become arrays of the trace)."""
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), tree)


def _node(z, classes: _Classes) -> Node:
    return Node.unpack(z, *classes.members.shape[-2:])


# The switching table's size beyond which the switchings are computed from the members instead (each node then
# computes R x C x R of them, m components each, which a table lookup saves: docs/dev/xla_notes.md; a 16 MiB
# constant is the most a compiled search should carry).
MAX_TABLE_BYTES = 1 << 24


def _classes_of(controls, members, norm: str, max_step) -> _Classes:
    """The ``_Classes`` of ``controls`` ``[M, m]`` grouped as ``members`` ``[C, R]`` (``input_classes``)."""
    filled = np.where(members >= 0, members, members[:, :1])  # padding repeats the first member
    U = controls.astype(float)[filled]  # [C, R, m]
    ok = members >= 0
    classes = _Classes(members=U, member_index=filled.astype(float), member_ok=ok.astype(float),
                       du_norm=np.linalg.norm(U - U[:, :1], axis=-1), l1=np.float64(norm == "abs"),
                       max_step=None if max_step is None else np.float64(max_step), switch=None)
    if 8 * members.size ** 2 > MAX_TABLE_BYTES:
        return classes
    unit, allowed = _switching(U[:, :, None, None, :], U[None, None, :, :, :], classes, xp=np)
    allowed &= ok[:, :, None, None] & ok[None, None, :, :]
    return classes._replace(switch=np.where(allowed, unit, -1.0))


def _switching(u_from, u_to, classes: _Classes, xp=jnp):
    """``(cost, allowed)`` of switching from ``u_from`` to ``u_to`` (``[..., m]``, broadcast against each other)
    per unit lambda_u: ||du||_1 or ||du||^2, and whether every component keeps within max_step. Summed one
    component at a time (XLA fuses that into one elementwise kernel; ``xp=np``: the same sums in NumPy, for the
    table)."""
    change = worst = 0
    for i in range(u_to.shape[-1]):
        step = xp.abs(u_to[..., i] - u_from[..., i])
        change = change + xp.where(classes.l1 > 0, step, step * step)
        worst = xp.maximum(worst, step)
    allowed = xp.ones_like(worst, bool) if classes.max_step is None else worst <= classes.max_step
    return change, allowed


def _steps(i, j, model: TrackingModel, classes: _Classes):
    """``[..., R, R]``: lambda_u times the switching from each member of classes ``i`` to each of classes ``j``
    (int arrays, broadcast against each other), +inf where it is not allowed."""
    if classes.switch is not None:
        unit = classes.switch[i, :, j, :]
        allowed = unit >= 0
    else:
        unit, allowed = _switching(classes.members[i][..., :, None, :], classes.members[j][..., None, :, :], classes)
        allowed &= (classes.member_ok[i][..., :, None] > 0) & (classes.member_ok[j][..., None, :] > 0)
    return jnp.where(allowed, model.lambda_u * unit, jnp.inf)


def _from_node(node: Node, model: TrackingModel, classes: _Classes):
    """``[C, R]`` the cheapest switching of the steps so far that ends on each member of each class after the
    node (+inf where none is allowed): from the root's ``u_prev``, or the min-plus step from the node's members."""
    unit, allowed = _switching(node.u_prev, classes.members, classes)
    from_root = jnp.where(allowed & (classes.member_ok > 0), model.lambda_u * unit, jnp.inf)
    C = classes.members.shape[0]
    via = jnp.where(node.o[None, :, None] >= 0,
                    node.o[None, :, None] + _steps(jnp.maximum(node.j, 0).astype(jnp.int32), jnp.arange(C), model,
                                                   classes), jnp.inf)  # [C, R (from), R (to)]
    return jnp.where(node.j < 0, from_root, jnp.min(via, axis=1))


def _squared_weight(lambda_u, norm, controls, max_step) -> float:
    """The weight of ||du||^2 in the cost-to-go W. For ``norm="abs"``: lambda_u / D, where D bounds every
    component's change between two controls (their range, capped by max_step): |du_i| <= D gives
    |du_i| >= du_i^2 / D, so the squared term is below the L1 term on every input sequence, and W, the
    continuous minimum of the squared problem, stays a lower bound (equal where every step is 0 or D: the
    inverters' unit steps under max_step = 1)."""
    if norm == "squared":
        return lambda_u
    D = float(np.max(np.ptp(controls, axis=0)))
    if max_step is not None:
        D = min(D, max_step)
    return lambda_u / D if D > 0 else lambda_u  # D = 0: no input ever changes, any weight is a bound


def _class(u, classes: _Classes):
    """``(class, found)``: the first class whose members include input ``u`` ``[m]``, and whether one does. (The
    searches give every child a constant input, so XLA computes this once per search, outside its loop.)"""
    hit = jnp.any(jnp.all(classes.members == u.astype(classes.members.dtype), axis=-1) & (classes.member_ok > 0),
                  axis=-1)
    C = hit.shape[0]
    return jnp.minimum(jnp.min(jnp.where(hit, jnp.arange(C), C)), C - 1), jnp.any(hit)


def _dynamics(z, u, k, data: TrackingParams, model: TrackingModel, classes: _Classes):
    node = _node(z, classes)
    n, m = node.x.shape[0], node.u_prev.shape[0]
    p = model.M.shape[1] - 2 * n - m
    j, found = _class(u, classes)  # an input of no class (not a control) has no child
    U, ok = classes.members[j], (classes.member_ok[j] > 0) & found  # [R, m], [R]
    xu = jnp.concatenate([node.x, U[0]])
    # The product as a sum of elementwise products: XLA:CPU runs a batch of these tiny matrix products as
    # library calls, one kernel each, which cost a node more than the arithmetic (docs/applications/inverter.md)
    out = jnp.sum(model.M[k] * xu, axis=1) + data.off[k]  # [x(k+1) (n), sqrt(Q) (y_ref[k] - C x(k+1)) (p), W's v]
    # W_{k+1}'s residual per member: member 0's plus how it moves with the member's input (a dot product here:
    # as elementwise products with a traced k, XLA gathered Tu[k] for every element, 1.5x the node's time)
    v = out[n + p:] + jnp.einsum("ri,ci->rc", U - U[0], model.Tu[k])  # [R, n + m]
    # W = ||v||^2 + s, rounded down by a bound on the rounding of v (its terms nearly cancel, and W must stay
    # admissible): ||v_true|| >= ||v|| - ||v - v_true||, with ||v - v_true|| <= gamma (||M_v|| ||[x; u]|| + ||off_v||
    # + ||Tu|| ||du||) + the rounding of off_v.
    off_v = data.off[k][n + p:]
    g = _gamma(z.dtype, n + 2 * m)
    err = g * (model.M_norm[k] * jnp.sqrt(xu @ xu) + jnp.sqrt(off_v @ off_v)
               + model.Tu_norm[k] * classes.du_norm[j]) + data.off_err[k]
    W = jnp.maximum(jnp.sqrt(jnp.sum(v * v, axis=1)) - err, 0) ** 2 * (1 - g) + data.s[k]
    # and by the factorisation's own error (``cost_to_go``): sqrt(W) is off by at most
    # err_s ||[x(k+1); u]|| + g_err
    x_next = out[:n]
    off_by = model.err_s[k] * jnp.sqrt(x_next @ x_next + jnp.sum(U * U, axis=1)) + data.g_err[k]
    W = jnp.maximum(jnp.sqrt(W) - off_by, 0) ** 2 * (1 - g)
    cost = jnp.where(ok, _from_node(node, model, classes)[j], jnp.inf)  # [R]: the node's part is once per node
    reached = jnp.isfinite(cost)
    switching = jnp.min(cost)  # +inf where no member is reached: the constraint discards that child
    o = jnp.where(reached, cost - switching, -1)
    # o + W: one more rounding of each sum, taken off the bound too
    bound = jnp.min(jnp.where(reached, (o + W) * (1 - g), jnp.inf))
    e = out[n:n + p]
    return Node(x_next, node.u_prev, j.astype(z.dtype), o, e @ e + switching, bound).pack()


def _stage_cost(z, u, k, data, model, classes):
    return _node(z, classes).stage


def _lower_bound(z, steps_left, data, model, classes):
    return _node(z, classes).W


def _constraint(z, u, k, data, model, classes):
    """Some member of the class can follow the node's (max_step). Decided on the switching costs alone, so a
    NaN state or reference reaches the searches' own check of non-finite nodes (``nan_encountered``)."""
    return jnp.any(_node(z, classes).o >= 0)


def _members(z0, sequence, model: TrackingModel, classes: _Classes):
    """``[N]`` the member (0 .. R-1) of each class of ``sequence`` on the cheapest switching path from the
    root ``z0``: the min-plus recursion of ``_dynamics`` forward, then its argmins backward."""
    j = jnp.maximum(sequence, 0)
    first = _from_node(_node(z0, classes), model, classes)[j[0]]  # [R]

    def forward(o_from, step):
        S = o_from[:, None] + _steps(step[0], step[1], model, classes)  # [R (from), R (to)]
        return jnp.min(S, axis=0), jnp.argmin(S, axis=0)

    last, came_from = jax.lax.scan(forward, first, jnp.stack([j[:-1], j[1:]], axis=1))  # came_from [N - 1, R]

    def backward(e, came):
        return came[e], e

    start, picked = jax.lax.scan(backward, jnp.argmin(last).astype(came_from.dtype), came_from, reverse=True)
    return jnp.concatenate([start[None], picked])


@jax.jit
def _sequence(z0, sequence, model: TrackingModel, classes: _Classes):
    picked = _members(z0, sequence, model, classes)
    index = classes.member_index[jnp.maximum(sequence, 0), picked].astype(jnp.int32)
    return jnp.where(sequence >= 0, index, -1)


def _first_input(z0, sequence, data, model: TrackingModel, classes: _Classes):
    """``first_input_of``: the first member on the cheapest switching path of the class ``sequence`` from
    ``z0``.

    This runs in every decision, so without a loop: the switching costs between the members of consecutive
    classes are R x R matrices, all read at once, and their min-plus product (associative) is reduced
    pairwise, log2(N) vectorised levels (a scan costs several microseconds a step on XLA:CPU, and an
    unrolled recursion made the work pool's compile time grow steeply with N: 340 s at N = 10)."""
    j = jnp.maximum(sequence, 0)
    first = _from_node(_node(z0, classes), model, classes)[j[0]]  # [R] the root to each first member
    chain = _steps(j[:-1], j[1:], model, classes)  # [N-1, R (from), R (to)]
    while chain.shape[0] > 1:  # min-plus products of neighbours; an odd one out waits a level
        pairs = chain.shape[0] // 2 * 2
        product = jnp.min(chain[:pairs:2, :, :, None] + chain[1:pairs:2, None, :, :], axis=2)
        chain = jnp.concatenate([product, chain[pairs:]])
    rest = jnp.min(chain[0], axis=1) if chain.shape[0] else jnp.zeros(first.shape, z0.dtype)
    return classes.members[j[0]][jnp.argmin(first + rest)]


_OBSERVERS = {}


def _observer(R: int):
    """``observe`` for trackers whose classes have R members: one function per R, so that controllers of
    equal shapes share their compiled loop."""
    if R not in _OBSERVERS:
        def observe(x, u_prev, p=None):
            """The search state, the root ``Node`` packed ``[n + m + R + 3]``: plant state ``x`` ``[n]`` after
            the input applied last ``u_prev`` ``[m]`` (no class, switching costs [0, -1, ...], stage cost and
            bound 0). The signature of ``fj.FIRHC``'s ``observe`` (``p`` unused)."""
            x = jnp.asarray(x)
            u_prev = jnp.asarray(u_prev, x.dtype)
            zero = jnp.zeros((), x.dtype)
            o = jnp.full((R,), -1, x.dtype).at[0].set(0)
            return Node(x, u_prev, -jnp.ones((), x.dtype), o, zero, zero).pack()

        _OBSERVERS[R] = observe
    return _OBSERVERS[R]


@jax.jit
def _params(maps: _DataMaps, y_ref, d) -> TrackingParams:
    dtype = y_ref.dtype
    lead = y_ref.shape[:-2]
    data = jnp.concatenate([y_ref.reshape(lead + (-1,)), d.reshape(lead + (-1,))], axis=-1)  # [..., N(p + n)]
    gamma = _gamma(dtype, data.shape[-1])

    def apply(M):  # M data and a bound on its rounding error
        return (jnp.einsum("kid,...d->...ki", M, data),
                gamma * jnp.einsum("kid,...d->...ki", jnp.abs(M), jnp.abs(data)))

    off, off_err = apply(maps.M_data)
    e, e_err = apply(maps.Ms)
    n_w = off.shape[-1] - d.shape[-1] - y_ref.shape[-1]  # n + m rows of W's residual, the last of off
    data_norm = jnp.sqrt(jnp.sum(data * data, axis=-1))
    return TrackingParams(off=off, off_err=jnp.sqrt(jnp.sum(off_err[..., -n_w:] ** 2, axis=-1)),
                          s=_norm2_below(e, e_err), g_err=maps.err_d * (data_norm * (1 + gamma))[..., None],
                          y_ref=y_ref, d=d)


def _gamma(dtype, terms: int):
    """Relative rounding bound of a dot product of ``terms`` terms (with margin)."""
    return jnp.finfo(dtype).eps * (terms + 2)


def _norm2_below(v, err):
    """A lower bound of ||v_true||^2 over the last axis, given |v - v_true| <= err
    elementwise: W must never exceed the true cost-to-go (T s and w nearly
    cancel, so their rounding matters in float32)."""
    sq = jnp.sum(jnp.maximum(jnp.abs(v) - err, 0) ** 2, axis=-1)
    return sq * (1 - _gamma(v.dtype, v.shape[-1]))


def _vector(name, a, shape, dtype):
    if not is_tracer(a):
        a = numeric(name, a, f"array {list(shape)}")
        finite(name, a)
    if tuple(a.shape) != shape:
        raise ValueError(f"{name} must have shape {list(shape)}, got {tuple(a.shape)}")
    return a.astype(dtype) if is_tracer(a) else np.asarray(a, dtype)  # a jitted call takes NumPy as it is
