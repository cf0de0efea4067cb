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

    # Each pass of the loop is half an iteration, with one application of M and of A:
    # the first half (``second`` false) forms p_k and v_k, the second t_k. Both halves'
    # formulas are evaluated and the pass's own selected; the operator and the
    # preconditioner, most of the program, then appear once in it, not twice.
    def body(state):
        x, r, p, v, s, rho, alpha, omega, second, _, k = state
        rho_new = jnp.vdot(b, r)
        p_new = r + (rho_new / rho * alpha / omega) * (p - omega * v)
        u = M(jnp.where(second, s, p_new))
        w = A(u)
        # First half: u = M p_k, w = v_k.
        alpha_new = rho_new / jnp.vdot(b, w)
        s_new = r - alpha_new * w
        early = jnp.vdot(s_new, s_new) < floor
        first = (x + alpha_new * u, jnp.where(early, s_new, r), p_new, w, s_new, rho_new,
                 alpha_new, omega, ~early, ~early, k + early)
        # Second half: u = M s_k, w = t_k.
        omega_new = jnp.vdot(w, s) / jnp.vdot(w, w)
        r_new = s - omega_new * w
        go = (jnp.vdot(r_new, r_new) > floor) & (k + 1 < maxiter) & (rho != 0) \
            & (alpha != 0) & (omega_new != 0)
        last = (x + omega_new * u, r_new, p, v, s, rho, alpha, omega_new, False, go, k + 1)
        return jax.tree_util.tree_map(lambda a, b: jnp.where(second, a, b), last, first)

    start = (jnp.zeros_like(b), b, b, b, b, one, one, one, False, jnp.vdot(b, b) > floor, 0)
    return jax.lax.while_loop(lambda state: state[9], body, start)[0]
