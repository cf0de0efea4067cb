"""Newton's method for the implicit stage equations, compiled with ``lax.while_loop``."""

from __future__ import annotations

import contextlib
import contextvars
import functools
from typing import Any, Callable, Iterator, NamedTuple

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from linalg.dense import rarely, solve
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

    The fallback (:func:`krylov_linear`) is most of a structured time loop's program and is
    rarely taken: XLA took 64 s to compile RATTLE's loop on ``rigid-chain:N=4`` with it and
    21 s without (``benchmarks/perf/compile_profile.py``, one core, load about 1). So the
    time loop compiles its steps this way first, and the loop with the fallback only when a
    step fails, continuing from that step (:func:`integrators.loop.march`)."""
    token = _deferred.set(True)
    try:
        yield
    finally:
        _deferred.reset(token)


def max_norm(tree) -> jax.Array:
    """``max |x_i|`` over every entry of every array in ``tree``."""
    return functools.reduce(jnp.maximum, (jnp.max(jnp.abs(a))
                                          for a in jax.tree_util.tree_leaves(tree)))


def dense_linear(residual: Callable[[jax.Array], jax.Array]) -> Linear:
    """Newton's correction with the dense autodiff Jacobian, solved by :func:`solve`."""

    def linear(z, r):
        J = jax.jacfwd(residual)(z)
        return solve(J, -r), jnp.max(jnp.abs(J) @ jnp.abs(z))

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
    longer compiled into one native kernel, and RATTLE's steps on chain:N=16 ran eight
    times slower (0.13 s against 0.017 s per solve, measured with
    ``benchmarks/perf/compile_profile.py``); BiCGSTAB (JAX's, then) left them as fast, and
    XLA's compilation of the loop grew from 2.1 s to 4.1 s.
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
           refactor: Callable[[Any], Linear] | None = None) -> NewtonResult:
    """Solve ``residual(z) = 0`` by Newton's method.

    ``linear`` gives each correction; by default the exact autodiff Jacobian, densely
    (:func:`dense_linear`). A structured method passes an approximate Jacobian instead
    (simplified Newton: one factorisation per step, linear convergence), under the same
    convergence test but for one exit (below). Where simplified Newton does not converge
    (it stops halving the residual above its round-off floor, diverges, meets a non-finite
    residual or runs out of its ``max_iter`` corrections), Newton's method with the exact
    Jacobian takes over for up to ``max_iter`` more (:func:`krylov_linear`), from the better
    of ``z0`` and the last finite iterate, preconditioned by ``refactor(z)`` at that
    iterate where given (the approximate Jacobian factorised afresh: the frozen one may be
    nearly singular, as at a singular configuration of a mechanism) and by ``linear``
    otherwise; only when that fails too has the solve failed. The structured path is then
    as robust as the dense one, whose Newton has the exact Jacobian throughout, and a step
    that simplified Newton solves costs no more at run time (the compiled program holds
    both iterations: see :func:`krylov_linear` for what that costs; inside
    :func:`deferred_fallback` it holds simplified Newton alone, and a time loop compiles
    the fallback only for a run that needs it).

    Converged when ``||residual(z)||_inf <= tol``. The test is on the residual, not on the
    correction, so that ``tol`` bounds the constraint violation left in the solution. More
    exits count as converged because no further iteration can gain anything: the
    correction is at round-off (``||dz||_inf <= 4 eps (1 + ||z||_inf)``); the residual has
    stopped contracting (less than halved) within a window of its round-off floor
    ``eps (1 + terms)``, with ``terms`` the magnitude of the terms the residual is computed
    from (the second value ``linear`` returns; ``max_i sum_j |J_ij| |z_j|`` with the last
    Jacobian ``J`` by default); and, with the exact dense Jacobian, an iteration contracted
    the residual by at least :data:`QUADRATIC` to within :data:`AT_FLOOR` times that floor.
    Scaling with the terms, not with ``|z|`` alone, matters where large forces cancel (stiff
    springs, large multipliers): there the residual cannot fall below ``eps`` times those
    forces. A ``tol`` below round-off (such as 1e-16) therefore means "iterate to
    round-off"; a larger ``tol`` does not widen the window.

    A residual that quadratic convergence brought to its floor ends the iteration at once:
    waiting for it to stop halving cost one more iteration to learn nothing, and it halves
    by chance at the floor (rounding moves it by a unit), which cost another. RATTLE on the
    pendulum took 2.58 iterations per step without this exit, 2.00 with it. Under
    ``jax.vmap`` a Newton loop runs until its slowest lane is done, so an ensemble pays the
    worst lane's count at every step: over 1024 lanes 4.01 iterations per step without it,
    2.0 to 2.2 with it. The contraction is part of the test because a floor estimated from
    ``terms`` can be far above the residual's rounding where the iteration is in trouble:
    on the undamped index-3 generalized-alpha method, whose multipliers blow up
    (``tests/test_genalpha.py``), a residual still contracting slowly fell below it, and
    the run went on with velocity errors of 1e5 instead of failing. Simplified Newton and
    its fallback do not take this exit: their ``terms`` bound the rounding of every datum
    the residual depends on, a floor that can lie well above the residual's own rounding,
    and stopping at twice it moved the structured path's solutions enough that the
    perturbed, chaotic ``sps-lattice:N=16,K=8,perturb=0.01`` (RATTLE, h = 0.005) met a
    step without a solution at t = 10.3 instead of running to t = 20.

    Simplified Newton does end where a residual already within the window reaches the
    floor itself (``r_k <= floor`` after ``r_{k-1} <= window floor``): the halving seen
    there is the rounding of the last units (2.2e-16 to 1.1e-16), and waiting for a
    residual that does not halve cost one or two iterations more, more often on some lanes
    than on others. The residual this accepts is at most the floor, below what the stall
    test accepts, and only after one already in the window. lobatto3ab3 on the pendulum
    (h = 0.01, 1024 lanes, 1000 steps) took 5.43 iterations per lane and step with the
    slowest lane at 6.78 on average, and 4.79 and 5.00 with this exit; 1024 lanes ran 5.3e5
    to 5.7e5 lane-steps/s against 4.0e5 to 4.2e5 (load 1.0, two runs each); RATTLE on the
    perturbed ``sps-lattice`` (``benchmarks.perf.robustness``, structured path) finished as
    before, with 8.53 iterations per step against 9.58.

    The window is :data:`EXACT_WINDOW` times the floor for Newton with the exact Jacobian,
    which converges quadratically, so that a residual that stops halving has reached what
    the arithmetic allows and the window only covers what the floor estimate leaves out.
    It is :data:`SIMPLIFIED_WINDOW` times the floor for simplified Newton, which converges
    linearly at a rate that nears 1 where the Jacobian moves away from the frozen one (near
    singular configurations): a residual that stops halving there may be far above
    round-off, so it is accepted only close to a floor that ``linear`` bounds completely
    (including the rounding of data the residual depends on besides ``z``), and above it
    the exact Jacobian takes over at once.

    ``z`` may be one array or a tuple (any pytree) of arrays, and ``residual`` returns one
    of its own structure; every norm is the max-norm over all their entries. Simplified
    Newton works on the blocks as they are, so that a method keeps its unknowns (stage
    positions, momenta, multipliers) in separate arrays: packed into one vector, every
    iteration sliced it and concatenated the residual and the correction, and on small
    systems that cost more than the arithmetic. lobatto3ab3's step took 1.75 to 1.84 us
    packed and 0.97 to 1.05 us in blocks on the pendulum, 1.18 to 1.93 against 0.87 to 1.11
    us on sps-receiver (one core, two runs each, scratch script). Newton with the exact
    Jacobian (the dense path, the fallback) works on the leaves flattened into one vector
    (``jax.flatten_util.ravel_pytree``), in their order.

    Returns the iterate, whether it converged, the number of iterations (each one
    correction) and the final residual norm.
    """

    # The loop's state is (z, r, |r|, done, go, iterations): each iteration decides
    # whether it was the last as it computes the new residual, so that the loop's
    # condition only reads a flag. Under vmap the norms and tests recomputed in a
    # separate condition were more passes over every lane per iteration: 1024 lanes of
    # RATTLE's step on the pendulum ran 2.5e7 lane-steps/s with them, 3.0e7 without
    # (scratch script, one core; one trajectory alike either way).
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

    def iterate(residual, z, r, it, linear, limit, window, contracting, quick=False):
        r_norm = max_norm(r)
        done, go = verdict(z, r_norm, jnp.inf, jnp.inf, max_norm(z), it, limit, window,
                           contracting, quick)

        def body(state):
            z, r, r_norm, _, _, it = state
            dz, terms = linear(z, r)
            z = jax.tree_util.tree_map(jnp.add, z, dz)
            r = residual(z)
            r_new = max_norm(r)
            return (z, r, r_new,
                    *verdict(z, r_new, r_norm, max_norm(dz), terms, it + 1, limit, window,
                             contracting, quick), it + 1)

        return jax.lax.while_loop(lambda state: state[4], body,
                                  (z, r, r_norm, done, go, it))

    def exact_iterate(z, r, it, linear, limit):
        # Newton with the exact Jacobian works on one flat vector (a dense Jacobian, a
        # Krylov solve), in the order of the leaves of z and of r.
        x, unravel = ravel_pytree(z)
        rx, unravel_r = ravel_pytree(r)

        def flat(x):
            return ravel_pytree(residual(unravel(x)))[0]

        if linear is None:
            solver = dense_linear(flat)
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
    if linear is None:
        return result(exact_iterate(z0, r0, 0, None, max_iter))
    state = iterate(residual, z0, r0, 0, linear, max_iter, SIMPLIFIED_WINDOW, True)
    if _deferred.get():
        return result(state)

    # Simplified Newton did not converge: the exact Jacobian takes over (docstring).
    def exact(state):
        z, r, r_norm, _, _, it = state
        better = jnp.isfinite(r_norm) & (r_norm < max_norm(r0))

        def pick(new, old):
            return jax.tree_util.tree_map(lambda a, b: jnp.where(better, a, b), new, old)

        z = pick(z, z0)
        precondition = linear if refactor is None else refactor(z)
        return exact_iterate(z, pick(r, r0), it, precondition, it + max_iter)

    simplified = result(state).converged
    return result(rarely(~simplified, exact, state, state))
