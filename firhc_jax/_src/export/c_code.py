"""A jaxpr as C99: one ``static`` function per callable, with loops over arrays of sizes fixed at export.

``Emitter`` is a value domain of ``firhc_jax._src.jaxpr.interpret``: every value is a C array (``CValue``)
declared in the function being written, or a scalar literal. Each primitive becomes a loop nest over its
output's elements with the index arithmetic written out (strides are constants), so the C compiler sees plain
scalar code it can unroll and keep in registers. Closed-over arrays become ``static const`` tables shared by
the translation unit. A primitive without a rule is refused with ``Unsupported``.
"""
from __future__ import annotations

import dataclasses
import itertools
import math
from typing import Callable, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..jaxpr.interpret import Unsupported, interpret

C_TYPES = {"float64": "double", "float32": "float", "int64": "int64_t", "int32": "int32_t", "int16": "int16_t",
           "int8": "int8_t", "uint64": "uint64_t", "uint32": "uint32_t", "uint16": "uint16_t", "uint8": "uint8_t",
           "bool": "unsigned char"}
INT_LIMITS = {"int64": ("INT64_MIN", "INT64_MAX"), "int32": ("INT32_MIN", "INT32_MAX"),
              "int16": ("INT16_MIN", "INT16_MAX"), "int8": ("INT8_MIN", "INT8_MAX"), "uint64": ("0", "UINT64_MAX"),
              "uint32": ("0", "UINT32_MAX"), "uint16": ("0", "UINT16_MAX"), "uint8": ("0", "UINT8_MAX")}
UNARY = {"neg": "(-{0})", "sin": "sin({0})", "cos": "cos({0})", "tan": "tan({0})", "asin": "asin({0})",
         "acos": "acos({0})", "atan": "atan({0})", "sinh": "sinh({0})", "cosh": "cosh({0})", "tanh": "tanh({0})",
         "asinh": "asinh({0})", "acosh": "acosh({0})", "atanh": "atanh({0})", "exp": "exp({0})",
         "exp2": "exp2({0})", "log": "log({0})", "log1p": "log1p({0})", "expm1": "expm1({0})", "sqrt": "sqrt({0})",
         "rsqrt": "(1 / sqrt({0}))", "cbrt": "cbrt({0})", "floor": "floor({0})", "ceil": "ceil({0})",
         "is_finite": "isfinite({0})", "logistic": "(1 / (1 + exp(-{0})))", "square": "({0} * {0})",
         "erf": "erf({0})", "erfc": "erfc({0})", "lgamma": "lgamma({0})", "copy": "{0}", "copy_p": "{0}",
         "reduce_precision": "{0}", "optimization_barrier": "{0}"}
BINARY = {"add": "({0} + {1})", "sub": "({0} - {1})", "mul": "({0} * {1})", "div": "({0} / {1})",
          "pow": "pow({0}, {1})", "atan2": "atan2({0}, {1})", "nextafter": "nextafter({0}, {1})",
          "eq": "({0} == {1})", "ne": "({0} != {1})", "lt": "({0} < {1})", "le": "({0} <= {1})",
          "gt": "({0} > {1})", "ge": "({0} >= {1})", "shift_left": "({0} << {1})"}
REDUCE = {"reduce_sum": ("0", "{acc} + {v}"), "reduce_prod": ("1", "{acc} * {v}"),
          "reduce_max": ("-INFINITY", "FJ_MAX({acc}, {v})"), "reduce_min": ("INFINITY", "FJ_MIN({acc}, {v})"),
          "reduce_and": ("1", "{acc} && {v}"), "reduce_or": ("0", "{acc} || {v}")}
CUMULATIVE = {"cumsum": "{acc} + {v}", "cumprod": "{acc} * {v}", "cummax": "FJ_MAX({acc}, {v})",
              "cummin": "FJ_MIN({acc}, {v})", "cumlogsumexp": "log(exp({acc}) + exp({v}))"}
SCATTER = {"scatter": "{v}", "scatter-add": "{old} + {v}", "scatter_add": "{old} + {v}",
           "scatter-mul": "{old} * {v}", "scatter_mul": "{old} * {v}", "scatter-min": "FJ_MIN({old}, {v})",
           "scatter_min": "FJ_MIN({old}, {v})", "scatter-max": "FJ_MAX({old}, {v})",
           "scatter_max": "FJ_MAX({old}, {v})"}
PRELUDE = """\
#define FJ_MAX(a, b) ((a) != (a) || (a) > (b) ? (a) : (b))
#define FJ_MIN(a, b) ((a) != (a) || (a) < (b) ? (a) : (b))
"""


def c_type(dtype) -> str:
    name = np.dtype(dtype).name
    if name not in C_TYPES:
        raise Unsupported("convert_element_type", f"dtype {name} has no C type here")
    return C_TYPES[name]


def literal(value, dtype) -> str:
    """One number as a C expression of ``dtype``, exactly."""
    dtype = np.dtype(dtype)
    if dtype == np.bool_:
        return "1" if value else "0"
    if dtype.kind in "iu":
        return f"(({c_type(dtype)}){int(value)}{'ULL' if dtype.kind == 'u' else 'LL'})"
    value = float(value)
    if math.isnan(value):
        text = "NAN"
    elif math.isinf(value):
        text = "INFINITY" if value > 0 else "-INFINITY"
    else:
        text = repr(value)
    return text if dtype == np.float64 else f"(({c_type(dtype)}){text})"


def strides(shape) -> list[int]:
    out, step = [], 1
    for size in reversed(shape):
        out.append(step)
        step *= size
    return out[::-1]


def flat(index: Sequence[str], shape) -> str:
    """The row-major offset of a multi-index (C expressions) in an array of ``shape``."""
    terms = [i if s == 1 else f"{i} * {s}" for i, s in zip(index, strides(shape), strict=True) if i != "0"]
    return " + ".join(terms) if terms else "0"


@dataclasses.dataclass(frozen=True)
class CValue:
    """A value in the C function: an array ``name`` (from ``offset`` on), or with ``text`` a scalar literal.
    ``varying``: it depends on the input of the loop over the control set (``translate_children``)."""

    shape: tuple
    dtype: np.dtype
    name: str = ""
    text: str = ""
    offset: str = ""
    varying: bool = False

    @property
    def size(self) -> int:
        return math.prod(self.shape)

    def at(self, index: str = "0") -> str:
        if self.text:
            return self.text
        if self.size == 1:
            index = "0"
        where = index if not self.offset else f"{self.offset} + {index}"
        return f"{self.name}[{where}]"

    def at_index(self, index: Sequence[str]) -> str:
        return self.at(flat(index, self.shape))

    def broadcast(self, index: Sequence[str]) -> str:
        """The element at an output's ``index`` of an elementwise operand: a scalar, or an array of the output's
        rank whose size-1 dimensions broadcast."""
        if self.size == 1:
            return self.at()
        return self.at_index([i if n != 1 else "0" for i, n in zip(index, self.shape, strict=True)])


class Emitter:
    """The C domain: ``apply`` writes an equation's loops and returns its outputs. An equation whose inputs do
    not vary with the loop's input is written before that loop (``outer``), the others inside it (``inner``):
    what only the parent state decides is computed once for all its children."""

    def __init__(self, tables: dict):
        self.outer: list[str] = []
        self.inner: list[str] = []
        self.lines = self.outer
        self.tables = tables  # bytes key -> (name, C definition): the unit's static const arrays
        self.names = itertools.count()
        self.depth = 1
        self.nesting = 0  # > 0 inside a body: it stays where its equation went

    # -- writing -------------------------------------------------------------------------------------------
    def emit(self, line: str) -> None:
        self.lines.append("    " * self.depth + line)

    def new(self, shape, dtype) -> CValue:
        value = CValue(tuple(shape), np.dtype(dtype), name=f"v{next(self.names)}")
        self.emit(f"{c_type(dtype)} {value.name}[{max(value.size, 1)}];")
        return value

    def loops(self, shape, body: Callable[[list[str]], None]) -> None:
        """``body(index)`` inside a loop nest over ``shape`` (index: one C expression a dimension)."""
        index, opened = [], 0
        for size in shape:
            if size == 1:
                index.append("0")
                continue
            i = f"i{next(self.names)}"
            self.emit(f"for (int {i} = 0; {i} < {size}; {i}++) {{")
            self.depth += 1
            opened += 1
            index.append(i)
        if math.prod(shape) > 0:
            body(index)
        for _ in range(opened):
            self.depth -= 1
            self.emit("}")

    def fill(self, out: CValue, element: Callable[[list[str]], str]) -> CValue:
        self.loops(out.shape, lambda ix: self.emit(f"{out.at_index(ix)} = {element(ix)};"))
        return out

    def copy(self, src: CValue, dst: CValue) -> None:
        self.loops(src.shape, lambda ix: self.emit(f"{dst.at_index(ix)} = ({c_type(dst.dtype)})({src.at_index(ix)});"))

    # -- the domain ----------------------------------------------------------------------------------------
    def constant(self, value: np.ndarray, aval) -> CValue:
        dtype = np.dtype(aval.dtype)
        value = np.asarray(value, dtype)
        if value.size == 1:
            return CValue(tuple(value.shape), dtype, text=literal(value.reshape(-1)[0], dtype))
        key = (dtype.str, value.shape, value.tobytes())
        if key not in self.tables:
            name = f"fj_table{len(self.tables)}"
            items = ", ".join(literal(v, dtype) for v in value.reshape(-1))
            self.tables[key] = (name, f"static const {c_type(dtype)} {name}[{value.size}] = {{{items}}};")
        return CValue(tuple(value.shape), dtype, name=self.tables[key][0])

    def apply(self, eqn, invals) -> list:
        if self.nesting:
            return self._rule(eqn, invals)
        varying = any(v.varying for v in invals)
        self.lines, depth = (self.inner, 2) if varying else (self.outer, 1)
        self.depth, self.nesting = depth, 1
        try:
            outs = self._rule(eqn, invals)
        finally:
            self.nesting = 0
        return [dataclasses.replace(o, varying=varying) for o in outs]

    def _rule(self, eqn, invals) -> list:
        name = eqn.primitive.name
        outs = [v.aval for v in eqn.outvars]
        rule = getattr(self, "_" + name.replace("-", "_"), None)
        if name in UNARY:
            return [self._elementwise(outs[0], invals, UNARY[name], name)]
        if name in BINARY:
            return [self._elementwise(outs[0], invals, BINARY[name], name)]
        if name in REDUCE:
            return [self._reduce(outs[0], invals[0], eqn.params["axes"], *REDUCE[name])]
        if name in CUMULATIVE:
            return [self._cumulative(invals[0], eqn.params["axis"], eqn.params["reverse"], CUMULATIVE[name])]
        if name in SCATTER:
            return [self._scatter(eqn, invals, SCATTER[name])]
        if rule is None:
            raise Unsupported(name)
        return rule(eqn, invals, outs)

    def _elementwise(self, aval, invals, template: str, name: str) -> CValue:
        kind = np.dtype(invals[0].dtype).kind
        if name in ("floor", "ceil") and kind in "iub":
            template = "{0}"
        return self.fill(self.new(aval.shape, aval.dtype),
                         lambda ix: template.format(*(v.broadcast(ix) for v in invals)))

    # Elementwise rules whose C depends on the dtype.
    def _abs(self, eqn, invals, outs):
        kind = invals[0].dtype.kind
        return [self._elementwise(outs[0], invals, "fabs({0})" if kind == "f" else "({0} < 0 ? -{0} : {0})", "abs")]

    def _sign(self, eqn, invals, outs):
        text = "({0} > 0 ? 1 : ({0} < 0 ? -1 : {0}))" if invals[0].dtype.kind == "f" else "(({0} > 0) - ({0} < 0))"
        return [self._elementwise(outs[0], invals, text, "sign")]

    def _round(self, eqn, invals, outs):
        method = int(eqn.params.get("rounding_method", 0))
        return [self._elementwise(outs[0], invals, "rint({0})" if method == 1 else "round({0})", "round")]

    def _not(self, eqn, invals, outs):
        return [self._elementwise(outs[0], invals, "(!{0})" if invals[0].dtype == np.bool_ else "(~{0})", "not")]

    def _logical(self, invals, outs, logical: str, bitwise: str):
        return [self._elementwise(outs[0], invals, logical if invals[0].dtype == np.bool_ else bitwise, "")]

    def _and(self, eqn, invals, outs):
        return self._logical(invals, outs, "({0} && {1})", "({0} & {1})")

    def _or(self, eqn, invals, outs):
        return self._logical(invals, outs, "({0} || {1})", "({0} | {1})")

    def _xor(self, eqn, invals, outs):
        return self._logical(invals, outs, "({0} != {1})", "({0} ^ {1})")

    def _max(self, eqn, invals, outs):
        return self._logical(invals, outs, "({0} || {1})", "FJ_MAX({0}, {1})")

    def _min(self, eqn, invals, outs):
        return self._logical(invals, outs, "({0} && {1})", "FJ_MIN({0}, {1})")

    def _rem(self, eqn, invals, outs):
        kind = invals[0].dtype.kind
        return [self._elementwise(outs[0], invals, "fmod({0}, {1})" if kind == "f" else "({0} % {1})", "rem")]

    def _shift_right_arithmetic(self, eqn, invals, outs):
        return [self._elementwise(outs[0], invals, "({0} >> {1})", "")]

    def _integer_pow(self, eqn, invals, outs):
        y = int(eqn.params["y"])
        x = invals[0]
        out = self.new(outs[0].shape, outs[0].dtype)

        def element(ix):
            base, acc, e = x.broadcast(ix), None, abs(y)
            if e == 0:
                return "1"
            b = f"b{next(self.names)}"
            self.emit(f"{c_type(x.dtype)} {b} = {base};")
            while e > 0:  # binary exponentiation in the order jax lowers it
                if e & 1:
                    acc = b if acc is None else f"({acc} * {b})"
                e >>= 1
                if e:
                    self.emit(f"{c_type(x.dtype)} {b}s = {b} * {b};")
                    b = f"{b}s"
            return acc if y > 0 else f"(1 / {acc})"
        return [self.fill(out, element)]

    def _select_n(self, eqn, invals, outs):
        which, *cases = invals
        out = self.new(outs[0].shape, outs[0].dtype)

        def element(ix):
            vals = [c.broadcast(ix) for c in cases]
            w = which.broadcast(ix)
            text = vals[-1]
            for i in range(len(vals) - 2, -1, -1):
                boolean = which.dtype == np.bool_
                text = f"({w} ? {text} : {vals[i]})" if boolean else f"({w} <= {i} ? {vals[i]} : {text})"
            return text
        return [self.fill(out, element)]

    def _clamp(self, eqn, invals, outs):
        lo, x, hi = invals
        return [self.fill(self.new(outs[0].shape, outs[0].dtype),
                          lambda ix: f"FJ_MIN(FJ_MAX({x.broadcast(ix)}, {lo.broadcast(ix)}), {hi.broadcast(ix)})")]

    def _convert_element_type(self, eqn, invals, outs):
        x, dtype = invals[0], np.dtype(outs[0].dtype)
        if dtype == np.bool_:
            return [self._elementwise(outs[0], invals, "({0} != 0)", "")]
        if dtype.kind in "iu" and x.dtype.kind == "f":  # XLA saturates, NaN to 0
            lo, hi = INT_LIMITS[dtype.name]
            t = c_type(dtype)
            text = (f"({{0}} != {{0}} ? 0 : {{0}} <= (double){lo} ? {lo} : {{0}} >= (double){hi} ? {hi} : "
                    f"({t}){{0}})")
            return [self._elementwise(outs[0], invals, text, "")]
        return [self._elementwise(outs[0], invals, f"(({c_type(dtype)}){{0}})", "")]

    def _iota(self, eqn, invals, outs):
        dim = eqn.params["dimension"]
        return [self.fill(self.new(outs[0].shape, outs[0].dtype), lambda ix: ix[dim])]

    # -- shapes --------------------------------------------------------------------------------------------
    def _reshaped(self, invals, outs):
        out = self.new(outs[0].shape, outs[0].dtype)
        x = invals[0]
        self.loops((out.size,), lambda ix: self.emit(f"{out.at(ix[0])} = {x.at(ix[0])};"))
        return [out]

    _reshape = _squeeze = _expand_dims = lambda self, eqn, invals, outs: self._reshaped(invals[:1], outs)

    def _broadcast_in_dim(self, eqn, invals, outs):
        x, dims = invals[0], eqn.params["broadcast_dimensions"]
        return [self.fill(self.new(outs[0].shape, outs[0].dtype),
                          lambda ix: x.at_index([ix[d] if x.shape[j] > 1 else "0" for j, d in enumerate(dims)]))]

    def _transpose(self, eqn, invals, outs):
        x, perm = invals[0], eqn.params["permutation"]
        inverse = np.argsort(perm)
        return [self.fill(self.new(outs[0].shape, outs[0].dtype),
                          lambda ix: x.at_index([ix[inverse[d]] for d in range(len(perm))]))]

    def _rev(self, eqn, invals, outs):
        x, dims = invals[0], eqn.params["dimensions"]
        return [self.fill(self.new(outs[0].shape, outs[0].dtype),
                          lambda ix: x.at_index([f"({x.shape[d] - 1} - {i})" if d in dims else i
                                                 for d, i in enumerate(ix)]))]

    def _slice(self, eqn, invals, outs):
        x = invals[0]
        start, step = eqn.params["start_indices"], eqn.params["strides"] or (1,) * len(x.shape)
        return [self.fill(self.new(outs[0].shape, outs[0].dtype),
                          lambda ix: x.at_index([f"({s} + {st} * {i})" for i, s, st in zip(ix, start, step,
                                                                                            strict=True)]))]

    def _starts(self, x: CValue, starts, sizes) -> list[str]:
        """Traced start indices clamped as XLA clamps them: into ``[0, dim - size]``."""
        out = []
        for s, dim, size in zip(starts, x.shape, sizes, strict=True):
            name = f"s{next(self.names)}"
            self.emit(f"int64_t {name} = (int64_t)({s.at()});")
            self.emit(f"{name} = {name} < 0 ? 0 : {name} > {dim - size} ? {dim - size} : {name};")
            out.append(name)
        return out

    def _dynamic_slice(self, eqn, invals, outs):
        x, *starts = invals
        s = self._starts(x, starts, eqn.params["slice_sizes"])
        return [self.fill(self.new(outs[0].shape, outs[0].dtype),
                          lambda ix: x.at_index([f"({a} + {i})" for a, i in zip(s, ix, strict=True)]))]

    def _dynamic_update_slice(self, eqn, invals, outs):
        x, update, *starts = invals
        out = self.new(outs[0].shape, outs[0].dtype)
        self.copy(x, out)
        s = self._starts(x, starts, update.shape)
        self.loops(update.shape, lambda ix: self.emit(
            f"{out.at_index([f'({a} + {i})' for a, i in zip(s, ix, strict=True)])} = {update.at_index(ix)};"))
        return [out]

    def _concatenate(self, eqn, invals, outs):
        axis = eqn.params["dimension"]
        out = self.new(outs[0].shape, outs[0].dtype)
        at = 0
        for x in invals:
            self.loops(x.shape, lambda ix, at=at, x=x: self.emit(
                f"{out.at_index([f'({at} + {i})' if d == axis else i for d, i in enumerate(ix)])} = "
                f"{x.at_index(ix)};"))
            at += x.shape[axis]
        return [out]

    def _stack(self, eqn, invals, outs):
        axis = eqn.params["axis"]
        out = self.new(outs[0].shape, outs[0].dtype)
        for at, x in enumerate(invals):
            self.loops(x.shape, lambda ix, at=at, x=x: self.emit(
                f"{out.at_index(ix[:axis] + [str(at)] + ix[axis:])} = {x.at_index(ix)};"))
        return [out]

    def _split(self, eqn, invals, outs):
        x, axis = invals[0], eqn.params["axis"]
        results, at = [], 0
        for aval in outs:
            results.append(self.fill(self.new(aval.shape, aval.dtype), lambda ix, at=at: x.at_index(
                [f"({at} + {i})" if d == axis else i for d, i in enumerate(ix)])))
            at += aval.shape[axis]
        return results

    def _pad(self, eqn, invals, outs):
        x, value = invals
        config = [tuple(int(c) for c in cfg) for cfg in eqn.params["padding_config"]]
        out = self.new(outs[0].shape, outs[0].dtype)
        self.fill(out, lambda ix: value.at())

        def put(ix):
            where = [f"({lo} + {i} * {interior + 1})" for i, (lo, _, interior) in zip(ix, config, strict=True)]
            inside = " && ".join(f"{w} >= 0 && {w} < {n}" for w, n in zip(where, out.shape, strict=True))
            self.emit(f"if ({inside}) {out.at_index(where)} = {x.at_index(ix)};")
        self.loops(x.shape, put)
        return [out]

    # -- reductions and products ---------------------------------------------------------------------------
    def _reduce(self, aval, x: CValue, axes, init: str, step: str) -> CValue:
        out = self.new(aval.shape, aval.dtype)
        kept = [d for d in range(len(x.shape)) if d not in axes]
        if x.dtype == np.bool_:
            init = {"-INFINITY": "0", "INFINITY": "1"}.get(init, init)
        elif x.dtype.kind in "iu":
            init = {"-INFINITY": INT_LIMITS[x.dtype.name][0], "INFINITY": INT_LIMITS[x.dtype.name][1]}.get(init, init)

        def body(ix):
            acc = f"a{next(self.names)}"
            self.emit(f"{c_type(aval.dtype)} {acc} = {init};")
            self.loops([x.shape[d] for d in axes], lambda jx: self.emit(
                f"{acc} = {step.format(acc=acc, v=x.at_index(self._merge(kept, ix, list(axes), jx)))};"))
            self.emit(f"{out.at_index(ix)} = {acc};")
        self.loops(aval.shape, body)
        return out

    @staticmethod
    def _merge(dims_a, ix_a, dims_b, ix_b) -> list[str]:
        full = dict(zip(dims_a, ix_a, strict=True))
        full.update(zip(dims_b, ix_b, strict=True))
        return [full[d] for d in range(len(full))]

    def _argmax(self, eqn, invals, outs, better=">"):
        x, (axis,) = invals[0], eqn.params["axes"]
        out = self.new(outs[0].shape, outs[0].dtype)
        kept = [d for d in range(len(x.shape)) if d != axis]

        def body(ix):
            best, at = f"a{next(self.names)}", f"a{next(self.names)}"
            self.emit(f"{c_type(x.dtype)} {best} = {x.at_index(self._merge(kept, ix, [axis], ['0']))};")
            self.emit(f"int64_t {at} = 0;")
            self.loops((x.shape[axis],), lambda jx: self.emit(
                f"{{ {c_type(x.dtype)} e = {x.at_index(self._merge(kept, ix, [axis], jx))}; "
                f"if (e {better} {best} || (e != e && {best} == {best})) {{ {best} = e; {at} = {jx[0]}; }} }}"))
            self.emit(f"{out.at_index(ix)} = {at};")
        self.loops(outs[0].shape, body)
        return [out]

    def _argmin(self, eqn, invals, outs):
        return self._argmax(eqn, invals, outs, better="<")

    def _cumulative(self, x: CValue, axis: int, reverse: bool, step: str) -> CValue:
        out = self.new(x.shape, x.dtype)
        others = [d for d in range(len(x.shape)) if d != axis]
        n = x.shape[axis]

        def body(ix):
            acc = f"a{next(self.names)}"
            self.emit(f"{c_type(x.dtype)} {acc} = 0;")
            j = f"i{next(self.names)}"
            k = f"({n - 1} - {j})" if reverse else j
            full = self._merge(others, ix, [axis], [k])
            self.emit(f"for (int {j} = 0; {j} < {n}; {j}++) {{")
            self.emit(f"    {acc} = {j} == 0 ? {x.at_index(full)} : {step.format(acc=acc, v=x.at_index(full))};")
            self.emit(f"    {out.at_index(full)} = {acc};")
            self.emit("}")
        self.loops([x.shape[d] for d in others], body)
        return out

    def _dot_general(self, eqn, invals, outs):
        lhs, rhs = invals
        (lc, rc), (lb, rb) = eqn.params["dimension_numbers"]
        lf = [d for d in range(len(lhs.shape)) if d not in lc and d not in lb]
        rf = [d for d in range(len(rhs.shape)) if d not in rc and d not in rb]
        aval = outs[0]
        out = self.new(aval.shape, aval.dtype)
        t = c_type(aval.dtype)

        def body(ix):
            nb, nl = len(lb), len(lf)
            batch, lfree, rfree = ix[:nb], ix[nb:nb + nl], ix[nb + nl:]
            acc = f"a{next(self.names)}"
            self.emit(f"{t} {acc} = 0;")

            def term(jx):
                li = self._merge(list(lb) + lf + list(lc), batch + lfree + jx, [], [])
                ri = self._merge(list(rb) + rf + list(rc), batch + rfree + jx, [], [])
                self.emit(f"{acc} += ({t}){lhs.at_index(li)} * ({t}){rhs.at_index(ri)};")
            self.loops([lhs.shape[d] for d in lc], term)
            self.emit(f"{out.at_index(ix)} = {acc};")
        self.loops(aval.shape, body)
        return [out]

    # -- gather and scatter --------------------------------------------------------------------------------
    def _window_starts(self, operand: CValue, indices: CValue, batch_ix, to_operand, sizes, clip: bool):
        """Start of a gather's or scatter's window in each operand dimension (C names) and an out-of-bounds
        test (C expression, "0" when clipped)."""
        starts, bad = {}, []
        for j, d in enumerate(to_operand):
            name = f"s{next(self.names)}"
            self.emit(f"int64_t {name} = (int64_t)({indices.at_index(batch_ix + [str(j)])});")
            limit = operand.shape[d] - sizes[d]
            if clip:
                self.emit(f"{name} = {name} < 0 ? 0 : {name} > {limit} ? {limit} : {name};")
            else:
                bad.append(f"{name} < 0 || {name} > {limit}")
            starts[d] = name
        return starts, " || ".join(bad) or "0"

    def _gather(self, eqn, invals, outs):
        operand, indices = invals
        dn, sizes = eqn.params["dimension_numbers"], eqn.params["slice_sizes"]
        if dn.operand_batching_dims:
            raise Unsupported("gather", "batching dimensions")
        mode = str(eqn.params["mode"])
        clip = "FILL" not in mode
        aval = outs[0]
        out = self.new(aval.shape, aval.dtype)
        window_dims = [d for d in range(len(operand.shape)) if d not in dn.collapsed_slice_dims]
        fill = eqn.params.get("fill_value")
        fill = literal(np.nan if fill is None and aval.dtype.kind == "f" else (fill or 0), aval.dtype)

        def body(ix):
            batch_ix = [i for d, i in enumerate(ix) if d not in dn.offset_dims]
            offsets = dict(zip(window_dims, [ix[d] for d in dn.offset_dims], strict=True))
            starts, bad = self._window_starts(operand, indices, batch_ix, dn.start_index_map, sizes, clip)
            where = [f"({starts.get(d, '0')} + {offsets.get(d, '0')})" for d in range(len(operand.shape))]
            self.emit(f"{out.at_index(ix)} = ({bad}) ? {fill} : {operand.at_index(where)};")
        self.loops(aval.shape, body)
        return [out]

    def _scatter(self, eqn, invals, template: str):
        operand, indices, updates = invals
        dn = eqn.params["dimension_numbers"]
        if dn.operand_batching_dims:
            raise Unsupported(eqn.primitive.name, "batching dimensions")
        clip = "CLIP" in str(eqn.params["mode"])
        out = self.new(operand.shape, operand.dtype)
        self.copy(operand, out)
        window_dims = [d for d in range(len(operand.shape)) if d not in dn.inserted_window_dims]
        sizes = [1] * len(operand.shape)
        for d, u in zip(window_dims, dn.update_window_dims, strict=True):
            sizes[d] = updates.shape[u]

        def body(ix):
            batch_ix = [i for d, i in enumerate(ix) if d not in dn.update_window_dims]
            offsets = dict(zip(window_dims, [ix[d] for d in dn.update_window_dims], strict=True))
            starts, bad = self._window_starts(operand, indices, batch_ix, dn.scatter_dims_to_operand_dims, sizes,
                                              clip)
            where = out.at_index([f"({starts.get(d, '0')} + {offsets.get(d, '0')})" for d in range(len(operand.shape))])
            self.emit(f"if (!({bad})) {where} = {template.format(old=where, v=updates.at_index(ix))};")
        self.loops(updates.shape, body)
        return out

    # -- control flow --------------------------------------------------------------------------------------
    def _block(self, closed, args) -> list:
        """Translate a body jaxpr inside the current block; returns its outputs."""
        return interpret(closed, args, self)

    def _carried(self, values) -> list[CValue]:
        out = []
        for v in values:
            c = self.new(v.shape, v.dtype)
            self.copy(v, c)
            out.append(c)
        return out

    def _assign(self, results, targets) -> None:
        """``targets = results`` with every result read before any target is written (a body may swap them)."""
        temps = []
        for r in results:
            t = self.new(r.shape, r.dtype)
            self.copy(r, t)
            temps.append(t)
        for t, target in zip(temps, targets, strict=True):
            self.copy(t, target)

    def _while(self, eqn, invals, outs):
        p = eqn.params
        cond_consts = invals[:p["cond_nconsts"]]
        body_consts = invals[p["cond_nconsts"]:p["cond_nconsts"] + p["body_nconsts"]]
        carry = self._carried(invals[p["cond_nconsts"] + p["body_nconsts"]:])
        self.emit("for (;;) {")
        self.depth += 1
        (go,) = self._block(p["cond_jaxpr"], cond_consts + carry)
        self.emit(f"if (!{go.at()}) break;")
        self._assign(self._block(p["body_jaxpr"], body_consts + carry), carry)
        self.depth -= 1
        self.emit("}")
        return carry

    def _scan(self, eqn, invals, outs):
        p = eqn.params
        nc, nk, length = p["num_consts"], p["num_carry"], p["length"]
        consts, carry, xs = invals[:nc], self._carried(invals[nc:nc + nk]), invals[nc + nk:]
        ys = [self.new(a.shape, a.dtype) for a in outs[nk:]]
        t = f"t{next(self.names)}"
        self.emit(f"for (int {t}_ = 0; {t}_ < {length}; {t}_++) {{")
        self.depth += 1
        self.emit(f"int {t} = {f'{length - 1} - {t}_' if p['reverse'] else f'{t}_'};")
        slices = [CValue(x.shape[1:], x.dtype, name=x.name, text=x.text,
                         offset=f"{x.offset + ' + ' if x.offset else ''}{t} * {math.prod(x.shape[1:])}")
                  for x in xs]
        results = self._block(p["jaxpr"], consts + carry + slices)
        for y, r in zip(ys, results[nk:], strict=True):
            view = CValue(y.shape[1:], y.dtype, name=y.name, offset=f"{t} * {math.prod(y.shape[1:])}")
            self.copy(r, view)
        self._assign(results[:nk], carry)
        self.depth -= 1
        self.emit("}")
        return carry + ys

    def _cond(self, eqn, invals, outs):
        index, *ops = invals
        branches = eqn.params["branches"]
        results = [self.new(a.shape, a.dtype) for a in outs]
        last = len(branches) - 1
        for i, branch in enumerate(branches):
            test = f"if ({index.at()} <= {i}) {{" if i < last else "{"
            self.emit(test if i == 0 else ("} else " + test))
            self.depth += 1
            for r, v in zip(results, self._block(branch, ops), strict=True):
                self.copy(v, r)
            self.depth -= 1
        self.emit("}")
        return results


def translate(name: str, fn: Callable, args: Sequence[jax.ShapeDtypeStruct], arg_names: Sequence[str],
              out_types: Sequence[str], tables: dict, where) -> str:
    """C function ``name(args..., outs...)`` computing ``fn(*args)``: each argument a ``const`` pointer of its
    dtype, each output a pointer of the C type in ``out_types``, written element by element. ``where`` names
    ``fn`` in messages (or, called with a primitive's name, names the callable that uses it)."""
    emitter, results = _emitted(fn, args, arg_names, tables, where)
    params = [_parameter(a, n) for a, n in zip(args, arg_names, strict=True)]
    params += [f"{t} *out{i}" for i, t in enumerate(out_types)]
    emitter.lines, emitter.depth = emitter.outer, 1
    for i, (r, t) in enumerate(zip(results, out_types, strict=True)):
        emitter.loops((r.size,), lambda ix, r=r, i=i, t=t: emitter.emit(f"out{i}[{ix[0]}] = ({t})({r.at(ix[0])});"))
    return f"static void {name}({', '.join(params)}) {{\n" + "\n".join(emitter.outer) + "\n}\n"


def translate_children(name: str, fn: Callable, args: Sequence[jax.ShapeDtypeStruct], arg_names: Sequence[str],
                       table: str, count: int, out_types: Sequence[str], tables: dict, where, *,
                       across: bool = False, rows: Optional[np.ndarray] = None) -> str:
    """C function ``name(args without u..., outs...)`` computing ``fn`` for every row ``u`` of ``table``
    (``count`` rows; ``u`` is the argument named "u"), output ``j`` of row ``c`` at ``out_j[c * size_j]``.
    What does not depend on ``u`` is computed once, before the loop over the rows. ``across``: each operation
    on every row at once (``fn`` vmapped over the rows), loops a compiler vectorises across the rows at ``-O3``;
    the faster form where a row's own code is a loop (a plant's sub-steps), the slower one elsewhere. ``rows``:
    the table's values; what depends on ``u`` alone is then computed here, once per row, into tables (JAX's
    partial evaluation splits ``fn``), and the loop computes the rest."""
    if across:
        return _translate_across(name, fn, args, arg_names, table, count, out_types, tables, where)
    if rows is not None:
        emitter, results = _emitted_folded(fn, args, arg_names, tables, where, rows)
    else:
        emitter, results = _emitted(fn, args, arg_names, tables, where, varying="u")
    u = args[arg_names.index("u")]
    params = [_parameter(a, n) for a, n in zip(args, arg_names, strict=True) if n != "u"]
    params += [f"{t} *out{i}" for i, t in enumerate(out_types)]
    emitter.lines, emitter.depth = emitter.inner, 2
    for i, (r, t) in enumerate(zip(results, out_types, strict=True)):
        emitter.loops((r.size,), lambda ix, r=r, i=i, t=t: emitter.emit(
            f"out{i}[child * {r.size} + {ix[0]}] = ({t})({r.at(ix[0])});"))
    loop = [f"    for (int child = 0; child < {count}; child++) {{",
            f"        const {c_type(u.dtype)} *u = &{table}[child * {math.prod(u.shape)}];", *emitter.inner, "    }"]
    return f"static void {name}({', '.join(params)}) {{\n" + "\n".join(emitter.outer + loop) + "\n}\n"


def _translate_across(name, fn, args, arg_names, table, count, out_types, tables, where) -> str:
    """``translate_children(..., across=True)``: ``fn`` vmapped over the rows of ``table``, translated whole."""
    iu = arg_names.index("u")
    rows = jax.ShapeDtypeStruct((count, *args[iu].shape), args[iu].dtype)
    vmapped = jax.vmap(fn, in_axes=tuple(0 if i == iu else None for i in range(len(args))))
    body = translate(f"{name}_rows", vmapped, [rows if i == iu else a for i, a in enumerate(args)],
                     ["u_rows" if i == iu else n for i, n in enumerate(arg_names)], out_types, tables, where)
    params = [_parameter(a, n) for a, n in zip(args, arg_names, strict=True) if n != "u"]
    params += [f"{t} *out{i}" for i, t in enumerate(out_types)]
    passed = [table if n == "u" else _parameter(a, n).split("*")[-1] for a, n in zip(args, arg_names, strict=True)]
    passed += [f"out{i}" for i in range(len(out_types))]
    return body + f"static void {name}({', '.join(params)}) {{\n    {name}_rows({', '.join(passed)});\n}}\n"


# Arguments the generated code always passes as double (states, the controller's inputs); where the jaxpr
# takes another float type, the translated function converts them on entry.
DOUBLE_ARGUMENTS = ("x", "x0", "u_in")


def _parameter(spec, name: str) -> str:
    """The C parameter of one argument."""
    if name in DOUBLE_ARGUMENTS and np.dtype(spec.dtype) != np.float64:
        return f"const double *{name}_in"
    return f"const {c_type(spec.dtype)} *{name}"


def _emitted(fn, args, arg_names, tables: dict, where, varying: str = "") -> tuple[Emitter, list]:
    """The emitter after translating ``fn``, and ``fn``'s outputs in it; a ``ValueError`` names the callable
    and the primitive the translation does not cover."""
    emitter = Emitter(tables)
    inputs = _inputs(emitter, args, arg_names, varying)
    return emitter, _interpreted(jax.make_jaxpr(fn)(*args), inputs, emitter, where)


def _emitted_folded(fn, args, arg_names, tables: dict, where, rows: np.ndarray) -> tuple[Emitter, list]:
    """``_emitted`` of ``fn`` with its part that depends on ``u`` alone computed for every row of ``rows``: the
    residuals of ``u``'s partial evaluation become tables read at the row (``child``), or constants where
    every row's is the same."""
    from jax._src.interpreters import partial_eval as pe

    closed = jax.make_jaxpr(fn)(*args)
    iu = arg_names.index("u")
    known, unknown, _, residuals = pe.partial_eval_jaxpr_nounits(
        closed, [i != iu for i in range(len(args))], instantiate=True)
    values = jax.vmap(jax.extend.core.jaxpr_as_fun(known))(jnp.asarray(rows, args[iu].dtype))
    emitter = Emitter(tables)
    inputs = []
    for aval, value in zip(residuals, values, strict=True):
        value = np.asarray(value)
        if np.all(value == value[:1]) or value.shape[0] == 1:
            inputs.append(emitter.constant(value[0], aval))
        else:
            table_value = emitter.constant(value, jax.ShapeDtypeStruct(value.shape, aval.dtype))
            size = math.prod(aval.shape)
            inputs.append(CValue(tuple(aval.shape), np.dtype(aval.dtype), name=table_value.name,
                                 offset=f"child * {size}", varying=True))
    others = [(a, n) for i, (a, n) in enumerate(zip(args, arg_names, strict=True)) if i != iu]
    inputs += _inputs(emitter, [a for a, _ in others], [n for _, n in others], "")
    return emitter, _interpreted(unknown, inputs, emitter, where)


def _inputs(emitter, args, arg_names, varying: str) -> list:
    """The translated function's arguments as values (a float32 session's states converted on entry)."""
    inputs = []
    for a, n in zip(args, arg_names, strict=True):
        if n in DOUBLE_ARGUMENTS and np.dtype(a.dtype) != np.float64:  # a float32 session: its own rounding
            emitter.emit(f"{c_type(a.dtype)} {n}[{max(1, math.prod(a.shape))}];")
            emitter.emit(f"for (int j = 0; j < {math.prod(a.shape)}; j++) {n}[j] = ({c_type(a.dtype)}){n}_in[j];")
        inputs.append(CValue(tuple(a.shape), np.dtype(a.dtype), name=n, varying=n == varying))
    return inputs


def _interpreted(closed, inputs, emitter, where) -> list:
    try:
        return interpret(closed, inputs, emitter)
    except Unsupported as e:
        culprit = where(e.primitive) if callable(where) else where
        raise ValueError(f"{culprit} uses {e}; the C export cannot translate it. Rewrite that part with the "
                         "supported primitives (the deployment guide lists them)") from None


def primitives(closed) -> set[str]:
    """Every primitive a jaxpr uses, in its sub-jaxprs too."""
    found = set()
    for eqn in closed.jaxpr.eqns:
        found.add(eqn.primitive.name)
        for value in eqn.params.values():
            for sub in value if isinstance(value, (tuple, list)) else (value,):
                if hasattr(sub, "jaxpr") and hasattr(sub, "consts"):
                    found |= primitives(sub)
                elif type(sub).__name__ == "Jaxpr":
                    found |= primitives(jax.extend.core.ClosedJaxpr(sub, ()))
    return found
