"""Newton's method for the implicit stage equations, compiled with ``lax.while_loop``."""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

EPS = float(jnp.finfo(jnp.float64).eps)


#: Pivots of the equilibrated LU below this fraction of the largest mark a matrix as
#: numerically rank deficient.
RANK_RTOL = 1e-12


def power_of_two_scale(x: jax.Array) -> jax.Array:
    """``2^-round(log2 x)`` for ``x > 0`` (1 where ``x`` is 0): scaling by it is exact."""
    return jnp.where(x > 0, jnp.exp2(-jnp.round(jnp.log2(jnp.where(x > 0, x, 1.0)))), 1.0)


def basic_solve(A: jax.Array, b: jax.Array, rtol: float) -> jax.Array:
    """A basic solution of ``A x = b`` by QR with column pivoting, for rank-deficient ``A``.

    ``A P = Q R`` with ``|R_kk|`` non-increasing; columns whose ``|R_kk|`` falls below
    ``rtol |R_00|`` are numerically dependent and their unknowns are set to zero, the
    leading triangle gives the others. For a consistent system this is an exact solution
    (not the minimum-norm one); ``b`` may be a vector or a matrix of columns.
    """
    Q, R, perm = jax.scipy.linalg.qr(A, pivoting=True)
    d = jnp.abs(jnp.diag(R))
    keep = d > rtol * d[0]
    mask = keep[:, None] if b.ndim == 2 else keep
    R = jnp.where(keep[:, None], R, jnp.eye(A.shape[0]))
    y = jax.scipy.linalg.solve_triangular(R, jnp.where(mask, Q.T @ b, 0.0))
    return jnp.zeros_like(y).at[perm].set(y)


def solve(A: jax.Array, b: jax.Array) -> jax.Array:
    """``A^{-1} b`` by LU; a rank-revealing basic solution if ``A`` is rank deficient.

    A 1 x 1 system is a division: a LAPACK call is opaque to XLA's fusion and costs
    microseconds, most of a small problem's step for a single constraint.

    Redundant constraints (a constraint Jacobian ``G`` of rank below ``m``, everywhere or at
    a singular configuration) make the Newton and projection matrices singular. LU with
    partial pivoting then leaves a pivot at round-off level, and its solution carries a
    meaningless, huge component along the null space. The matrix is first equilibrated,
    ``D_r A D_c`` with power-of-two row and column scalings (exact), so that the test does
    not mistake badly scaled variables (masses of 1e-7 next to unit lengths) for rank
    deficiency; when the smallest pivot of its LU falls below :data:`RANK_RTOL` times the
    largest (or is not finite), the solve switches to :func:`basic_solve` (QR with column
    pivoting) on the equilibrated system, which drops the dependent directions: for a
    consistent system it is an exact solution, and the multipliers it gives produce the
    same (unique) constraint force as any other.
    """
    if A.shape[0] == 1:
        return b / A[0, 0]
    r = power_of_two_scale(jnp.max(jnp.abs(A), axis=1))
    c = power_of_two_scale(jnp.max(jnp.abs(A * r[:, None]), axis=0))
    As = A * r[:, None] * c[None, :]
    rb = b * (r[:, None] if b.ndim == 2 else r)
    lu, piv = jax.scipy.linalg.lu_factor(As)
    pivots = jnp.abs(jnp.diag(lu))
    deficient = ~(jnp.min(pivots) > RANK_RTOL * jnp.max(pivots))
    y = jax.lax.cond(deficient, lambda: basic_solve(As, rb, RANK_RTOL),
                     lambda: jax.scipy.linalg.lu_solve((lu, piv), rb))
    return y * (c[:, None] if b.ndim == 2 else c)


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
    ``max(tol, eps (1 + max_i sum_j |J_ij| |z_j|))``,
    the rounding error of evaluating a residual whose terms have the magnitudes
    ``|J_ij z_j|`` (``J`` the last Jacobian). Scaling with the terms, not with ``|z|``
    alone, matters where large forces cancel (stiff springs, large multipliers): there the
    residual cannot fall below ``eps`` times those forces. A ``tol`` below round-off (such
    as 1e-16) therefore means "iterate to round-off".

    Returns the iterate, whether it converged, the number of iterations (each one
    Jacobian evaluation and one LU solve) and the final residual norm.
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

    def body(state):
        z, r, _, _, _, it = state
        J = jax.jacfwd(residual)(z)
        dz = solve(J, -r)
        terms = jnp.max(jnp.abs(J) @ jnp.abs(z))
        z = z + dz
        return z, residual(z), norm(r), norm(dz), terms, it + 1

    z, r, r_prev, dz_norm, terms, it = jax.lax.while_loop(
        cond, body, (z0, residual(z0), jnp.inf, jnp.inf, norm(z0), 0))
    converged = done(z, r, r_prev, dz_norm, terms) & jnp.all(jnp.isfinite(z))
    return NewtonResult(z, converged, it, norm(r))
