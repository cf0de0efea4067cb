"""Compiling with the large constants as arguments (:mod:`linalg.compiled`)."""

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from linalg.compiled import LIFT_BYTES, compile_lifted


def test_large_constants_become_arguments_once_per_value():
    # Two device copies of one index array (as a conversion at each call site makes
    # them), a table, and a constant below LIFT_BYTES that stays in the program.
    size = 4 * LIFT_BYTES // 8
    table = jnp.asarray(np.linspace(0.0, 1.0, size))
    index = np.arange(size)[::-1].copy()
    small = jnp.asarray([2.0, 3.0])

    def f(x, y):
        first = jnp.take(x * table, jnp.asarray(index))
        second = jnp.take(x, jnp.asarray(index))
        return {"sum": first + second + small[0], "y": y * small[1]}

    x, y = jnp.arange(size, dtype=jnp.float64), jnp.ones(3)
    lifted = compile_lifted(f, x, y)
    assert lifted.lifted_bytes == table.nbytes + jnp.asarray(index).nbytes
    expected = jax.jit(f)(x, y)
    got = lifted(x, y)
    # The same operations on the same values, only read from arguments: bit for bit.
    assert set(got) == {"sum", "y"}
    np.testing.assert_array_equal(got["sum"], expected["sum"])
    np.testing.assert_array_equal(got["y"], expected["y"])


def test_static_arguments_of_a_jitted_function_are_passed_by_name():
    @jax.jit
    def scale(x):
        return 2.0 * x

    @partial(jax.jit, static_argnames="power")
    def f(x, *, power):
        return scale(x) ** power

    lifted = compile_lifted(f, jnp.ones(4), power=3)
    np.testing.assert_array_equal(lifted(jnp.full(4, 2.0)), jnp.full(4, 64.0))
