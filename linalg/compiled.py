"""Compiling with the large constant arrays as arguments of the program, not inside it.

The structured linear algebra closes over index arrays (a banded assembly's gathers, a
block mass's seeds and group indices, a pattern's rows and columns), so JAX captures
them as constants of every program that calls it, and XLA embeds each in the executable
and copies it while it compiles. A constant is captured once per array, but an array
that JAX derives from one while tracing (``jnp.take`` converts its index to ``int64``) is
a new array at every call site: RATTLE's loop on ``rigid-chain:N=16384`` held 271
constants, 390 MB, most of them copies of a few arrays, and compiling it took the
process from 2.1 to 3.5 GB.

:func:`compile_lifted` traces the function, passes every constant of at least
:data:`LIFT_BYTES` to the executable as an argument instead (one buffer per distinct
value, kept with the executable), and compiles. Smaller constants stay in the program,
where XLA may fold them, so small systems compile as before. What the compiler freed is
then given back to the system (:func:`give_back_heap`).
"""

from __future__ import annotations

import ctypes
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

#: Constants of at least this many bytes become arguments.
LIFT_BYTES = 1 << 14


def _malloc_trim() -> Callable[[int], int] | None:
    try:
        return ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):  # not glibc: nothing to give back this way
        return None


_TRIM = _malloc_trim()


def give_back_heap() -> None:
    """Return the C heap's free pages to the system (glibc's ``malloc_trim``; elsewhere
    nothing).

    Set-up frees a lot at once: the compiler's working memory, a pattern tracing's Python
    sets (:func:`linalg.pattern.traced_sparsity`). glibc keeps such pages in the process,
    resident, under everything it does next: after building rigid-chain:N=8192 the
    process was 816 MB resident, 608 MB once they were given back.
    """
    if _TRIM is not None:
        _TRIM(0)


def device_index(a) -> jax.Array:
    """An index array on the device, as ``int32``, made once: a concrete array even when
    first asked for inside a trace (it is cached and used by later traces, so a tracer
    there would leak into them), and one constant for every program that reads it (a copy
    per call would be a constant per call site)."""
    with jax.ensure_compile_time_eval():
        return jnp.asarray(np.asarray(a, dtype=np.int32))


class Lifted:
    """A compiled function whose large constants are passed in as arguments.

    Called with the same (non-static) arguments as the function it was compiled from;
    :meth:`as_text` is the executable's.
    """

    def __init__(self, compiled, values: list[jax.Array], out_tree):
        self._compiled, self._values, self._out_tree = compiled, values, out_tree

    def __call__(self, *args):
        out = self._compiled(self._values, *jax.tree_util.tree_leaves(args))
        return jax.tree_util.tree_unflatten(self._out_tree, out)

    def as_text(self) -> str:
        return self._compiled.as_text()

    @property
    def lifted_bytes(self) -> int:
        """Bytes of the constants held as arguments."""
        return sum(v.nbytes for v in self._values)


def compile_lifted(fn: Callable, *args: Any, **static: Any) -> Lifted:
    """``jax.jit(fn).lower(*args, **static).compile()`` with the constants of at least
    :data:`LIFT_BYTES` passed as arguments (module notes).

    Parameters
    ----------
    fn : callable
        A function of arrays, or a ``jax.jit`` function (then ``static`` are its static
        arguments, by name).
    *args
        Arrays (or shape-dtype structures) of the call's shapes.
    """
    jitted = fn if hasattr(fn, "trace") else jax.jit(fn)
    traced = jitted.trace(*args, **static)
    closed = traced.jaxpr
    consts = list(closed.consts)
    # A trace has one input per argument leaf. More inputs are values it closed over that
    # JAX could not take as constants: a tracer leaked from an earlier trace, such as an
    # index array cached while tracing (hence linalg.compiled.device_index).
    if len(closed.jaxpr.invars) != len(jax.tree_util.tree_leaves(args)):
        raise RuntimeError(f"compile_lifted: the trace of {getattr(fn, '__name__', fn)} "
                           "closes over values that are not constants (a leaked tracer?)")
    values: list[jax.Array] = []
    slots: dict[int, int] = {}
    for i, c in enumerate(consts):
        if np.ndim(c) == 0 or c.nbytes < LIFT_BYTES:
            continue
        same = next((k for k, v in enumerate(values)
                     if v.shape == c.shape and v.dtype == c.dtype
                     and getattr(v, "weak_type", False) == getattr(c, "weak_type", False)
                     and bool(jnp.array_equal(v, c))), None)
        if same is None:
            values.append(jnp.asarray(c))
            same = len(values) - 1
        slots[i] = same
        consts[i] = None  # not kept: the copies go with the trace
    jaxpr = closed.jaxpr

    def run(lifted, *flat):
        bound = [lifted[slots[i]] if i in slots else c for i, c in enumerate(consts)]
        return jax.core.eval_jaxpr(jaxpr, bound, *flat)

    flat_args = jax.tree_util.tree_leaves(args)
    compiled = jax.jit(run).lower(values, *flat_args).compile()
    give_back_heap()
    return Lifted(compiled, values, traced.out_tree)
