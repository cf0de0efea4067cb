"""SuperLU on the host, reached from the compiled loop by a callback: the ``superlu`` solver.

The general sparse path: ``S`` assembled on the host from ``G``'s values and factorised by
SuperLU (fill-reducing minimum-degree ordering of ``S + S^T``, no pivoting off the diagonal
since ``S`` is positive definite). The factor of the last ``S`` is kept, so the solves of
one step with the same ``G`` factorise once.

``S``'s pattern is fixed by ``G``'s, so it is found once: each pair of ``G``'s entries in one
column ``j`` adds ``G_aj G_bj / M_jj`` to ``S_ab``, and a factorisation sums those products
into ``S``'s compressed columns (``numpy.bincount``) instead of multiplying sparse
matrices, whose overhead is most of a small system's factorisation (the same ``S`` to
round-off). Much of the rest of a step is the callbacks' own cost beyond the Python they
run, which is less with one operand per call (:meth:`SuperLU.factor`).
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from linalg.dense import RANK_RTOL, Factor, Schur
from linalg.pattern import Pattern, column_pairs


#: Largest number of constraints for which SuperLU, finding ``S`` singular, falls back to a
#: dense rank-revealing solve of ``S`` on the host (0.13 GB at 4096 constraints); larger
#: systems fail the step instead.
FALLBACK_MAX = 4096


class SuperLU(Schur):
    """``S`` assembled and factorised on the host by SuperLU, reached by a callback.

    Parameters are those of :class:`linalg.banded.Banded`.
    """

    name = "superlu"

    def __init__(self, pattern: Pattern, G_values: Callable[[jax.Array, jax.Array], jax.Array],
                 mass_diagonal: np.ndarray):
        self.pattern, self.G_values, self.mass_diagonal = pattern, G_values, mass_diagonal
        self.nnz = pattern.nnz
        m = pattern.m
        rows, cols = pattern.rows, pattern.cols
        first, second = column_pairs(np.arange(pattern.nnz), cols, pattern.n)   # S's terms
        # S's entries in compressed-column order (column-major keys, rows sorted within).
        keys, self._target = np.unique(rows[second] * m + rows[first], return_inverse=True)
        self._first, self._second = first, second
        self._weight = 1.0 / np.asarray(mass_diagonal, dtype=np.float64)[cols[first]]
        self._S_rows, self._S_cols = keys % m, keys // m
        self._indptr = np.concatenate([[0], np.cumsum(np.bincount(self._S_cols, minlength=m))])
        on_diagonal = np.flatnonzero(self._S_rows == self._S_cols)
        self._diagonal = (self._S_rows[on_diagonal], on_diagonal)
        self._last: tuple[bytes, Any] | None = None

    def assemble(self, values: np.ndarray) -> tuple[sp.csc_matrix, np.ndarray, float]:
        """``D S D`` with unit diagonal (CSC), ``D`` and ``||S||_inf``, for ``G``'s
        ``values`` (see the module notes)."""
        m = self.pattern.m
        S = np.bincount(self._target, values[self._first] * values[self._second] * self._weight,
                        minlength=len(self._S_rows))
        diagonal = np.zeros(m)
        diagonal[self._diagonal[0]] = S[self._diagonal[1]]
        D = 1.0 / np.sqrt(np.maximum(diagonal, np.finfo(float).tiny))
        norm = float(np.max(np.bincount(self._S_rows, np.abs(S), minlength=m), initial=0.0))
        Ss = sp.csc_matrix((S * D[self._S_rows] * D[self._S_cols], self._S_rows, self._indptr),
                           shape=(m, m))
        # Entries of the pattern that vanish here (G's structural entries that are zero at
        # this q) would be fill in SuperLU's ordering and factor: dropped, as a product of
        # sparse matrices drops them.
        Ss.eliminate_zeros()
        return Ss, D, norm

    def _factorise(self, values: np.ndarray):
        """A solver for the unit-diagonal ``S`` of ``G``'s values (the last one is kept):
        SuperLU's factor, or for a singular ``S`` of at most :data:`FALLBACK_MAX` rows the
        dense ``S`` (solved by least squares, rank by :data:`RANK_RTOL`), or ``None``."""
        # The values themselves are the key: comparing their bytes is far cheaper than
        # hashing them, and every Newton iteration's solve asks.
        key = values.tobytes()
        if self._last is not None and self._last[0] == key:
            return self._last[1]
        if not np.all(np.isfinite(values)):  # a diverged iterate: the step fails, as data
            entry = (None, None, np.nan, False)
            self._last = (key, entry)
            return entry
        Ss, D, norm = self.assemble(values)
        try:
            lu = spla.splu(Ss, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                           options=dict(SymmetricMode=True))
            pivots = np.abs(lu.U.diagonal())
            solver = lu.solve if pivots.min() > RANK_RTOL * pivots.max() else None
        except RuntimeError:  # exactly singular
            solver = None
        if solver is None and Ss.shape[0] <= FALLBACK_MAX:
            # The minimum-norm solution, not the basic one: both are exact for a
            # consistent system and give the same constraint force.
            def solver(r, dense=Ss.toarray()):
                return scipy.linalg.lstsq(dense, r, cond=RANK_RTOL)[0]
        entry = (solver, D, norm, solver is not None)
        self._last = (key, entry)
        return entry

    def factor(self, q, t) -> Factor:
        values = self.G_values(q, t)

        def host(values):
            _, _, norm, ok = self._factorise(np.asarray(values))
            return np.array([norm, ok], dtype=np.float64)

        # One operand and one result per callback: each costs on its own, so a solve's
        # callback takes G's values and the right-hand side packed into one array.
        norm, ok = jax.pure_callback(host, jax.ShapeDtypeStruct((2,), jnp.float64), values,
                                     vmap_method="sequential")
        return Factor(values, norm, ok > 0.0)

    def solve(self, F: Factor, rhs):
        nnz = self.nnz

        def host(packed):
            packed = np.asarray(packed)
            solver, D, _, ok = self._factorise(packed[:nnz])
            r = packed[nnz:].reshape(rhs.shape)
            # A singular S, or a diverged Newton iterate: NaN, which fails the step with
            # the loop's message instead of raising out of the compiled loop.
            if not ok or not np.all(np.isfinite(r)):
                return np.full(rhs.shape, np.nan)
            Dr = D[:, None] if r.ndim == 2 else D
            return Dr * solver(Dr * r)

        return jax.pure_callback(host, jax.ShapeDtypeStruct(rhs.shape, jnp.float64),
                                 jnp.concatenate([F.data, rhs.ravel()]),
                                 vmap_method="sequential")
