"""Newton's method for the implicit stage equations, compiled with ``lax.while_loop``."""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from linalg.dense import rarely, solve

#: Relative residual at which a Krylov solve of the fallback's Newton correction stops
#: (the forcing term of the inexact Newton method: each outer iteration contracts the
#: residual by about this factor until round-off).
KRYLOV_RTOL = 1e-10

#: Iteration limit of one Krylov solve.
KRYLOV_MAX_ITER = 100

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


def krylov_linear(residual: Callable[[jax.Array], jax.Array], linear: Linear) -> Linear:
    """Newton's correction with the exact Jacobian, matrix-free, preconditioned by ``linear``.

    Solves ``J(z) dz = -r`` by BiCGSTAB (van der Vorst, SIAM J. Sci. Stat. Comput. 13,
    1992) to a relative residual :data:`KRYLOV_RTOL`: ``J(z) x`` is one forward-mode
    derivative of ``residual`` (``O(nnz)``, ``J`` never formed) and the preconditioner is
    the approximate inverse that ``linear`` applies (``x -> -linear(z, x)``). This is
    Newton's method with the true Jacobian at the current iterate (a Jacobian-free
    Newton-Krylov method; Knoll and Keyes, J. Comput. Phys. 193, 2004): quadratic
    convergence up to the forcing term, where the frozen Jacobian of simplified Newton
    converges only linearly, or not at all when ``J`` has moved far from it (near a
    singular configuration, where the constraint forces change fastest).

    BiCGSTAB, not GMRES: with JAX's GMRES (either solve method) in it the time loop no
    longer compiled into one native kernel, and RATTLE's steps on chain:N=16 ran eight
    times slower (0.13 s against 0.017 s per solve, measured with
    ``benchmarks/perf/compile_profile.py``); BiCGSTAB leaves them as fast, and XLA's
    compilation of the loop grows from 2.1 s to 4.1 s.
    """

    def linear_exact(z, r):
        dz, _ = jax.scipy.sparse.linalg.bicgstab(
            lambda x: jax.jvp(residual, (z,), (x,))[1], -r, tol=KRYLOV_RTOL,
            maxiter=KRYLOV_MAX_ITER, M=lambda x: -linear(z, x)[0])
        # The bound on the residual's terms: the exact Jacobian's |J||z| by one more
        # derivative would cost as much as a Krylov iteration; the approximate one's serves.
        return dz, linear(z, r)[1]

    return linear_exact


def newton(residual: Callable[[jax.Array], jax.Array], z0: jax.Array, tol: float,
           max_iter: int, linear: Linear | None = None) -> NewtonResult:
    """Solve ``residual(z) = 0`` by Newton's method.

    ``linear`` gives each correction; by default the exact autodiff Jacobian, densely
    (:func:`dense_linear`). A structured method passes an approximate Jacobian instead
    (simplified Newton: one factorisation per step, linear convergence), under the same
    convergence test. Where simplified Newton does not converge within ``max_iter``
    corrections (it stalls, diverges or meets a non-finite residual), Newton's method with
    the exact Jacobian takes over for up to ``max_iter`` more (:func:`krylov_linear`,
    preconditioned by the same ``linear``), from the better of ``z0`` and the last finite
    iterate; only when that fails too has the solve failed. The structured path is then
    as robust as the dense one, whose Newton has the exact Jacobian throughout, and a
    step that simplified Newton solves costs no more at run time (the compiled program
    holds both iterations: see :func:`krylov_linear` for what that costs).

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

    def iterate(state, linear, limit):
        def cond(state):
            z, r, r_prev, dz_norm, terms, it = state
            return ((~done(z, r, r_prev, dz_norm, terms)) & (it < limit)
                    & jnp.all(jnp.isfinite(r)))

        def body(state):
            z, r, _, _, _, it = state
            dz, terms = linear(z, r)
            z = z + dz
            return z, residual(z), norm(r), norm(dz), terms, it + 1

        return jax.lax.while_loop(cond, body, state)

    def converged(state):
        z, r, r_prev, dz_norm, terms, _ = state
        return done(z, r, r_prev, dz_norm, terms) & jnp.all(jnp.isfinite(z))

    r0 = residual(z0)
    start = (z0, r0, jnp.inf, jnp.inf, norm(z0), 0)
    state = iterate(start, dense_linear(residual) if linear is None else linear, max_iter)
    if linear is not None:
        # Simplified Newton did not converge: the exact Jacobian takes over (docstring).
        def exact(state):
            z, r, it = state[0], state[1], state[-1]
            better = jnp.all(jnp.isfinite(r)) & (norm(r) < norm(r0))
            z = jnp.where(better, z, z0)
            restart = (z, jnp.where(better, r, r0), jnp.inf, jnp.inf, norm(z), it)
            return iterate(restart, krylov_linear(residual, linear), it + max_iter)

        state = rarely(~converged(state), lambda: exact(state), state)
    return NewtonResult(state[0], converged(state), state[-1], norm(state[1]))
