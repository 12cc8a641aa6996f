"""``Problem(lower_bound="auto")``: an admissible bound derived from the model by interval reachability.

From a state ``x`` with ``s`` steps left, ``AutoBound`` encloses by interval arithmetic on the callables'
jaxprs (``firhc_jax._src.jaxpr.intervals``) what any completion can reach. Step ``j`` starts from a box
(at first the point ``x``) and evaluates, for every input of the control set, the box of next states, the
lower end of the stage cost and whether the constraint can hold somewhere in the box. The inputs whose
constraint cannot hold drop out; the next step's box is the hull of the others' boxes, and step ``j``
costs at least the least of their stage-cost lower ends (clipped at 0, which stage costs never go below).
The bound sums these per-step minima over the ``s`` steps and adds the lower end of ``terminal_cost`` over
the last box. It is ``+inf`` where at some step no input's constraint can hold on the box, or where the
terminal set cannot meet the last box: then no completion is feasible. Each box holds every state some
feasible completion reaches, so the bound never exceeds the cost of one (admissible); states that violate
earlier constraints stay in the boxes, which only loosens it.

The result is lowered by ``4 (N + 2)`` ulps of the cost's dtype relative, so that the search's own sums
of the same costs, rounded in another order, never fall below it. Boxes that grow without limit give
infinite ends: their costs' lower ends become 0 (or ``-inf``, clipped to 0), never a wrong value. Without
``step_index``, a box that no longer changes from one step to the next is a fixed point: the remaining
steps each cost the same, and the loop stops there.

The bound is a plain callable ``bound(x, steps_left[, p])`` (the ``Problem.lower_bound`` contract): the
callables are traced to jaxprs for the shapes and dtypes it is called with, and the enclosure is ``jnp``
code, compiled into the search like a hand-written bound.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..jaxpr.interpret import Unsupported
from ..jaxpr.intervals import Interval, enclose

# The callables a bound reads, in the order their failures are reported.
MODEL_FIELDS = ("dynamics", "stage_cost", "constraint", "terminal", "terminal_cost")


class AutoBound:
    """The bound of ``lower_bound="auto"`` (module docstring) for one problem's callables and control set.

    Two ``AutoBound`` objects of the same callables, horizon, flags and control values are equal (and hash
    alike), so two problems built alike share one compiled search."""

    def __init__(self, *, dynamics, stage_cost, constraint, terminal, terminal_cost, horizon: int,
                 step_index: bool, previous_state: bool, controls: np.ndarray, controls_key):
        self.dynamics, self.stage_cost, self.constraint = dynamics, stage_cost, constraint
        self.terminal, self.terminal_cost = terminal, terminal_cost
        self.horizon, self.step_index, self.previous_state = horizon, step_index, previous_state
        self.controls = controls
        self._key = (dynamics, stage_cost, constraint, terminal, terminal_cost, horizon, step_index,
                     previous_state, controls_key)

    def __eq__(self, other):
        return isinstance(other, AutoBound) and self._key == other._key

    def __hash__(self):
        return hash(("AutoBound",) + self._key)

    def __repr__(self):
        return f"AutoBound(horizon={self.horizon}, controls={self.controls.shape[0]})"

    # -- the callables as jaxprs of (x_before, x, u, k, p) leaves --------------------------------------------
    def _call(self, name, x_before, x, u, k, p):
        fn = getattr(self, name)
        extra = (k,) if self.step_index else ()
        with_p = () if p is None else (p,)
        if name == "dynamics":
            return fn(x_before, u, *extra, *with_p)
        if name in ("stage_cost", "constraint"):
            before = (x_before,) if self.previous_state else ()
            return fn(*before, x, u, *extra, *with_p)
        return fn(x, *with_p)  # terminal, terminal_cost

    def _jaxpr(self, name, x, p):
        spec = jax.ShapeDtypeStruct(np.shape(x), jnp.result_type(x))
        u = jax.ShapeDtypeStruct(self.controls.shape[1:], self.controls.dtype)
        k = jax.ShapeDtypeStruct((), jnp.int32)
        p_spec = jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(np.shape(a), jnp.result_type(a)), p)
        return jax.make_jaxpr(lambda *a: self._call(name, *a))(spec, spec, u, k, p_spec)

    def _enclose(self, name, closed, before: Interval, box: Interval, u, k, p_leaves) -> Interval:
        try:
            return enclose(closed, [before, box, Interval(u), Interval(k), *map(Interval, p_leaves)])[0]
        except Unsupported as e:
            raise NotImplementedError(
                f'lower_bound="auto" cannot enclose {name}: its {e}; the interval arithmetic of the automatic '
                "bound has no rule for it. Write a lower_bound by hand, or pass lower_bound=None") from None

    # -- the bound ------------------------------------------------------------------------------------------
    def __call__(self, x, steps_left, *p):
        params = p[0] if p else None
        x = jnp.asarray(x)
        p_leaves = [jnp.asarray(a) for a in jax.tree_util.tree_leaves(params)]
        programs = {name: self._jaxpr(name, x, params) for name in MODEL_FIELDS if getattr(self, name) is not None}
        cost_dtype = programs["stage_cost"].out_avals[0].dtype
        controls = jnp.asarray(self.controls)
        N = self.horizon
        steps = jnp.clip(jnp.asarray(steps_left, jnp.int32), 0, N)
        inf = jnp.asarray(jnp.inf, cost_dtype)

        def child(lo, hi, u, k, first):
            box = Interval(x) if first else Interval(lo, hi)
            nxt = self._enclose("dynamics", programs["dynamics"], box, box, u, k, p_leaves)
            nxt_lo = jnp.broadcast_to(jnp.asarray(nxt.lo, x.dtype), x.shape)
            nxt_hi = jnp.broadcast_to(jnp.asarray(nxt.hi, x.dtype), x.shape)
            cost = self._enclose("stage_cost", programs["stage_cost"], box, nxt, u, k, p_leaves).lo
            cost = jnp.maximum(jnp.where(jnp.isnan(cost), 0, cost), 0).astype(cost_dtype)
            may = jnp.ones((), bool)
            if "constraint" in programs:
                may = self._enclose("constraint", programs["constraint"], box, nxt, u, k, p_leaves).hi
            return nxt_lo, nxt_hi, cost, jnp.asarray(may, bool)

        def step(lo, hi, j, first):
            k = N - steps + j
            nlo, nhi, cost, may = jax.vmap(lambda u: child(lo, hi, u, k, first))(controls)
            any_may = jnp.any(may)
            new_lo = jnp.min(jnp.where(may[:, None], nlo, jnp.inf), axis=0).astype(x.dtype)
            new_hi = jnp.max(jnp.where(may[:, None], nhi, -jnp.inf), axis=0).astype(x.dtype)
            least = jnp.min(jnp.where(may, cost, inf))
            return new_lo, new_hi, jnp.where(any_may, least, 0).astype(cost_dtype), any_may

        # The first step starts from the point x (evaluated once per input, as exactly as the model).
        lo, hi, first_cost, first_ok = step(x, x, 0, True)
        start = (jnp.ones((), jnp.int32), lo, hi, first_cost, first_ok, first_cost, jnp.zeros((), bool))

        def more(c):
            j, _, _, _, ok, _, fixed = c
            return (j < steps) & ok & ~fixed

        def body(c):
            j, lo, hi, total, ok, _, _ = c
            nlo, nhi, cost, may = step(lo, hi, j, False)
            fixed = jnp.zeros((), bool)
            if not self.step_index:
                fixed = jnp.all(nlo == lo) & jnp.all(nhi == hi)
            return j + 1, nlo, nhi, total + cost, ok & may, cost, fixed

        j, lo, hi, total, ok, last, fixed = jax.lax.while_loop(more, body, start)
        total = total + jnp.where(fixed, (steps - j).astype(cost_dtype) * last, 0)
        final = Interval(lo, hi)
        k_end = jnp.asarray(N, jnp.int32)
        any_u = controls[0]  # terminal and terminal_cost take no input: a placeholder for the jaxpr's argument
        if "terminal" in programs:
            ok = ok & jnp.asarray(self._enclose("terminal", programs["terminal"], final, final, any_u, k_end,
                                                p_leaves).hi, bool)
        if "terminal_cost" in programs:
            g = self._enclose("terminal_cost", programs["terminal_cost"], final, final, any_u, k_end, p_leaves).lo
            total = total + jnp.maximum(jnp.where(jnp.isnan(g), 0, g), 0).astype(cost_dtype)
        eps = float(jnp.finfo(cost_dtype).eps)
        total = jnp.nextafter(total * (1 - 4 * (N + 2) * eps), jnp.zeros((), cost_dtype))
        return jnp.where(steps == 0, jnp.zeros((), cost_dtype), jnp.where(ok, total, inf))
