"""SuperLU on the host, reached from the compiled loop by a callback: the ``superlu`` solver.

The general sparse path: ``S`` assembled on the host from ``G``'s values with scipy and
factorised by SuperLU (fill-reducing minimum-degree ordering of ``S + S^T``, no pivoting
off the diagonal since ``S`` is positive definite). The factor of the last ``S`` is kept,
so the solves of one step with the same ``G`` factorise once.
"""

from __future__ import annotations

import hashlib
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from linalg.dense import RANK_RTOL, Factor, Schur
from linalg.pattern import Pattern


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
        self.pattern, self.G_values = pattern, G_values
        self.nnz = pattern.nnz
        m, n = pattern.m, pattern.n
        self._G = sp.csr_matrix((np.arange(1, pattern.nnz + 1, dtype=np.float64),
                                 (pattern.rows, pattern.cols)), shape=(m, n))
        # Position in the CSR data of each pattern entry (the CSR sorts them).
        self._slot = np.empty(pattern.nnz, dtype=np.int64)
        self._slot[self._G.data.astype(np.int64) - 1] = np.arange(pattern.nnz)
        self._dinv = sp.diags(1.0 / np.asarray(mass_diagonal))
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
        values = self.G_values(q, t)

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


