"""Linear algebra chosen by the structure of the constraints.

Every family solves systems with the constraint Schur complement

.. math::

    S(q, t) = G(q, t)\\, M^{-1} G(q, t)^T \\qquad (m \\times m,\\ \\text{symmetric positive
    definite when } G \\text{ has full rank}),

in RATTLE's projections, in the eliminated stage equations of SPARK and in the index-1
accelerations of Baumgarte's method. Dense Cholesky of ``S`` costs ``O(m^3)`` and forming
``G`` densely ``O(m n)`` memory; the constraints of a chain, a truss or a ring of bars touch a
handful of coordinates each, so ``G`` has ``O(m)`` entries and ``S`` is sparse. Four
solvers share one interface (:class:`linalg.dense.Schur`: ``factor(q, t)`` then
``solve(factor, r)``):

``dense``
    ``G`` by forward-mode autodiff, ``S`` formed and factorised by Cholesky (a division
    for one constraint): the exact path for small systems, whose callers may run Newton
    with the exact Jacobian on it, and the only one for a configuration-dependent mass
    that is not block diagonal (:class:`linalg.blocks.Blocks`).
``banded`` (:mod:`linalg.banded`)
    ``G``'s values by compressed autodiff (a function of ``(q, t)`` the caller supplies),
    ``S`` assembled by gathers in a bandwidth-reducing order (reverse Cuthill-McKee) and
    factorised by a banded Cholesky written in JAX, so that it stays inside the compiled
    loop. Rows of ``G`` with many entries (a ring's hub rows: the centre of mass involves
    every point) would make the band full; they are kept as a dense *border* and
    eliminated through the Schur complement of the banded core. Cost ``O(m w^2)`` for
    bandwidth ``w``.
``superlu`` (:mod:`linalg.sparse`)
    The general sparse path: ``S`` assembled on the host from ``G``'s values with scipy and
    factorised by SuperLU (fill-reducing minimum-degree ordering of ``S + S^T``, no
    pivoting off the diagonal since ``S`` is positive definite), reached from the compiled
    loop by a callback. The factor of the last ``S`` is kept, so the solves of one step with
    the same ``G`` factorise once.
``kkt`` (:mod:`linalg.kkt`)
    For a constant mass that is not diagonal (natural coordinates), whose ``M^{-1}``, and so
    ``S``, is dense: solves with ``S`` are the multiplier block of solves with the augmented
    system ``[[M, G^T], [G, 0]]``, factorised ``L D L^T`` as a band in JAX (constraints
    ordered after their coordinates), ``O((n + m) w^2)``.

:func:`choose` picks by structure. A constant mass that is not diagonal: ``kkt`` above
:data:`DENSE_KKT_MAX` constraints when the augmented system's band is at most
:data:`linalg.kkt.KKT_BAND_MAX` wide, else ``dense``. Otherwise ``dense`` for at most
``dense_max`` constraints or a mass that is neither diagonal nor block diagonal (however
it was given: a matrix, a function ``M(q)`` or a kinetic energy); else ``banded``
when the bandwidth of the core after reordering is at most
:data:`linalg.banded.BAND_MAX`, else ``superlu``. ``dense_max`` is the caller's crossover:
a method that runs Newton on its whole stage system passes its own
(:meth:`integrators.fixed.FixedStep.dense_max`), the others take :data:`DENSE_MAX`.

Redundant constraints follow one policy on every path, the basic solution
(:mod:`linalg.dense`).
"""

from __future__ import annotations

from typing import Callable

import jax
import numpy as np

import scipy.sparse as sp

from linalg.banded import BAND_MAX, Banded
from linalg.blocks import BLOCK_MAX
from linalg.dense import Schur
from linalg.kkt import KKT, KKT_BAND_MAX
from linalg.pattern import Pattern
from linalg.sparse import SuperLU

#: Largest number of constraints solved densely by default, where the caller names no
#: crossover of its own: Baumgarte's index-1 accelerations and the projections (one solve
#: with ``S`` per evaluation, no Newton iteration), Radau IIA (whose structured iteration
#: leaves out the force Jacobian that its stiff problems need) and IDA's choice of a sparse
#: solver. The fixed-step families that run Newton name theirs
#: (``python -m benchmarks.perf.crossover``).
DENSE_MAX = 8

#: Largest number of constraints solved densely by default where the mass is constant but
#: not diagonal. The two paths leave the same ``|g|`` to round-off, and ``kkt`` is the
#: faster on four-bar from about N = 16 on (``python -m benchmarks.perf.four_bar
#: --crossover`` measures it); dense is kept while its step is cheap in absolute terms
#: (four-bar up to N = 63, bricard).
DENSE_KKT_MAX = 128

#: Names a run may ask for.
KINDS = ("auto", "dense", "banded", "superlu", "kkt")


def choose(kind: str, shape: tuple[int, int],
           G: Callable[[jax.Array, jax.Array], jax.Array],
           solve_mass: Callable[[jax.Array, jax.Array], jax.Array],
           mass_diagonal: np.ndarray | None = None,
           sparsity: Callable[[], tuple[np.ndarray, np.ndarray]] | None = None,
           G_values: Callable[[jax.Array, jax.Array], jax.Array] | None = None,
           mass_matrix: sp.spmatrix | None = None, dense_max: int = DENSE_MAX) -> Schur:
    """The solver for ``S = G M^{-1} G^T``: ``kind`` or, for ``"auto"``, by structure.

    Parameters
    ----------
    kind : {"auto", "dense", "banded", "superlu", "kkt"}
        The solver, or ``"auto"`` to choose by structure (module notes).
    shape : (int, int)
        ``(m, n)``: constraints and coordinates.
    G : callable
        ``G(q, t) -> (m, n)``, the constraint Jacobian (the dense path).
    solve_mass : callable
        ``solve_mass(q, b) -> M(q)^{-1} b`` (the dense path).
    mass_diagonal : ndarray, shape (n,), optional
        The constant diagonal of ``M`` where it is one; the structured solvers need it. A
        block-diagonal mass, constant or not, comes as a unit diagonal with ``G``
        whitened by the blocks' factors (:meth:`problems.mechanics.Mechanics.schur`).
    sparsity : callable, optional
        ``sparsity() -> (rows, cols)``: ``G``'s structural nonzeros, called only where a
        structured solver may be chosen (tracing the pattern costs set-up time).
    G_values : callable, optional
        ``G_values(q, t) -> (nnz,)``: ``G``'s entries in the order of ``sparsity``.
    mass_matrix : scipy.sparse matrix, optional
        A constant mass that is not diagonal; the ``kkt`` solver needs it (or
        ``mass_diagonal``).
    dense_max : int
        For ``"auto"``: the most constraints solved densely where a structured solver
        could run (module notes).

    Raises
    ------
    ValueError
        For an unknown ``kind``; ``banded`` or ``superlu`` on a system whose mass is neither
        diagonal nor block diagonal (they assemble ``S`` with ``M^{-1}`` diagonal, after
        whitening by the blocks); ``kkt`` on one
        whose mass is not constant, or whose augmented system is too wide a band.
    """
    if kind not in KINDS:
        raise ValueError(f"linear_solver = {kind!r}: expected one of {', '.join(KINDS)}")
    # A solver is built once and kept (Mechanics.schur): built on first use inside a trace,
    # its arrays would be tracers, leaked into every later compiled function that uses it.
    with jax.ensure_compile_time_eval():
        return _build(kind, shape, G, solve_mass, mass_diagonal, sparsity, G_values,
                      mass_matrix, dense_max)


def _build(kind, shape, G, solve_mass, mass_diagonal, sparsity, G_values, mass_matrix,
           dense_max) -> Schur:
    """:func:`choose`'s choice and construction, its arguments as validated there."""
    diagonal = mass_diagonal is not None
    if kind == "kkt" or (kind == "auto" and mass_matrix is not None
                         and shape[0] > DENSE_KKT_MAX):
        if mass_matrix is None and not diagonal:
            raise ValueError("linear_solver = 'kkt' needs a constant or block-diagonal mass; "
                             "this system's mass is neither (use dense)")
        M = mass_matrix if mass_matrix is not None else sp.diags(mass_diagonal)
        solver = KKT(M, *sparsity(), shape, G_values)
        if solver.bandwidth <= KKT_BAND_MAX:
            return solver
        if kind == "kkt":
            raise ValueError(f"linear_solver = 'kkt': the augmented system's bandwidth "
                             f"{solver.bandwidth} exceeds {KKT_BAND_MAX} (use dense)")
        return Schur(G, solve_mass)
    if kind == "dense" or (kind == "auto" and (shape[0] <= dense_max or not diagonal)):
        return Schur(G, solve_mass)
    if not diagonal:
        raise ValueError(f"linear_solver = {kind!r} needs a diagonal or block-diagonal mass "
                         f"(blocks of at most {BLOCK_MAX} coordinates); this system's mass is "
                         "neither (use dense"
                         + (" or kkt)" if mass_matrix is not None else ")"))
    pattern = Pattern(*sparsity(), shape)
    if kind == "banded" or (kind == "auto" and pattern.bandwidth <= BAND_MAX):
        if pattern.bandwidth > 4 * BAND_MAX and kind == "banded":
            raise ValueError(f"linear_solver = 'banded': the core bandwidth {pattern.bandwidth} "
                             f"exceeds {4 * BAND_MAX} (use superlu)")
        return Banded(pattern, G_values, mass_diagonal)
    return SuperLU(pattern, G_values, mass_diagonal)
