"""Newton's method for the implicit stage equations, compiled with ``lax.while_loop``."""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from linalg.dense import solve

EPS = float(jnp.finfo(jnp.float64).eps)


class NewtonResult(NamedTuple):
    z: jax.Array
    converged: jax.Array
    iterations: jax.Array
    residual: jax.Array


#: ``linear(z, r) -> (dz, terms)``: a Newton correction for the residual ``r`` at ``z`` and
#: the magnitude ``max_i sum_j |J_ij| |z_j|`` of the residual's terms (or a bound on it).
Linear = Callable[[jax.Array, jax.Array], tuple[jax.Array, jax.Array]]


def dense_linear(residual: Callable[[jax.Array], jax.Array]) -> Linear:
    """Newton's correction with the dense autodiff Jacobian, solved by :func:`solve`."""

    def linear(z, r):
        J = jax.jacfwd(residual)(z)
        return solve(J, -r), jnp.max(jnp.abs(J) @ jnp.abs(z))

    return linear


def newton(residual: Callable[[jax.Array], jax.Array], z0: jax.Array, tol: float,
           max_iter: int, linear: Linear | None = None) -> NewtonResult:
    """Solve ``residual(z) = 0`` by Newton's method.

    ``linear`` gives each correction; by default the exact autodiff Jacobian, densely
    (:func:`dense_linear`). A structured method passes an approximate Jacobian instead
    (simplified Newton: one factorisation per step, linear convergence), under the same
    convergence test.

    Converged when ``||residual(z)||_inf <= tol``. The test is on the residual, not on the
    correction, so that ``tol`` bounds the constraint violation left in the solution. Two
    more exits count as converged because no further iteration can gain anything: the
    correction is at round-off (``||dz||_inf <= 4 eps (1 + ||z||_inf)``), or the residual
    has stopped contracting (less than halved) within a thousand times its round-off floor
    ``max(tol, eps (1 + max_i sum_j |J_ij| |z_j|))``,
    the rounding error of evaluating a residual whose terms have the magnitudes
    ``|J_ij z_j|`` (``J`` the last Jacobian). Scaling with the terms, not with ``|z|``
    alone, matters where large forces cancel (stiff springs, large multipliers): there the
    residual cannot fall below ``eps`` times those forces. A ``tol`` below round-off (such
    as 1e-16) therefore means "iterate to round-off".

    Returns the iterate, whether it converged, the number of iterations (each one
    correction) and the final residual norm.
    """

    def norm(x):
        return jnp.max(jnp.abs(x))

    def done(z, r, r_prev, dz_norm, terms):
        floor = jnp.maximum(tol, EPS * (1.0 + terms))
        stalled = (norm(r) > 0.5 * r_prev) & (norm(r) <= 1e3 * floor)
        return (norm(r) <= tol) | (dz_norm <= 4 * EPS * (1.0 + norm(z))) | stalled

    def cond(state):
        z, r, r_prev, dz_norm, terms, it = state
        return ((~done(z, r, r_prev, dz_norm, terms)) & (it < max_iter)
                & jnp.all(jnp.isfinite(r)))

    linear = dense_linear(residual) if linear is None else linear

    def body(state):
        z, r, _, _, _, it = state
        dz, terms = linear(z, r)
        z = z + dz
        return z, residual(z), norm(r), norm(dz), terms, it + 1

    z, r, r_prev, dz_norm, terms, it = jax.lax.while_loop(
        cond, body, (z0, residual(z0), jnp.inf, jnp.inf, norm(z0), 0))
    converged = done(z, r, r_prev, dz_norm, terms) & jnp.all(jnp.isfinite(z))
    return NewtonResult(z, converged, it, norm(r))
