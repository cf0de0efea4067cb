"""Radau IIA (three stages, order 5) with step-size control, on the index-3 and the
stabilised index-2 forms of the equations of motion, in a compiled loop.

The equations are written as a DAE with a singular, state-dependent mass,
``B(y) y' = F(t, y)``, through its residual ``R(t, y, y') = B(y) y' - F(t, y)``: IDA's
stabilised index-2 residual (:func:`integrators.ida.ggl_residual`) or the index-3 one
here (:func:`index3_residual`). Its Jacobians come from autodiff of ``R`` in one place
(:func:`iteration_blocks`). The loop runs step attempts inside ``lax.while_loop`` in
chunks of a bounded number of accepted steps, which :class:`integrators.record.Recorder`
measures.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass
from functools import lru_cache, partial
from typing import Callable, ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from numpy.polynomial import Polynomial

from integrators.base import Failure, Grid, Integrator
from integrators.ida import EXCLUDED, consistent_values, ggl_residual
from integrators.loop import CACHE_SIZE, put
from integrators.record import Recorder, batch_length
from linalg.compiled import compile_lifted
from linalg.dense import LU, RANK_RTOL, basic_solve, power_of_two_scale
from problems.case import Case
from problems.mechanics import Mechanics

EPS = float(np.finfo(np.float64).eps)

#: Tolerance of the tableau identities (coefficients from polynomial algebra in double
#: precision, exact to a few ulps of the largest, ``|A^-1| ~ 10``).
TABLEAU_TOL = 1e-12


@dataclass(frozen=True)
class RadauTableau:
    """The three-stage Radau IIA method and what its simplified Newton iteration and its
    error estimate need, computed from the collocation conditions and checked.

    Nodes ``c``: the Radau right points on [0, 1], roots of
    ``P_3(2x - 1) - P_2(2x - 1)`` (``(4 - sqrt 6)/10, (4 + sqrt 6)/10, 1``);
    ``a_ij = int_0^{c_i} l_j`` (collocation), so the last row is ``b`` (stiffly accurate).
    ``A^{-1}`` has one real eigenvalue ``gamma`` and a complex pair ``alpha +- i beta``;
    with ``T = [u, x, y]`` (``u`` the real eigenvector, ``x + i y`` the one of
    ``alpha + i beta``), ``T^{-1} A^{-1} T = [[gamma, 0, 0], [0, alpha, beta],
    [0, -beta, alpha]]``. ``e`` gives the embedded solution's difference from ``y_{n+1}``:
    ``y_hat - y_{n+1} = gamma_0 h y'_n + sum_j e_j Z_j`` with ``gamma_0 = 1/gamma`` and the
    order-3 weights ``b_hat`` on the nodes ``(0, c)`` (Hairer and Wanner, *Solving
    Ordinary Differential Equations II*, 1996, section IV.8).
    """

    c: np.ndarray
    A: np.ndarray
    A_inv: np.ndarray
    gamma: float
    alpha: float
    beta: float
    T: np.ndarray
    T_inv: np.ndarray
    e: np.ndarray

    def __post_init__(self):
        c, A, Ai, T, Ti = self.c, self.A, self.A_inv, self.T, self.T_inv
        lam = np.array([[self.gamma, 0, 0], [0, self.alpha, self.beta],
                        [0, -self.beta, self.alpha]])
        gamma0 = 1.0 / self.gamma
        b_hat = (self.e @ A) + A[-1]  # e = A^-T (b_hat - b)
        checks = {
            "row sums equal c": np.max(np.abs(A.sum(1) - c)),
            # Order 5 = 2s - 1: the weights (last row) integrate degree 4 exactly.
            "quadrature exact to degree 4":
                max(abs(A[-1] @ c ** k - 1 / (k + 1)) for k in range(5)),
            # C(3): a_ij integrate polynomials of degree 2 exactly on [0, c_i].
            "collocation C(3)": max(np.max(np.abs(A @ c ** k - c ** (k + 1) / (k + 1)))
                                    for k in range(3)),
            "A^-1 is the inverse": np.max(np.abs(Ai @ A - np.eye(3))),
            "T^-1 A^-1 T is block diagonal": np.max(np.abs(Ti @ Ai @ T - lam)),
            "embedded weights of order 3": max(
                abs(gamma0 * (k == 0) + b_hat @ c ** k - 1 / (k + 1)) for k in range(3)),
        }
        for name, err in checks.items():
            if not err <= TABLEAU_TOL:
                raise ValueError(f"Radau IIA tableau: {name} fails (error {err:.2e})")


@lru_cache(maxsize=None)
def radau_iia() -> RadauTableau:
    """The three-stage Radau IIA tableau (:class:`RadauTableau`)."""
    nodes = (Polynomial([-1, 2]) ** 3 * 2.5 - Polynomial([-1, 2]) * 1.5
             - (Polynomial([-1, 2]) ** 2 * 1.5 - 0.5))  # P_3(2x - 1) - P_2(2x - 1)
    c = np.sort(nodes.roots().real)
    c[-1] = 1.0
    A = np.zeros((3, 3))
    for j in range(3):
        others = np.delete(c, j)
        integral = (Polynomial.fromroots(others) / np.prod(c[j] - others)).integ()
        A[:, j] = integral(c) - integral(0.0)
    A_inv = np.linalg.inv(A)
    values, vectors = np.linalg.eig(A_inv)
    real = int(np.argmin(np.abs(values.imag)))
    pair = int(np.argmax(values.imag))
    T = np.stack([vectors[:, real].real, vectors[:, pair].real, vectors[:, pair].imag], 1)
    gamma = float(values[real].real)
    gamma0 = 1.0 / gamma
    # The embedded weights: gamma_0 on y'_n and b_hat on the stages, order 3 on (0, c).
    b_hat = np.linalg.solve(np.vander(c, increasing=True).T,
                            1.0 / np.arange(1, 4) - gamma0 * (np.arange(3) == 0))
    e = A_inv.T @ (b_hat - A[-1])
    return RadauTableau(c, A, A_inv, gamma, float(values[pair].real), float(values[pair].imag),
                        T, np.linalg.inv(T), e)


def index3_residual(mech: Mechanics):
    """Index-3 form, ``y = (q, v, lam)``:

    .. math::

        0 = q' - v, \\quad 0 = M(q) v' - f(t, q, v) + G^T \\lambda, \\quad 0 = g(q, t),

    with ``f`` the full right-hand side (:meth:`Mechanics.force`). Its components have
    index 1 (``q``), 2 (``v``) and 3 (``lam``).
    """
    n, m = mech.n, mech.m

    def R(t, y, yp):
        q, v, lam = y[:n], y[n:2 * n], y[2 * n:2 * n + m]
        return jnp.concatenate([
            yp[:n] - v,
            mech.mass_times(q, yp[n:2 * n]) - mech.force(t, q, v) + mech.GT(q, t, lam),
            mech.g(q, t),
        ])

    return R


class Formulation(NamedTuple):
    """A DAE form: its residual ``R(t, y, y')``, its multiplier blocks of size ``m``, the
    index of ``q``, ``v`` and each multiplier block (the error of a component of index
    ``k`` is scaled by ``h^(k-1)``), and the constraint levels among its equations."""

    residual: Callable[[Mechanics], Callable]
    multiplier_blocks: int
    index: tuple[int, ...]
    enforces: tuple[str, ...]

    def indices(self, n: int, m: int) -> np.ndarray:
        """The index of every component of ``y``."""
        sizes = (n, n) + (m,) * self.multiplier_blocks
        return np.concatenate([np.full(k, i) for k, i in zip(sizes, self.index)])


#: ``formulation`` option -> DAE form.
FORMULATIONS: dict[str, Formulation] = {
    "index3": Formulation(index3_residual, 1, (1, 2, 3), ("position",)),
    "ggl": Formulation(ggl_residual, 2, (1, 1, 2, 2), ("position", "velocity")),
}


def combine(C, X):
    """``C @ X`` for coefficients ``C`` (3 x 3, or 3) and the stages ``X`` (3 x N), written
    as sums of scaled rows: XLA:CPU hands a matrix product of this shape to a library
    kernel once ``N`` is a few tens, a separate call in every Newton iteration, where the
    sums fuse with the elementwise work around them."""
    C = jnp.asarray(C)
    if C.ndim == 1:
        return C[0] * X[0] + C[1] * X[1] + C[2] * X[2]
    return jnp.stack([combine(row, X) for row in C])


def stage_residual(R, t, y, h, Z):
    """The collocation equations for the stage increments ``Z`` (3 x N) of a step of size
    ``h`` from ``(t, y)``: ``R(t + c_i h, y + Z_i, K_i)`` with the stage derivatives
    ``K = (A^{-1} Z)/h``, stacked (3 x N)."""
    tab = radau_iia()
    return jax.vmap(R)(t + jnp.asarray(tab.c) * h, y + Z, combine(tab.A_inv, Z) / h)


def iteration_blocks(R, t, y, yp):
    """``J = dR/dy`` at ``(t, y, y')`` and ``B = dR/dy'`` (the singular mass ``B(y)``), by
    forward-mode autodiff of the residual."""
    J = jax.jacfwd(lambda z: R(t, z, yp))(y)
    B = jax.jacfwd(lambda w: R(t, y, w))(yp)
    return J, B


class Params(NamedTuple):
    """The run's numbers, traced (one compilation serves every tolerance and horizon);
    ``fnewt`` is the tolerance of Newton's test on the scaled increments
    (:attr:`RadauIIA.fnewt`)."""

    t_end: jax.Array
    rtol: jax.Array
    atol: jax.Array
    multiplier_atol: jax.Array
    thet: jax.Array
    fnewt: jax.Array
    newton_tol: jax.Array
    safety: jax.Array
    first_step: jax.Array
    max_step: jax.Array
    max_steps: jax.Array


class LoopState(NamedTuple):
    """What the loop carries between step attempts.

    ``frozen`` is what the iteration matrices were last evaluated from (``fresh`` while
    that is the current ``y``; :class:`DenseStages`, :class:`SchurStages`), ``factors``
    their factorisations for the step ``h_lu``; ``Z, h_z`` the stage
    increments and step of the last accepted step (the starting values of the next come
    from its collocation polynomial); ``f0 = F(t, y)``, ``w = y'(t)``; ``work`` the counts
    of :data:`WORK`; ``h_acc, err_acc`` the last accepted step and its error (the
    predictive controller's memory); ``cause`` the worst reason (:data:`CAUSES`) among
    the rejections since the last accepted step, which an underflow reports.
    """

    t: jax.Array
    h: jax.Array
    y: jax.Array
    w: jax.Array
    f0: jax.Array
    frozen: tuple
    factors: tuple
    h_lu: jax.Array
    fresh: jax.Array
    need_jac: jax.Array
    Z: jax.Array
    h_z: jax.Array
    faccon: jax.Array
    h_acc: jax.Array
    err_acc: jax.Array
    first: jax.Array
    reject: jax.Array
    n_accepted: jax.Array
    work: jax.Array
    cause: jax.Array
    code: jax.Array


#: The work counted in :class:`LoopState`'s ``work``: the COUNTERS of
#: :mod:`integrators.base` but ``n_steps``, and the LU decompositions (pairs).
WORK = ("n_rejected", "n_f_evals", "n_jac_evals", "n_newton", "n_lin_solves", "n_lu")

#: Newton's contraction factor up to which the Jacobian is kept for the next step (the
#: default of :attr:`RadauIIA.thet`, RADAU5's ``WORK(3)``), and the step-size ratios within
#: which the step (and the factorisations) are kept (RADAU5's, Hairer and Wanner 1996,
#: section IV.8). RADAU5's default ``thet`` of 1e-3 lies below the contraction that Newton
#: reaches here even with a Jacobian from the step's start, so it re-evaluated the
#: Jacobian, and refactorised, at nearly every step; its documentation suggests 0.1 where
#: Jacobians are costly. At 0.05 a Jacobian serves several steps while the step count and
#: the final errors barely move, and slow contractions still ask for a fresh one.
THETA_KEEP = 0.05
KEEP_RATIOS = (1.0, 1.2)
#: Bounds of the ratio of a new step size to the last.
FACTOR_MIN, FACTOR_MAX = 0.2, 8.0
#: Once RADAU5's test on the scaled increments passes, Newton goes on (at most
#: ``NEWTON_EXTRA`` iterations) until they are ``NEWTON_TIGHT`` times smaller, the residual
#: is at its round-off floor, or the iteration stops contracting. The index scaling lets
#: the velocities' iteration error be ``fnewt (atol + rtol |v|) / h`` per step, and the
#: positions integrate it: on andrews at rtol = 1e-10 (index 3) that alone left a final
#: error of 2.0e-8, ten times the reference's floor, at the same steps.
NEWTON_TIGHT, NEWTON_EXTRA = 1e-2, 2
#: Steps below this many ulps of ``t`` have underflowed.
UNDERFLOW_ULPS = 16
#: Why attempts were rejected, from the least to the most telling: a step that
#: underflows reports the last of these that its rejections met.
CAUSES = (Failure.NONE, Failure.UNDERFLOW, Failure.NEWTON, Failure.NON_FINITE)


#: Largest stage system factorised by the unrolled elimination of :func:`inline_lu_factor`
#: rather than by LAPACK (and solved by unrolled substitutions also outside Newton's loop,
#: :func:`_solve`): a library call is opaque to XLA, so each one costs a call and a copy,
#: which for a few unknowns is most of its price; unrolled, the elimination is ``N^3/3``
#: multiply-adds fused into the loop body, and its code grows like ``N^2``.
INLINE_MAX = 12


def inline_lu_factor(A: jax.Array) -> LU:
    """:func:`linalg.dense.lu_factor` (the same power-of-two equilibration ``D_r A D_c``
    and rank test) by Gaussian elimination with partial pivoting unrolled over the ``N``
    columns, in plain array operations; ``piv`` is the row permutation (``P A = L U`` with
    ``(P A)_i = A_{piv_i}``), not LAPACK's sequence of swaps. For :func:`inline_lu_solve`."""
    N = A.shape[0]
    r = power_of_two_scale(jnp.max(jnp.abs(A), axis=1))
    c = power_of_two_scale(jnp.max(jnp.abs(A * r[:, None]), axis=0))
    As = A * r[:, None] * c[None, :]
    lu, perm, rows = As, jnp.arange(N), jnp.arange(N)
    for k in range(N):
        p = jnp.argmax(jnp.where(rows >= k, jnp.abs(lu[:, k]), -1.0))
        swap = jnp.where(rows == k, p, jnp.where(rows == p, k, rows))
        lu, perm = lu[swap], perm[swap]
        l = lu[k + 1:, k] / lu[k, k]
        lu = lu.at[k + 1:, k].set(l).at[k + 1:, k + 1:].add(-l[:, None] * lu[k, k + 1:])
    pivots = jnp.abs(jnp.diag(lu))
    deficient = ~(jnp.min(pivots) > RANK_RTOL * jnp.max(pivots))
    return LU(lu, perm, As, r, c, deficient)


def looped_basic_solve(A: jax.Array, b: jax.Array) -> jax.Array:
    """:func:`linalg.dense.basic_solve` (the basic solution, ``A`` real or complex, ``b`` a
    vector) without LAPACK, in two loops: Householder QR with column pivoting (the
    remaining column of largest norm below row ``k`` swapped in, the first of equals, as
    LAPACK's ``xGEQP3``), then back substitution with the unknowns of columns whose
    ``|R_kk| <= RANK_RTOL |R_00|`` set to zero.

    For the rank-deficient branch of :func:`inline_lu_solve`, so that the small systems'
    loop is all fused code; looped rather than unrolled, its code does not grow with
    ``N``, and its speed, in a branch that is rarely taken, does not matter."""
    N = A.shape[0]
    rows = jnp.arange(N)

    def reflect(k, carry):
        R, y, perm = carry
        below = rows >= k
        norms = jnp.sum(jnp.where(below[:, None], jnp.abs(R) ** 2, 0.0), axis=0)
        j = jnp.argmax(jnp.where(below, norms, -1.0))
        swap = jnp.where(rows == k, j, jnp.where(rows == j, k, rows))
        R, perm = R[:, swap], perm[swap]
        x = jnp.where(below, R[:, k], 0.0)
        norm = jnp.sqrt(jnp.sum(jnp.abs(x) ** 2))
        # H = I - 2 v v^H / (v^H v) maps x to alpha e_k, alpha of the phase opposite to
        # x_k's (no cancellation in v_k).
        xk = R[k, k]
        phase = jnp.where(xk != 0, xk / jnp.where(xk != 0, jnp.abs(xk), 1.0), 1.0)
        v = x - (rows == k) * (-phase * norm)
        vv = jnp.sum(jnp.abs(v) ** 2)
        # A zero column (vv = 0) needs no reflection.
        scale = jnp.where(vv > 0, 2.0 / jnp.where(vv > 0, vv, 1.0), 0.0)
        return (R - scale * jnp.outer(v, v.conj() @ R), y - scale * v * (v.conj() @ y),
                perm)

    R, y, perm = jax.lax.fori_loop(0, N - 1, reflect, (A, b, rows))
    d = jnp.abs(jnp.diag(R))
    keep = d > RANK_RTOL * d[0]

    def substitute(k, x):
        i = N - 1 - k
        return x.at[i].set(jnp.where(keep[i], (y[i] - R[i] @ x)
                                     / jnp.where(keep[i], R[i, i], 1.0), 0.0))

    x = jax.lax.fori_loop(0, N, substitute, jnp.zeros_like(y))
    return jnp.zeros_like(x).at[perm].set(x)


def inline_lu_solve(F: LU, b: jax.Array) -> jax.Array:
    """``A^{-1} b`` for ``F = inline_lu_factor(A)`` and a vector ``b``: the triangular
    solves unrolled; the basic solution of :func:`linalg.dense.basic_solve` where ``A``
    is rank deficient (the one rank policy), by :func:`looped_basic_solve`."""
    N = b.shape[0]
    rb = b * F.row
    x = rb[F.piv]
    for i in range(1, N):
        # x_i - l x, not x_i + (-l) x: the same number, but -l would be a loop-invariant
        # operation that XLA moves out of Newton's loop, one separate kernel per row.
        x = x.at[i].set(x[i] - F.lu[i, :i] @ x[:i])
    for i in reversed(range(N)):
        x = x.at[i].set((x[i] - F.lu[i, i + 1:] @ x[i + 1:]) / F.lu[i, i])
    return _unless_deficient(F, looped_basic_solve, x, rb)


def _unless_deficient(F: LU, basic, x: jax.Array, rb: jax.Array) -> jax.Array:
    """``x`` (the equilibrated system's solution by the LU factors), or, where ``F`` is rank
    deficient, ``basic(F.scaled, rb)``: the basic solution (the one rank policy of
    :mod:`linalg.dense`), unscaled by the column scaling.

    ``lax.cond``, not :func:`linalg.dense.rarely`: the Radau loop is never mapped over
    lanes, so ``cond`` evaluates only the branch taken, whereas the one-pass loop of
    ``rarely`` costs at every solve, more than the triangular solves themselves."""
    return jax.lax.cond(F.deficient, basic, lambda A, b: x, F.scaled, rb) * F.col


def lapack_lu_factor(A: jax.Array) -> LU:
    """:func:`linalg.dense.lu_factor` (LAPACK's LU of the equilibrated ``D_r A D_c``, the
    same rank test) with ``piv`` the row permutation, as :func:`inline_lu_factor` gives it:
    a solve inside the loop then applies it directly, where LAPACK's sequence of swaps
    would be turned into a permutation at every solve."""
    r = power_of_two_scale(jnp.max(jnp.abs(A), axis=1))
    c = power_of_two_scale(jnp.max(jnp.abs(A * r[:, None]), axis=0))
    As = A * r[:, None] * c[None, :]
    lu, _, perm = jax.lax.linalg.lu(As)
    pivots = jnp.abs(jnp.diag(lu))
    deficient = ~(jnp.min(pivots) > RANK_RTOL * jnp.max(pivots))
    return LU(lu, perm, As, r, c, deficient)


def _factor(J, B, h, tab: RadauTableau):
    """LU of the real ``gamma/h B + J`` and of the complex ``(alpha - i beta)/h B + J``
    (unrolled up to :data:`INLINE_MAX` unknowns, else LAPACK's)."""
    factor = inline_lu_factor if J.shape[0] <= INLINE_MAX else lapack_lu_factor
    E1 = factor(tab.gamma / h * B + J)
    E2 = factor(((tab.alpha - 1j * tab.beta) / h) * B + J.astype(jnp.complex128))
    return E1, E2


def _solve(F: LU, r: jax.Array, newton: bool = True) -> jax.Array:
    """``A^{-1} r`` with a factorisation from :func:`_factor`.

    Inside Newton's loop (``newton``) and for small systems, by the unrolled substitutions
    of :func:`inline_lu_solve`: with no library call in its body, XLA:CPU compiles the
    Newton loop into one kernel, where each call would otherwise cost a dispatch of its
    own and split the elementwise work around it into separate kernels. Outside it (the
    error estimate, in a step attempt that LAPACK's factorisations already split), by
    LAPACK's triangular solves, two calls where the unrolled substitutions would be ``2N``
    separate kernels; :func:`linalg.dense.basic_solve` where ``A`` is rank deficient."""
    if newton or r.shape[0] <= INLINE_MAX:
        return inline_lu_solve(F, r)
    rb = r * F.row
    x = jax.lax.linalg.triangular_solve(F.lu, rb[F.piv][:, None], left_side=True, lower=True,
                                        unit_diagonal=True)
    x = jax.lax.linalg.triangular_solve(F.lu, x, left_side=True, lower=False)[:, 0]
    return _unless_deficient(F, basic_solve, x, rb)


def _real_linear(f):
    """A real linear map ``f`` extended to complex arguments, part by part: ``S``, ``M``,
    ``G`` and ``P`` are real, the complex pair's shift is not."""

    def apply(x):
        return f(x.real) + 1j * f(x.imag) if jnp.iscomplexobj(x) else f(x)

    return apply


class DenseStages(NamedTuple):
    """The stage systems' linear algebra on the dense path: the exact iteration blocks
    ``J, B`` (frozen), the LU of ``gamma/h B + J`` and of ``(alpha - i beta)/h B + J``
    (refactorised when ``h`` changes), residual floors from ``|J||y| + |B||y'|``."""

    R: Callable
    tab: RadauTableau

    #: The factorisations depend on ``h``.
    scaled = True

    def freeze(self, t, y, w):
        return iteration_blocks(self.R, t, y, w)

    def factor(self, frozen, h):
        return _factor(*frozen, h, self.tab)

    def solve_real(self, frozen, factors, h, r, newton=True):
        return _solve(factors[0], r, newton)

    def solve_complex(self, frozen, factors, h, r):
        return _solve(factors[1], r, True)

    def floor(self, frozen, t, y, w):
        J, B = frozen
        return EPS * (1.0 + jnp.abs(J) @ jnp.abs(y) + jnp.abs(B) @ jnp.abs(w))


class SchurStages(NamedTuple):
    """The stage systems' linear algebra on the structured path (large sparse systems,
    :meth:`Mechanics.schur`): simplified Newton with the iteration matrix frozen at
    ``q_n`` without the force Jacobian and the derivatives of ``M``, ``G^T lambda`` and
    ``G v`` (as :meth:`integrators.genalpha.AlphaMethod.simplified`), for a shift ``c``
    (``gamma/h``, or ``(alpha - i beta)/h`` for the complex pair).

    Index 3, ``[[c I, -I, 0], [0, c M, G^T], [G, 0, 0]] (dq, dv, dlam) = (r_q, r_v, r_g)``:
    ``S dlam = G M^{-1} r_v - c^2 r_g + c G r_q`` with ``S = G M^{-1} G^T``, then
    ``dv = M^{-1} (r_v - G^T dlam) / c`` and ``dq = (r_q + dv) / c``. GGL adds ``G^T dmu``
    to the first row and ``G dv = r_w`` as the last: ``S dlam = G M^{-1} r_v - c r_w``, ``dv``
    as before, ``P dmu = G r_q + r_w - c r_g`` with the Gram matrix ``P = G G^T``, and
    ``dq = (r_q + dv - G^T dmu) / c``. ``S`` and ``P`` do not depend on ``c``: one
    factorisation of each serves the real and the complex system (its real and imaginary
    parts solved apart) and every step size, until Newton asks for a fresh Jacobian.
    Residual floors are per block: ``eps`` times the largest term of the block's rows.
    """

    mech: Mechanics
    linear_solver: str
    ggl: bool

    scaled = False

    def freeze(self, t, y, w):
        return y[:self.mech.n], t

    def factor(self, frozen, h):
        q, t = frozen
        schur = self.mech.schur(self.linear_solver)
        # M(q_n)'s block factors are kept with S's: each Newton iteration solves with M twice
        mass = self.mech.mass_factor(q)
        factors = (schur.factor(q, t), mass)
        if self.ggl:
            factors += (self.mech.gram(schur.name).factor(q, t),)
        return factors

    def _solve(self, frozen, factors, c, r):
        mech, (q, t) = self.mech, frozen
        n, m = mech.n, mech.m
        schur = mech.schur(self.linear_solver)
        M_inv = _real_linear(mech.mass_solver(q, factors[1]))
        G = _real_linear(partial(mech.G_times, q, t))
        GT = _real_linear(partial(mech.GT, q, t))
        S_inv = _real_linear(partial(schur.solve, factors[0]))
        r_q, r_v, r_g = r[:n], r[n:2 * n], r[2 * n:2 * n + m]
        Minv_rv = M_inv(r_v)
        if self.ggl:
            r_w = r[2 * n + m:]
            dlam = S_inv(G(Minv_rv) - c * r_w)
        else:
            dlam = S_inv(G(Minv_rv) - c * c * r_g + c * G(r_q))
        dv = (Minv_rv - M_inv(GT(dlam))) / c
        if not self.ggl:
            return jnp.concatenate([(r_q + dv) / c, dv, dlam])
        P_inv = _real_linear(partial(mech.gram(schur.name).solve, factors[2]))
        dmu = P_inv(G(r_q) + r_w - c * r_g)
        return jnp.concatenate([(r_q + dv - GT(dmu)) / c, dv, dlam, dmu])

    def solve_real(self, frozen, factors, h, r, newton=True):
        return self._solve(frozen, factors, radau_iia().gamma / h, r)

    def solve_complex(self, frozen, factors, h, r):
        tab = radau_iia()
        return self._solve(frozen, factors, (tab.alpha - 1j * tab.beta) / h, r)

    def floor(self, frozen, t, y, w):
        mech = self.mech
        n, m = mech.n, mech.m
        q, v, lam = y[:n], y[n:2 * n], y[2 * n:2 * n + m]
        top = jnp.max(jnp.abs(w[:n])) + jnp.max(jnp.abs(v))
        dyn = (jnp.max(jnp.abs(mech.mass_times(q, w[n:2 * n])))
               + jnp.max(jnp.abs(mech.force(t, q, v))) + jnp.max(jnp.abs(mech.GT(q, t, lam))))
        blocks = [jnp.full(n, top), jnp.full(n, dyn), jnp.full(m, mech.rounding(q, t))]
        if self.ggl:
            blocks.append(jnp.full(m, mech.rounding(q, t, v)))
        return EPS * (1.0 + jnp.concatenate(blocks))


def stages(mech: Mechanics, formulation: str, linear_solver: str):
    """The stage systems' linear algebra: :class:`SchurStages` where
    :meth:`Mechanics.schur` chooses a structured solver, :class:`DenseStages` otherwise."""
    if mech.schur(linear_solver).name == "dense":
        return DenseStages(FORMULATIONS[formulation].residual(mech), radau_iia())
    return SchurStages(mech, linear_solver, formulation == "ggl")


def _extrapolate(Z, r, c):
    """Starting increments for the next step from the collocation polynomial ``P`` of the
    last (``P(0) = 0``, ``P(c_k) = Z_k``): ``P(1 + c_i r) - P(1)``, ``r`` the ratio of the
    new step to the last."""
    x = np.concatenate([[0.0], c])
    theta = 1.0 + jnp.asarray(c) * r
    L = jnp.stack([
        jnp.prod(jnp.stack([(theta - x[j]) / (x[k] - x[j]) for j in range(4) if j != k]), 0)
        for k in range(1, 4)], axis=1)
    return combine(L, Z) - Z[2]


@partial(jax.jit, static_argnames=("mech", "formulation", "linear_solver"))
def initial_state(y0, yp0, t0, params: Params, *, mech: Mechanics, formulation: str,
                  linear_solver: str) -> LoopState:
    """The loop state at ``t0``: the iteration blocks and their factorisations for the
    first step, ``F(t0, y0)``."""
    R, lin = FORMULATIONS[formulation].residual(mech), stages(mech, formulation, linear_solver)
    N = y0.shape[0]
    frozen = lin.freeze(t0, y0, yp0)
    h0 = jnp.minimum(jnp.minimum(params.first_step, params.max_step), params.t_end - t0)
    factors = lin.factor(frozen, h0)
    f0 = -R(t0, y0, jnp.zeros(N))
    # One residual, one Jacobian and one pair of decompositions so far.
    work = jnp.array([0, 1, 1, 0, 0, 1], jnp.int64)
    false, true = jnp.asarray(False), jnp.asarray(True)
    return LoopState(t0, h0, y0, yp0, f0, frozen, factors, h0, true, false, jnp.zeros((3, N)),
                     h0, jnp.asarray(1.0), h0, jnp.asarray(1e-2), true, false,
                     jnp.zeros((), jnp.int64), work, jnp.zeros((), jnp.int32),
                     jnp.zeros((), jnp.int32))


def _attempt(st: LoopState, p: Params, mech: Mechanics, formulation: str, nit: int,
             linear_solver: str):
    """One step attempt: ``(state, accepted)``."""
    tab, form = radau_iia(), FORMULATIONS[formulation]
    R, lin = form.residual(mech), stages(mech, formulation, linear_solver)
    n, N = mech.n, st.y.shape[0]
    A_inv = jnp.asarray(tab.A_inv)
    T, T_inv = jnp.asarray(tab.T), jnp.asarray(tab.T_inv)
    exponent = jnp.asarray(form.indices(mech.n, mech.m) - 1, jnp.float64)
    zeros = jnp.zeros(N)

    def constraints(t, y):
        # The constraint rows of R do not involve y' (XLA drops the rest).
        return R(t, y, zeros)[2 * n:]

    t, y = st.t, st.y
    # A step that would end within 1e-4 h of t_end ends there.
    last = t + 1.0001 * st.h >= p.t_end
    h = jnp.where(last, p.t_end - t, st.h)
    t1 = jnp.where(last, p.t_end, t + h)
    frozen = jax.lax.cond(st.need_jac, lambda: lin.freeze(t, y, st.w), lambda: st.frozen)
    refactor = st.need_jac | ((h != st.h_lu) & lin.scaled)
    factors = jax.lax.cond(refactor, lambda: lin.factor(frozen, h), lambda: st.factors)
    fresh = st.fresh | st.need_jac
    # Components of index k count with h^(k-1) in the error and Newton norms, the
    # multipliers with their own atol (out of both by default: class notes).
    h_index = h ** exponent
    atol = jnp.where(jnp.arange(N) < 2 * n, p.atol, p.multiplier_atol)
    scal = (atol + p.rtol * jnp.abs(y)) / h_index
    Z0 = jnp.where(st.first, jnp.zeros((3, N)), _extrapolate(st.Z, h / st.h_z, tab.c))
    # Round-off floors, row by row (newton.py's rule): eps times the magnitude of the
    # terms of each residual row; residuals are measured in these units.
    floor = lin.floor(frozen, t, y, st.w)
    faccon0 = jnp.maximum(st.faccon, EPS) ** 0.8

    def body(s):
        Z, k, k_ok, dynold, thqold, theta, theta_ok, faccon, cres, held, res_prev, _, hhfac = s
        Rs = stage_residual(R, t, y, h, Z)
        res = jnp.max(jnp.abs(Rs) / floor)
        at_floor = res <= 1e3
        # A residual that has stopped contracting at its round-off floor: Z solves the
        # stage equations, and the increments are rounding noise (amplified ~1/h in the
        # multipliers, which no scaled test would pass at tight tolerances).
        noise = (k >= 1) & at_floor & (res > 0.5 * res_prev) & held
        rho = -combine(T_inv, Rs)
        d12 = lin.solve_complex(frozen, factors, h, rho[1] + 1j * rho[2])
        dW = jnp.stack([lin.solve_real(frozen, factors, h, rho[0]), d12.real, d12.imag])
        dyno = jnp.sqrt(jnp.mean((dW / scal) ** 2))
        k = k + 1
        thq = dyno / dynold
        theta = jnp.where(k == 1, theta, jnp.where(k == 2, thq, jnp.sqrt(thq * thqold)))
        contracting = theta < 0.99
        faccon = jnp.where((k > 1) & contracting, theta / (1.0 - theta), faccon)
        # Simplified Newton converges linearly: the error left after the iterations still
        # allowed is about faccon dyno theta^(nit - 1 - k); if it is predicted to stay
        # above the tolerance, a smaller step is cheaper than going on.
        dyth = faccon * dyno * theta ** (nit - 1 - k) / p.fnewt
        # Past RADAU5's test a stalled contraction is rounding noise, not divergence.
        diverged = ~jnp.all(jnp.isfinite(dW)) | ((k > 1) & ~contracting & ~at_floor
                                                 & (k_ok == 0))
        slow = (k > 1) & (k < nit) & (k_ok == 0) & (dyth >= 1.0) & ~at_floor
        hhfac = 0.8 * jnp.clip(dyth, 1e-4, 20.0) ** (-1.0 / (4 + nit - 1 - k))
        Z1 = Z + combine(T, dW)
        passed = (k_ok == 0) & (faccon * dyno <= p.fnewt)
        # The contraction that decides the Jacobian's reuse is the one measured up to
        # RADAU5's test: the iterations past it run into round-off, where the ratio of
        # successive increments says nothing about the iteration matrix.
        theta_ok = jnp.where(passed, theta, theta_ok)
        k_ok = jnp.where(passed, k, k_ok)
        tight = faccon * dyno <= NEWTON_TIGHT * p.fnewt
        done = (k_ok > 0) & (tight | at_floor | ~contracting | (k - k_ok >= NEWTON_EXTRA))
        # Then the constraints at the step end to round-off (up to nit more iterations).
        con = jnp.abs(constraints(t1, y + Z1[2]))
        cres1 = jnp.max(con / floor[2 * n:], initial=0.0)
        # Evaluating g at y + Z rounds to a few units of the floor: 100 is round-off.
        held1 = (jnp.max(con, initial=0.0) <= p.newton_tol) | ((cres1 > 0.5 * cres)
                                                                & (cres1 <= 1e2))
        spent = jnp.where(k_ok == 0, k >= nit, k - k_ok >= nit)
        status = jnp.where(noise, 1, jnp.where(diverged, 2, jnp.where(slow, 3, jnp.where(
            done & held1, 1, jnp.where(spent, 2, 0))))).astype(jnp.int32)
        return (jnp.where(noise, Z, Z1), k, k_ok, jnp.maximum(dyno, EPS), thq, theta,
                theta_ok, faccon, cres1, held1, res, status, hhfac)

    int0, false = jnp.zeros((), jnp.int32), jnp.asarray(False)
    s0 = (Z0, int0, int0, jnp.asarray(1.0), jnp.asarray(1.0), jnp.asarray(0.0),
          jnp.asarray(0.0), faccon0, jnp.asarray(jnp.inf), false, jnp.asarray(jnp.inf), int0,
          jnp.asarray(1.0))
    Z, k, k_ok, _, _, _, theta, faccon, _, _, _, status, hhfac = jax.lax.while_loop(
        lambda s: s[11] == 0, body, s0)
    y1 = y + Z[2]
    converged = (status == 1) & jnp.all(jnp.isfinite(y1))

    def estimate():
        """The embedded error, filtered through the real iteration matrix (stiff
        components damped)."""
        gamma0 = 1.0 / tab.gamma
        ez = combine(tab.e / gamma0, Z) / h
        Bez = jax.jvp(lambda w: R(t, y, w), (zeros,), (ez,))[1]
        scal_e = (atol + p.rtol * jnp.maximum(jnp.abs(y), jnp.abs(y1))) / h_index

        def norm(err):
            return jnp.sqrt(jnp.mean((err / scal_e) ** 2))

        err = lin.solve_real(frozen, factors, h, st.f0 + Bez, newton=False)
        # On a first or a retried step a large estimate may be an unresolved stiff
        # component: one more filtering through F at y + err (Hairer and Wanner).
        again = (norm(err) >= 1.0) & (st.first | st.reject)
        err = jax.lax.cond(again, lambda: lin.solve_real(frozen, factors, h,
                                                         -R(t, y + err, zeros) + Bez,
                                                         newton=False),
                           lambda: err)
        return jnp.maximum(norm(err), 1e-10), again

    en, again = jax.lax.cond(converged, estimate,
                             lambda: (jnp.asarray(jnp.inf), jnp.asarray(False)))
    accept = converged & (en < 1.0)
    # The next step: h err^(-1/4) with a safety factor that shrinks as Newton needed
    # more iterations to its test, and, after an accepted step, Gustafsson's predictive
    # controller.
    fac = jnp.minimum(p.safety, p.safety * (1 + 2 * nit) / (k_ok + 2 * nit))
    quot = jnp.clip(en ** 0.25 / fac, 1.0 / FACTOR_MAX, 1.0 / FACTOR_MIN)
    gus = jnp.clip((st.h_acc / h) * (en ** 2 / st.err_acc) ** 0.25 / p.safety,
                   1.0 / FACTOR_MAX, 1.0 / FACTOR_MIN)
    quot = jnp.where(accept & (st.n_accepted >= 1), jnp.maximum(quot, gus), quot)
    h_new = jnp.minimum(h / quot, p.max_step)
    new_jac = theta > p.thet
    ratio = h_new / h
    h_acc_next = jnp.where(st.reject, jnp.minimum(h_new, h), h_new)
    # A step size that would barely change keeps the factorisations (and the step).
    h_acc_next = jnp.where(~new_jac & (ratio >= KEEP_RATIOS[0]) & (ratio <= KEEP_RATIOS[1]),
                           h, h_acc_next)
    # Newton failing with a Jacobian kept from an earlier step says nothing against the
    # step size: the attempt is retried at the same step with a fresh Jacobian (as
    # SUNDIALS' integrators do), and only a fresh Jacobian's failure shrinks the step.
    stale = ~converged & ~fresh
    h_next = jnp.where(accept, h_acc_next,
                       jnp.where(stale, h,
                                 jnp.where(status == 2, 0.5 * h,
                                           jnp.where(status == 3, hhfac * h,
                                                     jnp.where(st.first, 0.1 * h, h_new)))))
    need_jac = jnp.where(accept, new_jac, jnp.where(converged, False, ~fresh))
    f0 = jax.lax.cond(accept, lambda: -R(t1, y1, zeros), lambda: st.f0)
    underflow = ~accept & (h_next <= UNDERFLOW_ULPS * EPS * jnp.maximum(1.0, jnp.abs(t)))
    cause = jnp.where(accept, 0, jnp.maximum(st.cause, jnp.where(
        converged, 1, jnp.where(jnp.all(jnp.isfinite(y1)), 2, 3)))).astype(jnp.int32)
    code = jnp.where(underflow, jnp.asarray([int(f) for f in CAUSES])[cause],
                     Failure.NONE).astype(jnp.int32)
    extra = again.astype(jnp.int64)
    work = st.work + jnp.stack([
        (~accept).astype(jnp.int64),
        3 * k + accept + extra,
        st.need_jac.astype(jnp.int64),
        jnp.asarray(k, jnp.int64),
        2 * k + converged + extra,
        refactor.astype(jnp.int64)])

    def pick(new, old):
        return jnp.where(accept, new, old)

    state = LoopState(
        t=pick(t1, t), h=h_next, y=pick(y1, y), w=pick(combine(A_inv[2], Z) / h, st.w), f0=f0,
        frozen=frozen, factors=factors, h_lu=h, fresh=fresh & ~accept, need_jac=need_jac,
        Z=pick(Z, st.Z), h_z=pick(h, st.h_z), faccon=faccon,
        h_acc=pick(h, st.h_acc), err_acc=pick(jnp.maximum(1e-2, en), st.err_acc),
        first=st.first & ~accept, reject=~accept, n_accepted=st.n_accepted + accept,
        work=work, cause=cause, code=code)
    return state, accept


@partial(jax.jit, static_argnames=("mech", "formulation", "nit", "linear_solver"))
def run_chunk(state: LoopState, params: Params, *, mech: Mechanics, formulation: str,
              nit: int, linear_solver: str):
    """Make step attempts until a batch of accepted steps is full, or the run ends.

    Returns ``(state, t, q, v, k)``: the accepted steps are ``t[:k]``, ``q[:k]``,
    ``v[:k]``. The run ends at ``t_end``, on a failure code, or after
    ``params.max_steps`` accepted steps.
    """
    rows, n = batch_length(mech.n), mech.n

    def cond(carry):
        k, st = carry[0], carry[1]
        return ((k < rows) & (st.t < params.t_end) & (st.code == 0)
                & (st.n_accepted < params.max_steps))

    def body(carry):
        k, st, buf_t, buf_q, buf_v = carry
        st, accept = _attempt(st, params, mech, formulation, nit, linear_solver)
        # In-place row updates rather than scatters (see integrators.loop on why).
        buf_t = put(buf_t, k, jnp.where(accept, st.t, buf_t[k]))
        buf_q = put(buf_q, k, jnp.where(accept, st.y[:n], buf_q[k]))
        buf_v = put(buf_v, k, jnp.where(accept, st.y[n:2 * n], buf_v[k]))
        return k + accept, st, buf_t, buf_q, buf_v

    carry = (jnp.zeros((), jnp.int64), state, jnp.zeros(rows), jnp.zeros((rows, n)),
             jnp.zeros((rows, n)))
    return jax.lax.while_loop(cond, body, carry)


#: Compiled chunks kept for reuse, keyed by system, formulation and iteration limit.
_CHUNKS: OrderedDict = OrderedDict()


def compiled_chunk(state: LoopState, params: Params, mech: Mechanics, formulation: str,
                   nit: int, linear_solver: str):
    """:func:`run_chunk` compiled for this system and options (or the kept executable)."""
    key = (mech, formulation, nit, linear_solver)
    if key not in _CHUNKS:
        _CHUNKS[key] = compile_lifted(run_chunk, state, params, mech=mech,
                                      formulation=formulation, nit=nit,
                                      linear_solver=linear_solver)
        while len(_CHUNKS) > CACHE_SIZE:
            _CHUNKS.popitem(last=False)
    _CHUNKS.move_to_end(key)
    return _CHUNKS[key]


@dataclass(frozen=True)
class RadauIIA(Integrator):
    """Radau IIA with three stages (order 5, adaptive) on the index-3 or the stabilised
    index-2 form of the equations of motion, after Hairer and Wanner's RADAU5 (*Solving
    Ordinary Differential Equations II*, 2nd ed., 1996, sections IV.8 and VII.4).

    The equations of motion ``M(q) q'' = f(t, q, q') - G^T lambda``, ``g(q, t) = 0`` in
    first-order form ``B(y) y' = F(t, y)`` with a singular mass ``B``:

    - ``formulation = "index3"``, ``y = (q, v, lambda)`` (:func:`index3_residual`):
      ``q' = v``, ``M(q) v' = f - G^T lambda``, ``0 = g(q, t)``; ``q`` has index 1, ``v``
      index 2, ``lambda`` index 3. Enforces ``g = 0`` at every step end (the last stage is
      the step end: the method is stiffly accurate); ``G v + g_t`` is not enforced.
    - ``formulation = "ggl"``, ``y = (q, v, lambda, mu)``
      (:func:`integrators.ida.ggl_residual`, Gear, Gupta and Leimkuhler 1985):
      ``q' = v - G^T mu``, ``M(q) v' = f - G^T lambda``, ``0 = g``, ``0 = G v + g_t``;
      ``q, v`` of index 1, the multipliers of index 2. Enforces both levels.

    **Method.** Collocation at the Radau points ``c = ((4 - sqrt 6)/10, (4 + sqrt 6)/10,
    1)`` (:func:`radau_iia`): the stage increments ``Z_i = Y_i - y_n`` solve
    ``B(Y_i) K_i = F(t_n + c_i h, Y_i)`` with ``K = (A^{-1} Z)/h`` the stage derivatives,
    and ``y_{n+1} = y_n + Z_3``. Order 5 (``2s - 1``) in ``y`` for ODEs; on the index-3
    form the positions keep order 5, the velocities order 3 and the multipliers order 2
    (Hairer, Lubich and Roche 1989); on the index-2 form ``q, v`` keep order 5 and the
    multipliers order 3. Not symplectic; L-stable.

    **Newton.** Simplified Newton with the iteration matrix ``A^{-1}/h (x) B + I (x) J``
    frozen at the ``(t_n, y_n, y'_n)`` of the step where it was last evaluated (see
    "Jacobian reuse"; ``J = dR/dy``, ``B = dR/dy'``, autodiff of the
    residual ``R = B y' - F``, :func:`iteration_blocks`), block-diagonalised by the
    eigenvectors of ``A^{-1}``: each iteration solves one real system with
    ``gamma/h B + J`` and one complex system with ``(alpha - i beta)/h B + J``, each
    factorised once (LU, equilibrated, :func:`linalg.dense.lu_factor`, unrolled in the
    loop body for small systems: :data:`INLINE_MAX`) and reused while
    ``h`` and ``J`` are. Starting values come from the collocation polynomial of the last
    step, extrapolated. Convergence: RADAU5's test on the scaled increments,
    ``theta/(1 - theta) ||dZ|| <= fnewt`` with the contraction rate ``theta``, then at
    most two more iterations towards ``fnewt/100`` (stopping early at the residual's
    round-off floor or when the contraction stalls: :data:`NEWTON_TIGHT`), and, since
    the forms hold the constraints as equations, ``max |constraint rows at t_{n+1}| <=
    newton_tol`` or at its round-off floor (as :func:`integrators.newton.newton`
    defines it): ``g`` (and ``G v + g_t``) hold to round-off at every step end. A Newton
    failure with a Jacobian kept from an earlier step re-evaluates it and retries the same
    step; with a fresh one, divergence (``theta >= 0.99``) halves ``h`` and a predicted
    slow convergence shrinks it (RADAU5 shrinks the step in both cases).

    **Error and step size.** Hairer's embedded estimate ``err = (gamma/h B + J)^{-1}
    (F(t_n, y_n) + B sum_j d_j Z_j / h)``, ``d = (-(13 + 7 sqrt 6)/3, (-13 + 7 sqrt 6)/3,
    -1/3)`` (order 3; the solve damps stiff components), filtered once more through
    ``F(y_n + err)`` on a first or retried step with ``||err|| >= 1``. Its RMS norm (over
    all ``N`` components) weighs component ``i`` by ``(atol_i + rtol max(|y_n|,
    |y_{n+1}|)) / h^(k_i - 1)`` with ``k_i`` its index (RADAU5's ``nind`` scaling: the
    local errors of components of higher index are ``O(h^(1-k))`` larger by nature).

    **The multipliers' error.** One rule for both forms: ``atol_i = atol`` for ``q`` and
    ``v``, ``atol_i = multiplier_atol`` for the multipliers (``lambda``, and ``mu`` on
    the stabilised form), the same weights in the error test and in Newton's test. The
    default, :data:`integrators.ida.EXCLUDED` (``1e30``), leaves the multipliers out of
    both, as ``ida-ggl`` does (SUNDIALS' GGL example suppresses the algebraic variables):
    they are functions of ``(q, v)`` and the step size is chosen for ``(q, v)``. Two
    failures of keeping them in (``multiplier_atol = atol`` is RADAU5's rule, still
    available): the stabilised form's ``mu`` is zero in the exact solution, so its weight
    is ``atol / h`` and its estimate, not ``rtol``, sets the step size (the same step count
    at every ``rtol``); and where a multiplier passes through zero its weight is
    ``atol / h^2`` while the rounding of the constraint rows reaches it through the
    iteration matrix as ``O(eps / h^2)`` too, so Newton's increments stall above the test
    at every step size, the step collapses by orders of magnitude, and at those steps the
    velocities' weight ``(atol + rtol |v|) / h`` lets ``G v + g_t`` jump by orders of
    magnitude (the index-3 form does not hold it). New step ``h fac err^(-1/4)``,
    ``fac = safety (1 + 2 nit)/(newt + 2 nit)`` capped at ``safety`` (``newt`` the
    iterations Newton's test took), ratio in [0.2, 8]; after an accepted step the smaller
    of that and Gustafsson's predictive ``h_n/h_{n-1} (err_{n-1}/err_n^2)^(1/4)`` step;
    no increase right after a rejection.

    **Jacobian reuse** (RADAU5's): after an accepted step the Jacobian is kept when
    Newton's contraction ``theta``, as measured when its test passed (the iterations past
    it approach round-off, where the ratio of increments says nothing about the matrix), is
    at most ``thet``; the step and its factorisations are kept when the new step's ratio to
    the last is in [1, 1.2] and the Jacobian is; otherwise the kept Jacobian is
    refactorised for the new step. A rejection by the error test keeps the Jacobian; a
    Newton failure re-evaluates it unless it was fresh (see "Newton").

    **Tolerances.** The error test takes ``rtol`` and ``atol`` as given, as the suite's
    other adaptive methods do. RADAU5 itself first maps them to ``rtol' = 0.1
    rtol^(2/3)``, ``atol' = rtol' atol/rtol``, meant to make the global error follow
    ``rtol``; here that mapping gave final errors on the pendulum (10 s) of 6, 64 and 149
    times ``rtol`` = 1e-6, 1e-8 and 1e-10 (index-3 form; 4, 35 and 78 for ``ggl``): the
    order-3 estimate overstates the order-5 local error by a factor that grows as ``h``
    shrinks, and the mapping undoes too much of it. Taken as given they give 1.7, 0.6
    and 0.18 times ``rtol`` (0.6, 0.3 and 0.09 for ``ggl``), at 1.0, 2.5 and 3.8 times the
    steps.

    Redundant constraints (``G(q0)`` of rank below ``m``) make the stage systems singular
    everywhere: the run fails at once, saying so (as IDA's does).

    **Counts.** ``n_steps`` accepted and ``n_rejected`` rejected attempts (error test or
    Newton), ``n_f_evals`` residual evaluations (three per Newton iteration, one per
    accepted step for ``F(t_{n+1}, y_{n+1})``, one per extra filtering; the constraint
    checks evaluate ``g`` alone and are not counted), ``n_jac_evals`` evaluations of
    ``J`` and ``B``, ``n_newton`` Newton iterations, ``n_lin_solves`` solves (a real and
    a complex one per iteration, one per error estimate), and ``extra["n_lu"]`` the
    factorisations (pairs of a real and a complex LU). Measured at every accepted step.

    Parameters
    ----------
    formulation : {"index3", "ggl"}
        The DAE form (:data:`FORMULATIONS`).
    rtol : float
        Relative tolerance.
    atol : float
        Absolute tolerance on ``q`` and ``v``; NaN (the default) sets it equal to ``rtol``
        at construction.
    multiplier_atol : float
        Absolute tolerance on the multipliers in the error and Newton's tests; the default
        :data:`integrators.ida.EXCLUDED` keeps them out of both, ``atol`` gives RADAU5's
        rule (see "The multipliers' error").
    thet : float
        Newton's contraction up to which the Jacobian is kept for the next step (RADAU5's
        ``WORK(3)``; default :data:`THETA_KEEP`); a negative value re-evaluates it after
        every accepted step.
    newton_tol : float
        Bound on the constraint rows at the step end; the default 1e-16 means "to
        round-off".
    newton_max_iter : int
        Newton iterations per attempt (RADAU5's ``nit``).
    safety : float
        Safety factor of the step-size control.
    first_step : float
        First step attempted (RADAU5's default, 1e-6).
    max_step : float
        Largest step; ``inf`` for none.
    max_steps : int
        Accepted steps allowed over the run; reaching it fails the run.
    linear_solver : {"auto", "dense", "banded", "superlu", "kkt"}
        The stage systems' linear algebra (:func:`linalg.schur.choose`): dense LU of the
        exact iteration matrices, or, for large sparse systems, the structured simplified
        Newton of :class:`SchurStages` with one factorisation of ``G M^{-1} G^T``.
    """

    adaptive: ClassVar[bool] = True
    family: ClassVar[str] = "Radau IIA"
    nominal_order: ClassVar[int] = 5

    formulation: str = "index3"
    rtol: float = 1e-6
    atol: float = math.nan
    multiplier_atol: float = EXCLUDED
    thet: float = THETA_KEEP
    newton_tol: float = 1e-16
    newton_max_iter: int = 7
    safety: float = 0.9
    first_step: float = 1e-6
    max_step: float = math.inf
    max_steps: int = 10_000_000
    linear_solver: str = "auto"

    @property
    def enforces(self) -> tuple[str, ...]:
        return FORMULATIONS[self.formulation].enforces

    def check(self) -> None:
        super().check()
        name = type(self).__name__
        self.check_choice("formulation", FORMULATIONS)
        if not math.isfinite(self.thet):
            raise ValueError(f"{name}: thet = {self.thet} must be finite")
        if not self.multiplier_atol > 0:
            raise ValueError(f"{name}: multiplier_atol = {self.multiplier_atol} must be > 0")
        if not 0 < self.safety <= 1:
            raise ValueError(f"{name}: safety = {self.safety} must lie in (0, 1]")
        if not (self.first_step > 0 and self.max_step > 0 and self.max_steps >= 1):
            raise ValueError(f"{name}: need first_step > 0, max_step > 0 and max_steps >= 1")

    @property
    def fnewt(self) -> float:
        """RADAU5's tolerance of Newton's test on the scaled increments,
        ``max(10 eps/rtol, min(0.03, rtol^(1/2)))``."""
        return max(10 * EPS / self.rtol, min(0.03, self.rtol ** 0.5))

    def prepare(self, case: Case, grid: Grid):
        self.check()
        mech = case.mech
        n = mech.n
        form = FORMULATIONS[self.formulation]
        t0, t_end = float(grid.t0), float(grid.t_end)
        schur = mech.schur(self.linear_solver)
        y0, yp0 = consistent_values(mech, form.multiplier_blocks, t0, case.q0, case.v0,
                                    schur=schur)
        f64 = partial(jnp.asarray, dtype=jnp.float64)
        params = Params(f64(t_end), f64(self.rtol), f64(self.atol),
                        f64(self.multiplier_atol), f64(self.thet), f64(self.fnewt),
                        f64(self.newton_tol),
                        f64(self.safety), f64(self.first_step), f64(self.max_step),
                        jnp.asarray(self.max_steps, jnp.int64))
        recorder = Recorder(mech, grid)
        sampling = "every internal step (accepted steps)"
        solver_record = dict(linear_solver=schur.name, pattern_nnz=schur.nnz)
        if schur.name != "dense" and self.formulation == "ggl":
            # Built outside the traces that use it: built inside one, its arrays would be
            # that trace's constants, which the compiled chunk would then expect as inputs.
            mech.gram(schur.name)
        # Redundant constraints make the stage systems singular everywhere. Their basic
        # solutions (linalg.dense) keep Newton going, but at a crawl, with more rejected
        # steps than accepted ones (bricard, rank 23 of 24). (The structured solvers apply
        # the one rank policy of linalg.dense themselves.)
        rank = mech.m if schur.name != "dense" else int(np.linalg.matrix_rank(
            np.asarray(mech.G(f64(case.q0), f64(t0)))))
        if rank < mech.m:
            def refuse():
                recorder.start(t0, y0[:n], y0[n:2 * n])
                return recorder.trajectory(
                    f"G(q0) has rank {rank} < m = {mech.m} (redundant constraints): the "
                    "stage systems are singular", t0, y0[:n], y0[n:2 * n], {"n_steps": 0},
                    sampling, **solver_record)
            return refuse
        static = dict(mech=mech, formulation=self.formulation,
                      linear_solver=self.linear_solver)
        args = (f64(y0), f64(yp0), f64(t0), params)
        state0 = compile_lifted(initial_state, *args, **static)(*args)
        chunk = compiled_chunk(state0, params, nit=self.newton_max_iter, **static)

        def solve():
            recorder.start(t0, y0[:n], y0[n:2 * n])
            state = state0
            while True:
                k, state, buf_t, buf_q, buf_v = chunk(state, params)
                k = int(k)
                buf_t, buf_q, buf_v = jax.device_get((buf_t, buf_q, buf_v))
                assert buf_q.dtype == np.float64, "the loop must run in float64"
                recorder.extend(buf_t[:k], buf_q[:k], buf_v[:k])
                code, t, steps = jax.device_get((state.code, state.t, state.n_accepted))
                code, t, steps = int(code), float(t), int(steps)
                if code or t >= t_end or steps >= self.max_steps:
                    break
            work = dict(zip(WORK, (int(x) for x in jax.device_get(state.work))))
            counts = {"n_steps": steps, **{key: work[key] for key in WORK if key != "n_lu"}}
            y = np.asarray(jax.device_get(state.y))
            if code == 0 and t < t_end:
                code = Failure.MAX_STEPS
            message = ""
            if code:
                what = Failure(code).message.format(max_steps=self.max_steps, t_end=t_end)
                message = (f"{what}; at step {steps + 1} (t = {t:.6g}, step size reduced to "
                           f"{float(state.h):.3g})")
            return recorder.trajectory(message, t, y[:n], y[n:2 * n], counts, sampling,
                                       extra={"n_lu": work["n_lu"]}, **solver_record)

        return solve
