"""BiCGSTAB for the matrix-free Newton corrections, as one plain ``lax.while_loop``.

:func:`jax.scipy.sparse.linalg.bicgstab` wraps its loop in ``lax.custom_linear_solve``
so that the solution can be differentiated implicitly. That wrapper traces the operator
and the preconditioner several times over and transposes the operator while the program
is built, a cost every compiled loop with a structured Newton paid although nothing here
differentiates through a solve (on andrews given by its kinetic energy, the block path,
it is about half of lobatto3ab3's tracing). The loop below is
the same iteration without the wrapper, and it starts from ``x = 0`` without evaluating
``A`` there.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

Operator = Callable[[jax.Array], jax.Array]


def bicgstab(A: Operator, b: jax.Array, M: Operator, tol: float, maxiter: int) -> jax.Array:
    """Solve ``A x = b`` by preconditioned BiCGSTAB (van der Vorst, SIAM J. Sci. Stat.
    Comput. 13, 1992) from ``x_0 = 0``.

    Each iteration applies ``M`` (an approximate ``A^{-1}``) and ``A`` twice:

    .. math::

        \\rho_k &= \\hat r^T r_k, \\quad
        p_k = r_k + \\frac{\\rho_k \\alpha_{k-1}}{\\rho_{k-1} \\omega_{k-1}}
              (p_{k-1} - \\omega_{k-1} v_{k-1}), \\quad v_k = A M p_k, \\quad
        \\alpha_k = \\rho_k / \\hat r^T v_k, \\\\
        s_k &= r_k - \\alpha_k v_k, \\quad t_k = A M s_k, \\quad
        \\omega_k = t_k^T s_k / t_k^T t_k, \\\\
        x_{k+1} &= x_k + \\alpha_k M p_k + \\omega_k M s_k, \\quad
        r_{k+1} = s_k - \\omega_k t_k,

    with ``\\hat r = r_0 = b``. Stops when ``||r||_2 <= tol ||b||_2`` (an ``s_k`` that small
    already ends the step without its second half), after ``maxiter`` iterations, or at a
    breakdown (``rho``, ``alpha`` or ``omega`` zero), returning the last iterate.

    Parameters
    ----------
    A, M : callable
        ``x -> A x`` and ``x -> M x`` (``M ~ A^{-1}``).
    b : jax.Array
        Right-hand side.
    tol : float
        Relative residual at which to stop.
    maxiter : int
        Iteration limit.
    """
    floor = tol * tol * jnp.vdot(b, b)
    one = jnp.ones((), b.dtype)

    def body(state):
        x, r, p, v, rho, alpha, omega, _, k = state
        rho_new = jnp.vdot(b, r)
        p = r + (rho_new / rho * alpha / omega) * (p - omega * v)
        p_hat = M(p)
        v = A(p_hat)
        alpha = rho_new / jnp.vdot(b, v)
        s = r - alpha * v
        early = jnp.vdot(s, s) < floor
        s_hat = M(s)
        t = A(s_hat)
        omega = jnp.vdot(t, s) / jnp.vdot(t, t)
        x = jnp.where(early, x + alpha * p_hat, x + alpha * p_hat + omega * s_hat)
        r = jnp.where(early, s, s - omega * t)
        go = (jnp.vdot(r, r) > floor) & (k + 1 < maxiter) & (rho_new != 0) & (alpha != 0) \
            & (omega != 0)
        return x, r, p, v, rho_new, alpha, omega, go, k + 1

    start = (jnp.zeros_like(b), b, b, b, one, one, one, jnp.vdot(b, b) > floor, 0)
    return jax.lax.while_loop(lambda state: state[7], body, start)[0]
