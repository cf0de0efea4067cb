"""The augmented (KKT) system for a constant sparse mass: the ``kkt`` solver, and ``M`` banded.

Where ``M`` is constant but not diagonal (natural coordinates: a rod couples the points it
spans), ``M^{-1}`` is dense and so is ``S = G M^{-1} G^T``: forming it costs ``O(m n)``
memory and its factorisation ``O(m^3)``. The saddle-point system

.. math::

    K = \\begin{pmatrix} M & G^T \\\\ G & 0 \\end{pmatrix}, \\qquad
    K \\begin{pmatrix} x \\\\ -y \\end{pmatrix} = \\begin{pmatrix} 0 \\\\ r \\end{pmatrix}
    \\iff S y = r \\quad (x = M^{-1} G^T y),

is as sparse as ``M`` and ``G`` together, so solves with ``S`` are the second block of solves
with ``K`` (:class:`KKT`). ``K`` is symmetric indefinite; it is factorised as ``K = L D
L^T`` (``L`` unit lower triangular, ``D`` diagonal) without pivoting, in an order in which
every constraint comes after all the coordinates it involves (:func:`order`): then each
leading block is itself a saddle-point system of a principal block of ``M`` and the rows
of ``G`` that live on it, which is nonsingular exactly when those rows are independent, so
coordinates get positive pivots and constraints negative ones, and a constraint pivot
vanishes exactly where its row depends on the rows before it. Such a row is dropped as the
factorisation meets it (a pivot at most :data:`linalg.dense.RANK_RTOL` times the magnitude
of the terms it was computed from), which sets its multiplier to zero: the basic solution
of :mod:`linalg.dense`'s rank policy. The coordinates are ordered by reverse Cuthill-McKee
on the pattern of ``M + G^T G`` and each constraint is placed after its last coordinate,
so that a chain-like mechanism gives ``K`` a narrow band; the factorisation and the solves
are then banded scans in JAX that stay inside the compiled loop (as
:func:`linalg.banded.band_cholesky`), ``O((n + m) w^2)`` for bandwidth ``w``.

``K`` is scaled first, coordinates by ``M_jj^{-1/2}`` and constraints by ``(G diag(M)^{-1}
G^T)_ii^{-1/2}``, so that constraints in different units are not taken for dependent ones.

Solves with ``M`` itself (``M^{-1} x``, needed beside ``S``) use the banded Cholesky factor
of the constant ``M``, computed once (:class:`BandedMass`).
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import reverse_cuthill_mckee

from linalg.banded import band_cholesky, band_solve, divide, unroll
from linalg.dense import RANK_RTOL, Factor, Schur, unit_diagonal
from linalg.pattern import gather, row_sum

#: Largest bandwidth of the reordered ``K`` that the ``kkt`` solver takes (bricard, 48 unknowns
#: in all, gives 25; four-bar 7 at any N): its cost per row
#: grows like the bandwidth squared, and the factorisation is unrolled to this width.
KKT_BAND_MAX = 32


def band_ldl(Kb: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``K = L D L^T`` of a symmetric band matrix without pivoting, row by row.

    ``Kb[i, k] = K[i, i - k]`` for ``k = 0..w`` (zero above the matrix). Row ``i`` solves
    ``L_W u = K[i, i-w:i]`` with the unit lower ``w x w`` window ``L_W`` of the previous
    rows; then ``L[i, j] = u_j / D_j`` and ``D_i = K_ii - sum_j L[i, j] u_j``. A pivot
    whose magnitude is at most :data:`RANK_RTOL` times the sum of the magnitudes of those
    terms (``|K_ii| + sum_j |L[i, j] u_j|``) marks a row that depends on the rows before
    it: ``D_i = 0``, and its column of ``L`` is zero (module notes).

    Returns
    -------
    X : Array, shape (N, w)
        ``X[i, a] = L[i, i - w + a]`` (zero above the matrix).
    D : Array, shape (N,)
        The pivots (0 for a dropped row).
    """
    w = Kb.shape[1] - 1

    def row(carry, s):
        W, d = carry
        u = []
        for a in range(w):
            acc = s[a]
            for l in range(a):
                acc = acc - W[a, l] * u[l]
            u.append(acc)
        u = jnp.stack(u)
        x = divide(u, d)
        terms = x * u
        pivot = s[w] - jnp.sum(terms)
        scale = jnp.abs(s[w]) + jnp.sum(jnp.abs(terms))
        pivot = jnp.where(jnp.abs(pivot) > RANK_RTOL * scale, pivot, 0.0)
        top = jnp.concatenate([W[1:, 1:], jnp.zeros((w - 1, 1))], axis=1)
        W = jnp.concatenate([top, jnp.concatenate([x[1:], jnp.ones(1)])[None, :]], axis=0)
        return (W, jnp.concatenate([d[1:], pivot[None]])), (x, pivot)

    _, (X, D) = jax.lax.scan(row, (jnp.eye(w), jnp.ones(w)), Kb[:, ::-1], unroll=unroll(w))
    return X, D


def band_ldl_solve(X: jax.Array, D: jax.Array, r: jax.Array) -> jax.Array:
    """``K^{-1} r`` for :func:`band_ldl`'s factor; ``r`` is ``(N, k)``. Dropped rows get
    zero unknowns."""
    N, w = X.shape

    def forward(y, row):
        xi, ri = row
        yi = ri - xi @ y
        return jnp.concatenate([y[1:], yi[None]]), yi

    _, y = jax.lax.scan(forward, jnp.zeros((w, r.shape[1])), (X, r), unroll=unroll(w))
    z = divide(y, D[:, None])
    # L^T's row i holds L[i + k, i] = X[i + k, w - k], k = 1..w.
    padded = jnp.concatenate([X, jnp.zeros((w, w))])
    upper = jnp.stack([padded[k:k + N, w - k] for k in range(1, w + 1)], axis=1)

    def backward(x, row):
        ui, zi = row
        xi = zi - ui @ x
        return jnp.concatenate([xi[None], x[:-1]]), xi

    _, x = jax.lax.scan(backward, jnp.zeros((w, r.shape[1])), (upper, z), reverse=True,
                        unroll=unroll(w))
    return x


def rcm(A: sp.spmatrix) -> tuple[np.ndarray, np.ndarray, int]:
    """Reverse Cuthill-McKee order of a symmetric pattern: the order, the rank of each
    index in it, and the bandwidth it gives."""
    A = sp.coo_matrix(A)
    perm = np.asarray(reverse_cuthill_mckee(sp.csr_matrix(A), symmetric_mode=True),
                      dtype=np.int64)
    rank = np.argsort(perm)
    return perm, rank, int(max(1, np.max(np.abs(rank[A.row] - rank[A.col]), initial=0)))


def band_slots(rank_i: np.ndarray, rank_j: np.ndarray, w: int) -> np.ndarray:
    """Flat positions in an ``(N, w + 1)`` lower band layout of the entries ``(i, j)`` at
    ranks ``rank_i >= rank_j``."""
    return rank_i * (w + 1) + (rank_i - rank_j)


class BandedMass:
    """A constant sparse symmetric positive definite ``M``: products and solves in band form.

    ``M`` is reordered by reverse Cuthill-McKee, stored as a band and factorised once by
    :func:`linalg.banded.band_cholesky`; ``M x`` and ``M^{-1} x`` are then ``O(n w)``
    gathers and scans (``w`` the bandwidth) instead of dense ``O(n^2)`` products.

    Parameters
    ----------
    M : scipy.sparse matrix, shape (n, n)

    Raises
    ------
    ValueError
        If ``M`` is not positive definite (a pivot of its Cholesky factor is not positive).
    """

    def __init__(self, M: sp.spmatrix):
        M = sp.coo_matrix(M)
        self.n = n = M.shape[0]
        perm, rank, w = rcm(M)
        self.bandwidth = w
        ri, rj = rank[M.row], rank[M.col]
        lower = ri >= rj
        band = np.zeros(n * (w + 1))
        band[band_slots(ri[lower], rj[lower], w)] = M.data[lower]
        self.band = band.reshape(n, w + 1)
        self.order, self.inverse = jnp.asarray(perm), jnp.asarray(rank)
        self.L = jax.jit(band_cholesky)(jnp.asarray(self.band))
        if not np.all(np.asarray(self.L[:, 0]) > 0):
            raise ValueError("the mass matrix is not positive definite")

    def _columns(self, x: jax.Array, apply) -> jax.Array:
        cols = x[:, None] if x.ndim == 1 else x
        out = gather(apply(gather(cols, self.order)), self.inverse)
        return out[:, 0] if x.ndim == 1 else out

    def times(self, x: jax.Array) -> jax.Array:
        """``M x`` (a vector or ``(n, k)`` columns)."""
        n, w = self.n, self.bandwidth
        band = jnp.asarray(self.band)
        padded_band = jnp.concatenate([band, jnp.zeros((w, w + 1))])

        def apply(y):
            z = jnp.zeros((w,) + y.shape[1:])
            padded = jnp.concatenate([z, y, z])
            out = band[:, :1] * y
            for k in range(1, w + 1):
                out = out + band[:, k:k + 1] * padded[w - k:w - k + n]          # M[i, i-k]
                out = out + padded_band[k:k + n, k:k + 1] * padded[w + k:w + k + n]  # M[i, i+k]
            return out

        return self._columns(x, apply)

    def solve(self, b: jax.Array) -> jax.Array:
        """``M^{-1} b`` (a vector or ``(n, k)`` columns)."""
        return self._columns(b, lambda y: band_solve(self.L, y))


def order(M: sp.spmatrix, rows: np.ndarray, cols: np.ndarray,
          shape: tuple[int, int]) -> np.ndarray:
    """The elimination order of ``K``'s unknowns (coordinates ``0..n-1``, then constraint
    ``i`` as ``n + i``): coordinates by reverse Cuthill-McKee on the pattern of ``M + G^T
    G``, each constraint right after the last of its coordinates (module notes)."""
    m, n = shape
    G = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(m, n))
    _, rank, _ = rcm(abs(sp.csr_matrix(M)) + G.T @ G)
    last = np.full(m, -1, dtype=np.int64)
    np.maximum.at(last, np.asarray(rows, dtype=np.int64), rank[np.asarray(cols, dtype=np.int64)])
    keys = np.concatenate([rank, last])
    kinds = np.concatenate([np.zeros(n, dtype=np.int64), np.ones(m, dtype=np.int64)])
    return np.lexsort((np.arange(n + m), kinds, keys))


class KKT(Schur):
    """Solves with ``S = G M^{-1} G^T`` through the banded ``L D L^T`` of ``K`` (module notes).

    Parameters
    ----------
    M : scipy.sparse matrix, shape (n, n)
        The constant mass.
    rows, cols : ndarray
        ``G``'s structural nonzeros, in the order of its values.
    shape : (int, int)
        ``(m, n)``.
    G_values : callable
        ``G_values(q, t) -> (nnz,)``.

    Attributes
    ----------
    bandwidth : int
        The bandwidth of the reordered ``K``. Above :data:`KKT_BAND_MAX` the solver is
        not built (no index arrays) and cannot be used.
    """

    name = "kkt"

    def __init__(self, M: sp.spmatrix, rows: np.ndarray, cols: np.ndarray,
                 shape: tuple[int, int], G_values: Callable[[jax.Array, jax.Array], jax.Array]):
        m, n = shape
        rows, cols = np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)
        self.G_values, self.nnz, self.shape = G_values, len(rows), shape
        perm = order(M, rows, cols, shape)
        rank = np.argsort(perm)
        M = sp.coo_matrix(M)
        mi, mj = rank[M.row], rank[M.col]
        gi, gj = rank[n + rows], rank[cols]
        self.bandwidth = w = int(max(1, np.max(np.abs(mi - mj), initial=0),
                                     np.max(gi - gj, initial=0)))
        if w > KKT_BAND_MAX:
            return  # too wide for the band: no index arrays of (n + m) x w
        N = n + m
        lower = mi >= mj
        constant = np.zeros(N * (w + 1))
        constant[band_slots(mi[lower], mj[lower], w)] = M.data[lower]
        where = np.full(N * (w + 1), self.nnz, dtype=np.int64)   # nnz: an appended zero
        where[band_slots(gi, gj, w)] = np.arange(self.nnz)
        self._constant, self._where = jnp.asarray(constant), jnp.asarray(where)
        # Scaling: 1/sqrt(M_jj) per coordinate; per constraint, from its row of G.
        self._coord_scale = jnp.asarray(1.0 / np.sqrt(M.tocsr().diagonal()))
        self._cols = jnp.asarray(cols)
        by_row = np.argsort(rows, kind="stable")
        counts = np.bincount(rows, minlength=m)
        width = max(1, int(counts.max(initial=0)))
        table = np.full((m, width), self.nnz, dtype=np.int64)
        table[rows[by_row], np.arange(len(rows)) - np.repeat(np.cumsum(counts) - counts,
                                                             counts)] = by_row
        self._row_table = jnp.asarray(table)
        by_col = np.argsort(cols, kind="stable")
        counts = np.bincount(cols, minlength=n)
        table = np.full((n, max(1, int(counts.max(initial=0)))), self.nnz, dtype=np.int64)
        table[cols[by_col], np.arange(len(cols)) - np.repeat(np.cumsum(counts) - counts,
                                                             counts)] = by_col
        self._col_table = jnp.asarray(table)
        self._order = jnp.asarray(perm)
        # Right-hand sides in K's order: 0 for a coordinate, 1 + i for constraint i.
        self._rhs_index = jnp.asarray(np.where(perm >= n, perm - n + 1, 0))
        self._multiplier = jnp.asarray(rank[n:])
        # ||M^-1||_inf (M is symmetric: the 1-norm), estimated once (Hager-Higham), for the
        # bound on ||S||_inf that Newton's convergence test uses.
        lu = spla.splu(M.tocsc())
        self._minv_norm = float(spla.onenormest(spla.LinearOperator(
            (n, n), matvec=lu.solve, rmatvec=lu.solve, dtype=np.float64)))

    def factor(self, q, t) -> Factor:
        w = self.bandwidth
        Gv = self.G_values(q, t)
        Gx = jnp.concatenate([Gv, jnp.zeros(1)])
        Kb = (self._constant + gather(Gx, self._where)).reshape(-1, w + 1)
        c = self._coord_scale
        scaled = jnp.concatenate([Gv * gather(c, self._cols), jnp.zeros(1)])
        r = unit_diagonal(row_sum(gather(scaled ** 2, self._row_table)))
        s = gather(jnp.concatenate([c, r]), self._order)
        N = s.shape[0]
        shifted = jnp.stack([jnp.concatenate([jnp.ones(k), s[:N - k]]) for k in range(w + 1)], 1)
        X, D = band_ldl(Kb * s[:, None] * shifted)
        absG = jnp.abs(Gx)
        norm = (jnp.max(row_sum(gather(absG, self._row_table))) * self._minv_norm
                * jnp.max(row_sum(gather(absG, self._col_table))))
        ok = jnp.all(jnp.isfinite(X)) & jnp.all(jnp.isfinite(D))
        return Factor((X, D, s), norm, ok)

    def solve(self, F: Factor, rhs):
        X, D, s = F.data
        r = rhs[:, None] if rhs.ndim == 1 else rhs
        rK = gather(jnp.concatenate([jnp.zeros((1, r.shape[1])), r]), self._rhs_index)
        x = band_ldl_solve(X, D, rK * s[:, None]) * s[:, None]
        y = -gather(x, self._multiplier)
        return y[:, 0] if rhs.ndim == 1 else y
