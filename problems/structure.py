"""Linear algebra chosen by the structure of the constraints.

Every family solves systems with the constraint Schur complement

.. math::

    S(q, t) = G(q, t)\\, M^{-1} G(q, t)^T \\qquad (m \\times m,\\ \\text{symmetric positive
    definite when } G \\text{ has full rank}),

in RATTLE's projections, in the eliminated stage equations of SPARK and in the index-1
accelerations of Baumgarte's method. Dense Cholesky of ``S`` costs ``O(m^3)`` and forming
``G`` densely ``O(m n)`` memory; the constraints of a chain, a truss or a ring of bars touch a
handful of coordinates each, so ``G`` has ``O(m)`` entries and ``S`` is sparse. Three
solvers share one interface (:class:`Schur`: ``factor(q, t)`` then ``solve(factor, r)``):

``dense``
    ``G`` by forward-mode autodiff, ``S`` formed and factorised by Cholesky: one compiled
    kernel, the fastest path for small systems (and the only one for a configuration-
    dependent or non-diagonal mass).
``banded``
    ``G``'s values by compressed autodiff (:meth:`problems.mechanics.Mechanics.G_values`),
    ``S`` assembled by gathers in a bandwidth-reducing order (reverse Cuthill-McKee) and
    factorised by a banded Cholesky written in JAX, so that it stays inside the compiled
    loop. Rows of ``G`` with many entries (a ring's hub rows: the centre of mass involves
    every point) would make the band full; they are kept as a dense *border* and
    eliminated through the Schur complement of the banded core. Cost ``O(m w^2)`` for
    bandwidth ``w``.
``superlu``
    The general sparse path: ``S`` assembled on the host from ``G``'s values with scipy and
    factorised by SuperLU (fill-reducing minimum-degree ordering of ``S + S^T``, no
    pivoting off the diagonal since ``S`` is positive definite), reached from the compiled
    loop by a callback. The factor of the last ``S`` is kept, so the solves of one step with
    the same ``G`` factorise once.

:func:`schur` picks by structure: ``dense`` for at most :data:`DENSE_MAX` constraints or a
mass that is not a constant diagonal; otherwise ``banded`` when the bandwidth of the core
after reordering is at most :data:`BAND_MAX`, else ``superlu``.

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
and without leaving the compiled loop (:func:`band_cholesky`); SuperLU, which cannot, hands
a singular ``S`` to a dense basic solve on the host for up to :data:`FALLBACK_MAX`
constraints, and above that the step fails with that message.
"""

from __future__ import annotations

import hashlib
from functools import cached_property
from typing import TYPE_CHECKING, Any, Callable, NamedTuple

import asdex
import jax
import jax.experimental.sparse as jsparse
import jax.numpy as jnp
import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import reverse_cuthill_mckee

if TYPE_CHECKING:
    from problems.mechanics import Mechanics

#: Pivot ratio below which a factorisation is taken as numerically rank deficient.
RANK_RTOL = 1e-12

#: Largest number of constraints solved densely by default. Measured with RATTLE on the
#: chain (``python -m benchmarks.perf.scaling``): dense is faster below about this size.
DENSE_MAX = 8

#: Largest core bandwidth the banded Cholesky takes; wider bands go to SuperLU (its cost
#: per row grows like the bandwidth squared, and the band solve is unrolled to this width).
BAND_MAX = 16

#: A row of ``G`` with more entries than this (and than four times the median row) joins
#: the dense border of the banded solver.
BORDER_MIN = 32

#: Largest number of constraints for which SuperLU, finding ``S`` singular, falls back to a
#: dense rank-revealing solve of ``S`` on the host (0.13 GB at 4096 constraints); larger
#: systems fail the step instead.
FALLBACK_MAX = 4096

#: Names a run may ask for.
KINDS = ("auto", "dense", "banded", "superlu")


# --- dense: the one rank-deficiency policy --------------------------------------------------
def power_of_two_scale(x: jax.Array) -> jax.Array:
    """``2^-round(log2 x)`` for ``x > 0`` (1 where ``x`` is 0): scaling by it is exact."""
    return jnp.where(x > 0, jnp.exp2(-jnp.round(jnp.log2(jnp.where(x > 0, x, 1.0)))), 1.0)


def basic_solve(A: jax.Array, b: jax.Array, rtol: float = RANK_RTOL) -> jax.Array:
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
    """``A^{-1} b`` by LU of the equilibrated ``A``; the basic solution if rank deficient.

    A 1 x 1 system is a division: a LAPACK call is opaque to XLA's fusion and costs
    microseconds, most of a small problem's step for a single constraint. Otherwise
    ``D_r A D_c`` (power-of-two row and column scalings, exact) is factorised by LU with
    partial pivoting; when its smallest pivot is below :data:`RANK_RTOL` times the largest
    (or not finite) the solve switches to :func:`basic_solve` on the equilibrated system
    (see the module notes).
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
    y = jax.lax.cond(deficient, lambda: basic_solve(As, rb),
                     lambda: jax.scipy.linalg.lu_solve((lu, piv), rb))
    return y * (c[:, None] if b.ndim == 2 else c)


def unit_diagonal(d: jax.Array) -> jax.Array:
    """``1 / sqrt(d)`` where ``d > 0`` (1 elsewhere): the scaling of ``S`` to unit diagonal."""
    return jnp.where(d > 0, 1.0 / jnp.sqrt(jnp.where(d > 0, d, 1.0)), 1.0)


def spd_solve(S: jax.Array, rhs: jax.Array) -> jax.Array:
    """``S^{-1} rhs`` for a symmetric positive semidefinite ``S``, under the one policy.

    ``S`` is scaled to unit diagonal (``D S D``) and factorised by Cholesky; if its
    smallest squared pivot is below :data:`RANK_RTOL` times the largest, or the factor
    breaks down, the basic solution of the scaled system is used (:func:`basic_solve`).
    """
    D = unit_diagonal(jnp.diag(S))
    Ss = S * D[:, None] * D[None, :]
    Dr = D[:, None] if rhs.ndim == 2 else D
    if S.shape[0] == 1:
        return rhs / S[0, 0]
    factor = jax.scipy.linalg.cho_factor(Ss, lower=True)
    pivots = jnp.diag(factor[0]) ** 2
    deficient = ~(jnp.min(pivots) > RANK_RTOL * jnp.max(pivots))
    y = jax.lax.cond(deficient, lambda: basic_solve(Ss, Dr * rhs),
                     lambda: jax.scipy.linalg.cho_solve(factor, Dr * rhs))
    return Dr * y


def gather(a: jax.Array, index: jax.Array) -> jax.Array:
    """``a[index]`` along the first axis, as a gather with a flat index.

    XLA:CPU compiles a loop into one native kernel only if its gathers take a flat index
    (measured: a ``(k, 2)`` index array keeps the loop out of the kernel).
    """
    return jnp.take(a, index.ravel(), axis=0).reshape(index.shape + a.shape[1:])


# --- compressed Jacobians ----------------------------------------------------------------
class SparseJacobian:
    """The Jacobian of ``f: R^n -> R^m`` by compressed autodiff, its pattern traced from ``f``.

    Column colouring (forward mode) fails on a Jacobian with dense rows, row colouring
    (reverse mode) on one with dense columns, and a ring's hub makes both: its constraint
    rows involve every point and their multipliers act on every point. Rows and columns
    with more than :data:`BORDER_MIN` entries (and four times the median) are therefore
    evaluated one by one (a reverse pass per dense row, a forward pass per dense column),
    and the rest of the pattern is coloured by columns (greedy colouring of the column
    intersection graph): about ``c + d`` passes for ``c`` colours and ``d`` dense lines
    instead of ``n``.

    Parameters
    ----------
    f : callable
        ``f(x) -> (m,)``, JAX-traceable.
    x : array
        A point of the right shape (the pattern is structural, not taken from values).
    """

    def __init__(self, f: Callable[[jax.Array], jax.Array], x: jax.Array):
        pattern = asdex.jacobian_sparsity(f, x)
        self.shape = (pattern.m, pattern.n)
        self.rows = np.asarray(pattern.rows, dtype=np.int64)
        self.cols = np.asarray(pattern.cols, dtype=np.int64)
        self.nnz = len(self.rows)
        m, n = self.shape
        row_count = np.bincount(self.rows, minlength=m)
        col_count = np.bincount(self.cols, minlength=n)
        dense_rows = row_count > max(BORDER_MIN, 4 * np.median(row_count))
        dense_cols = col_count > max(BORDER_MIN, 4 * np.median(col_count))
        self.dense_rows = np.flatnonzero(dense_rows)
        self.dense_cols = np.flatnonzero(dense_cols)
        rest = ~dense_rows[self.rows] & ~dense_cols[self.cols]
        reduced = sp.coo_matrix((np.ones(rest.sum()), (self.rows[rest], self.cols[rest])),
                                shape=(m, n)).toarray() if m * n <= 1 << 22 else \
            jsparse.BCOO((jnp.ones(rest.sum()), jnp.asarray(np.stack(
                [self.rows[rest], self.cols[rest]], 1))), shape=(m, n))
        colour = np.asarray(asdex.jacobian_coloring_from_sparsity(reduced, mode="fwd").colors)
        self.n_colours = int(colour.max(initial=-1)) + 1
        seeds = np.zeros((self.n_colours, n))
        seeds[colour[self.cols[rest]], self.cols[rest]] = 1.0
        self.seeds = jnp.asarray(seeds)
        # Where each entry of the pattern is read from, in the stacked passes
        # [J seeds^T (m x c) | J e_j for dense j (m x d_c)] and [e_i^T J (d_r x n)].
        where_col = np.full(n, -1)
        where_col[self.dense_cols] = np.arange(len(self.dense_cols))
        where_row = np.full(m, -1)
        where_row[self.dense_rows] = np.arange(len(self.dense_rows))
        forward = np.where(dense_cols[self.cols], self.n_colours + where_col[self.cols],
                           colour[self.cols].clip(0))
        from_rows = dense_rows[self.rows]
        self.forward_index = jnp.asarray(self.rows * (self.n_colours + len(self.dense_cols))
                                         + forward)
        self.reverse_index = jnp.asarray(where_row[self.rows].clip(0) * n + self.cols)
        self.from_rows = jnp.asarray(from_rows)
        self.f = f

    def values(self, x: jax.Array, f: Callable[[jax.Array], jax.Array] | None = None) -> jax.Array:
        """The Jacobian's entries at ``x``, in the order of ``rows``, ``cols``.

        ``f`` defaults to the traced function; another with the same pattern (the same
        function with other parameters) may be passed.
        """
        f = self.f if f is None else f
        directions = jnp.concatenate([self.seeds, jnp.eye(self.shape[1])[self.dense_cols]])
        forward = jax.vmap(lambda d: jax.jvp(f, (x,), (d,))[1])(directions).T
        values = gather(forward.ravel(), self.forward_index)
        if len(self.dense_rows):
            pullback = jax.vjp(f, x)[1]
            reverse = jax.vmap(lambda e: pullback(e)[0])(jnp.eye(self.shape[0])[self.dense_rows])
            values = jnp.where(self.from_rows, gather(reverse.ravel(), self.reverse_index),
                               values)
        return values


# --- banded Cholesky in JAX -------------------------------------------------------------------
def unroll(w: int) -> int:
    """Rows per scan iteration: a narrow band's row is a few operations, and unrolling 16
    of them halved the cost per row of the tridiagonal factor and solve (m = 16384)."""
    return max(1, 16 // w)


def pivot(d2: jax.Array, diagonal: jax.Array) -> jax.Array:
    """A Cholesky pivot ``sqrt(d2)``, or 0 for a dependent row: ``d2 <= RANK_RTOL diagonal``."""
    return jnp.where(d2 > RANK_RTOL * diagonal, jnp.sqrt(jnp.where(d2 > 0, d2, 1.0)), 0.0)


def divide(a: jax.Array, d: jax.Array) -> jax.Array:
    """``a / d``, and 0 where the pivot ``d`` is 0 (a dropped row: its unknown is zero)."""
    return jnp.where(d != 0, a / jnp.where(d != 0, d, 1.0), 0.0)


def band_cholesky(Sb: jax.Array) -> jax.Array:
    """Cholesky factor of a symmetric positive semidefinite band matrix, row by row.

    ``Sb[i, k] = S[i, i - k]`` for ``k = 0..w`` (zero above the matrix). Returns ``Lb`` of the
    same layout with ``S = L L^T``. Row ``i`` of ``L`` within the band solves the triangular
    system ``L_W x = S[i, i-w:i]`` with the ``w x w`` window ``L_W`` of the previous rows,
    then ``L_ii = sqrt(S_ii - x^T x)``: ``O(w^2)`` per row, carried by a scan of plain
    arithmetic (the substitution is unrolled: a LAPACK call would keep XLA from compiling
    the loop into one kernel).

    A row whose squared pivot ``S_ii - x^T x`` is at most :data:`RANK_RTOL` ``S_ii`` depends
    on the rows before it: it gets ``L_ii = 0`` and a zero column below, so that the
    remaining rows are factorised as if it were absent, and :func:`band_solve` sets its
    unknown to zero (the basic solution of the module notes).
    """
    w = Sb.shape[1] - 1

    def row(W, s):
        x = []
        for a in range(w):
            acc = s[a]
            for l in range(a):
                acc = acc - W[a, l] * x[l]
            x.append(divide(acc, W[a, a]))
        x = jnp.stack(x)
        d = pivot(s[w] - x @ x, s[w])
        top = jnp.concatenate([W[1:, 1:], jnp.zeros((w - 1, 1))], axis=1)
        W = jnp.concatenate([top, jnp.concatenate([x[1:], d[None]])[None, :]], axis=0)
        return W, jnp.concatenate([x, d[None]])

    _, L = jax.lax.scan(row, jnp.eye(w), Sb[:, ::-1], unroll=unroll(w))
    return L[:, ::-1]


def band_solve(Lb: jax.Array, r: jax.Array) -> jax.Array:
    """``(L L^T)^{-1} r`` for a band Cholesky factor (layout of :func:`band_cholesky`).

    ``r`` has shape ``(m, k)``: forward substitution with ``L``, then back substitution
    with ``L^T``, each a scan carrying the last ``w`` solved rows. Dropped rows (zero
    pivots) get zero unknowns.
    """
    m, w = Lb.shape[0], Lb.shape[1] - 1
    lower = Lb[:, :0:-1]  # L[i, i-w .. i-1]
    diag = Lb[:, 0]

    def forward(y, row):
        li, di, ri = row
        yi = divide(ri - li @ y, di)
        return jnp.concatenate([y[1:], yi[None]]), yi

    _, y = jax.lax.scan(forward, jnp.zeros((w, r.shape[1])), (lower, diag, r), unroll=unroll(w))
    # L^T's row i holds L[i + k, i] = Lb[i + k, k], k = 1..w.
    padded = jnp.concatenate([Lb, jnp.zeros((w, w + 1))])
    upper = jnp.stack([padded[k:k + m, k] for k in range(1, w + 1)], axis=1)

    def backward(x, row):
        ui, di, yi = row
        xi = divide(yi - ui @ x, di)
        return jnp.concatenate([xi[None], x[:-1]]), xi

    _, x = jax.lax.scan(backward, jnp.zeros((w, r.shape[1])), (upper, diag, y), reverse=True,
                        unroll=unroll(w))
    return x


def small_cholesky(T: jax.Array) -> jax.Array:
    """Cholesky factor of a small dense positive semidefinite matrix, unrolled (no LAPACK
    call in the loop), dropping dependent rows as :func:`band_cholesky` does."""
    k = T.shape[0]
    L = [[None] * k for _ in range(k)]
    for i in range(k):
        for j in range(i + 1):
            acc = T[i, j] - sum((L[i][l] * L[j][l] for l in range(j)), jnp.asarray(0.0))
            L[i][j] = pivot(acc, T[i, i]) if i == j else divide(acc, L[j][j])
    return jnp.stack([jnp.stack([L[i][j] if j <= i else jnp.asarray(0.0) for j in range(k)])
                      for i in range(k)])


def small_cho_solve(L: jax.Array, r: jax.Array) -> jax.Array:
    """``(L L^T)^{-1} r`` for :func:`small_cholesky`'s factor, unrolled; ``r`` is ``(k, p)``."""
    k = L.shape[0]
    y = []
    for i in range(k):
        y.append(divide(r[i] - sum((L[i, l] * y[l] for l in range(i)), jnp.zeros_like(r[i])),
                        L[i, i]))
    x = [None] * k
    for i in reversed(range(k)):
        x[i] = divide(y[i] - sum((L[l, i] * x[l] for l in range(i + 1, k)), jnp.zeros_like(r[i])),
                      L[i, i])
    return jnp.stack(x)


# --- the solvers --------------------------------------------------------------------------------
class Factor(NamedTuple):
    """A factorised ``S``: the solver's arrays, ``||S||_inf`` (bounded above) and whether
    ``S`` can be solved with (``ok``: false for a singular ``S`` that SuperLU cannot hand
    to the dense solve, and for a factor with non-finite values)."""

    data: Any
    norm: jax.Array
    ok: jax.Array


class Schur:
    """Solves with ``S = G M^{-1} G^T``: ``factor(q, t)`` once, then ``solve`` any number of times.

    Attributes
    ----------
    name : str
        ``"dense"``, ``"banded"`` or ``"superlu"`` (recorded with every run).
    nnz : int or None
        Structural nonzeros of ``G`` (``None`` on the dense path, which needs no pattern).
    """

    name = "dense"
    nnz: int | None = None

    def __init__(self, mech: "Mechanics"):
        self.mech = mech

    def factor(self, q: jax.Array, t: jax.Array) -> Factor:
        mech = self.mech
        G = mech.G(q, t)
        S = G @ mech.solve_mass(q, G.T)
        return Factor(S, jnp.max(jnp.sum(jnp.abs(S), axis=1), initial=0.0), jnp.asarray(True))

    def solve(self, F: Factor, rhs: jax.Array) -> jax.Array:
        """``S^{-1} rhs`` for a vector or an ``(m, k)`` matrix of columns."""
        return spd_solve(F.data, rhs)


class Pattern:
    """The structure of ``S`` built once from ``G``'s sparsity and a constant diagonal mass."""

    def __init__(self, mech: "Mechanics"):
        self.mech = mech
        sparsity = mech.G_coloring.sparsity
        m, n = mech.m, mech.n
        self.rows = np.asarray(sparsity.rows, dtype=np.int64)
        self.cols = np.asarray(sparsity.cols, dtype=np.int64)
        self.nnz = len(self.rows)
        counts = np.bincount(self.rows, minlength=m)
        wide = counts > max(BORDER_MIN, 4 * np.median(counts))
        self.border = np.flatnonzero(wide)
        core = np.flatnonzero(~wide)
        in_core = ~wide[self.rows]
        entries = sp.csr_matrix((np.ones(in_core.sum()), (self.rows[in_core], self.cols[in_core])),
                                shape=(m, n))[core]
        adjacency = (entries @ entries.T).tocsr()
        perm = np.asarray(reverse_cuthill_mckee(adjacency, symmetric_mode=True), dtype=np.int64)
        self.core = core[perm]  # constraint index of each core position
        self.order = np.concatenate([self.core, self.border])
        self.inverse = np.argsort(self.order)
        coo = adjacency.tocoo()
        rank = perm.argsort()
        spread = np.abs(rank[coo.row] - rank[coo.col])
        self.bandwidth = int(max(1, spread.max(initial=0)))

    @cached_property
    def gathers(self):
        """Index arrays that assemble the band of ``S`` and the border blocks by gathers."""
        m, n, w = self.mech.m, self.mech.n, self.bandwidth
        mc = len(self.core)
        position = np.full(m, -1)
        position[self.core] = np.arange(mc)
        sentinel = self.nnz  # index of an appended zero
        # Band slots: every pair of core entries sharing a column contributes
        # G_e1 G_e2 / M_jj to S[pos(e1), pos(e2)] (pos(e1) >= pos(e2)).
        order = np.argsort(self.cols, kind="stable")
        cols_sorted = self.cols[order]
        starts = np.searchsorted(cols_sorted, np.arange(n + 1))
        slot, first, second, column = [], [], [], []
        for j in range(n):
            es = [e for e in order[starts[j]:starts[j + 1]] if position[self.rows[e]] >= 0]
            for e1 in es:
                for e2 in es:
                    p1, p2 = position[self.rows[e1]], position[self.rows[e2]]
                    if p1 >= p2:
                        slot.append(p1 * (w + 1) + (p1 - p2))
                        first.append(e1)
                        second.append(e2)
                        column.append(j)
        slot = np.asarray(slot, dtype=np.int64)
        per_slot = np.bincount(slot, minlength=mc * (w + 1))
        depth = max(1, int(per_slot.max(initial=0)))
        index = np.full((mc * (w + 1), depth, 3), [sentinel, sentinel, n], dtype=np.int64)
        by_slot = np.argsort(slot, kind="stable")
        rank = np.arange(len(slot)) - np.repeat(np.cumsum(per_slot) - per_slot, per_slot)
        index[slot[by_slot], rank] = np.stack([np.asarray(first)[by_slot],
                                               np.asarray(second)[by_slot],
                                               np.asarray(column)[by_slot]], axis=1)
        # Core rows of G, padded (for S_cb = G_c M^{-1} G_b^T).
        row_counts = np.bincount(position[self.rows][position[self.rows] >= 0], minlength=mc)
        width = max(1, int(row_counts.max(initial=0)))
        core_entries = np.full((mc, width), sentinel, dtype=np.int64)
        core_cols = np.zeros((mc, width), dtype=np.int64)
        mask = position[self.rows] >= 0
        e_core = np.flatnonzero(mask)
        p = position[self.rows[e_core]]
        by_row = np.argsort(p, kind="stable")
        r_rank = np.arange(len(p)) - np.repeat(np.cumsum(row_counts) - row_counts, row_counts)
        core_entries[p[by_row], r_rank] = e_core[by_row]
        core_cols[p[by_row], r_rank] = self.cols[e_core[by_row]]
        # Border rows of G, dense.
        border_index = np.full((len(self.border), n), sentinel, dtype=np.int64)
        where = np.full(m, -1)
        where[self.border] = np.arange(len(self.border))
        e_border = np.flatnonzero(where[self.rows] >= 0)
        border_index[where[self.rows[e_border]], self.cols[e_border]] = e_border
        return (jnp.asarray(index), jnp.asarray(core_entries), jnp.asarray(core_cols),
                jnp.asarray(border_index))


class Banded(Schur):
    """Banded Cholesky of the reordered core of ``S`` with a dense border (see module notes)."""

    name = "banded"

    def __init__(self, mech: "Mechanics", pattern: Pattern):
        super().__init__(mech)
        self.pattern = pattern
        self.nnz = pattern.nnz
        self.gathers = pattern.gathers
        self.core, self.border, self.inverse = (jnp.asarray(pattern.core),
                                                jnp.asarray(pattern.border),
                                                jnp.asarray(pattern.inverse))

    def factor(self, q, t) -> Factor:
        mech, pat = self.mech, self.pattern
        index, core_entries, core_cols, border_index = self.gathers
        w, mc, nb = pat.bandwidth, len(pat.core), len(pat.border)
        Gx = jnp.concatenate([mech.G_values(q, t), jnp.zeros(1)])
        dinv = jnp.asarray(1.0 / mech.mass_diagonal)
        dx = jnp.concatenate([dinv, jnp.zeros(1)])
        Sb = jnp.sum(gather(Gx, index[..., 0]) * gather(Gx, index[..., 1])
                     * gather(dx, index[..., 2]), axis=1)
        Sb = Sb.reshape(mc, w + 1)
        Dc = unit_diagonal(Sb[:, 0])
        shifted = jnp.stack([jnp.concatenate([jnp.zeros(k), Dc[:mc - k]]) for k in range(w + 1)], 1)
        Ss = Sb * Dc[:, None] * shifted
        L = band_cholesky(Ss)
        absband = jnp.abs(Sb)
        padded = jnp.concatenate([absband, jnp.zeros((w, w + 1))])
        norm = jnp.max(jnp.sum(absband, 1) - absband[:, 0]
                       + sum(padded[k:k + mc, k] for k in range(w + 1)))
        if nb == 0:
            return Factor((L, Dc, None, None, None, None), norm, jnp.all(jnp.isfinite(L)))
        Gb = gather(Gx, border_index)                             # (nb, n)
        MinvGbT = (Gb * dinv[None, :]).T                          # (n, nb)
        Scb = jnp.einsum("ir,irb->ib", gather(Gx, core_entries), gather(MinvGbT, core_cols))
        Sbb = Gb @ MinvGbT
        Db = unit_diagonal(jnp.diag(Sbb))
        Scb_s = Scb * Dc[:, None] * Db[None, :]
        X = band_solve(L, Scb_s)
        T = Sbb * Db[:, None] * Db[None, :] - Scb_s.T @ X
        LT = small_cholesky(T)
        ok = jnp.all(jnp.isfinite(L)) & jnp.all(jnp.isfinite(LT))
        norm = jnp.maximum(norm + jnp.max(jnp.sum(jnp.abs(Scb), 1)),
                           jnp.max(jnp.sum(jnp.abs(Scb), 0) + jnp.sum(jnp.abs(Sbb), 1)))
        return Factor((L, Dc, Db, Scb_s, X, LT), norm, ok)

    def solve(self, F: Factor, rhs):
        pat = self.pattern
        L, Dc, Db, Scb_s, X, LT = F.data
        r = rhs[:, None] if rhs.ndim == 1 else rhs
        rc = gather(r, self.core) * Dc[:, None]
        y = band_solve(L, rc)
        if Db is None:
            out = y * Dc[:, None]
        else:
            rb = gather(r, self.border) * Db[:, None]
            lb = small_cho_solve(LT, rb - Scb_s.T @ y)
            out = jnp.concatenate([(y - X @ lb) * Dc[:, None], lb * Db[:, None]])
        out = gather(out, self.inverse)
        return out[:, 0] if rhs.ndim == 1 else out


class SuperLU(Schur):
    """``S`` assembled and factorised on the host by SuperLU, reached by a callback."""

    name = "superlu"

    def __init__(self, mech: "Mechanics", pattern: Pattern):
        super().__init__(mech)
        self.pattern = pattern
        self.nnz = pattern.nnz
        m, n = mech.m, mech.n
        self._G = sp.csr_matrix((np.arange(1, pattern.nnz + 1, dtype=np.float64),
                                 (pattern.rows, pattern.cols)), shape=(m, n))
        # Position in the CSR data of each pattern entry (the CSR sorts them).
        self._slot = np.empty(pattern.nnz, dtype=np.int64)
        self._slot[self._G.data.astype(np.int64) - 1] = np.arange(pattern.nnz)
        self._dinv = sp.diags(1.0 / np.asarray(mech.mass_diagonal))
        self._last: tuple[bytes, Any] | None = None

    def _factorise(self, values: np.ndarray):
        """A solver for the unit-diagonal ``S`` of ``G``'s values (the last one is kept):
        SuperLU's factor, or for a singular ``S`` of at most :data:`FALLBACK_MAX` rows the
        dense ``S`` (solved by least squares, rank by :data:`RANK_RTOL`), or ``None``."""
        key = hashlib.blake2b(values.tobytes(), digest_size=16).digest()
        if self._last is not None and self._last[0] == key:
            return self._last[1]
        if not np.all(np.isfinite(values)):  # a diverged iterate: the step fails, as data
            entry = (None, None, np.nan, False)
            self._last = (key, entry)
            return entry
        G = self._G.copy()
        G.data = values[self._slot]
        S = (G @ self._dinv @ G.T).tocsc()
        D = 1.0 / np.sqrt(np.maximum(S.diagonal(), np.finfo(float).tiny))
        Ss = (sp.diags(D) @ S @ sp.diags(D)).tocsc()
        norm = float(np.max(np.asarray(abs(S).sum(axis=1)), initial=0.0))
        try:
            lu = spla.splu(Ss, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                           options=dict(SymmetricMode=True))
            pivots = np.abs(lu.U.diagonal())
            solver = lu.solve if pivots.min() > RANK_RTOL * pivots.max() else None
        except RuntimeError:  # exactly singular
            solver = None
        if solver is None and S.shape[0] <= FALLBACK_MAX:
            # The minimum-norm solution, not the basic one: both are exact for a
            # consistent system and give the same constraint force.
            def solver(r, dense=Ss.toarray()):
                return scipy.linalg.lstsq(dense, r, cond=RANK_RTOL)[0]
        entry = (solver, D, norm, solver is not None)
        self._last = (key, entry)
        return entry

    def factor(self, q, t) -> Factor:
        values = self.mech.G_values(q, t)

        def host(values):
            _, _, norm, ok = self._factorise(np.asarray(values))
            return np.float64(norm), np.bool_(ok)

        norm, ok = jax.pure_callback(
            host, (jax.ShapeDtypeStruct((), jnp.float64), jax.ShapeDtypeStruct((), jnp.bool_)),
            values, vmap_method="sequential")
        return Factor(values, norm, ok)

    def solve(self, F: Factor, rhs):
        def host(values, rhs):
            solver, D, _, ok = self._factorise(np.asarray(values))
            r = np.asarray(rhs)
            # A singular S, or a diverged Newton iterate: NaN, which fails the step with
            # the loop's message instead of raising out of the compiled loop.
            if not ok or not np.all(np.isfinite(r)):
                return np.full(rhs.shape, np.nan)
            Dr = D[:, None] if r.ndim == 2 else D
            return Dr * solver(Dr * r)

        return jax.pure_callback(host, jax.ShapeDtypeStruct(rhs.shape, jnp.float64),
                                 F.data, rhs, vmap_method="sequential")


def schur(mech: "Mechanics", kind: str = "auto") -> Schur:
    """The solver for ``S = G M^{-1} G^T`` of ``mech``: ``kind`` or, for ``"auto"``, by structure.

    Raises
    ------
    ValueError
        For an unknown ``kind``, or a structured one on a system whose mass is not a
        constant diagonal (the structured solvers assemble ``S`` with ``M^{-1}`` diagonal).
    """
    if kind not in KINDS:
        raise ValueError(f"linear_solver = {kind!r}: expected one of {', '.join(KINDS)}")
    diagonal = mech.mass_diagonal is not None
    if kind == "dense" or (kind == "auto" and (mech.m <= DENSE_MAX or not diagonal)):
        return Schur(mech)
    if not diagonal:
        raise ValueError(f"linear_solver = {kind!r} needs a constant diagonal mass; "
                         "this system's mass is not one (use dense)")
    pattern = Pattern(mech)
    if kind == "banded" or (kind == "auto" and pattern.bandwidth <= BAND_MAX):
        if pattern.bandwidth > 4 * BAND_MAX and kind == "banded":
            raise ValueError(f"linear_solver = 'banded': the core bandwidth {pattern.bandwidth} "
                             f"exceeds {4 * BAND_MAX} (use superlu)")
        return Banded(mech, pattern)
    return SuperLU(mech, pattern)
