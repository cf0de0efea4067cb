"""Newton's method for the implicit stage equations, compiled with ``lax.while_loop``."""

from __future__ import annotations

import contextlib
import contextvars
import functools
from typing import Any, Callable, Iterator, NamedTuple

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from linalg.dense import rarely, reused_factor, reused_solve, solve
from linalg.krylov import bicgstab

#: Relative residual at which a Krylov solve of the fallback's Newton correction stops
#: (the forcing term of the inexact Newton method: each outer iteration contracts the
#: residual by about this factor until round-off).
KRYLOV_RTOL = 1e-10

#: Iteration limit of one Krylov solve.
KRYLOV_MAX_ITER = 100

EPS = float(jnp.finfo(jnp.float64).eps)

#: Multiple of the round-off floor within which Newton with the exact Jacobian may stop
#: once the residual no longer halves (:func:`newton`).
EXACT_WINDOW = 1e3

#: The same for simplified Newton (:func:`newton`).
SIMPLIFIED_WINDOW = 8.0

#: Unknowns from which Newton without an approximate Jacobian (the dense path) first
#: iterates with the exact Jacobian at the start, factorised once (:func:`frozen_linear`).
#: Below it a Jacobian and factorisation per iteration cost less than the extra
#: corrections of a linear rate (``python -m benchmarks.perf.crossover`` times the dense
#: path).
FROZEN_MIN = 24

#: Multiple of the round-off floor within which a residual that the last iteration
#: contracted by at least :data:`QUADRATIC` counts as at the floor: Newton stops there at
#: once (:func:`newton`).
AT_FLOOR = 2.0

#: The contraction of one iteration that shows Newton in its quadratic regime.
QUADRATIC = 1e-2


class NewtonResult(NamedTuple):
    z: Any
    converged: jax.Array
    iterations: jax.Array
    residual: jax.Array


#: ``linear(z, r) -> (dz, terms)``: a Newton correction (of ``z``'s structure) for the residual
#: ``r`` at ``z`` and the magnitude ``max_i sum_j |J_ij| |z_j|`` of the residual's terms (or a
#: bound on it).
Linear = Callable[[Any, Any], tuple[Any, jax.Array]]


_deferred: contextvars.ContextVar[bool] = contextvars.ContextVar("deferred", default=False)


@contextlib.contextmanager
def deferred_fallback() -> Iterator[None]:
    """Trace :func:`newton` without the exact-Jacobian fallback of simplified Newton inside
    this block: where simplified Newton does not converge, the solve fails.

    The fallback (:func:`krylov_linear` on the structured paths, :func:`dense_linear`
    after :func:`frozen_linear`) is rarely taken, and it is up to most of a time loop's
    program and of XLA's compilation time (``python -m benchmarks.perf.compile_profile``
    measures it). So the time loop compiles its steps this way first, and the loop with
    the fallback only when a step fails, continuing from that step
    (:func:`integrators.loop.march`)."""
    token = _deferred.set(True)
    try:
        yield
    finally:
        _deferred.reset(token)


def max_norm(tree) -> jax.Array:
    """``max |x_i|`` over every entry of every array in ``tree``."""
    return functools.reduce(jnp.maximum, (jnp.max(jnp.abs(a))
                                          for a in jax.tree_util.tree_leaves(tree)))


def anderson_step(z, r, dz, history):
    """The correction of :func:`newton`'s ``anderson`` mixing at ``z`` with residual ``r``
    and simplified-Newton correction ``dz``, and the history for the next iteration.

    ``gamma`` is 0 at the first iteration, and where ``<dr, dr>`` vanishes or the
    quotient is not finite: the plain correction."""
    z_old, r_old, dz_old, seen = history
    leaves = jax.tree_util.tree_leaves
    dr = [a - b for a, b in zip(leaves(r), leaves(r_old))]
    num = sum(jnp.vdot(d, a) for d, a in zip(dr, leaves(r)))
    den = sum(jnp.vdot(d, d) for d in dr)
    gamma = jnp.where(seen & (den > 0), num / jnp.where(den > 0, den, 1.0), 0.0)
    gamma = jnp.where(jnp.isfinite(gamma), gamma, 0.0)
    step = jax.tree_util.tree_map(lambda x, x0, d, d0: d - gamma * ((x - x0) + (d - d0)),
                                  z, z_old, dz, dz_old)
    return step, (z, r, dz, jnp.array(True))


def dense_linear(residual: Callable[[jax.Array], jax.Array],
                 rows: jax.Array | None = None) -> Linear:
    """Newton's correction with the dense autodiff Jacobian, solved by :func:`solve`;
    with ``rows``, the system's rows divided by them first (an equilibration: the same
    correction, from a matrix whose conditioning does not depend on the residual's row
    scaling)."""

    def linear(z, r):
        J = jax.jacfwd(residual)(z)
        terms = jnp.max(jnp.abs(J) @ jnp.abs(z))
        if rows is not None:
            J, r = J / rows[:, None], r / rows
        return solve(J, -r), terms

    return linear


def frozen_linear(residual: Callable[[Any], Any], z0: Any, rows: Any | None = None) -> Linear:
    """Simplified Newton's correction with the exact Jacobian at ``z0``, factorised once
    (:func:`linalg.dense.reused_factor`, rows equilibrated by ``rows`` as in
    :func:`dense_linear`) and applied to every residual: one Jacobian and one factorisation
    per solve in place of one per iteration. ``terms`` is ``max_i sum_j |J_0,ij| |z_j|``."""
    x0, unravel = ravel_pytree(z0)

    def flat(x):
        return ravel_pytree(residual(unravel(x)))[0]

    J = jax.jacfwd(flat)(x0)
    # The residual has z's structure (newton), so the row weights broadcast against z0's.
    weights = None if rows is None else ravel_pytree(jax.tree_util.tree_map(
        lambda w, a: jnp.broadcast_to(w, jnp.shape(a)), rows, z0))[0]
    F = reused_factor(J if weights is None else J / weights[:, None])
    magnitude = jnp.abs(J)

    def linear(z, r):
        x, rx = ravel_pytree(z)[0], ravel_pytree(r)[0]
        dx = reused_solve(F, -(rx if weights is None else rx / weights))
        return unravel(dx), jnp.max(magnitude @ jnp.abs(x))

    return linear


def krylov_linear(residual: Callable[[jax.Array], jax.Array], linear: Linear) -> Linear:
    """Newton's correction with the exact Jacobian, matrix-free, preconditioned by ``linear``.

    Solves ``J(z) dz = -r`` by BiCGSTAB (:func:`linalg.krylov.bicgstab`) to a relative
    residual :data:`KRYLOV_RTOL`: ``J(z) x`` is one forward-mode derivative of ``residual``,
    linearised at ``z`` once per correction (``O(nnz)``, ``J`` never formed), and the
    preconditioner is the approximate inverse that ``linear`` applies (``x -> -linear(z,
    x)``). This is Newton's method with the true Jacobian at the current iterate (a
    Jacobian-free Newton-Krylov method; Knoll and Keyes, J. Comput. Phys. 193, 2004):
    quadratic convergence up to the forcing term, where the frozen Jacobian of simplified
    Newton converges only linearly, or not at all when ``J`` has moved far from it (near a
    singular configuration, where the constraint forces change fastest).

    BiCGSTAB, not GMRES: with JAX's GMRES (either solve method) in it the time loop no
    longer compiles into one native kernel and the steps run several times slower;
    BiCGSTAB leaves the steps as fast (``python -m benchmarks.perf.compile_profile``).
    """

    def linear_exact(z, r):
        # Linearised once per correction: the Krylov loop's two products per iteration
        # evaluate the tangent program, without the primal residual each time.
        _, J = jax.linearize(residual, z)
        dz = bicgstab(J, -r, lambda x: -linear(z, x)[0], KRYLOV_RTOL, KRYLOV_MAX_ITER)
        # The bound on the residual's terms: the exact Jacobian's |J||z| by one more
        # derivative would cost as much as a Krylov iteration; the approximate one's serves.
        return dz, linear(z, r)[1]

    return linear_exact


def newton(residual: Callable[[Any], Any], z0: Any, tol: float,
           max_iter: int, linear: Linear | None = None,
           refactor: Callable[[Any], Linear] | None = None,
           rows: Any | None = None, anderson: bool = False) -> NewtonResult:
    """Solve ``residual(z) = 0`` by Newton's method.

    Iteration: ``z <- z + dz`` with ``dz`` from ``linear``. A structured method passes an
    approximate, once-factorised Jacobian (simplified Newton, linear convergence). Without
    one, the Jacobian is the exact autodiff one, dense: for fewer than :data:`FROZEN_MIN`
    unknowns formed and factorised at every iteration (:func:`dense_linear`); from
    :data:`FROZEN_MIN` on, formed at ``z0`` and factorised once (:func:`frozen_linear`),
    since ``K`` forward derivatives and an ``O(K^3)`` factorisation per iteration cost more
    than the extra corrections of a linear rate, with the per-iteration Jacobian as the
    fallback below (simplified Newton with the exact Jacobian at the start: Hairer and
    Wanner, *Solving ODEs II*, IV.8).

    Stopping rule: converged when ``||residual(z)||_inf <= tol`` (on the residual, so that
    ``tol`` bounds the constraint violation left), or when no iteration can gain more:

    - the correction is at round-off, ``||dz||_inf <= 4 eps (1 + ||z||_inf)``;
    - the residual is less than halved within a window of its round-off floor
      ``eps (1 + terms)``, ``terms`` being the magnitude of the terms it is computed from
      (the second value ``linear`` returns, by default ``max_i sum_j |J_ij| |z_j|``). The
      floor scales with the terms, not with ``|z|``, because large cancelling forces
      (stiff springs, large multipliers) keep the residual at ``eps`` times them. The
      window is :data:`EXACT_WINDOW` floors for the exact Jacobian (quadratic: a stall
      means round-off) and :data:`SIMPLIFIED_WINDOW` for simplified Newton, whose rate
      nears 1 near singular configurations, so that a stall far above round-off hands
      over to the fallback instead;
    - exact dense Jacobian only: an iteration contracted the residual by at least
      :data:`QUADRATIC` to within :data:`AT_FLOOR` floors. Waiting for a stall there costs
      iterations that learn nothing, and under ``jax.vmap`` every lane pays the slowest
      lane's count. The contraction is required because a floor estimated from ``terms``
      can lie far above the residual's rounding when the iteration is in trouble (the
      undamped index-3 generalized-alpha method, ``tests/test_genalpha.py``). Simplified
      Newton does not take this exit: its ``terms`` bound the rounding of every datum the
      residual depends on, and stopping at twice that floor moves solutions of chaotic
      problems enough to lose a step;
    - simplified Newton only: a residual already within the window reaches the floor
      (``r_k <= floor`` after ``r_{k-1} <= window floor``); its halving there is the
      rounding of the last units.

    ``tol`` below round-off (such as 1e-16) means "iterate to round-off"; a larger ``tol``
    does not widen the window.

    Fallback: where simplified Newton does not converge (it stalls above the window,
    diverges, meets a non-finite residual or uses its ``max_iter`` corrections), Newton
    with the exact Jacobian (:func:`krylov_linear`; the dense :func:`dense_linear` after
    :func:`frozen_linear`) takes over for up to ``max_iter`` more
    from the better of ``z0`` and the last finite iterate, preconditioned by ``refactor(z)``
    where given (the approximate Jacobian factorised afresh: the frozen one may be nearly
    singular) and by ``linear`` otherwise. The structured path is thus as robust as the
    dense one, and a step that simplified Newton solves costs no more at run time; inside
    :func:`deferred_fallback` the fallback is left out of the program.

    ``z`` may be any pytree of arrays and ``residual`` returns one of its structure; every
    norm is the max-norm over all entries. Simplified Newton works on the blocks as they
    are (stage positions, momenta, multipliers in separate arrays): packing them into one
    vector costs a slice and a concatenation per iteration, more than the arithmetic on
    small systems. Newton with the exact Jacobian works on the leaves flattened into one
    vector (``jax.flatten_util.ravel_pytree``), in their order.

    ``rows`` (a pytree of the residual's structure, each leaf a scalar or an array of its
    row's shape) equilibrates the dense exact Jacobian's solve: its rows are divided by
    them before the factorisation. The correction is the same; the stop reads the
    residual as ``residual`` returns it.

    ``anderson`` mixes each simplified-Newton correction with the previous one (Anderson
    acceleration of depth one; Anderson 1965, J. ACM 12:547-560; Walker and Ni 2011, SIAM
    J. Numer. Anal. 49:1715-1735): with ``dr = r_k - r_{k-1}`` and ``gamma = <dr, r_k> /
    <dr, dr>`` (Euclidean over all entries), ``z_{k+1} = z_k + dz_k - gamma (z_k - z_{k-1}
    + dz_k - dz_{k-1})``, the correction from the combination of the last two iterates
    whose linearised residual is least. Simplified Newton contracts the error by the
    spectral radius ``theta`` of ``I - J_0^{-1} J``; where ``theta`` is not small (a
    stiffness the frozen matrix leaves out), the mixing removes much of the error that one
    correction leaves. The fixed point, the stop and the fallback are unchanged, so the
    solution is the same to round-off.

    Returns the iterate, whether it converged, the number of iterations (each one
    correction) and the final residual norm.
    """

    # The loop's state is (z, r, |r|, done, go, iterations): each iteration decides
    # whether it was the last as it computes the new residual, so that the loop's
    # condition only reads a flag: under vmap, norms and tests recomputed in a separate
    # condition are more passes over every lane per iteration.
    def verdict(z, r_norm, r_prev, dz_norm, terms, it, limit, window, contracting, quick):
        floor = EPS * (1.0 + terms)
        halved = r_norm <= 0.5 * r_prev
        if contracting:
            # Within the window already, a residual that reaches the floor has halved by
            # the rounding of its last units: another iteration cannot gain (docstring).
            halved = halved & ~((r_norm <= floor) & (r_prev <= window * floor))
        stalled = ~halved & (r_norm <= window * floor)
        done = (r_norm <= tol) | (dz_norm <= 4 * EPS * (1.0 + max_norm(z))) | stalled
        if quick:
            # Only after an iteration: the start's terms are |z0|, not |J| |z|, no floor.
            done = done | ((r_norm <= AT_FLOOR * floor) & (r_norm <= QUADRATIC * r_prev)
                           & jnp.isfinite(r_prev))
        go = (~done) & (it < limit) & jnp.isfinite(r_norm)
        # Simplified Newton stops where it no longer halves the residual (docstring).
        return done, (go & (r_norm <= 0.5 * r_prev)) if contracting else go

    def iterate(residual, z, r, it, linear, limit, window, contracting, quick=False,
                mixed=False):
        r_norm = max_norm(r)
        done, go = verdict(z, r_norm, jnp.inf, jnp.inf, max_norm(z), it, limit, window,
                           contracting, quick)
        # The previous iterate, its residual and its correction (``anderson``); none yet.
        history = ((z, r, jax.tree_util.tree_map(jnp.zeros_like, z), jnp.array(False))
                   if mixed else ())

        def body(state):
            z, r, r_norm, _, _, it, history = state
            dz, terms = linear(z, r)
            step = dz
            if mixed:
                step, history = anderson_step(z, r, dz, history)
            z = jax.tree_util.tree_map(jnp.add, z, step)
            r = residual(z)
            r_new = max_norm(r)
            return (z, r, r_new,
                    *verdict(z, r_new, r_norm, max_norm(dz), terms, it + 1, limit, window,
                             contracting, quick), it + 1, history)

        *state, _ = jax.lax.while_loop(lambda state: state[4], body,
                                       (z, r, r_norm, done, go, it, history))
        return tuple(state)

    def exact_iterate(z, r, it, linear, limit):
        # Newton with the exact Jacobian works on one flat vector (a dense Jacobian, a
        # Krylov solve), in the order of the leaves of z and of r.
        x, unravel = ravel_pytree(z)
        rx, unravel_r = ravel_pytree(r)

        def flat(x):
            return ravel_pytree(residual(unravel(x)))[0]

        if linear is None:
            weights = None if rows is None else ravel_pytree(jax.tree_util.tree_map(
                lambda w, a: jnp.broadcast_to(w, jnp.shape(a)), rows, r))[0]
            solver = dense_linear(flat, weights)
        else:
            def precondition(x, rx):
                dz, terms = linear(unravel(x), unravel_r(rx))
                return ravel_pytree(dz)[0], terms

            solver = krylov_linear(flat, precondition)
        x, rx, *rest = iterate(flat, x, rx, it, solver, limit, EXACT_WINDOW, False,
                               quick=linear is None)
        return (unravel(x), unravel_r(rx), *rest)

    def result(state):
        z, _, r_norm, done, _, it = state
        finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(a))
                                    for a in jax.tree_util.tree_leaves(z)]))
        return NewtonResult(z, done & finite, it, r_norm)

    r0 = residual(z0)
    dense = linear is None
    if dense and ravel_pytree(z0)[0].size < FROZEN_MIN:
        return result(exact_iterate(z0, r0, 0, None, max_iter))
    if dense:
        linear = frozen_linear(residual, z0, rows)
    state = iterate(residual, z0, r0, 0, linear, max_iter, SIMPLIFIED_WINDOW, True,
                    mixed=anderson)
    if _deferred.get():
        return result(state)

    # Simplified Newton did not converge: the exact Jacobian takes over (docstring).
    def exact(state):
        z, r, r_norm, _, _, it = state
        better = jnp.isfinite(r_norm) & (r_norm < max_norm(r0))

        def pick(new, old):
            return jax.tree_util.tree_map(lambda a, b: jnp.where(better, a, b), new, old)

        z = pick(z, z0)
        precondition = None if dense else linear if refactor is None else refactor(z)
        return exact_iterate(z, pick(r, r0), it, precondition, it + max_iter)

    simplified = result(state).converged
    return result(rarely(~simplified, exact, state, state))
