"""Interval arithmetic on a jaxpr: sound enclosures of a callable's outputs over boxes of its inputs.

``IntervalDomain`` is a ``Domain`` of ``interpret``: every value is an ``Interval`` of two arrays, ``lo`` and
``hi``, of the value's shape and dtype, computed with ``jnp`` operations, so that an enclosure is traced
into a compiled program like any other code (the searches evaluate it on traced states). Booleans are
intervals of the order False < True: ``lo`` True means surely True, ``hi`` False surely False.

What an enclosure contains. For each value the callable computes in floating point (any rounding of the
same operations, a fused multiply-add or a reduction summed in another order included), and for its exact
real value, ``lo <= value <= hi``:

* add, sub, mul, div, sqrt and the conversions are rounded outward by one ulp, which also covers the other
  rounding of the concrete evaluation (a value in ``[lo, hi]`` rounds into ``[lo - ulp, hi + ulp]``);
* sums (``reduce_sum``, ``dot_general``, ``cumsum``) widen by ``2 (n + 2) eps`` times the sum of magnitudes,
  the error bound of any summation order of n terms;
* the transcendental functions (exp, log, tanh, sin, ...) widen by ``TRANSCENDENTAL_ULPS`` ulps relative
  plus as many of 1 for log and the trigonometric ones: XLA's approximations are a few ulps off;
* a value that may be NaN (``sqrt`` or ``log`` of a possibly negative argument, a division by an interval
  holding 0, ``inf - inf``) is ``[-inf, +inf]``: every comparison on it is then both possibly True and
  possibly False, which covers the concrete NaN's answers, and the primitives that would narrow that
  interval although NaN passes through them (abs, mul, max, tanh, reductions, ...) give ``[-inf, +inf]``
  again.

Integer arithmetic is exact and assumed not to overflow. A primitive without a rule raises ``Unsupported``,
naming it; so does a ``while`` loop (its trip count may depend on the values), while ``scan`` (a fixed
number of iterations) and ``cond`` (the hull of every branch the index can take) are evaluated.
"""
from __future__ import annotations

from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .interpret import Unsupported, interpret

TRANSCENDENTAL_ULPS = 32


class Interval:
    """``[lo, hi]`` elementwise; a point (an exact value, e.g. a parameter) has ``lo is hi``."""

    __slots__ = ("lo", "hi")

    def __init__(self, lo, hi=None):
        self.lo = lo
        self.hi = lo if hi is None else hi

    @property
    def point(self) -> bool:
        return self.lo is self.hi

    def __repr__(self):
        return f"Interval({self.lo!r}, {self.hi!r})"


def _is_float(a) -> bool:
    return jnp.issubdtype(jnp.result_type(a), jnp.inexact)


def _is_bool(a) -> bool:
    return jnp.result_type(a) == jnp.bool_


def _eps(a):
    return float(jnp.finfo(jnp.result_type(a)).eps)


def _outward(lo, hi, relative=0.0, absolute=0.0) -> Interval:
    """``[lo, hi]`` widened: NaN ends become infinite, then ``relative`` times the magnitude plus ``absolute``,
    then one ulp (floating values only)."""
    if not _is_float(lo):
        return Interval(lo, hi)
    lo = jnp.where(jnp.isnan(lo), -jnp.inf, lo)
    hi = jnp.where(jnp.isnan(hi), jnp.inf, hi)
    if not (isinstance(relative, float) and isinstance(absolute, float) and relative == absolute == 0.0):
        lo = lo - (relative * jnp.abs(lo) + absolute).astype(lo.dtype)
        hi = hi + (relative * jnp.abs(hi) + absolute).astype(hi.dtype)
    return Interval(jnp.nextafter(lo, jnp.asarray(-jnp.inf, lo.dtype)),
                    jnp.nextafter(hi, jnp.asarray(jnp.inf, hi.dtype)))


def _everything(aval) -> Interval:
    """The interval of every value of ``aval``'s shape and dtype."""
    dtype = aval.dtype
    if dtype == jnp.bool_:
        low, high = False, True
    elif jnp.issubdtype(dtype, jnp.inexact):
        low, high = -np.inf, np.inf
    else:
        info = jnp.iinfo(dtype)
        low, high = info.min, info.max
    return Interval(jnp.full(aval.shape, low, dtype), jnp.full(aval.shape, high, dtype))


def _top(dtype):
    if dtype == jnp.bool_:
        return True
    return np.inf if jnp.issubdtype(dtype, jnp.inexact) else jnp.iinfo(dtype).max


def _bottom(dtype):
    if dtype == jnp.bool_:
        return False
    return -np.inf if jnp.issubdtype(dtype, jnp.inexact) else jnp.iinfo(dtype).min


def _times(a, b):
    """``a * b`` with ``0 * inf = 0``: an infinite end stands for a large finite value."""
    if not _is_float(a) and not _is_float(b):
        return a * b
    return jnp.where((a == 0) | (b == 0), jnp.zeros((), jnp.result_type(a, b)), a * b)


def _hull(*values):
    lo = values[0]
    hi = values[0]
    for v in values[1:]:
        lo, hi = jnp.minimum(lo, v), jnp.maximum(hi, v)
    return lo, hi


def _magnitude(v: Interval):
    return jnp.maximum(jnp.abs(v.lo), jnp.abs(v.hi))


# ---------------------------------------------------------------- rules
# Each rule takes (eqn, *intervals) and returns one Interval or a list of them (multiple results).

def _structural(eqn, *vals):
    """Shape and selection primitives: applied to the lower and the upper ends apart (monotone, exact)."""
    lo = eqn.primitive.bind(*(v.lo for v in vals), **eqn.params)
    if all(v.point for v in vals):
        return _wrap(eqn, lo, lo)
    hi = eqn.primitive.bind(*(v.hi for v in vals), **eqn.params)
    return _wrap(eqn, lo, hi)


def _wrap(eqn, lo, hi):
    if eqn.primitive.multiple_results:
        return [Interval(a, b) for a, b in zip(lo, hi, strict=True)]
    return Interval(lo, hi)


def _add(eqn, a, b):
    if a.point and b.point:
        v = a.lo + b.lo
        return _outward(v, v)
    return _outward(a.lo + b.lo, a.hi + b.hi)


def _sub(eqn, a, b):
    if a.point and b.point:
        v = a.lo - b.lo
        return _outward(v, v)
    return _outward(a.lo - b.hi, a.hi - b.lo)


def _mul(eqn, a, b):
    if a.point and b.point:
        v = a.lo * b.lo
        return _outward(v, v)
    return _outward(*_hull(_times(a.lo, b.lo), _times(a.lo, b.hi), _times(a.hi, b.lo), _times(a.hi, b.hi)))


def _div(eqn, a, b):
    if not _is_float(a.lo):  # integer division truncates, a monotone function of the real quotient
        if not (a.point and b.point):
            raise Unsupported("div", "integer division of ranges")
        return Interval(lax.div(a.lo, b.lo))
    lo, hi = _hull(a.lo / b.lo, a.lo / b.hi, a.hi / b.lo, a.hi / b.hi)
    holds_zero = (b.lo <= 0) & (b.hi >= 0)
    return _outward(jnp.where(holds_zero, -jnp.inf, lo), jnp.where(holds_zero, jnp.inf, hi))


def _neg(eqn, a):
    return Interval(-a.hi, -a.lo) if not a.point else Interval(-a.lo)


def _abs(eqn, a):
    if a.point:
        return Interval(jnp.abs(a.lo))
    lo = jnp.where(a.lo >= 0, a.lo, jnp.where(a.hi <= 0, -a.hi, jnp.zeros_like(a.lo)))
    return Interval(lo, jnp.maximum(jnp.abs(a.lo), jnp.abs(a.hi)))


def _integer_pow(eqn, a, y=None):
    y = eqn.params["y"] if y is None else y
    if a.point:
        v = lax.integer_pow(a.lo, y)
        return _outward(v, v, relative=(abs(y) + 1) * _eps(v)) if _is_float(v) else Interval(v)
    if y % 2 == 0:
        base = _abs(eqn, a)
        lo, hi = lax.integer_pow(base.lo, y), lax.integer_pow(base.hi, y)
        if y < 0:  # decreasing in |a|; 1 / 0 is inf, which is right for an interval holding 0
            lo, hi = hi, lo
    else:
        lo, hi = lax.integer_pow(a.lo, y), lax.integer_pow(a.hi, y)
        if y < 0:  # decreasing on each side of 0, unbounded across it
            holds_zero = (a.lo <= 0) & (a.hi >= 0)
            lo, hi = jnp.where(holds_zero, -jnp.inf, hi), jnp.where(holds_zero, jnp.inf, lo)
    if _is_float(lo):
        return _outward(lo, hi, relative=(abs(y) + 1) * _eps(lo))
    return Interval(lo, hi)


def _square(eqn, a):
    return _integer_pow(eqn, a, 2)


def _monotone(fn, low_domain=None, low_inclusive=True, range_=(None, None), ulps=TRANSCENDENTAL_ULPS,
              absolute=False, decreasing=False):
    """A rule for a monotone function of one argument: ``fn`` at both ends, widened by ``ulps`` ulps relative
    (plus as many of 1 with ``absolute``), clipped to its ``range_``; an argument that may lie below
    ``low_domain`` (where the function is NaN) gives everything."""
    def rule(eqn, a):
        lo, hi = fn(a.lo), fn(a.hi) if not a.point else None
        hi = lo if hi is None else hi
        if decreasing:
            lo, hi = hi, lo
        eps = _eps(lo)
        out = _outward(lo, hi, relative=ulps * eps, absolute=ulps * eps if absolute else 0.0)
        lo, hi = out.lo, out.hi
        if range_[0] is not None:
            lo = jnp.maximum(lo, jnp.asarray(range_[0], lo.dtype))
        if range_[1] is not None:
            hi = jnp.minimum(hi, jnp.asarray(range_[1], hi.dtype))
        if low_domain is not None:
            outside = (a.lo < low_domain) if low_inclusive else (a.lo <= low_domain)
            lo, hi = jnp.where(outside, -jnp.inf, lo), jnp.where(outside, jnp.inf, hi)
        return Interval(lo, hi)
    return rule


def _exact_monotone(eqn, a):
    """Monotone non-decreasing and computed alike in the search (floor, ceil, round, sign, reduce_precision):
    the concrete value of an argument in ``[lo, hi]`` lies between the values at the ends."""
    return _structural(eqn, a)


def _trig(shift):
    """``cos(a + shift)`` (sin: shift = -pi/2): the ends, and -1 or +1 where the interval holds a minimum
    (``pi (2j + 1) - shift``) or a maximum (``2 pi j - shift``); intervals wider than 2 pi are [-1, 1]."""
    fn = jnp.cos if shift == 0.0 else jnp.sin

    def holds(a, at):  # some at + 2 pi j in [lo, hi], counted generously so that rounding never misses one
        two_pi = 2 * np.pi
        j = jnp.ceil((a.lo - at) / two_pi - 1e-6)
        return at + two_pi * j <= a.hi + 1e-6 * (1 + jnp.abs(a.hi))

    def rule(eqn, a):
        lo, hi = _hull(fn(a.lo), fn(a.hi))
        if not a.point:
            wide = (a.hi - a.lo >= 2 * np.pi) | ~jnp.isfinite(a.lo) | ~jnp.isfinite(a.hi)
            lo = jnp.where(wide | holds(a, np.pi - shift), -1, lo)
            hi = jnp.where(wide | holds(a, -shift), 1, hi)
        eps = _eps(lo)
        out = _outward(lo, hi, absolute=TRANSCENDENTAL_ULPS * eps * (1 + jnp.maximum(jnp.abs(a.lo), jnp.abs(a.hi))))
        return Interval(jnp.maximum(out.lo, -1), jnp.minimum(out.hi, 1))
    return rule


def _pow(eqn, a, b):
    """``a ** b`` for ``a > 0``: ``exp(b log a)`` is extreme at a corner of the box; otherwise everything."""
    corners = [lax.pow(x, y) for x in (a.lo, a.hi) for y in (b.lo, b.hi)]
    out = _outward(*_hull(*corners), relative=TRANSCENDENTAL_ULPS * _eps(corners[0]))
    positive = a.lo > 0
    return Interval(jnp.where(positive, jnp.maximum(out.lo, 0), -jnp.inf), jnp.where(positive, out.hi, jnp.inf))


def _compare(op):
    def rule(eqn, a, b):
        if a.point and b.point:
            return Interval(op(a.lo, b.lo))
        if op is jnp.less:
            return Interval(a.hi < b.lo, a.lo < b.hi)
        if op is jnp.less_equal:
            return Interval(a.hi <= b.lo, a.lo <= b.hi)
        if op is jnp.greater:
            return Interval(b.hi < a.lo, b.lo < a.hi)
        if op is jnp.greater_equal:
            return Interval(b.hi <= a.lo, b.lo <= a.hi)
        may_equal = (a.lo <= b.hi) & (b.lo <= a.hi)
        surely_equal = (a.lo == a.hi) & (b.lo == b.hi) & (a.lo == b.lo)
        if op is jnp.equal:
            return Interval(surely_equal, may_equal)
        return Interval(~may_equal, ~surely_equal)
    return rule


def _logical(op):
    """and / or on booleans (monotone); on integers, bitwise, only for exact values."""
    def rule(eqn, a, b):
        if a.point and b.point:
            return Interval(op(a.lo, b.lo))
        if not _is_bool(a.lo):
            return _everything(eqn.outvars[0].aval)
        return Interval(op(a.lo, b.lo), op(a.hi, b.hi))
    return rule


def _not(eqn, a):
    if a.point:
        return Interval(~a.lo)
    return Interval(~a.hi, ~a.lo)  # booleans, and ~x = -x - 1 on integers: decreasing


def _xor(eqn, a, b):
    if a.point and b.point:
        return Interval(a.lo ^ b.lo)
    if not _is_bool(a.lo):
        return _everything(eqn.outvars[0].aval)
    surely = (a.lo & ~b.hi) | (~a.hi & b.lo)
    maybe = (a.hi & ~b.lo) | (~a.lo & b.hi)
    return Interval(surely, maybe)


def _select_n(eqn, which, *cases):
    if which.point:
        return _structural_select(which.lo, cases)
    dtype = jnp.result_type(cases[0].lo)
    if _is_bool(which.lo):
        possible = [~which.lo, which.hi]
    else:
        possible = [(which.lo <= i) & (i <= which.hi) for i in range(len(cases))]
    lo = hi = None
    for may, case in zip(possible, cases, strict=True):
        c_lo = jnp.where(may, case.lo, _top(dtype))
        c_hi = jnp.where(may, case.hi, _bottom(dtype))
        lo = c_lo if lo is None else jnp.minimum(lo, c_lo)
        hi = c_hi if hi is None else jnp.maximum(hi, c_hi)
    return Interval(lo, hi)


def _structural_select(which, cases):
    lo = lax.select_n(which, *(c.lo for c in cases))
    if all(c.point for c in cases):
        return Interval(lo)
    return Interval(lo, lax.select_n(which, *(c.hi for c in cases)))


def _convert(eqn, a):
    new = eqn.params["new_dtype"]
    old = jnp.result_type(a.lo)
    if new == jnp.bool_ and old != jnp.bool_:  # x != 0
        if a.point:
            return Interval(a.lo != 0)
        return Interval((a.lo > 0) | (a.hi < 0), ~((a.lo == 0) & (a.hi == 0)))
    out = _structural(eqn, a)
    if jnp.issubdtype(new, jnp.inexact) and not (old == jnp.bool_ or jnp.finfo(new).bits >= _bits(old)):
        return _outward(out.lo, out.hi)  # a narrowing float or a wide integer rounds
    return out


def _bits(dtype) -> int:
    return jnp.finfo(dtype).bits if jnp.issubdtype(dtype, jnp.inexact) else 2 * jnp.iinfo(dtype).bits


def _summed(lo, hi, magnitude, n: int) -> Interval:
    """Sums of ``n`` terms each: widened by the error bound of any summation order."""
    if not _is_float(lo):
        return Interval(lo, hi)
    slack = (2 * (n + 2) * _eps(lo)) * magnitude
    return _outward(lo - slack, hi + slack)


def _sum_of(eqn, a, n: int):
    """A sum of ``n`` terms (a reduction or a cumulative sum) over the ends, widened by its rounding."""
    lo = eqn.primitive.bind(a.lo, **eqn.params)
    hi = lo if a.point else eqn.primitive.bind(a.hi, **eqn.params)
    if not _is_float(lo):
        return Interval(lo, hi)
    return _summed(lo, hi, eqn.primitive.bind(_magnitude(a), **eqn.params), n)


def _reduce_sum(eqn, a):
    axes = eqn.params["axes"]
    return _sum_of(eqn, a, int(np.prod([np.shape(a.lo)[i] for i in axes])) if axes else 1)


def _cumsum(eqn, a):
    return _sum_of(eqn, a, np.shape(a.lo)[eqn.params["axis"]])


def _arg_reduce(eqn, a):
    if a.point:
        return Interval(eqn.primitive.bind(a.lo, **eqn.params))
    aval = eqn.outvars[0].aval
    size = np.shape(a.lo)[eqn.params["axes"][0]]
    return Interval(jnp.zeros(aval.shape, aval.dtype), jnp.full(aval.shape, size - 1, aval.dtype))


def _dot_general(eqn, a, b):
    """Midpoint and radius: ``[ma mb - r, ma mb + r]``, ``r = |ma| rb + ra |mb| + ra rb``, widened by the
    error bound of the sums."""
    def dot(x, y):
        return eqn.primitive.bind(x, y, **eqn.params)

    if not _is_float(a.lo) or not _is_float(b.lo):
        if a.point and b.point:
            return Interval(dot(a.lo, b.lo))
        raise Unsupported("dot_general", "integer operands that are ranges")
    (contract_a, _), _ = eqn.params["dimension_numbers"]
    n = int(np.prod([np.shape(a.lo)[i] for i in contract_a])) if contract_a else 1

    def mid_rad(v):
        if v.point:
            return v.lo, None
        mid = (v.lo + v.hi) / 2
        rad = jnp.maximum(v.hi - mid, mid - v.lo)
        return mid, jnp.nextafter(rad, jnp.asarray(jnp.inf, rad.dtype))

    ma, ra = mid_rad(a)
    mb, rb = mid_rad(b)
    center = dot(ma, mb)
    scale = dot(jnp.abs(ma), jnp.abs(mb))
    radius = jnp.zeros_like(center)
    if rb is not None:
        radius = radius + dot(jnp.abs(ma), rb)
    if ra is not None:
        radius = radius + dot(ra, jnp.abs(mb))
        if rb is not None:
            radius = radius + dot(ra, rb)
    slack = (2 * (n + 2) * _eps(center)) * (scale + radius) + radius * (4 * _eps(center))
    return _outward(center - radius - slack, center + radius + slack)


def _clamp(eqn, low, x, high):
    return _structural(eqn, low, x, high)


def _sort(eqn, *vals):
    if all(v.point for v in vals):
        return _structural(eqn, *vals)
    if len(vals) != 1:
        raise Unsupported("sort", "sorting several operands together (argsort) over ranges")
    return _structural(eqn, *vals)  # each order statistic is monotone in every element


_INDEX_OPERANDS = {"dynamic_slice": slice(1, None), "dynamic_update_slice": slice(2, None), "gather": slice(1, 2),
                   "scatter": slice(1, 2), "scatter-add": slice(1, 2), "scatter-min": slice(1, 2),
                   "scatter-max": slice(1, 2)}


def _indexed(eqn, *vals):
    """Reads and writes at computed positions. With exact positions, applied to both ends (monotone in the
    data; scatter-add rounds outward). A read at positions that are ranges is the hull of the whole operand
    (everything where out-of-range reads fill); a write there is refused."""
    name = eqn.primitive.name
    if all(v.point for v in vals[_INDEX_OPERANDS[name]]):
        out = _structural(eqn, *vals)
        return _outward(out.lo, out.hi) if name == "scatter-add" and not out.point else out
    if name not in ("gather", "dynamic_slice"):
        raise Unsupported(name, "a write at positions that are ranges")
    aval = eqn.outvars[0].aval
    if "FILL" in str(eqn.params.get("mode", "")):
        return _everything(aval)
    data = vals[0]
    return Interval(jnp.full(aval.shape, jnp.min(data.lo), aval.dtype),
                    jnp.full(aval.shape, jnp.max(data.hi), aval.dtype))


def _is_finite(eqn, a):
    if a.point:
        return Interval(jnp.isfinite(a.lo))
    finite = jnp.isfinite(a.lo) & jnp.isfinite(a.hi)
    return Interval(finite, (a.lo < jnp.inf) & (a.hi > -jnp.inf))


def _rem(eqn, a, b):
    """fmod: the sign of ``a``, smaller in magnitude than ``b`` and than ``a``."""
    if a.point and b.point:
        v = lax.rem(a.lo, b.lo)
        return _outward(v, v) if _is_float(v) else Interval(v)
    size = _magnitude(b)
    zero = jnp.zeros_like(a.lo)
    lo = jnp.where(a.lo >= 0, zero, jnp.maximum(a.lo, -size))
    hi = jnp.where(a.hi <= 0, zero, jnp.minimum(a.hi, size))
    return Interval(lo, hi)


def _atan2(eqn, a, b):
    if a.point and b.point:
        v = lax.atan2(a.lo, b.lo)
        return _outward(v, v, relative=TRANSCENDENTAL_ULPS * _eps(v))
    pi = jnp.asarray(np.pi, jnp.result_type(a.lo))
    return _outward(jnp.full(np.shape(a.lo), -pi), jnp.full(np.shape(a.lo), pi))


def _cosh(eqn, a):
    base = _abs(eqn, a)
    return _monotone(jnp.cosh, range_=(1, None))(eqn, base)


def _cond(domain):
    def rule(eqn, which, *operands):
        branches = eqn.params["branches"]
        outs = [interpret(branch, operands, domain) for branch in branches]
        return [_select_n(eqn, which, *(o[i] for o in outs)) for i in range(len(outs[0]))]
    return rule


def _scan(domain):
    def rule(eqn, *vals):
        p = eqn.params
        body, consts_n, carry_n = p["jaxpr"], p["num_consts"], p["num_carry"]
        consts, carry, xs = vals[:consts_n], vals[consts_n:consts_n + carry_n], vals[consts_n + carry_n:]
        out_avals = [v.aval for v in body.jaxpr.outvars]

        def as_arrays(v, aval):
            return (jnp.broadcast_to(jnp.asarray(v.lo, aval.dtype), aval.shape),
                    jnp.broadcast_to(jnp.asarray(v.hi, aval.dtype), aval.shape))

        def step(c, x):
            outs = interpret(body, list(consts) + [Interval(*e) for e in c] + [Interval(*e) for e in x], domain)
            return ([as_arrays(o, a) for o, a in zip(outs[:carry_n], out_avals[:carry_n], strict=True)],
                    [as_arrays(o, a) for o, a in zip(outs[carry_n:], out_avals[carry_n:], strict=True)])

        start = [as_arrays(v, a.aval) for v, a in zip(carry, eqn.invars[consts_n:consts_n + carry_n], strict=True)]
        seq = [(v.lo, v.hi) for v in xs]
        last, ys = lax.scan(step, start, seq, length=p["length"], reverse=p["reverse"])
        return [Interval(*e) for e in last] + [Interval(*e) for e in ys]
    return rule


_STRUCTURAL = ("broadcast_in_dim", "reshape", "squeeze", "expand_dims", "transpose", "rev", "slice",
               "concatenate", "stack", "pad", "copy", "copy_p", "split", "reduce_max", "reduce_min", "reduce_and",
               "reduce_or", "cummax", "cummin", "max", "min", "iota", "optimization_barrier")

_RULES = {
    **{name: _structural for name in _STRUCTURAL},
    "add": _add, "add_any": _add, "sub": _sub, "mul": _mul, "div": _div, "neg": _neg, "abs": _abs,
    "integer_pow": _integer_pow, "square": _square, "pow": _pow,
    "sqrt": _monotone(jnp.sqrt, low_domain=0.0, range_=(0, None), ulps=1),
    "rsqrt": _monotone(lax.rsqrt, low_domain=0.0, low_inclusive=False, range_=(0, None), ulps=4, decreasing=True),
    "cbrt": _monotone(jnp.cbrt, ulps=4),
    "exp": _monotone(jnp.exp, range_=(0, None)), "exp2": _monotone(jnp.exp2, range_=(0, None)),
    "expm1": _monotone(jnp.expm1, range_=(-1, None)),
    "log": _monotone(jnp.log, low_domain=0.0, absolute=True),
    "log1p": _monotone(jnp.log1p, low_domain=-1.0, absolute=True),
    "tanh": _monotone(jnp.tanh, range_=(-1, 1)), "logistic": _monotone(jax.nn.sigmoid, range_=(0, 1)),
    "erf": _monotone(lax.erf, range_=(-1, 1)), "atan": _monotone(jnp.arctan, absolute=True),
    "asinh": _monotone(jnp.arcsinh, absolute=True), "sinh": _monotone(jnp.sinh),
    "cosh": _cosh, "sin": _trig(-np.pi / 2), "cos": _trig(0.0), "atan2": _atan2,
    "floor": _exact_monotone, "ceil": _exact_monotone, "round": _exact_monotone, "sign": _exact_monotone,
    "reduce_precision": _exact_monotone,
    "lt": _compare(jnp.less), "le": _compare(jnp.less_equal), "gt": _compare(jnp.greater),
    "ge": _compare(jnp.greater_equal), "eq": _compare(jnp.equal), "ne": _compare(jnp.not_equal),
    "and": _logical(jnp.bitwise_and), "or": _logical(jnp.bitwise_or), "not": _not, "xor": _xor,
    "select_n": _select_n, "convert_element_type": _convert, "reduce_sum": _reduce_sum, "cumsum": _cumsum,
    "argmax": _arg_reduce, "argmin": _arg_reduce, "dot_general": _dot_general, "clamp": _clamp, "sort": _sort,
    **{name: _indexed for name in _INDEX_OPERANDS},
    "is_finite": _is_finite, "rem": _rem,
}


# Primitives whose rule would narrow [-inf, inf], the interval of a value that may be NaN, although their
# concrete result is then NaN again (abs(NaN), 0 * NaN, max(NaN, 1), tanh(NaN), ...): where an input may be
# NaN their output is everything, elementwise or (for reductions and sorts) as a whole.
_NAN_ELEMENTWISE = {"abs", "mul", "max", "min", "clamp", "sign", "exp", "exp2", "expm1", "tanh", "logistic", "erf",
                    "atan", "integer_pow", "square", "cosh", "sin", "cos", "atan2", "pow", "rem"}
_NAN_WHOLE = {"reduce_max", "reduce_min", "cummax", "cummin", "sort", "argmax", "argmin"}


def _may_be_nan(v: Interval):
    return (v.lo == -jnp.inf) & (v.hi == jnp.inf)


def _guard_nan(name: str, invals: Sequence[Interval], outs: list) -> list:
    floats = [v for v in invals if not v.point and _is_float(v.lo)]
    if not floats:
        return outs
    guarded = []
    for out in outs:
        if not _is_float(out.lo):
            guarded.append(out)
            continue
        if name in _NAN_WHOLE:
            flag = jnp.any(jnp.stack([jnp.any(_may_be_nan(v)) for v in floats]))
        else:
            flag = jnp.zeros(np.shape(out.lo), bool)
            for v in floats:
                flag = flag | jnp.broadcast_to(_may_be_nan(v), np.shape(out.lo))
        guarded.append(Interval(jnp.where(flag, -jnp.inf, out.lo), jnp.where(flag, jnp.inf, out.hi)))
    return guarded


class IntervalDomain:
    """The ``Domain`` of intervals (module docstring). ``apply`` raises ``Unsupported`` for a primitive
    without a rule."""

    def constant(self, value: np.ndarray, aval) -> Interval:
        return Interval(jnp.asarray(value, aval.dtype))

    def apply(self, eqn, invals: Sequence[Interval]) -> list:
        name = eqn.primitive.name
        if all(v.point for v in invals) and not any(_is_float(v.aval.dtype) for v in eqn.outvars):
            exact = eqn.primitive.bind(*(v.lo for v in invals), **eqn.params)  # integers and booleans: exact
            return [Interval(v) for v in exact] if eqn.primitive.multiple_results else [Interval(exact)]
        if name == "cond":
            rule = _cond(self)
        elif name == "scan":
            rule = _scan(self)
        else:
            rule = _RULES.get(name)
        if rule is None:
            why = "a loop whose number of iterations may depend on the values" if name == "while" else ""
            raise Unsupported(name, why)
        out = rule(eqn, *invals)
        out = out if isinstance(out, list) else [out]
        if name in _NAN_ELEMENTWISE or name in _NAN_WHOLE:
            out = _guard_nan(name, invals, out)
        return out


def enclose(closed, args: Sequence[Interval]) -> list[Interval]:
    """The enclosures of ``closed``'s outputs for inputs in ``args``."""
    return interpret(closed, args, IntervalDomain())
