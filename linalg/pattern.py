"""Sparsity patterns: compressed Jacobians and the structure of ``S = G M^{-1} G^T``.

Patterns are structural (traced from the functions, not read from values) and found once;
what they give (colourings, orderings, index arrays) is what lets the compiled loop work
with ``O(nnz)`` gathers instead of dense ``m x n`` matrices.
"""

from __future__ import annotations

import copy
from functools import cached_property
from typing import Callable

import asdex
import jax
import jax.experimental.sparse as jsparse
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import reverse_cuthill_mckee

from linalg.compiled import compile_lifted, device_index, give_back_heap

#: Most entries of the directions that :meth:`SparseJacobian.values` differentiates along
#: at once; with more, it takes them one by one.
BATCH_ENTRIES = 1 << 21

#: Most entries (colours times ``max(m, n)``) of the passes of ``G``'s compressed autodiff
#: (:meth:`problems.mechanics.Mechanics.G_values`) taken at once; with more, they are
#: taken one by one. At once, each intermediate of ``g``'s derivative is held for every
#: colour, and past a typical 2 MiB second-level cache that costs more than the separate
#: passes save (on rigid-chain, 7 colours, the crossover lies between N = 4096 and 8192).
CACHED_ENTRIES = 1 << 18

#: A row of ``G`` with more entries than this (and than four times the median row) joins
#: the dense border of the banded solver.
BORDER_MIN = 32


def traced_sparsity(detect: Callable, f: Callable, x: jax.Array) -> asdex.SparsityPattern:
    """``detect(f, x)`` (``asdex.jacobian_sparsity`` or ``asdex.hessian_sparsity``), then the
    heap pages it freed given back to the system.

    The tracing holds a Python set per element of every intermediate array of ``f``;
    freed, that memory would stay resident (:func:`linalg.compiled.give_back_heap`).
    """
    pattern = detect(f, x)
    give_back_heap()
    return pattern


def row_sum(a: jax.Array) -> jax.Array:
    """``a.sum(axis=1)`` for an ``(r, k)`` array with a short second axis, as ``k - 1``
    additions of its columns.

    XLA:CPU (jaxlib 0.10) hands a reduction to the YNNPACK library, which on a short axis
    is far slower than the additions that XLA fuses with the products they sum (the sums
    of the band of ``S`` are a large part of baumgarte-rk4's step on rigid-chain).
    """
    return sum((a[:, j] for j in range(1, a.shape[1])), a[:, 0])


def gather(a: jax.Array, index: jax.Array) -> jax.Array:
    """``a[index]`` along the first axis, as a gather with a flat index.

    XLA:CPU compiles a loop into one native kernel only if its gathers take a flat index
    (measured: a ``(k, 2)`` index array keeps the loop out of the kernel). Every index is
    in bounds by construction (the patterns' own), so ``mode="clip"`` leaves XLA's gather
    as it is, without the bounds test and select per entry that the default mode adds.
    """
    return jnp.take(a, index.ravel(), axis=0, mode="clip").reshape(index.shape + a.shape[1:])


def column_pairs(entries: np.ndarray, cols: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Every ordered pair ``(first, second)`` of ``entries`` (indices into ``cols``) that
    share a column, as two index arrays: the pairs of a column ``first``-major, the columns
    ascending, the entries of a column in the order given. Each pair is a term
    ``G_first G_second / M_jj`` of ``S = G M^{-1} G^T``, as many as a sparse product
    multiplies (the squares of the column counts, summed)."""
    order = entries[np.argsort(cols[entries], kind="stable")]
    per_col = np.bincount(cols[order], minlength=n)
    repeat = per_col[cols[order]]
    first = np.repeat(order, repeat)
    within = np.arange(len(first)) - np.repeat(np.cumsum(repeat) - repeat, repeat)
    second = order[np.repeat((np.cumsum(per_col) - per_col)[cols[order]], repeat) + within]
    return first, second


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
    pattern : (rows, cols, (m, n)), optional
        The pattern, or a structural superset of it, where the caller knows one: tracing
        ``f`` holds a Python set per element of every intermediate array, which for a large
        system is more memory than anything else (see :meth:`agrees` to check it).
    """

    def __init__(self, f: Callable[[jax.Array], jax.Array], x: jax.Array,
                 pattern: tuple[np.ndarray, np.ndarray, tuple[int, int]] | None = None):
        if pattern is None:
            traced = traced_sparsity(asdex.jacobian_sparsity, f, x)
            pattern = (traced.rows, traced.cols, (traced.m, traced.n))
        rows, cols, self.shape = pattern
        m, n = self.shape
        # Sorted by row, then column, and without repeats.
        flat = np.unique(np.asarray(rows, dtype=np.int64) * n + np.asarray(cols, dtype=np.int64))
        self.rows, self.cols = flat // n, flat % n
        self.nnz = len(self.rows)
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
        # [seeds J^T (c x m) ; e_j^T J^T for dense j (d_c x m)] and [e_i^T J (d_r x n)].
        where_col = np.full(n, -1)
        where_col[self.dense_cols] = np.arange(len(self.dense_cols))
        where_row = np.full(m, -1)
        where_row[self.dense_rows] = np.arange(len(self.dense_rows))
        forward = np.where(dense_cols[self.cols], self.n_colours + where_col[self.cols],
                           colour[self.cols].clip(0))
        from_rows = dense_rows[self.rows]
        self.forward_index = jnp.asarray(forward * m + self.rows)
        self.reverse_index = jnp.asarray(where_row[self.rows].clip(0) * n + self.cols)
        self.from_rows = jnp.asarray(from_rows)
        self.f = f

    def agrees(self, x: jax.Array, entries: np.ndarray) -> bool:
        """Whether ``J(x) w``, assembled from ``entries`` (:meth:`values` at ``x``, in the
        order of ``rows``, ``cols``), equals the Jacobian-vector product of ``f`` along a
        random ``w`` to round-off.

        A pattern that misses a structural entry fails this at a random ``x`` (where the
        entry is almost surely nonzero); a non-finite product counts as disagreement.
        """
        w = np.random.default_rng(0).standard_normal(self.shape[1])
        exact = np.asarray(compile_lifted(lambda x, w: jax.jvp(self.f, (x,), (w,))[1],
                                          x, jnp.asarray(w))(x, jnp.asarray(w)))
        terms = np.asarray(entries) * w[self.cols]
        assembled = np.bincount(self.rows, terms, minlength=self.shape[0])
        scale = np.bincount(self.rows, np.abs(terms), minlength=self.shape[0])
        finite = np.all(np.isfinite(exact)) and np.all(np.isfinite(assembled))
        return bool(finite and np.all(np.abs(assembled - exact)
                                      <= 1e-10 * scale + 1e-14 * np.max(scale, initial=0.0)))

    def values(self, x: jax.Array, f: Callable[[jax.Array], jax.Array] | None = None) -> jax.Array:
        """The Jacobian's entries at ``x``, in the order of ``rows``, ``cols``.

        ``f`` defaults to the traced function; another with the same pattern (the same
        function with other parameters) may be passed.
        """
        f = self.f if f is None else f
        directions = jnp.concatenate([self.seeds, jnp.eye(self.shape[1])[self.dense_cols]])
        forward = self._passes(lambda d: jax.jvp(f, (x,), (d,))[1], directions)
        values = gather(forward.ravel(), self.forward_index)
        if len(self.dense_rows):
            pullback = jax.vjp(f, x)[1]
            reverse = self._passes(lambda e: pullback(e)[0],
                                   jnp.eye(self.shape[0])[self.dense_rows])
            values = jnp.where(self.from_rows, gather(reverse.ravel(), self.reverse_index),
                               values)
        return values

    def _passes(self, one, seeds: jax.Array) -> jax.Array:
        """``one(s)`` for every row ``s`` of ``seeds``, stacked.

        All at once where they are few, one by one where they are not: all at once hold
        every intermediate of ``f`` that many times (26 directions on rigid-chain:N=16384:
        about 1 GB of temporaries), and batches of a few cost more than either.
        """
        if len(seeds) * max(self.shape) > BATCH_ENTRIES:
            return jax.lax.map(one, seeds)
        return jax.vmap(one)(seeds)

    def reordered(self, order: np.ndarray) -> SparseJacobian:
        """The same Jacobian with its entries in the order ``order`` (a permutation of
        ``range(nnz)``: entry ``k`` of the result is entry ``order[k]`` of this one).

        :meth:`values` then gathers each entry from the passes straight to its place, where
        a permutation of its result would read and write every entry once more.
        """
        other = copy.copy(self)
        other.rows, other.cols = self.rows[order], self.cols[order]
        other.forward_index = self.forward_index[order]
        other.reverse_index = self.reverse_index[order]
        other.from_rows = self.from_rows[order]
        return other


class Pattern:
    """The structure of ``S`` built once from ``G``'s sparsity (for a constant diagonal mass).

    Rows of ``G`` with many entries form the dense *border*; the others, the *core*, are
    reordered by reverse Cuthill-McKee so that the core of ``S`` is a narrow band.

    Parameters
    ----------
    rows, cols : array_like of int
        The structural nonzeros of ``G``, in the order of its values.
    shape : (int, int)
        ``(m, n)``.
    """

    def __init__(self, rows, cols, shape: tuple[int, int]):
        self.m, self.n = m, n = shape
        self.rows = np.asarray(rows, dtype=np.int64)
        self.cols = np.asarray(cols, dtype=np.int64)
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
        """Index arrays (``int32``) that assemble the band of ``S`` and the border blocks by
        gathers: ``band``, a ``(first, second)`` pair of ``(slots, d)`` arrays for each
        number ``d`` of terms a band slot sums, and ``place``, where each slot's sum lands
        among theirs (an empty slot on a zero appended after them); the core rows of ``G``
        padded (entries and columns); the border rows of ``G`` dense.

        Slots are grouped by their number of terms rather than all padded to the largest:
        the index arrays then hold the pairs themselves. Padded, more than half of them
        would be padding on rigid-chain, and at large N they would no longer fit in the
        cache.
        """
        m, n, w = self.m, self.n, self.bandwidth
        mc = len(self.core)
        position = np.full(m, -1)
        position[self.core] = np.arange(mc)
        sentinel = self.nnz  # index of an appended zero: padding of the core and border rows below
        # Band slots: every pair of core entries sharing a column contributes
        # G_e1 G_e2 / M_jj to S[pos(e1), pos(e2)] (pos(e1) >= pos(e2)). The pairs of a
        # column are listed e1-major, the columns in ascending order and the entries of a
        # column by index, so that each slot sums its terms in a fixed order.
        first, second = column_pairs(np.flatnonzero(position[self.rows] >= 0), self.cols, n)
        p1, p2 = position[self.rows[first]], position[self.rows[second]]
        keep = p1 >= p2
        first, second, slot = first[keep], second[keep], (p1 * (w + 1) + (p1 - p2))[keep]
        per_slot = np.bincount(slot, minlength=mc * (w + 1))
        # The pairs slot by slot, each slot's in the order listed; slot s's are at
        # start[s] .. start[s] + per_slot[s] - 1.
        by_slot = np.argsort(slot, kind="stable")
        start = np.cumsum(per_slot) - per_slot
        band, place, done = [], np.empty(mc * (w + 1), dtype=np.int64), 0
        for d in np.unique(per_slot[per_slot > 0]):
            slots = np.flatnonzero(per_slot == d)
            at = by_slot[start[slots][:, None] + np.arange(d)[None, :]]
            band.append((device_index(first[at]), device_index(second[at])))
            place[slots] = done + np.arange(len(slots))
            done += len(slots)
        place[per_slot == 0] = done
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
        return (tuple(band), *(device_index(a) for a in (
            place, core_entries, core_cols, border_index)))


