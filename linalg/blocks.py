"""Block-diagonal mass matrices: one small dense block per body, found from the pattern.

A rigid body in Euler parameters, a node of natural coordinates with its own inertia, or a
point mass contributes a block of the mass matrix that couples only its own coordinates,
so ``M(q)`` is block diagonal after a permutation. :class:`Blocks` finds the blocks as the
connected components of the pattern of ``M`` (traced by the caller) and works with them
in ``O(n k^2)`` for blocks of size at most ``k``, grouped by size so that each group is one
batched operation:

- the values of every block from ``k`` products ``M(q) s_c`` with the seeds
  ``s_c = sum of e_j over the coordinates j at position c of their block`` (the column
  colouring of a block-diagonal matrix: no two columns of one colour share a row);
- the Cholesky factors ``M_b = L_b L_b^T``, solves with ``M``, and the *whitening* of
  ``G``'s entries, ``\\hat G = G L^{-T}``, which turns ``S = G M^{-1} G^T`` into ``S = \\hat G
  \\hat G^T``: the structured Schur solvers then run with a unit mass on ``\\hat G``, whose
  pattern is that of ``G`` with every entry spread over its block (:meth:`Blocks.spread`).
  Each piece of a row of ``G`` on one block, ``r``, becomes ``L_b^{-1} r`` (forward
  substitution), all pieces of a group of blocks at once (:meth:`Blocks.whitening`).

The factorisation and the substitutions are unrolled over the entries of a block and
vectorised over the blocks of a group, and every gather takes a flat index: LAPACK calls
and multi-dimensional gathers would keep XLA from compiling the time loop into one kernel
(:mod:`linalg.banded`, :func:`linalg.pattern.gather`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from linalg.compiled import device_index
from linalg.pattern import gather

#: Largest block treated as a block: bodies and nodes have up to 7 coordinates (a rigid
#: body in Euler parameters) or 12 (a body in natural coordinates).
BLOCK_MAX = 12


class Whitening(NamedTuple):
    """Where :meth:`Blocks.whiten_rows` takes ``G``'s entries from and puts ``G L^{-T}``'s:
    the spread pattern ``(rows, cols)``, per group of blocks the pieces' sources ``(k, P)``
    and blocks ``(P,)``, and each output entry's place among the pieces."""

    rows: np.ndarray
    cols: np.ndarray
    pieces: list
    index: jax.Array


class Blocks:
    """The block structure of a symmetric ``n x n`` pattern (module notes).

    Parameters
    ----------
    rows, cols : ndarray
        The structural nonzeros of ``M``.
    n : int
        Its size.

    Attributes
    ----------
    groups : list of ndarray, each (B, k)
        The coordinates of each block, grouped by block size ``k`` (ascending within a
        block).
    size : int
        The largest block size (the number of seeds :meth:`values` needs).
    """

    def __init__(self, rows: np.ndarray, cols: np.ndarray, n: int):
        graph = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
        _, label = connected_components(graph, directed=False)
        members: dict[int, list[int]] = {}
        for j, b in enumerate(label):
            members.setdefault(int(b), []).append(j)
        by_size: dict[int, list[list[int]]] = {}
        for coords in members.values():
            by_size.setdefault(len(coords), []).append(coords)
        self.n = n
        self.groups = [np.array(by_size[k], dtype=np.int64) for k in sorted(by_size)]
        self.size = max(by_size)
        if not self.block_diagonal:
            return  # treated as dense: no index arrays of n x size
        #: Position of each coordinate within its block, and its block's coordinates
        #: (a row per coordinate, padded with -1).
        self.position = np.empty(n, dtype=np.int64)
        self.members = np.full((n, self.size), -1, dtype=np.int64)
        for group in self.groups:
            k = group.shape[1]
            self.position[group] = np.arange(k)[None, :]
            self.members[group.ravel(), :k] = np.repeat(group, k, axis=0)
        #: Where each coordinate lands when the groups are laid out one after the other,
        #: position-major within a group (the order :meth:`solve` works in).
        self.inverse = np.argsort(np.concatenate([g.T.ravel() for g in self.groups]))
        # The index arrays and seeds the compiled code reads, on the device once: an array
        # made afresh at each call is a constant of its own in every compiled program that
        # calls it (rattle's loop on rigid-chain:N=1024 held 53 copies of the seeds and
        # over 200 of the group indices; at N=16384, 390 MB of constants).
        self._group_index = [device_index(g.T.ravel()) for g in self.groups]
        self._inverse = device_index(self.inverse)
        with jax.ensure_compile_time_eval():   # concrete even when first built in a trace
            self._seeds = jnp.asarray(
                (self.position[None, :] == np.arange(self.size)[:, None]).astype(np.float64))

    @property
    def block_diagonal(self) -> bool:
        """Whether every block is at most :data:`BLOCK_MAX` (else treat ``M`` as dense)."""
        return self.size <= BLOCK_MAX

    def seeds(self) -> jax.Array:
        """``(size, n)``: seed ``c`` is 1 on the coordinates at position ``c`` of a block."""
        return self._seeds

    def values(self, products: jax.Array) -> list[jax.Array]:
        """The blocks ``(k, k, B)`` of each group from ``products[c] = M s_c`` (``(size,
        n)``): entry ``(i, j)`` of block ``b`` is row ``coords[i]`` of the product with the
        seed of position ``j``."""
        out = []
        for group, index in zip(self.groups, self._group_index):
            B, k = group.shape
            rows = gather(products[:k].T, index)                          # (k B, k)
            out.append(rows.reshape(k, B, k).transpose(0, 2, 1))
        return out

    def factor(self, blocks: list[jax.Array]) -> list[list[list[jax.Array]]]:
        """The lower Cholesky factors of the blocks, entry by entry (``L[i][j]`` is a
        ``(B,)`` vector over the group's blocks)."""
        factors = []
        for A in blocks:
            k = A.shape[0]
            L = [[None] * k for _ in range(k)]
            for j in range(k):
                for i in range(j, k):
                    acc = A[i, j] - sum((L[i][l] * L[j][l] for l in range(j)),
                                        jnp.zeros_like(A[i, j]))
                    L[i][j] = jnp.sqrt(acc) if i == j else acc / L[j][j]
            factors.append(L)
        return factors

    def solve(self, factors, x: jax.Array) -> jax.Array:
        """``M^{-1} x = L^{-T} L^{-1} x`` blockwise (``x`` a vector or ``(n, r)`` columns)."""
        vec = x.ndim == 1
        x = x[:, None] if vec else x
        parts = []
        for group, index, L in zip(self.groups, self._group_index, factors):
            B, k = group.shape
            y = list(gather(x, index).reshape(k, B, -1))
            for i in range(k):
                y[i] = (y[i] - sum((L[i][l][:, None] * y[l] for l in range(i)),
                                   jnp.zeros_like(y[i]))) / L[i][i][:, None]
            for i in reversed(range(k)):
                y[i] = (y[i] - sum((L[l][i][:, None] * y[l] for l in range(i + 1, k)),
                                   jnp.zeros_like(y[i]))) / L[i][i][:, None]
            parts.append(jnp.stack(y).reshape(k * B, -1))
        out = gather(jnp.concatenate(parts), self._inverse)
        return out[:, 0] if vec else out

    def whitening(self, rows: np.ndarray, cols: np.ndarray) -> Whitening:
        """The index arrays of :meth:`whiten_rows` for a matrix ``G`` with the structural
        nonzeros ``(rows, cols)`` (its entries in that order).

        A *piece* is a row of ``G`` restricted to one block; the pieces of the blocks of each
        group are laid out position-major as a ``(k, P)`` array, gathered from ``G``'s
        entries (a structural zero of the piece from an appended zero)."""
        rows, cols = np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)
        out_rows, out_cols = self.spread(rows, cols)
        group_of, block_of = np.empty(self.n, dtype=np.int64), np.empty(self.n, dtype=np.int64)
        for g, group in enumerate(self.groups):
            group_of[group] = g
            block_of[group] = np.arange(len(group))[:, None]
        pieces, out, offset = [], np.empty(len(out_rows), dtype=np.int64), 0
        for g, group in enumerate(self.groups):
            B, k = group.shape
            mine = np.flatnonzero(group_of[cols] == g)
            keys, slot = np.unique(rows[mine] * B + block_of[cols[mine]], return_inverse=True)
            source = np.full((k, len(keys)), len(rows), dtype=np.int64)
            source[self.position[cols[mine]], slot] = mine
            lands = np.flatnonzero(group_of[out_cols] == g)
            piece = np.searchsorted(keys, out_rows[lands] * B + block_of[out_cols[lands]])
            out[lands] = offset + self.position[out_cols[lands]] * len(keys) + piece
            offset += k * len(keys)
            pieces.append((device_index(source), device_index(keys % B)))
        return Whitening(out_rows, out_cols, pieces, device_index(out))

    def whiten_rows(self, factors, values: jax.Array, plan: Whitening) -> jax.Array:
        """The entries of ``G L^{-T}`` in the order of ``plan.rows, plan.cols`` (the spread
        pattern) from ``G``'s ``values`` (in the order :meth:`whitening` was given).

        Each piece ``r`` of a row on block ``b`` becomes ``L_b^{-1} r``, since ``(G
        L^{-T})^T = L^{-1} G^T``: a forward substitution unrolled over the block's entries and
        vectorised over the group's pieces, the factor's entries gathered per piece.
        ``O(nnz k)``, with no derivative of ``g`` through the factor."""
        x = jnp.concatenate([values, jnp.zeros(1)])
        parts = []
        for (source, block), L in zip(plan.pieces, factors):
            k = len(L)
            entry = {(i, j): gather(L[i][j], block) for i in range(k) for j in range(i + 1)}
            r, y = gather(x, source), []                                        # r: (k, P)
            for i in range(k):
                y.append((r[i] - sum((entry[i, l] * y[l] for l in range(i)),
                                     jnp.zeros_like(r[i]))) / entry[i, i])
            parts.append(jnp.stack(y).ravel())
        return gather(jnp.concatenate(parts), plan.index)

    def spread(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The pattern of ``G L^{-T}`` from that of ``G``: each entry spread over its
        column's block (sorted by row, then column)."""
        spread = self.members[cols]                               # (nnz, size)
        keep = spread >= 0
        # int64: row times n passes 2^31 for large systems.
        rows = np.repeat(np.asarray(rows, dtype=np.int64), self.size)[keep.ravel()]
        flat = np.unique(rows * self.n + spread[keep])
        return flat // self.n, flat % self.n
