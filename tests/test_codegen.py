"""Straight-line C from JAX functions (linalg.codegen): each kernel, compiled and called,
gives JAX's values; what has no C form is refused."""

from __future__ import annotations

import ctypes
import shutil
import subprocess

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from linalg.codegen import Unsupported, c_function

pytestmark = pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None,
                                reason="no C compiler")


def compiled(source: str, name: str, tmp_path):
    c_file, lib = tmp_path / "k.c", tmp_path / "k.so"
    c_file.write_text("#include <math.h>\n" + source
                      + f"void call(double *a, double *b, double *out) {{ {name}(a[0], b, out); }}\n")
    subprocess.run([shutil.which("cc") or "gcc", "-O2", "-shared", "-fPIC", "-o", str(lib),
                    str(c_file), "-lm"], check=True)
    return ctypes.CDLL(str(lib)).call


def values(function, t: float, x: np.ndarray, tmp_path) -> np.ndarray:
    """``function(t, x)`` through its C kernel."""
    expected = np.asarray(function(t, jnp.asarray(x)))
    source = c_function(function, "kernel", {"t": (), "x": x.shape}, "out")
    call = compiled(source, "kernel", tmp_path)
    out = np.empty(expected.size)
    p = ctypes.POINTER(ctypes.c_double)
    call(np.array([t]).ctypes.data_as(p), np.ascontiguousarray(x).ctypes.data_as(p),
         out.ctypes.data_as(p))
    return out.reshape(expected.shape), expected


def structural(t, x):
    a = jnp.concatenate([x[::-1], jnp.sin(x[1:3]), jnp.zeros(2)])
    b = jax.lax.pad(x, 0.5, [(1, -1, 2)])
    m = jnp.outer(x, a[:4]).T @ x + jnp.sum(x ** 3) * t
    c = jnp.where(x > 0.1, jnp.exp(x), jnp.cos(x) ** -2) * jnp.sign(x - 0.2)
    stack = jnp.stack([jnp.outer(x, x[::-1]), jnp.outer(x, x) - t])  # a batch of matrices
    batched = jnp.einsum("bij,jb->bi", stack, jnp.stack([x, x ** 2], axis=1)).ravel()
    return jnp.concatenate([a, b, m, c, batched, jnp.array([jnp.max(x), jnp.min(x), jnp.sqrt(x @ x),
                                                   jnp.arctan2(x[0], x[1]), x[2] / x[3]])])


def mechanical(t, x):
    # A residual of the kind IDA receives: a configuration-dependent mass times an
    # acceleration, constraint forces, and its forward-mode Jacobian.
    def F(y):
        q, v = y[:2], y[2:]
        M = jnp.array([[2.0 + jnp.cos(q[1]), 0.3 * jnp.sin(q[0])],
                       [0.3 * jnp.sin(q[0]), 1.0 + q[1] ** 2]])
        G = jnp.array([[2 * q[0], 2 * q[1]]])
        return jnp.concatenate([M @ v + G.T @ jnp.array([t]), G @ v])
    return jax.jacfwd(F)(x)


@pytest.mark.parametrize("function, size", [(structural, 4), (mechanical, 4)])
def test_kernel_gives_jax_values(function, size, tmp_path):
    rng = np.random.default_rng(3)
    for _ in range(3):
        x = rng.standard_normal(size)
        got, expected = values(function, 0.7, x, tmp_path)
        np.testing.assert_allclose(got, expected, rtol=1e-13, atol=1e-14)


def test_autodiff_seeds_fold_away():
    # jacfwd of a linear map is a constant matrix: no statement survives.
    source = c_function(lambda t, x: jax.jacfwd(lambda y: 3.0 * y[::-1])(x), "k",
                        {"t": (), "x": (3,)}, "J", column_major=True)
    assert "const double s" not in source
    assert "J[2] = 0x1.8000000000000p+1;" in source


def test_what_has_no_straight_line_form_is_refused():
    def loop(t, x):
        return jax.lax.fori_loop(0, 3, lambda i, y: y * t, x)

    with pytest.raises(Unsupported, match="primitive .(scan|while)."):
        c_function(loop, "k", {"t": (), "x": (2,)}, "out")
