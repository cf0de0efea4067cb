"""Banded Cholesky in JAX, inside the compiled loop: the ``banded`` solver for ``S``.

``S = G M^{-1} G^T`` is assembled by gathers from ``G``'s values in a bandwidth-reducing
order (reverse Cuthill-McKee, :class:`linalg.pattern.Pattern`) and factorised by a banded
Cholesky written in JAX, so that no LAPACK call leaves the loop. Rows of ``G`` with many
entries (a ring's hub rows: the centre of mass involves every point) would make the band
full; they are kept as a dense *border* and eliminated through the Schur complement of the
banded core. Cost ``O(m w^2)`` for bandwidth ``w``. Dependent rows are dropped as the
factorisation meets them (the basic solution of :mod:`linalg.dense`'s rank policy).
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from linalg.dense import RANK_RTOL, Factor, Schur, unit_diagonal
from linalg.compiled import device_index
from linalg.pattern import Pattern, gather, row_sum

#: Largest core bandwidth the banded Cholesky takes; wider bands go to SuperLU (its cost
#: per row grows like the bandwidth squared, and the band solve is unrolled to this width).
BAND_MAX = 16


def unroll(w: int) -> int:
    """Rows per scan iteration: a narrow band's row is a few operations, and the scan's own
    cost per iteration is most of it. Four rows are best, or within the noise of best, for
    the factor and the solve at bandwidths 1, 2 and 6; wider bands, whose rows are long
    already, take
    fewer (their code grows like the bandwidth squared times the rows unrolled). The same
    rule serves :mod:`linalg.kkt`'s band ``L D L^T``; bandwidths 7 and 8 (``four-bar``'s
    augmented system has 7) take four rows like 6 without a measurement of their own."""
    return 4 if w <= 8 else max(1, 16 // w)


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

    Each row multiplies by its pivot's reciprocal (0 for a dropped row), computed for all
    rows before the scans: a substitution is a chain, each row waiting for the one before,
    and a division in it, whose latency is several multiplications', would set its pace.
    """
    m, w = Lb.shape[0], Lb.shape[1] - 1
    lower = Lb[:, :0:-1]  # L[i, i-w .. i-1]
    inv = divide(1.0, Lb[:, 0])

    def forward(y, row):
        li, di, ri = row
        yi = (ri - li @ y) * di
        return jnp.concatenate([y[1:], yi[None]]), yi

    _, y = jax.lax.scan(forward, jnp.zeros((w, r.shape[1])), (lower, inv, r), unroll=unroll(w))
    # L^T's row i holds L[i + k, i] = Lb[i + k, k], k = 1..w.
    padded = jnp.concatenate([Lb, jnp.zeros((w, w + 1))])
    upper = jnp.stack([padded[k:k + m, k] for k in range(1, w + 1)], axis=1)

    def backward(x, row):
        ui, di, yi = row
        xi = (yi - ui @ x) * di
        return jnp.concatenate([xi[None], x[:-1]]), xi

    _, x = jax.lax.scan(backward, jnp.zeros((w, r.shape[1])), (upper, inv, y), reverse=True,
                        unroll=unroll(w))
    return x


def band_norm(Sb: jax.Array) -> jax.Array:
    """``||S||_inf = max_i sum_j |S_ij|`` of the symmetric band matrix ``Sb[i, k] = S[i, i - k]``.

    Row ``i`` holds ``S[i, i - k] = Sb[i, k]`` left of the diagonal and ``S[i, i + k] =
    Sb[i + k, k]`` right of it. Summed over the transposed band, whose columns ``k`` are
    contiguous rows there: taken from the band itself, each strided column is a pass of
    its own before the reduction, a cost RATTLE's step pays through its stall test. Both
    orders give the same norm to its last bit.
    """
    A = jnp.abs(Sb).T
    left = sum(A[k] for k in range(len(A)))   # the diagonal and left of it
    right = sum(jnp.concatenate([A[k, k:], jnp.zeros(k)]) for k in range(1, len(A)))
    return jnp.max(left + right)


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


class Banded(Schur):
    """Banded Cholesky of the reordered core of ``S`` with a dense border (see module notes).

    Parameters
    ----------
    pattern : Pattern
        The structure of ``S``.
    G_values : callable
        ``G_values(q, t) -> (nnz,)``: ``G``'s entries in the order of ``pattern``.
    mass_diagonal : ndarray, shape (n,)
        The constant diagonal of ``M``.
    """

    name = "banded"

    def __init__(self, pattern: Pattern, G_values: Callable[[jax.Array, jax.Array], jax.Array],
                 mass_diagonal: np.ndarray):
        self.pattern, self.G_values, self.mass_diagonal = pattern, G_values, mass_diagonal
        self.nnz = pattern.nnz
        self.gathers = pattern.gathers
        self.core, self.border, self.inverse, self.cols = (
            device_index(a) for a in (pattern.core, pattern.border, pattern.inverse, pattern.cols))
        self.dinv = jnp.asarray(1.0 / mass_diagonal)
        # A unit mass (a whitened block-diagonal one: Mechanics.schur) needs no scaling.
        self.unit = bool(np.all(np.asarray(mass_diagonal) == 1.0))

    def factor(self, q, t) -> Factor:
        pat = self.pattern
        band, place, core_entries, core_cols, border_index = self.gathers
        w, mc, nb = pat.bandwidth, len(pat.core), len(pat.border)
        Gx = jnp.concatenate([self.G_values(q, t), jnp.zeros(1)])
        # 1 / M_jj of each entry's column: both entries of a pair share it.
        dx = None if self.unit else gather(self.dinv, self.cols)
        sums = []
        for first, second in band:
            products = gather(Gx, first) * gather(Gx, second)
            if dx is not None:
                products = products * gather(dx, first)
            sums.append(row_sum(products))
        Sb = gather(jnp.concatenate(sums + [jnp.zeros(1)]), place).reshape(mc, w + 1)
        Dc = unit_diagonal(Sb[:, 0])
        shifted = jnp.stack([jnp.concatenate([jnp.zeros(k), Dc[:mc - k]]) for k in range(w + 1)], 1)
        Ss = Sb * Dc[:, None] * shifted
        L = band_cholesky(Ss)
        norm = band_norm(Sb)
        if nb == 0:
            return Factor((L, Dc, None, None, None, None), norm, jnp.all(jnp.isfinite(L)))
        Gb = gather(Gx, border_index)                             # (nb, n)
        MinvGbT = (Gb * self.dinv[None, :]).T                    # (n, nb)
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


