"""Newton's method for the implicit stage equations, compiled with ``lax.while_loop``."""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

EPS = float(jnp.finfo(jnp.float64).eps)


def solve(A: jax.Array, b: jax.Array) -> jax.Array:
    """``A^{-1} b``; a 1 x 1 system is a division.

    A LAPACK call is opaque to XLA's fusion and costs microseconds; for a single
    constraint that overhead is most of a small problem's step.
    """
    if A.shape[0] == 1:
        return b / A[0, 0]
    return jnp.linalg.solve(A, b)


class NewtonResult(NamedTuple):
    z: jax.Array
    converged: jax.Array
    iterations: jax.Array
    residual: jax.Array


def newton(residual: Callable[[jax.Array], jax.Array], z0: jax.Array, tol: float,
           max_iter: int) -> NewtonResult:
    """Solve ``residual(z) = 0`` by Newton with the autodiff Jacobian.

    Converged when ``||residual(z)||_inf <= tol``. The test is on the residual, not on the
    correction, so that ``tol`` bounds the constraint violation left in the solution. Two
    more exits count as converged because no further iteration can gain anything: the
    correction is at round-off (``||dz||_inf <= 4 eps (1 + ||z||_inf)``), or the residual
    has stopped contracting (less than halved) within a thousand times its round-off floor
    ``max(tol, eps (1 + ||z||_inf))``. A ``tol`` below round-off (such as 1e-16) therefore
    means "iterate to round-off".

    Returns the iterate, whether it converged, the number of iterations (each one
    Jacobian evaluation and one LU solve) and the final residual norm.
    """

    def norm(x):
        return jnp.max(jnp.abs(x))

    def done(z, r, r_prev, dz_norm):
        floor = jnp.maximum(tol, EPS * (1.0 + norm(z)))
        stalled = (norm(r) > 0.5 * r_prev) & (norm(r) <= 1e3 * floor)
        return (norm(r) <= tol) | (dz_norm <= 4 * EPS * (1.0 + norm(z))) | stalled

    def cond(state):
        z, r, r_prev, dz_norm, it = state
        return (~done(z, r, r_prev, dz_norm)) & (it < max_iter) & jnp.all(jnp.isfinite(r))

    def body(state):
        z, r, _, _, it = state
        dz = solve(jax.jacfwd(residual)(z), -r)
        z = z + dz
        return z, residual(z), norm(r), norm(dz), it + 1

    z, r, r_prev, dz_norm, it = jax.lax.while_loop(
        cond, body, (z0, residual(z0), jnp.inf, jnp.inf, 0))
    converged = done(z, r, r_prev, dz_norm) & jnp.all(jnp.isfinite(z))
    return NewtonResult(z, converged, it, norm(r))
