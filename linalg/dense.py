"""Dense solves under the one policy for rank deficiency, and the dense Schur solver.

Redundant constraints
---------------------
One policy for every family and path: the *basic* solution. Systems are first equilibrated
by a diagonal scaling (``S`` to unit diagonal; a general matrix by powers of two, which is
exact), so that constraints in different units are not taken for dependent ones. A pivot
below :data:`RANK_RTOL` (relative to the largest pivot of a dense factorisation, to the
unit diagonal of the equilibrated ``S`` in the banded one; a non-finite pivot counts as
small) marks a numerically dependent constraint: ``G`` has rank below ``m`` (redundant
constraints, or a singular configuration). Its multiplier is set to zero and the others
solve the remaining equations, which for a consistent system is an exact solution, whose
multipliers give the same, unique constraint force ``G^T lambda`` as any other. The dense
path finds the dependent constraints by QR with column pivoting (:func:`basic_solve`); the
banded Cholesky drops them as it meets them, in its elimination order, at no extra cost
and without leaving the compiled loop (:func:`linalg.banded.band_cholesky`); SuperLU,
which cannot, hands a singular ``S`` to a dense basic solve on the host for up to
:data:`linalg.sparse.FALLBACK_MAX` constraints, and above that the step fails with that
message.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

#: Pivot ratio below which a factorisation is taken as numerically rank deficient.
RANK_RTOL = 1e-12

#: Largest system factorised by unrolled scalar code (:func:`small_cho_factor`,
#: :func:`small_basic_solve`) instead of LAPACK.
SMALL_DENSE = 4


def power_of_two_scale(x: jax.Array) -> jax.Array:
    """``2^-round(log2 x)`` for ``x > 0`` (1 where ``x`` is 0): scaling by it is exact.

    From the binary exponent (``x = f 2^e`` with ``1/2 <= f < 1``, so ``round(log2 x)`` is
    ``e - 1`` where ``f < 1/sqrt 2``, else ``e``), and the power of two written as its bits
    (the exponent clipped to the normal range), not as ``exp2(-round(log2 x))``: XLA's
    ``exp2`` on the CPU is not exact at integers, and about half of such scalings were off
    a power of two by up to 4e-14 (measured over 2e6 values), so that equilibrating
    rounded the matrix."""
    f, e = jnp.frexp(jnp.where(x > 0, x, 1.0))
    k = jnp.clip((f < 0.5 ** 0.5).astype(jnp.int64) - e, -1022, 1023)
    scale = jax.lax.bitcast_convert_type((k + 1023) << 52, jnp.float64)
    return jnp.where(x > 0, scale, 1.0)


class Basic(NamedTuple):
    """QR with column pivoting, ``A P = Q R``, for basic solutions (:func:`basic_factor`):
    ``R`` with the rows of dependent columns replaced by the identity's, ``keep`` the
    independent ones."""

    Q: jax.Array
    R: jax.Array
    perm: jax.Array
    keep: jax.Array


def basic_factor(A: jax.Array, rtol: float = RANK_RTOL) -> Basic:
    """``A``'s factorisation for :func:`basic_apply`: ``A P = Q R`` with ``|R_kk|``
    non-increasing; columns whose ``|R_kk|`` falls below ``rtol |R_00|`` are numerically
    dependent."""
    Q, R, perm = jax.scipy.linalg.qr(A, pivoting=True)
    d = jnp.abs(jnp.diag(R))
    keep = d > rtol * d[0]
    return Basic(Q, jnp.where(keep[:, None], R, jnp.eye(A.shape[0])), perm, keep)


def basic_apply(B: Basic, b: jax.Array) -> jax.Array:
    """The basic solution of ``A x = b`` from ``A``'s :func:`basic_factor`: the dependent
    columns' unknowns are zero, the leading triangle gives the others."""
    mask = B.keep[:, None] if b.ndim == 2 else B.keep
    y = jax.scipy.linalg.solve_triangular(B.R, jnp.where(mask, B.Q.conj().T @ b, 0.0))
    return jnp.zeros_like(y).at[B.perm].set(y)


def basic_solve(A: jax.Array, b: jax.Array, rtol: float = RANK_RTOL) -> jax.Array:
    """A basic solution of ``A x = b`` by QR with column pivoting, for rank-deficient ``A``
    (:func:`basic_factor`, :func:`basic_apply`). For a consistent system this is an exact
    solution (not the minimum-norm one); ``b`` may be a vector or a matrix of columns,
    ``A`` real or complex.
    """
    if A.shape[0] == A.shape[1] <= SMALL_DENSE and not jnp.iscomplexobj(A):
        return small_basic_solve(A, b, rtol)
    return basic_apply(basic_factor(A, rtol), b)


def small_basic_solve(A: jax.Array, b: jax.Array, rtol: float = RANK_RTOL) -> jax.Array:
    """:func:`basic_solve` for a small real ``A`` (``m <= SMALL_DENSE``), written out:
    Householder QR with column pivoting (at step ``k`` the remaining column of largest
    norm below row ``k`` is swapped in, as LAPACK's ``dgeqp3`` chooses it, the first of
    equals), then the same basic solution.

    No LAPACK call: one inside a loop's body costs at every entry of the loop even where
    the body never runs (:func:`rarely`), which for a few constraints is most of a step.
    """
    m = A.shape[0]
    cols = jnp.arange(m)
    R, y, perm = A, b, cols
    for k in range(m):
        j = k + jnp.argmax(jnp.sum(R[k:, k:] ** 2, axis=0))
        swap = jnp.where(cols == k, j, jnp.where(cols == j, k, cols))
        R, perm = R[:, swap], perm[swap]
        if k == m - 1:
            break
        x = R[k:, k]
        norm = jnp.sqrt(jnp.sum(x * x))
        alpha = jnp.where(x[0] > 0, -norm, norm)
        v = x.at[0].add(-alpha)
        vv = jnp.sum(v * v)
        # A zero column (vv = 0) needs no reflection.
        scale = jnp.where(vv > 0, 2.0 / jnp.where(vv > 0, vv, 1.0), 0.0)
        R = R.at[k:, :].add(-scale * jnp.outer(v, v @ R[k:, :]))
        y = y.at[k:].add(-scale * (jnp.outer(v, v @ y[k:]) if y.ndim == 2 else v * (v @ y[k:])))
    d = jnp.abs(jnp.diag(R))
    keep = d > rtol * d[0]
    x = [None] * m
    for i in reversed(range(m)):
        rhs = y[i] - sum(R[i, k] * x[k] for k in range(i + 1, m))
        x[i] = jnp.where(keep[i], rhs / jnp.where(keep[i], R[i, i], 1.0), 0.0)
    return jnp.zeros_like(b).at[perm].set(jnp.stack(x))


class LU(NamedTuple):
    """An equilibrated LU factorisation (:func:`lu_factor`) for any number of solves."""

    lu: jax.Array
    piv: jax.Array
    #: The equilibrated matrix ``D_r A D_c``, for the basic solution of a deficient one.
    scaled: jax.Array
    row: jax.Array
    col: jax.Array
    deficient: jax.Array


def lu_factor(A: jax.Array) -> LU:
    """``D_r A D_c`` (power-of-two row and column scalings, exact) factorised by LU with
    partial pivoting, and whether its smallest pivot is below :data:`RANK_RTOL` times the
    largest (or not finite): then :func:`lu_solve` takes the basic solution (see the
    module notes). ``A`` may be real or complex."""
    r = power_of_two_scale(jnp.max(jnp.abs(A), axis=1))
    c = power_of_two_scale(jnp.max(jnp.abs(A * r[:, None]), axis=0))
    As = A * r[:, None] * c[None, :]
    lu, piv = jax.scipy.linalg.lu_factor(As)
    pivots = jnp.abs(jnp.diag(lu))
    deficient = ~(jnp.min(pivots) > RANK_RTOL * jnp.max(pivots))
    return LU(lu, piv, As, r, c, deficient)


def lu_solve(F: LU, b: jax.Array) -> jax.Array:
    """``A^{-1} b`` for the factorised ``A`` (:func:`lu_factor`); ``b`` a vector or a
    matrix of columns."""
    rb = b * (F.row[:, None] if b.ndim == 2 else F.row)
    y = rarely(F.deficient, basic_solve, jax.scipy.linalg.lu_solve((F.lu, F.piv), rb),
               F.scaled, rb)
    return y * (F.col[:, None] if b.ndim == 2 else F.col)


def solve(A: jax.Array, b: jax.Array) -> jax.Array:
    """``A^{-1} b`` by LU of the equilibrated ``A``; the basic solution if rank deficient.

    A 1 x 1 system is a division: a LAPACK call is opaque to XLA's fusion and costs
    microseconds, most of a small problem's step for a single constraint. Otherwise
    :func:`lu_factor` then :func:`lu_solve`.
    """
    if A.shape[0] == 1:
        return b / A[0, 0]
    return lu_solve(lu_factor(A), b)


class Reused(NamedTuple):
    """A factorisation for many solves with one matrix (:func:`reused_factor`)."""

    lu: LU
    #: :func:`basic_factor` of the equilibrated matrix where it is rank deficient (zeros
    #: elsewhere).
    basic: Basic


def reused_factor(A: jax.Array) -> Reused:
    """:func:`lu_factor` of ``A`` and, where it is rank deficient, the QR of the basic
    solution as well, once: :func:`reused_solve` then costs substitutions only, where
    :func:`lu_solve` would redo the QR at every solve with a deficient ``A``."""
    F = lu_factor(A)
    blank = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype),
                                   jax.eval_shape(basic_factor, F.scaled))
    return Reused(F, rarely(F.deficient, basic_factor, blank, F.scaled))


def reused_solve(F: Reused, b: jax.Array) -> jax.Array:
    """``A^{-1} b`` (the basic solution if ``A`` is rank deficient) for ``A`` factorised
    by :func:`reused_factor`."""
    rb = b * F.lu.row
    y = rarely(F.lu.deficient, basic_apply,
               jax.scipy.linalg.lu_solve((F.lu.lu, F.lu.piv), rb), F.basic, rb)
    return y * F.lu.col


def rarely(pred: jax.Array, fn: Callable[..., Any], otherwise: Any, *operands: Any) -> Any:
    """``fn(*operands)`` where ``pred``, else ``otherwise``: a branch taken rarely,
    evaluated only when taken, also under ``jax.vmap``.

    ``lax.cond`` on a batched predicate becomes a select of both branches, so an ensemble
    would pay for the QR of :func:`basic_solve` at every solve. A while loop of at most one
    iteration runs its body under ``vmap`` only while some lane's predicate holds, and
    keeps the other lanes' values.

    The branch's inputs go in as ``operands`` and reach ``fn`` through an optimisation
    barrier with the loop's predicate, which makes them values of the loop. A body whose
    inputs are all fixed before the loop is loop-invariant, and XLA hoists it out of the
    batched loop, evaluating it every time, so that lanes whose systems are never
    deficient would pay for the QR.
    """

    def body(state):
        live, _ = state
        _, ops = jax.lax.optimization_barrier((live, operands))
        return False, fn(*ops)

    return jax.lax.while_loop(lambda state: state[0], body, (pred, otherwise))[1]


def unit_diagonal(d: jax.Array) -> jax.Array:
    """``1 / sqrt(d)`` where ``d > 0`` (1 elsewhere): the scaling of ``S`` to unit diagonal."""
    return jnp.where(d > 0, 1.0 / jnp.sqrt(jnp.where(d > 0, d, 1.0)), 1.0)


def small_cho_factor(S: jax.Array) -> jax.Array:
    """The lower Cholesky factor of a small ``S`` (``m <= SMALL_DENSE``), written out
    entry by entry: ``L_jj = sqrt(S_jj - sum_k L_jk^2)``,
    ``L_ij = (S_ij - sum_k L_ik L_jk) / L_jj`` (``k < j``). A LAPACK call is opaque to
    XLA's fusion and has a fixed cost that the ``m^3 / 6`` operations of a few constraints
    do not approach; unrolled, the factor fuses with the code around it. A breakdown
    leaves NaN on the diagonal, which :func:`spd_solve`'s rank test takes as a small pivot,
    as it does LAPACK's."""
    m = S.shape[0]
    L = [[jnp.zeros((), S.dtype)] * m for _ in range(m)]
    for j in range(m):
        L[j][j] = jnp.sqrt(S[j, j] - sum(L[j][k] * L[j][k] for k in range(j)))
        for i in range(j + 1, m):
            L[i][j] = (S[i, j] - sum(L[i][k] * L[j][k] for k in range(j))) / L[j][j]
    return jnp.stack([jnp.stack(row) for row in L])


def small_cho_solve(L: jax.Array, b: jax.Array) -> jax.Array:
    """``(L L^T)^{-1} b`` by forward and back substitution, unrolled (see
    :func:`small_cho_factor`); ``b`` a vector or a matrix of columns."""
    m = L.shape[0]
    z = []
    for i in range(m):
        z.append((b[i] - sum(L[i, k] * z[k] for k in range(i))) / L[i, i])
    x = [None] * m
    for i in reversed(range(m)):
        x[i] = (z[i] - sum(L[k, i] * x[k] for k in range(i + 1, m))) / L[i, i]
    return jnp.stack(x)


def spd_solve(S: jax.Array, rhs: jax.Array) -> jax.Array:
    """``S^{-1} rhs`` for a symmetric positive semidefinite ``S``, under the one policy.

    ``S`` is scaled to unit diagonal (``D S D``) and factorised by Cholesky; if its
    smallest squared pivot is below :data:`RANK_RTOL` times the largest, or the factor
    breaks down, the basic solution of the scaled system is used (:func:`basic_solve`).
    A system of up to :data:`SMALL_DENSE` unknowns is factorised by unrolled code
    (:func:`small_cho_factor`), a larger one by LAPACK.
    """
    D = unit_diagonal(jnp.diag(S))
    Ss = S * D[:, None] * D[None, :]
    Dr = D[:, None] if rhs.ndim == 2 else D
    if S.shape[0] == 1:
        return rhs / S[0, 0]
    if S.shape[0] <= SMALL_DENSE:
        L = small_cho_factor(Ss)
        solution = small_cho_solve(L, Dr * rhs)
    else:
        L = jax.scipy.linalg.cho_factor(Ss, lower=True)[0]
        solution = jax.scipy.linalg.cho_solve((L, True), Dr * rhs)
    pivots = jnp.diag(L) ** 2
    deficient = ~(jnp.min(pivots) > RANK_RTOL * jnp.max(pivots))
    y = rarely(deficient, basic_solve, solution, Ss, Dr * rhs)
    return Dr * y


class Factor(NamedTuple):
    """A factorised ``S``: the solver's arrays, ``||S||_inf`` (bounded above) and whether
    ``S`` can be solved with (``ok``: false for a singular ``S`` that SuperLU cannot hand
    to the dense solve, and for a factor with non-finite values)."""

    data: Any
    norm: jax.Array
    ok: jax.Array


class Schur:
    """Solves with ``S = G M^{-1} G^T``: ``factor(q, t)`` once, then ``solve`` any number of times.

    This class is the dense solver (``S`` formed and factorised by Cholesky under the rank
    policy, :func:`spd_solve`) and the interface of the structured ones.

    Parameters
    ----------
    G : callable
        ``G(q, t) -> (m, n)``, the constraint Jacobian.
    solve_mass : callable
        ``solve_mass(q, b) -> M(q)^{-1} b`` for a matrix ``b`` of columns.

    Attributes
    ----------
    name : str
        ``"dense"``, ``"banded"`` or ``"superlu"`` (recorded with every run).
    nnz : int or None
        Structural nonzeros of ``G`` (``None`` on the dense path, which needs no pattern).
    """

    name = "dense"
    nnz: int | None = None

    def __init__(self, G: Callable[[jax.Array, jax.Array], jax.Array],
                 solve_mass: Callable[[jax.Array, jax.Array], jax.Array]):
        self.G, self.solve_mass = G, solve_mass

    def factor(self, q: jax.Array, t: jax.Array) -> Factor:
        G = self.G(q, t)
        S = G @ self.solve_mass(q, G.T)
        return Factor(S, jnp.max(jnp.sum(jnp.abs(S), axis=1), initial=0.0), jnp.asarray(True))

    def solve(self, F: Factor, rhs: jax.Array) -> jax.Array:
        """``S^{-1} rhs`` for a vector or an ``(m, k)`` matrix of columns."""
        return spd_solve(F.data, rhs)

