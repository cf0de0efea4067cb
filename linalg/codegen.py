"""Straight-line C from a JAX function of small fixed-size arrays.

A function is traced to its jaxpr (:func:`jax.make_jaxpr`) and the jaxpr is evaluated once
on *symbols*: every array becomes a NumPy object array of scalar expressions, so that the
structural primitives (slices, reshapes, broadcasts, transposes, pads, concatenations) only
rearrange names and cost nothing at run time, and the arithmetic ones emit one C statement
per scalar. Constants are folded, ``x * 0``, ``x * 1`` and ``x + 0`` are simplified and
repeated expressions are shared, which removes most of what forward-mode autodiff writes
(the identity seeds of :func:`jax.jacfwd` fold away). What remains is the arithmetic of the
function itself, as a C compiler sees it in a hand-written kernel.

Only what a mechanical system's residual and Jacobian use is supported: elementwise
arithmetic and elementary functions, ``dot_general``, reductions by sum, max and min, and
the structural primitives, with nested calls inlined. Anything else (loops, conditionals on
traced values, scatters, linear solves) raises :class:`Unsupported`, and the caller keeps
its compiled-JAX path.
"""

from __future__ import annotations

import itertools
import math
import re
from typing import Callable

import jax
from jax.extend.core import Literal
import numpy as np

#: Largest number of C statements a kernel may have; larger systems keep the JAX path
#: (their arithmetic no longer fits the straight-line form a compiler handles quickly).
MAX_STATEMENTS = 20_000


class Unsupported(ValueError):
    """The function uses a primitive (or a size) that has no straight-line C form here."""


class Sym:
    """A scalar expression: the name of a C variable holding it."""

    __slots__ = ("name", "kernel", "ctype")

    def __init__(self, name: str, kernel: "Kernel", ctype: str = "double"):
        self.name, self.kernel, self.ctype = name, kernel, ctype

    def __add__(self, other):
        return self.kernel.binary("+", self, other)

    def __radd__(self, other):
        return self.kernel.binary("+", other, self)

    def __sub__(self, other):
        return self.kernel.binary("-", self, other)

    def __rsub__(self, other):
        return self.kernel.binary("-", other, self)

    def __mul__(self, other):
        return self.kernel.binary("*", self, other)

    def __rmul__(self, other):
        return self.kernel.binary("*", other, self)

    def __truediv__(self, other):
        return self.kernel.binary("/", self, other)

    def __rtruediv__(self, other):
        return self.kernel.binary("/", other, self)

    def __neg__(self):
        return self.kernel.unary("-", self)


def _literal(x) -> str:
    """A double as C source, exactly (hexadecimal floating constant for finite values)."""
    x = float(x)
    if math.isnan(x):
        return "(0.0 / 0.0)"
    if math.isinf(x):
        return "(1.0 / 0.0)" if x > 0 else "(-1.0 / 0.0)"
    return x.hex()


class Kernel:
    """The statements of one C function, built by evaluating a jaxpr on symbols."""

    def __init__(self):
        self.lines: list[tuple[str, str, str]] = []  # (name, C type, expression)
        self._cache: dict[tuple, object] = {}
        self._names = itertools.count()

    def operand(self, x) -> str:
        return x.name if isinstance(x, Sym) else _literal(x)

    def emit(self, key: tuple, expression: str, ctype: str = "double") -> Sym:
        if key in self._cache:
            return self._cache[key]
        if len(self.lines) >= MAX_STATEMENTS:
            raise Unsupported(f"more than {MAX_STATEMENTS} statements")
        name = f"s{next(self._names)}"
        self.lines.append((name, ctype, expression))
        self._cache[key] = sym = Sym(name, self, ctype)
        return sym

    def binary(self, op: str, a, b):
        a_const, b_const = not isinstance(a, Sym), not isinstance(b, Sym)
        if a_const and b_const:
            a, b = float(a), float(b)
            return {"+": a + b, "-": a - b, "*": a * b,
                    "/": a / b if b != 0 else math.copysign(math.inf, a) * math.copysign(1, b)
                    if a != 0 else math.nan}[op]
        if op == "+":
            if a_const and a == 0:
                return b
            if b_const and b == 0:
                return a
        elif op == "-":
            if not a_const and not b_const and a.name == b.name:
                return 0.0  # x - x, for the finite values a residual holds
            if b_const and b == 0:
                return a
            if a_const and a == 0:
                return self.unary("-", b)
        elif op == "*":
            # x * 0 = 0 drops a NaN or an infinity in x, which a finite residual never has.
            if (a_const and a == 0) or (b_const and b == 0):
                return 0.0
            if a_const and a == 1:
                return b
            if b_const and b == 1:
                return a
            if a_const and a == -1:
                return self.unary("-", b)
            if b_const and b == -1:
                return self.unary("-", a)
        elif op == "/" and b_const and b == 1:
            return a
        if op in "+*" and not a_const and not b_const and a.name > b.name:
            a, b = b, a  # one key for a commutative pair
        key = (op, self.operand(a), self.operand(b))
        return self.emit(key, f"{self.operand(a)} {op} {self.operand(b)}")

    def unary(self, op: str, a):
        if not isinstance(a, Sym):
            return -float(a) if op == "-" else float(a)
        return self.emit((op, a.name), f"{op}{a.name}")

    def call(self, function: str, *args, fold: Callable | None = None, ctype="double"):
        if fold is not None and not any(isinstance(a, Sym) for a in args):
            with np.errstate(all="ignore"):
                return float(fold(*map(np.float64, args)))
        operands = [self.operand(a) for a in args]
        return self.emit((function, *operands), f"{function}({', '.join(operands)})", ctype)

    def compare(self, op: str, a, b):
        if not isinstance(a, Sym) and not isinstance(b, Sym):
            return {"==": a == b, "!=": a != b, "<": a < b, "<=": a <= b,
                    ">": a > b, ">=": a >= b}[op]
        return self.emit((op, self.operand(a), self.operand(b)),
                         f"{self.operand(a)} {op} {self.operand(b)}", "int")

    def select(self, predicate, on_false, on_true):
        if not isinstance(predicate, Sym):
            return on_true if predicate else on_false
        if not isinstance(on_false, Sym) and not isinstance(on_true, Sym) \
                and float(on_false) == float(on_true):
            return on_false
        a, b = self.operand(on_true), self.operand(on_false)
        return self.emit(("?", predicate.name, a, b), f"{predicate.name} ? {a} : {b}")


def _map(function, *arrays):
    """``function`` applied elementwise to object arrays, with NumPy's broadcasting."""
    arrays = np.broadcast_arrays(*[np.asarray(a, dtype=object) for a in arrays])
    out = np.empty(arrays[0].shape, dtype=object)
    for index in np.ndindex(out.shape):
        out[index] = function(*(a[index] for a in arrays))
    return out


def _integer_power(kernel: Kernel, x, k: int):
    if k == 0:
        return 1.0
    if k < 0:
        return kernel.binary("/", 1.0, _integer_power(kernel, x, -k))
    result = None
    base = x
    while k:  # binary powering, as XLA expands integer powers
        if k & 1:
            result = base if result is None else kernel.binary("*", result, base)
        k >>= 1
        if k:
            base = kernel.binary("*", base, base)
    return result


_ELEMENTARY = {  # primitive -> (C function, fold: NumPy's, so NaN where C gives NaN)
    "sin": ("sin", np.sin), "cos": ("cos", np.cos), "tan": ("tan", np.tan),
    "asin": ("asin", np.arcsin), "acos": ("acos", np.arccos), "atan": ("atan", np.arctan),
    "sinh": ("sinh", np.sinh), "cosh": ("cosh", np.cosh), "tanh": ("tanh", np.tanh),
    "exp": ("exp", np.exp), "log": ("log", np.log), "sqrt": ("sqrt", np.sqrt),
    "abs": ("fabs", np.abs), "log1p": ("log1p", np.log1p), "expm1": ("expm1", np.expm1),
}
_BINARY = {"add": "+", "add_any": "+", "sub": "-", "mul": "*", "div": "/"}
_COMPARE = {"eq": "==", "ne": "!=", "lt": "<", "le": "<=", "gt": ">", "ge": ">="}
_NESTED = ("pjit", "jit", "closed_call", "core_call", "remat", "checkpoint",
           "custom_jvp_call", "custom_vjp_call", "custom_vjp_call_jaxpr")


def _inner(params):
    for key in ("jaxpr", "call_jaxpr", "fun_jaxpr"):
        if key in params:
            inner = params[key]
            return (inner.jaxpr, inner.consts) if hasattr(inner, "consts") else (inner, ())
    raise Unsupported("a nested call without a jaxpr")


def _dot_general(lhs, rhs, params):
    """``lax.dot_general``: batch dimensions first, then the lhs's free ones, then the rhs's."""
    (lc, rc), (lb, rb) = params["dimension_numbers"]
    if not lb:
        return np.tensordot(lhs, rhs, axes=(tuple(lc), tuple(rc)))
    lhs = np.moveaxis(lhs, lb, range(len(lb)))
    rhs = np.moveaxis(rhs, rb, range(len(rb)))
    # The contracting axes within one batch entry, the batch axes taken out.
    lc = [c - sum(b < c for b in lb) for c in lc]
    rc = [c - sum(b < c for b in rb) for c in rc]
    batch = lhs.shape[:len(lb)]
    parts = [np.tensordot(lhs[index], rhs[index], axes=(tuple(lc), tuple(rc)))
             for index in np.ndindex(batch)]
    return np.stack(parts).reshape(batch + parts[0].shape)


def _pad(x, value, config):
    """``lax.pad``: edge padding ``lo``, ``hi`` (negative crops) and ``interior`` between."""
    for axis, (lo, hi, interior) in enumerate(config):
        size = x.shape[axis]
        dilated = size + max(size - 1, 0) * interior
        shape = list(x.shape)
        shape[axis] = max(lo, 0) + dilated + max(hi, 0)
        out = np.full(shape, value, dtype=object)
        index = [slice(None)] * x.ndim
        index[axis] = slice(max(lo, 0), max(lo, 0) + dilated, interior + 1)
        out[tuple(index)] = x
        index[axis] = slice(max(-lo, 0), shape[axis] - max(-hi, 0))
        x = out[tuple(index)]
    return x


def _evaluate(kernel: Kernel, jaxpr, consts, args):
    env = {}

    def read(v):
        if isinstance(v, Literal):
            return np.asarray(v.val).astype(object)
        return env[v]

    for var, value in zip(jaxpr.constvars, consts):
        env[var] = np.asarray(value).astype(object)
    for var, value in zip(jaxpr.invars, args):
        env[var] = value
    for eqn in jaxpr.eqns:
        name, params = eqn.primitive.name, eqn.params
        ins = [read(v) for v in eqn.invars]
        if name in _NESTED:
            inner, inner_consts = _inner(params)
            outs = _evaluate(kernel, inner, inner_consts, ins)
        elif not any(isinstance(x, Sym) for a in ins for x in np.asarray(a, object).flat):
            # Constants are folded by the primitive itself, exactly as JAX computes them
            # (integer division, other precisions, NaN rules).
            concrete = [np.asarray(a.tolist(), dtype=v.aval.dtype)
                        for a, v in zip(ins, eqn.invars)]
            folded = eqn.primitive.bind(*concrete, **params)
            outs = folded if eqn.primitive.multiple_results else [folded]
            outs = [np.asarray(o).astype(object) if np.asarray(o).dtype.kind != "f"
                    else np.vectorize(float, otypes=[object])(np.asarray(o, np.float64))
                    for o in outs]
        elif any(v.aval.dtype != np.float64 for v in eqn.outvars
                 if np.issubdtype(v.aval.dtype, np.floating)):
            raise Unsupported(f"a traced value in {eqn.outvars[0].aval.dtype} ({name})")
        else:
            result = _primitive(kernel, name, params, ins, eqn)
            outs = result if eqn.primitive.multiple_results else [result]
        for var, value in zip(eqn.outvars, outs):
            shape = tuple(var.aval.shape)
            value = np.asarray(value, dtype=object)
            if value.shape != shape:
                value = np.broadcast_to(value, shape)
            env[var] = value
    return [read(v) for v in jaxpr.outvars]


def _primitive(kernel: Kernel, name: str, params, ins, eqn):
    if name in _BINARY:
        return _map(lambda a, b: kernel.binary(_BINARY[name], a, b), *ins)
    if name == "neg":
        return _map(lambda a: kernel.unary("-", a), ins[0])
    if name in _ELEMENTARY:
        function, fold = _ELEMENTARY[name]
        return _map(lambda a: kernel.call(function, a, fold=fold), ins[0])
    if name == "integer_pow":
        return _map(lambda a: _integer_power(kernel, a, params["y"]), ins[0])
    if name == "square":
        return _map(lambda a: kernel.binary("*", a, a), ins[0])
    if name == "rsqrt":
        return _map(lambda a: kernel.binary("/", 1.0, kernel.call(
            "sqrt", a, fold=np.sqrt)), ins[0])
    if name in ("max", "min"):
        # lax.max and lax.min propagate NaN (C's fmax and fmin drop it).
        op = ">" if name == "max" else "<"
        return _map(lambda a, b: kernel.emit(
            (name, kernel.operand(a), kernel.operand(b)),
            f"({kernel.operand(a)} != {kernel.operand(a)} || {kernel.operand(a)} {op} "
            f"{kernel.operand(b)}) ? {kernel.operand(a)} : {kernel.operand(b)}"), *ins)
    if name in ("pow", "atan2", "rem"):
        function = {"pow": "pow", "atan2": "atan2", "rem": "fmod"}[name]
        fold = {"pow": np.power, "atan2": np.arctan2, "rem": np.fmod}[name]
        return _map(lambda a, b: kernel.call(function, a, b, fold=fold), *ins)
    if name == "sign":
        return _map(lambda a: kernel.emit(("sign", a.name), f"(double)(({a.name} > 0) - "
                                          f"({a.name} < 0))") if isinstance(a, Sym)
                    else float(np.sign(a)), ins[0])
    if name in _COMPARE:
        return _map(lambda a, b: kernel.compare(_COMPARE[name], a, b), *ins)
    if name == "select_n":
        if len(ins) != 3:
            raise Unsupported("select_n with more than two cases")
        return _map(kernel.select, *ins)
    if name == "convert_element_type":
        if not np.issubdtype(params["new_dtype"], np.floating):
            if any(isinstance(a, Sym) for a in ins[0].flat):
                raise Unsupported("a traced value converted to an integer or a boolean")
            return ins[0].astype(params["new_dtype"]).astype(object)
        return _map(lambda a: kernel.select(a, 0.0, 1.0) if isinstance(a, Sym)
                    and a.ctype == "int" else a if isinstance(a, Sym) else float(a), ins[0])
    if name in ("copy", "copy_p", "stop_gradient", "optimization_barrier"):
        return ins[0]
    if name == "iota":
        shape, axis = params["shape"], params["dimension"]
        values = np.arange(shape[axis]).reshape([-1 if i == axis else 1
                                                 for i in range(len(shape))])
        return np.broadcast_to(values, shape).astype(object)
    if name == "broadcast_in_dim":
        x, shape, dims = ins[0], params["shape"], params["broadcast_dimensions"]
        expanded = [1] * len(shape)
        for axis, dim in enumerate(dims):
            expanded[dim] = x.shape[axis]
        return np.broadcast_to(x.reshape(expanded), shape)
    if name in ("reshape", "squeeze", "expand_dims"):
        return ins[0].reshape(tuple(eqn.outvars[0].aval.shape))
    if name == "transpose":
        return np.transpose(ins[0], params["permutation"])
    if name == "slice":
        strides = params["strides"] or (1,) * ins[0].ndim
        return ins[0][tuple(slice(a, b, s) for a, b, s in zip(
            params["start_indices"], params["limit_indices"], strides))]
    if name == "concatenate":
        return np.concatenate(ins, axis=params["dimension"])
    if name == "stack":
        return np.stack(ins, axis=params["axis"])
    if name == "split":
        axis, bounds = params["axis"], np.cumsum(params["sizes"])[:-1]
        return np.split(ins[0], bounds, axis=axis)
    if name == "pad":
        return _pad(ins[0], ins[1].item(), params["padding_config"])
    if name == "rev":
        return np.flip(ins[0], axis=params["dimensions"])
    if name in ("reduce_sum", "reduce_max", "reduce_min"):
        x, axes = ins[0], tuple(params["axes"])
        combine = {"reduce_sum": lambda a, b: kernel.binary("+", a, b),
                   "reduce_max": lambda a, b: _primitive(kernel, "max", {}, [a, b], eqn).item(),
                   "reduce_min": lambda a, b: _primitive(kernel, "min", {}, [a, b], eqn).item()
                   }[name]
        x = np.moveaxis(x, axes, range(-len(axes), 0))
        flat = x.reshape(x.shape[:x.ndim - len(axes)] + (-1,))
        out = np.empty(flat.shape[:-1], dtype=object)
        for index in np.ndindex(out.shape):
            terms = list(flat[index])
            value = terms[0] if terms else 0.0
            for term in terms[1:]:
                value = combine(value, term)
            out[index] = value
        return out
    if name == "dot_general":
        lhs, rhs = ins
        # tensordot on object arrays multiplies and adds through the symbols' operators
        # with a leading integer 0, which the kernel folds away.
        return _dot_general(lhs, rhs, params)
    raise Unsupported(f"primitive {name!r}")


def live(lines: list[tuple[str, str, str]], outputs: list[str]):
    """The statements the outputs depend on, in order (the primal part of a Jacobian's
    trace, for one, is dead)."""
    needed = set(re.findall(r"\bs\d+\b", " ".join(outputs)))
    kept = []
    for name, ctype, expression in reversed(lines):
        if name in needed:
            needed.update(re.findall(r"\bs\d+\b", expression))
            kept.append((name, ctype, expression))
    return kept[::-1]


def c_function(function: Callable, name: str, inputs: dict[str, tuple], output: str,
               column_major: bool = False) -> str:
    """C source of ``void name(inputs..., double *output)`` computing ``function``.

    ``inputs`` maps each argument's C name to its shape (``()`` for a ``double``, else a
    ``const double *`` read in C order). The output is written whole: every entry,
    zeros included; a 2-D output goes in column-major order with ``column_major``
    (SUNDIALS' dense matrices), else in C order.

    Raises
    ------
    Unsupported
        For a primitive without a straight-line form, or a kernel over
        :data:`MAX_STATEMENTS` statements.
    """
    kernel = Kernel()
    specs = [jax.ShapeDtypeStruct(shape, np.float64) for shape in inputs.values()]
    closed = jax.make_jaxpr(function)(*specs)
    args = []
    for arg, shape in inputs.items():
        if shape == ():
            args.append(np.asarray(Sym(arg, kernel), dtype=object))
            continue
        flat = np.array([Sym(f"{arg}[{i}]", kernel) for i in range(math.prod(shape))],
                        dtype=object)
        args.append(flat.reshape(shape))
    (result,) = _evaluate(kernel, closed.jaxpr, closed.consts, args)
    if column_major and result.ndim == 2:
        result = result.T
    outputs = [kernel.operand(x) for x in np.asarray(result, dtype=object).ravel()]
    body = [f"    const {ctype} {name} = {expression};"
            for name, ctype, expression in live(kernel.lines, outputs)]
    body += [f"    {output}[{i}] = {x};" for i, x in enumerate(outputs)]
    params = ", ".join(f"double {arg}" if shape == () else f"const double *restrict {arg}"
                       for arg, shape in inputs.items())
    return (f"static void {name}({params}, double *restrict {output})\n{{\n"
            + "\n".join(body) + "\n}\n")
