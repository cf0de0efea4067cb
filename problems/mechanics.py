"""Constrained mechanical systems and every quantity derived from them.

A problem author writes only the physics of

.. math::

    M(q)\\,\\ddot q = -\\nabla U(q) + f(t, q, \\dot q) + c(q, \\dot q) - G(q, t)^T \\lambda,
    \\qquad g(q, t) = 0,

as pure JAX functions: the mass matrix ``M(q)`` (or a constant matrix or diagonal, or,
for large models, the kinetic energy ``T(q, v) = v^T M(q) v / 2`` so that ``M`` is never
formed), the
potential ``U(q)``, the holonomic constraints ``g(q, t)`` and optional non-conservative
forces ``f(t, q, v)``. This module is the one place where everything else is derived by
automatic differentiation: the constraint Jacobian ``G = dg/dq``, ``g_t``, the
acceleration-level term ``gamma`` with ``G a + gamma = 0``, the quadratic-velocity forces
``c(q, v)`` of a configuration-dependent mass, the momentum ``p = M v`` and the Hamiltonian
``H(q, p) = p^T M(q)^{-1} p / 2 + U(q)`` with its gradients. No integrator differentiates
anything itself.

The structure of the constraints is derived here too: the sparsity pattern of ``G`` by
tracing ``g`` (:attr:`Mechanics.G_coloring`) and its values by compressed autodiff
(:meth:`Mechanics.G_values`), which :mod:`linalg` turns into linear algebra
whose cost grows with the number of entries of ``G`` rather than with ``m n``.

Each of the author's functions is wrapped in ``jax.jit`` once per system, so that it is
traced once per argument shape: a compiled loop calls ``M(q)`` or ``g`` in many places and
under several transformations (a Radau step on ``andrews`` evaluates the mass 42 times
while it is traced). XLA inlines the calls, so the compiled program does the same
arithmetic up to the order of a few operations, so results agree at round-off (chaotic
problems amplify it in their final error). Re-running the author's Python at every call
would be about half of a set-up's tracing time.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from functools import cached_property, partial
from typing import Callable, Mapping

import asdex
import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402

from linalg.blocks import Blocks, Whitening  # noqa: E402
from linalg.compiled import device_index  # noqa: E402
from linalg.kkt import KKT_BAND_MAX, BandedMass, rcm  # noqa: E402
from linalg.pattern import CACHED_ENTRIES, traced_sparsity  # noqa: E402
from linalg.schur import DENSE_KKT_MAX, DENSE_MAX, choose  # noqa: E402
from problems.source import refuse  # noqa: E402

Array = jax.Array


@dataclass(frozen=True, eq=False)
class System:
    """The physics of a constrained mechanical system, written once.

    Parameters
    ----------
    n, m : int
        Number of coordinates and of constraints.
    mass : callable or array_like or scipy.sparse matrix or None
        ``mass(q) -> (n, n)``, or a constant ``(n, n)`` matrix (dense or, for large
        systems, a scipy sparse matrix, so that it is never formed densely), or a constant
        diagonal ``(n,)``. Symmetric positive definite. ``None`` when ``kinetic`` gives it.
        A function is taken as the kinetic energy ``v^T M(q) v / 2`` (the same path and
        cost as ``kinetic``), its blocks traced from it (:attr:`Mechanics.mass_blocks`).
    constraints : callable
        ``g(q, t) -> (m,)``, holonomic; may depend on ``t`` (then set ``rheonomic``).
    potential : callable, optional
        ``U(q) -> scalar``; conservative forces are ``-grad U``.
    forces : callable, optional
        ``f(t, q, v) -> (n,)``, non-conservative generalised forces.
    rheonomic : bool
        Whether ``g`` depends explicitly on time (energy is then not conserved).
        Without a conserved energy (``forces`` or ``rheonomic``) the suite measures the
        energy balance ``H - H0 - W`` instead, the work ``W`` derived from these same
        functions (:meth:`Mechanics.power`): no invariant needs to be declared for it.
    invariants : mapping of str to callable
        Conserved quantities beyond energy, ``I(q, v) -> scalar`` (for example angular
        momentum components).
    sensitive : bool
        The motion is chaotic: exact comparisons against a reference are meaningless and
        the drift gate reports but does not gate it.
    kinetic : callable, optional
        ``T(q, v) -> scalar``, the kinetic energy ``v^T M(q) v / 2``, in place of ``mass``:
        ``M`` is then never formed. Its pattern is traced from ``T`` (the Hessian in
        ``v``), and a block-diagonal one (one block per body; a small fully coupled ``M``
        is one block) is solved blockwise and on the structured linear algebra
        (:mod:`linalg.blocks`).
    """

    n: int
    m: int
    mass: Callable[[Array], Array] | np.ndarray
    constraints: Callable[[Array, Array], Array]
    potential: Callable[[Array], Array] | None = None
    forces: Callable[[Array, Array, Array], Array] | None = None
    rheonomic: bool = False
    invariants: Mapping[str, Callable[[Array, Array], Array]] = field(default_factory=dict)
    sensitive: bool = False
    kinetic: Callable[[Array, Array], Array] | None = None

    def __post_init__(self):
        # Refused here, at the user's System(...) line, not deep inside the first run.
        for name in ("n", "m"):
            value = getattr(self, name)
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) \
                    or value < (1 if name == "n" else 0):
                raise refuse(f"System {name} = {value!r} must be an int >= "
                             f"{1 if name == 'n' else 0}", __file__)
        if not callable(self.constraints):
            raise refuse("System constraints must be callable, g(q, t) -> (m,)", __file__)
        for name in ("potential", "forces", "kinetic"):
            if getattr(self, name) is not None and not callable(getattr(self, name)):
                raise refuse(f"System {name} must be callable or None", __file__)
        if (self.mass is None) == (self.kinetic is None):
            raise refuse("System: give the mass either as mass or as kinetic, not "
                         + ("neither" if self.mass is None else "both"), __file__)
        for name in ("rheonomic", "sensitive"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise refuse(f"System {name} = {getattr(self, name)!r} must be True or False",
                             __file__)
        if not (isinstance(self.invariants, Mapping) and all(
                isinstance(k, str) and callable(f) for k, f in self.invariants.items())):
            raise refuse("System invariants must map names to functions I(q, v) -> scalar",
                         __file__)

    @cached_property
    def mech(self) -> "Mechanics":
        """The derived quantities of this system (built once)."""
        return Mechanics(self)


class Mechanics:
    """Quantities derived by autodiff from a :class:`System`.

    All methods are pure and JAX-traceable; integrators call them inside their compiled
    loops.
    """

    def __init__(self, system: System):
        self.system = system
        self.n, self.m = system.n, system.m
        # The user's functions, each traced once per argument shape: a compiled loop calls
        # them in many places and under several transformations, and re-running their
        # Python at every call would be half of a set-up's tracing time (module notes).
        self._mass_fn = jax.jit(system.mass) if callable(system.mass) else None
        self._potential = None if system.potential is None else jax.jit(system.potential)
        self._constraints = jax.jit(system.constraints)
        self._forces = None if system.forces is None else jax.jit(system.forces)
        #: The kinetic energy ``T(q, v) = v^T M(q) v / 2`` of a configuration-dependent
        #: mass, however it was given: every quantity of a varying mass is derived from it
        #: (or from ``M(q)`` where that was given and is cheaper), so that one physics
        #: written with ``mass`` or with ``kinetic`` takes one path at one cost.
        self.kinetic = None
        if system.kinetic is not None:
            self.kinetic = jax.jit(system.kinetic)
        elif self._mass_fn is not None:
            mass_fn = self._mass_fn
            self.kinetic = jax.jit(lambda q, v: 0.5 * v @ (mass_fn(q) @ v))
        self.constant_mass = self.kinetic is None
        #: The constant diagonal of ``M`` when it is one (``None`` otherwise): such a mass is
        #: never formed as a matrix, so that its cost and memory stay ``O(n)``.
        self.mass_diagonal = None
        #: A constant mass that is not diagonal, as a scipy sparse matrix (``None`` for
        #: any other mass): the ``kkt`` solver works with it (:mod:`linalg.kkt`).
        self.mass_matrix = None
        #: Its banded factor where the system is large (more than
        #: :data:`linalg.schur.DENSE_KKT_MAX` constraints, where the linear algebra is
        #: chosen structured) and ``M`` a band of at most :data:`linalg.kkt.KKT_BAND_MAX`
        #: after reordering: ``M x`` and ``M^{-1} x`` then cost ``O(n)``, not ``O(n^2)``.
        self.mass_band = None
        if self.constant_mass:
            mass = system.mass
            mass = (sp.csr_matrix(mass, dtype=np.float64) if sp.issparse(mass)
                    else np.asarray(mass, dtype=np.float64))
            if mass.ndim == 1 and mass.shape != (self.n,):
                raise ValueError(f"mass has shape {mass.shape}, expected ({self.n},)")
            if mass.ndim == 2 and mass.shape != (self.n, self.n):
                raise ValueError(f"mass has shape {mass.shape}, expected ({self.n}, {self.n})")
            diagonal = mass.ndim == 1 or not (
                (mass - sp.diags(mass.diagonal())).count_nonzero() if sp.issparse(mass)
                else np.any(mass - np.diag(np.diag(mass))))
            if diagonal:
                self.mass_diagonal = mass if mass.ndim == 1 else np.asarray(mass.diagonal()).copy()
                # On the device once: a copy per call is a constant of its own in every
                # compiled program that calls it (linalg.blocks says what that cost).
                self._mass_diagonal = jnp.asarray(self.mass_diagonal)
            else:
                self.mass_matrix = sp.csr_matrix(mass)
                if self.m > DENSE_KKT_MAX and rcm(self.mass_matrix)[2] <= KKT_BAND_MAX:
                    self.mass_band = BandedMass(self.mass_matrix)
                else:
                    dense = mass.toarray() if sp.issparse(mass) else mass
                    self._M = jnp.asarray(dense)
                    self._Minv = jnp.asarray(np.linalg.inv(dense))
        # Energy is conserved only for a scleronomic system without applied forces; any
        # other system balances its energy against the work done on it (power).
        self.has_energy = system.forces is None and not system.rheonomic
        self.separable = self.constant_mass and system.forces is None

    # --- mass, momentum, Hamiltonian -------------------------------------------------
    @cached_property
    def mass_blocks(self) -> Blocks | None:
        """The block-diagonal structure of a configuration-dependent mass (``None`` for a
        constant one, or where a block exceeds :data:`linalg.blocks.BLOCK_MAX`); a fully
        coupled small ``M(q)`` is one block.

        Structural, like ``G``'s pattern: for ``mass(q)``, the entries of ``M`` that depend
        on ``q`` (traced) and those that do not and are nonzero (their value at ``q = 0`` is
        their value everywhere); for ``kinetic``, the Hessian pattern of ``T`` in ``v``,
        traced at ``q = 0`` (a product of ``v`` with a matrix is traced as coupling all of
        its entries, so there the pattern of ``M`` is not read off ``T``)."""
        if self.kinetic is None:
            return None
        # Numpy zeros: made with jnp inside a trace, they would be tracers.
        n, zeros = self.n, np.zeros(self.n)
        if self._mass_fn is None:
            pattern = traced_sparsity(asdex.hessian_sparsity,
                                      lambda v: self.kinetic(zeros, v), zeros)
            rows, cols = np.asarray(pattern.rows), np.asarray(pattern.cols)
        else:
            varying = traced_sparsity(asdex.jacobian_sparsity,
                                      lambda q: jnp.ravel(self._mass_fn(q)), zeros)
            with jax.ensure_compile_time_eval():   # concrete even when asked in a trace
                filled = np.ravel(np.asarray(self._mass_fn(jnp.asarray(zeros))) != 0)
            filled[np.asarray(varying.rows, dtype=np.int64)] = True
            rows, cols = np.divmod(np.flatnonzero(filled), n)
        blocks = Blocks(rows, cols, n)
        return blocks if blocks.block_diagonal else None

    def mass_factor(self, q: Array) -> list[Array] | None:
        """The Cholesky factors of the blocks of ``M(q)`` (:attr:`mass_blocks`), from one
        product ``M(q) s`` per seed; ``None`` for a mass without blocks."""
        blocks = self.mass_blocks
        if blocks is None:
            return None
        products = jax.vmap(lambda s: self.mass_times(q, s))(blocks.seeds())
        return blocks.factor(blocks.values(products))

    def mass(self, q: Array) -> Array:
        """Mass matrix ``M(q)`` (dense; :meth:`mass_times` avoids forming it)."""
        if self.mass_diagonal is not None:
            return jnp.diag(self._mass_diagonal)
        if self._mass_fn is not None:
            return self._mass_fn(q)
        if self.kinetic is not None or self.mass_band is not None:
            return jax.jacfwd(lambda v: self.mass_times(q, v))(jnp.zeros(self.n))
        return self._M

    def mass_times(self, q: Array, x: Array) -> Array:
        """``M(q) x`` (x may be a vector or a matrix of columns)."""
        if self.mass_diagonal is not None:
            d = self._mass_diagonal
            return (d[:, None] if x.ndim == 2 else d) * x
        if self.mass_band is not None:
            return self.mass_band.times(x)
        if self.kinetic is not None and self._mass_fn is None:
            # T is quadratic in v: its gradient in v at x is M(q) x.
            Mx = jax.grad(self.kinetic, argnums=1)
            return jax.vmap(lambda c: Mx(q, c), 1, 1)(x) if x.ndim == 2 else Mx(q, x)
        return self.mass(q) @ x

    def solve_mass(self, q: Array, b: Array) -> Array:
        """``M(q)^{-1} b`` (b may be a vector or a matrix of columns)."""
        if self.mass_diagonal is not None:
            d = self._mass_diagonal
            return b / (d[:, None] if b.ndim == 2 else d)
        if self.mass_band is not None:
            return self.mass_band.solve(b)
        if self.constant_mass:
            return self._Minv @ b
        if self.mass_blocks is not None:
            return self.mass_blocks.solve(self.mass_factor(q), b)
        # LU, not Cholesky: under jacfwd the Cholesky solve's tangents become batched
        # triangular solves, which XLA's CPU backend runs far slower than LU's.
        return jnp.linalg.solve(self.mass(q), b)

    def mass_solver(self, q: Array, factors: list[Array] | None = None
                    ) -> Callable[[Array], Array]:
        """``b -> M(q)^{-1} b`` at one configuration, with what depends on ``q`` alone (the
        Cholesky factors of :attr:`mass_blocks`, the LU factors of a dense ``M(q)``)
        computed once, here, or the former given as ``factors`` (:meth:`mass_factor`) by a
        caller that keeps them across steps.

        For the solves that a frozen Newton matrix repeats at one ``q`` in every iteration:
        XLA does not move the factorisation out of the Newton loop by itself, and
        :meth:`solve_mass` there would factorise at every iteration.
        """
        if self.mass_blocks is not None:
            factors = self.mass_factor(q) if factors is None else factors
            return lambda b: self.mass_blocks.solve(factors, b)
        if self.constant_mass or self.mass_diagonal is not None or self.mass_band is not None:
            return partial(self.solve_mass, q)
        # A dense M(q): LU, as in solve_mass.
        return partial(jax.scipy.linalg.lu_solve, jax.scipy.linalg.lu_factor(self.mass(q)))

    def potential(self, q: Array) -> Array:
        """Potential energy ``U(q)`` (zero when none is declared)."""
        return jnp.asarray(0.0) if self._potential is None else self._potential(q)

    def momentum(self, q: Array, v: Array) -> Array:
        """Conjugate momentum ``p = M(q) v``."""
        return self.mass_times(q, v)

    def velocity(self, q: Array, p: Array) -> Array:
        """Velocity ``v = H_p(q, p) = M(q)^{-1} p``."""
        return self.solve_mass(q, p)

    def hamiltonian(self, q: Array, p: Array) -> Array:
        """``H(q, p) = p^T M(q)^{-1} p / 2 + U(q)``."""
        return 0.5 * p @ self.solve_mass(q, p) + self.potential(q)

    def energy(self, q: Array, v: Array) -> Array:
        """Total energy ``v^T M(q) v / 2 + U(q)`` in velocity form."""
        return 0.5 * v @ self.mass_times(q, v) + self.potential(q)

    def H_q(self, q: Array, p: Array, v: Array | None = None) -> Array:
        """``dH/dq``, including the derivative of ``M(q)^{-1}`` for a varying mass; ``v``,
        where the caller has it, is ``H_p(q, p)`` (a mass given by ``kinetic`` then needs
        no solve here)."""
        if self.constant_mass:
            return self.grad_potential(q)
        # H_q(q, p) = -L_q(q, v) at v = H_p(q, p): no derivative through the solve.
        v = self.velocity(q, p) if v is None else v
        return self.grad_potential(q) - jax.grad(self.kinetic, argnums=0)(q, v)

    def H_p(self, q: Array, p: Array) -> Array:
        """``dH/dp = M(q)^{-1} p``."""
        return self.velocity(q, p)

    def grad_potential(self, q: Array) -> Array:
        """``grad U(q)``."""
        if self._potential is None:
            return jnp.zeros(self.n)
        return jax.grad(self._potential)(q)

    # --- forces ------------------------------------------------------------------------
    def external(self, t: Array, q: Array, v: Array) -> Array:
        """Non-conservative generalised forces ``f(t, q, v)`` (zero when none)."""
        return jnp.zeros(self.n) if self._forces is None else self._forces(t, q, v)

    def power(self, t: Array, q: Array, v: Array) -> Array:
        """Power of the forces that :meth:`energy` does not hold, ``P = f(t, q, v) . v +
        lam . g_t(q, t)``, so that ``dH/dt = P`` along exact solutions.

        Along a solution ``dH/dt = v . (f - G^T lam)`` (the quadratic-velocity forces of a
        varying mass do no net work), and ``-v . G^T lam = lam . g_t`` on the velocity
        manifold ``G v + g_t = 0``: a moving (rheonomic) constraint works on the system
        through its multiplier, from :meth:`accelerations`; a fixed one does no work, and
        no multiplier is computed for it. Written with ``g_t`` rather than ``G v`` so that a
        method's velocity drift is not counted as work.
        """
        P = self.external(t, q, v) @ v
        if self.system.rheonomic:
            _, lam = self.accelerations(t, q, v)
            P = P + lam @ self.g_t(q, t)
        return P

    def force(self, t: Array, q: Array, v: Array) -> Array:
        """Right-hand side of ``M a = force - G^T lam``.

        ``-grad U + f + c(q, v)`` with the quadratic-velocity term of a varying mass,
        ``c = grad_q(v^T M v)/2 - (dM/dq . v) v``.
        """
        F = -self.grad_potential(q) + self.external(t, q, v)
        if self.kinetic is not None:
            # Lagrange: d/dt (dT/dv) - dT/dq = M a + D_q(M(q) v)[v] - dT/dq.
            Mv = jax.jvp(lambda x: self.mass_times(x, v), (q,), (v,))[1]
            return F + jax.grad(self.kinetic, argnums=0)(q, v) - Mv
        return F

    # --- constraints ---------------------------------------------------------------------
    def g(self, q: Array, t: Array) -> Array:
        """Holonomic constraints ``g(q, t)``."""
        return self._constraints(q, t)

    def G(self, q: Array, t: Array) -> Array:
        """Constraint Jacobian ``dg/dq`` (m x n)."""
        return jax.jacfwd(self._constraints, argnums=0)(q, t)

    def G_times(self, q: Array, t: Array, v: Array) -> Array:
        """``G(q, t) v`` as one forward-mode derivative of ``g`` along ``v`` (``G`` never formed)."""
        return jax.jvp(lambda x: self.g(x, t), (q,), (v,))[1]

    def GT(self, q: Array, t: Array, lam: Array) -> Array:
        """``G(q, t)^T lam`` as one reverse-mode derivative of ``g`` (``G`` is never formed)."""
        return jax.vjp(lambda x: self.g(x, t), q)[1](lam)[0]

    @cached_property
    def G_coloring(self) -> asdex.ColoredPattern:
        """The sparsity pattern of ``G`` and a colouring of it, found once.

        The pattern is traced from ``g`` itself (which outputs depend on which inputs, at
        ``q = 0``, ``t = 0``: structurally, not numerically, so no entry that merely happens
        to vanish there is lost); rows (or columns) that share no column (row) get one
        colour, and one reverse (forward) derivative per colour gives all of ``G``.
        """
        pattern = traced_sparsity(asdex.jacobian_sparsity,
                                  lambda q: self.g(q, jnp.asarray(0.0)), jnp.zeros(self.n))
        with warnings.catch_warnings():
            # A tiny G (one pendulum constraint) needs as many colours as columns: fine.
            warnings.simplefilter("ignore", asdex.DenseColoringWarning)
            return asdex.jacobian_coloring_from_sparsity(pattern)

    def G_pattern(self) -> tuple[np.ndarray, np.ndarray]:
        """Rows and columns of the structural nonzeros of ``G`` (:attr:`G_coloring`'s)."""
        sparsity = self.G_coloring.sparsity
        return np.asarray(sparsity.rows), np.asarray(sparsity.cols)

    @cached_property
    def curvature_pattern(self) -> tuple[np.ndarray, np.ndarray]:
        """Rows and columns of the Hessian pattern of ``sum_i g_i(q, t)`` in ``q``: what the
        derivatives of ``G(q)^T lam`` in ``q`` can touch, for any ``lam`` (structural,
        traced at ``q = 0``, ``t = 0``)."""
        pattern = traced_sparsity(asdex.hessian_sparsity,
                                  lambda q: jnp.sum(self.g(q, jnp.asarray(0.0))),
                                  jnp.zeros(self.n))
        return np.asarray(pattern.rows, dtype=np.int64), np.asarray(pattern.cols, dtype=np.int64)

    def mass_pattern(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Rows and columns that ``M(q)`` can fill: its diagonal, the entries of a constant
        mass, or the blocks of a block-diagonal one (:attr:`mass_blocks`); ``None`` for a
        mass with no known structure."""
        if self.mass_diagonal is not None:
            diagonal = np.arange(self.n, dtype=np.int64)
            return diagonal, diagonal
        if self.mass_matrix is not None:
            rows, cols = self.mass_matrix.nonzero()
            return rows.astype(np.int64), cols.astype(np.int64)
        if self.mass_blocks is None:
            return None
        diagonal = np.arange(self.n, dtype=np.int64)
        return self.mass_blocks.spread(diagonal, diagonal)

    @cached_property
    def dynamics_pattern(self) -> tuple[np.ndarray, np.ndarray] | None:
        """A structural superset of the pattern of the ``n x 2n`` Jacobian of
        ``M(q) a - force(t, q, v)`` in ``(q, v)``, for any ``a``, found without tracing the
        force (``None`` where that cannot be done: a varying mass with no block structure).

        ``-grad U`` contributes the Hessian pattern of ``U`` and the applied forces their
        Jacobian pattern, both traced. A varying block-diagonal mass contributes its blocks,
        in the ``q`` and the ``v`` columns: ``M(q) a`` and the quadratic-velocity term
        ``c(q, v)`` (:meth:`force`) are derivatives of ``T``, and an entry of their Jacobian
        is structurally nonzero only where the matching second derivative of ``T`` is
        (a function whose derivative is not identically zero is not identically zero), so
        within the blocks of ``d^2 T / dv^2`` as long as each block of ``M`` depends on its
        own coordinates only. That last condition is not checked here: the caller checks
        the Jacobian it assembles (:meth:`linalg.pattern.SparseJacobian.agrees`).
        """
        n = self.n
        parts = []
        if not self.constant_mass:
            mass = self.mass_pattern()
            if mass is None:
                return None
            parts += [mass, (mass[0], mass[1] + n)]
        if self._potential is not None:
            hessian = traced_sparsity(asdex.hessian_sparsity, self._potential, jnp.zeros(n))
            parts.append((np.asarray(hessian.rows), np.asarray(hessian.cols)))
        if self._forces is not None:
            jacobian = traced_sparsity(
                asdex.jacobian_sparsity,
                lambda x: self._forces(jnp.asarray(0.0), x[:n], x[n:]), jnp.zeros(2 * n))
            parts.append((np.asarray(jacobian.rows), np.asarray(jacobian.cols)))
        empty = np.zeros(0, dtype=np.int64)
        return (np.concatenate([np.asarray(r, dtype=np.int64) for r, _ in parts] + [empty]),
                np.concatenate([np.asarray(c, dtype=np.int64) for _, c in parts] + [empty]))

    def G_values(self, q: Array, t: Array) -> Array:
        """The entries of ``G(q, t)`` in the order of :attr:`G_coloring` (compressed autodiff:
        one pass per colour, all at once or, past :data:`linalg.pattern.CACHED_ENTRIES`, one
        by one)."""
        coloring = self.G_coloring
        at_once = coloring.num_colors * max(self.m, self.n) <= CACHED_ENTRIES
        compressed = asdex.compressed_jacobian_from_coloring(
            lambda x: self.g(x, t), coloring, chunk_size=None if at_once else 1)(q)
        return asdex.decompress_data(compressed, coloring)

    def rounding(self, q: Array, t: Array, x: Array | None = None) -> Array:
        """``max_i sum_j |G_ij(q, t)| |x_j|`` (``x = q`` by default), from ``G``'s entries.

        The round-off that rounding ``x`` puts into ``G x``, and for ``x = q`` into ``g(q)``:
        with coordinates of size ``L`` (a long chain's far end) ``g`` cannot be computed to
        better than about ``eps L |G|``, which a Newton solve's stall test must know.
        """
        rows, cols = self._G_index
        x = q if x is None else x
        terms = jnp.abs(self.G_values(q, t)) * jnp.abs(x[cols])
        return jnp.max(jax.ops.segment_sum(terms, rows, num_segments=self.m))

    @cached_property
    def _G_index(self) -> tuple[Array, Array]:
        return tuple(device_index(a) for a in self.G_pattern())

    @cached_property
    def whitening(self) -> Whitening:
        """The pattern of ``G L^{-T}`` (``M = L L^T`` blockwise: :attr:`mass_blocks`), ``G``'s
        with each entry spread over its block, and the index arrays that compute its
        entries from ``G``'s (:meth:`linalg.blocks.Blocks.whitening`), found once."""
        return self.mass_blocks.whitening(*self.G_pattern())

    def whitened_values(self, q: Array, t: Array) -> Array:
        """The entries of ``G(q, t) L(q)^{-T}`` in the order of :attr:`whitening`'s pattern:
        the structured Schur solvers take them with a unit mass, since ``(G L^{-T})(G
        L^{-T})^T = G M^{-1} G^T``.

        ``G``'s entries by compressed autodiff (:meth:`G_values`), then each row's pieces
        on the blocks whitened by forward substitution with the blocks' factors: cheaper
        than the compressed derivative of ``y -> g(q + L^{-T} y)`` at ``y = 0``, whose
        forward passes each go through the blockwise substitution and ``g``."""
        return self.mass_blocks.whiten_rows(self.mass_factor(q), self.G_values(q, t),
                                            self.whitening)

    def schur(self, kind: str = "auto", dense_max: int = DENSE_MAX):
        """The solver for ``G M^{-1} G^T`` (see :func:`linalg.schur.choose`; ``dense_max``
        the caller's crossover for ``"auto"``), built once.

        A block-diagonal mass reaches the structured solvers whitened: ``G L^{-T}`` with a
        unit mass (:meth:`whitened_values`); a constant one that is not diagonal, the
        augmented system (:mod:`linalg.kkt`)."""
        cache = self.__dict__.setdefault("_schur", {})
        # dense_max decides only whether "auto" may stay dense at this size.
        key = (kind, kind == "auto" and self.m <= dense_max)
        if key not in cache:
            if self.mass_blocks is not None:
                def whitened_pattern():
                    return self.whitening.rows, self.whitening.cols
                cache[key] = choose(kind, (self.m, self.n), self.G, self.solve_mass,
                                    np.ones(self.n), whitened_pattern, self.whitened_values,
                                    dense_max=dense_max)
            else:
                cache[key] = choose(kind, (self.m, self.n), self.G, self.solve_mass,
                                    self.mass_diagonal, self.G_pattern, self.G_values,
                                    self.mass_matrix, dense_max=dense_max)
        return cache[key]

    def gram(self, kind: str = "auto"):
        """The solver for the Gram matrix ``G G^T`` (a unit mass; the stabilised index-2
        forms move ``q`` along ``G^T mu``), built once, of the kind :meth:`schur` uses
        (chosen by structure where that is ``kkt``: the unit mass is diagonal)."""
        kind = "auto" if kind == "kkt" else kind
        cache = self.__dict__.setdefault("_gram", {})
        if kind not in cache:
            cache[kind] = choose(kind, (self.m, self.n), self.G, lambda q, b: b,
                                 np.ones(self.n), self.G_pattern, self.G_values)
        return cache[kind]

    def g_t(self, q: Array, t: Array) -> Array:
        """Explicit time derivative ``dg/dt`` (zero for a scleronomic system)."""
        if not self.system.rheonomic:
            return jnp.zeros(self.m)
        return jax.jacfwd(self._constraints, argnums=1)(q, t)

    def vel_residual(self, q: Array, v: Array, t: Array) -> Array:
        """Velocity-level constraint ``G(q, t) v + g_t(q, t)``."""
        return self.G_times(q, t, v) + self.g_t(q, t)

    def gamma(self, q: Array, v: Array, t: Array) -> Array:
        """Acceleration-level term: ``G a + gamma = 0`` is ``d^2 g / dt^2 = 0``.

        ``gamma = (d/dt (G v + g_t)) at fixed v``: curvature ``(dG/dq . v) v`` plus
        ``2 G_t v + g_tt``, as one forward-mode derivative along ``(q', t') = (v, 1)``.
        """
        return jax.jvp(lambda x, s: self.vel_residual(x, v, s), (q, t), (v, jnp.ones_like(t)))[1]

    def accelerations(self, t: Array, q: Array, v: Array, stab: Array | None = None,
                      schur=None):
        """Accelerations and multipliers from the index-1 system.

        Solves ``[M G^T; G 0] [a; lam] = [force; -gamma - stab]`` through the Schur
        complement, ``G M^{-1} G^T lam = G M^{-1} force + gamma + stab``, then
        ``a = M^{-1} (force - G^T lam)``. ``stab`` is an extra acceleration-level right-hand
        side (Baumgarte terms); ``None`` means zero. ``schur`` is the solver of
        :meth:`schur` to use (default: dense); redundant constraints are handled by its
        policy (:mod:`linalg.dense`).

        Returns
        -------
        a, lam : Array
            Not finite where a structured solver found ``S`` numerically singular.
        """
        schur = self.schur("dense") if schur is None else schur
        solve = self.mass_solver(q)
        MinvF = solve(self.force(t, q, v))
        rhs = self.G_times(q, t, MinvF) + self.gamma(q, v, t)
        if stab is not None:
            rhs = rhs + stab
        lam = schur.solve(schur.factor(q, t), rhs)
        return MinvF - solve(self.GT(q, t, lam)), lam

    def invariant_values(self, q: Array, v: Array) -> Array:
        """Declared invariants beyond energy, stacked (empty when none)."""
        funcs = self.system.invariants
        if not funcs:
            return jnp.zeros(0)
        return jnp.stack([jnp.asarray(f(q, v)) for f in funcs.values()])
