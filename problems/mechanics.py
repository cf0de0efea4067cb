"""Constrained mechanical systems and every quantity derived from them.

A problem author writes only the physics of

.. math::

    M(q)\\,\\ddot q = -\\nabla U(q) + f(t, q, \\dot q) + c(q, \\dot q) - G(q, t)^T \\lambda,
    \\qquad g(q, t) = 0,

as pure JAX functions: the mass matrix ``M(q)`` (or a constant matrix or diagonal), the
potential ``U(q)``, the holonomic constraints ``g(q, t)`` and optional non-conservative
forces ``f(t, q, v)``. This module is the one place where everything else is derived by
automatic differentiation: the constraint Jacobian ``G = dg/dq``, ``g_t``, the
acceleration-level term ``gamma`` with ``G a + gamma = 0``, the quadratic-velocity forces
``c(q, v)`` of a configuration-dependent mass, the momentum ``p = M v`` and the Hamiltonian
``H(q, p) = p^T M(q)^{-1} p / 2 + U(q)`` with its gradients. No integrator differentiates
anything itself.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Callable, Mapping

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

Array = jax.Array


@dataclass(frozen=True, eq=False)
class System:
    """The physics of a constrained mechanical system, written once.

    Parameters
    ----------
    n, m : int
        Number of coordinates and of constraints.
    mass : callable or array_like
        ``mass(q) -> (n, n)``, or a constant ``(n, n)`` matrix, or a constant diagonal
        ``(n,)``. Symmetric positive definite.
    constraints : callable
        ``g(q, t) -> (m,)``, holonomic; may depend on ``t`` (then set ``rheonomic``).
    potential : callable, optional
        ``U(q) -> scalar``; conservative forces are ``-grad U``.
    forces : callable, optional
        ``f(t, q, v) -> (n,)``, non-conservative generalised forces.
    rheonomic : bool
        Whether ``g`` depends explicitly on time (energy is then not conserved).
    invariants : mapping of str to callable
        Conserved quantities beyond energy, ``I(q, v) -> scalar`` (for example angular
        momentum components).
    sensitive : bool
        The motion is chaotic: exact comparisons against a reference are meaningless and
        the drift gate reports but does not gate it.
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
        self.constant_mass = not callable(system.mass)
        if self.constant_mass:
            mass = np.asarray(system.mass, dtype=np.float64)
            matrix = np.diag(mass) if mass.ndim == 1 else mass
            if matrix.shape != (self.n, self.n):
                raise ValueError(f"mass has shape {matrix.shape}, expected ({self.n}, {self.n})")
            self._M = jnp.asarray(matrix)
            self._Minv = jnp.asarray(np.linalg.inv(matrix))
        # Energy is conserved only for a scleronomic system without applied forces.
        self.has_energy = system.forces is None and not system.rheonomic
        self.separable = self.constant_mass and system.forces is None

    # --- mass, momentum, Hamiltonian -------------------------------------------------
    def mass(self, q: Array) -> Array:
        """Mass matrix ``M(q)``."""
        return self._M if self.constant_mass else self.system.mass(q)

    def solve_mass(self, q: Array, b: Array) -> Array:
        """``M(q)^{-1} b`` (b may be a vector or a matrix of columns)."""
        if self.constant_mass:
            return self._Minv @ b
        # LU, not Cholesky: under jacfwd the Cholesky solve's tangents become batched
        # triangular solves, which XLA's CPU backend runs about 200x slower than LU's.
        return jnp.linalg.solve(self.mass(q), b)

    def potential(self, q: Array) -> Array:
        """Potential energy ``U(q)`` (zero when none is declared)."""
        return jnp.asarray(0.0) if self.system.potential is None else self.system.potential(q)

    def momentum(self, q: Array, v: Array) -> Array:
        """Conjugate momentum ``p = M(q) v``."""
        return self.mass(q) @ v

    def velocity(self, q: Array, p: Array) -> Array:
        """Velocity ``v = H_p(q, p) = M(q)^{-1} p``."""
        return self.solve_mass(q, p)

    def hamiltonian(self, q: Array, p: Array) -> Array:
        """``H(q, p) = p^T M(q)^{-1} p / 2 + U(q)``."""
        return 0.5 * p @ self.solve_mass(q, p) + self.potential(q)

    def energy(self, q: Array, v: Array) -> Array:
        """Total energy ``v^T M(q) v / 2 + U(q)`` in velocity form."""
        return 0.5 * v @ self.mass(q) @ v + self.potential(q)

    def H_q(self, q: Array, p: Array) -> Array:
        """``dH/dq``, including the derivative of ``M(q)^{-1}`` for a varying mass."""
        if self.constant_mass:
            return self.grad_potential(q)
        return jax.grad(self.hamiltonian, argnums=0)(q, p)

    def H_p(self, q: Array, p: Array) -> Array:
        """``dH/dp = M(q)^{-1} p``."""
        return self.velocity(q, p)

    def grad_potential(self, q: Array) -> Array:
        """``grad U(q)``."""
        if self.system.potential is None:
            return jnp.zeros(self.n)
        return jax.grad(self.system.potential)(q)

    # --- forces ------------------------------------------------------------------------
    def external(self, t: Array, q: Array, v: Array) -> Array:
        """Non-conservative generalised forces ``f(t, q, v)`` (zero when none)."""
        return jnp.zeros(self.n) if self.system.forces is None else self.system.forces(t, q, v)

    def force(self, t: Array, q: Array, v: Array) -> Array:
        """Right-hand side of ``M a = force - G^T lam``.

        ``-grad U + f + c(q, v)`` with the quadratic-velocity term of a varying mass,
        ``c = grad_q(v^T M v)/2 - (dM/dq . v) v``.
        """
        F = -self.grad_potential(q) + self.external(t, q, v)
        if not self.constant_mass:
            dM_v = jax.jvp(self.system.mass, (q,), (v,))[1]
            F = F + 0.5 * jax.grad(lambda x: v @ self.system.mass(x) @ v)(q) - dM_v @ v
        return F

    # --- constraints ---------------------------------------------------------------------
    def g(self, q: Array, t: Array) -> Array:
        """Holonomic constraints ``g(q, t)``."""
        return self.system.constraints(q, t)

    def G(self, q: Array, t: Array) -> Array:
        """Constraint Jacobian ``dg/dq`` (m x n)."""
        return jax.jacfwd(self.system.constraints, argnums=0)(q, t)

    def g_t(self, q: Array, t: Array) -> Array:
        """Explicit time derivative ``dg/dt`` (zero for a scleronomic system)."""
        if not self.system.rheonomic:
            return jnp.zeros(self.m)
        return jax.jacfwd(self.system.constraints, argnums=1)(q, t)

    def vel_residual(self, q: Array, v: Array, t: Array) -> Array:
        """Velocity-level constraint ``G(q, t) v + g_t(q, t)``."""
        return self.G(q, t) @ v + self.g_t(q, t)

    def gamma(self, q: Array, v: Array, t: Array) -> Array:
        """Acceleration-level term: ``G a + gamma = 0`` is ``d^2 g / dt^2 = 0``.

        ``gamma = (d/dt (G v + g_t)) at fixed v``: curvature ``(dG/dq . v) v`` plus
        ``2 G_t v + g_tt``, as one forward-mode derivative along ``(q', t') = (v, 1)``.
        """
        return jax.jvp(lambda x, s: self.vel_residual(x, v, s), (q, t), (v, jnp.ones_like(t)))[1]

    def accelerations(self, t: Array, q: Array, v: Array, stab: Array | None = None):
        """Accelerations and multipliers from the index-1 system.

        Solves ``[M G^T; G 0] [a; lam] = [force; -gamma - stab]`` through the Schur
        complement ``G M^{-1} G^T`` (m x m, Cholesky; least squares when redundant
        constraints make it singular, see :meth:`schur_solve`). ``stab`` is an extra
        acceleration-level right-hand side (Baumgarte terms); ``None`` means zero.

        Returns
        -------
        a, lam : Array
        """
        F = self.force(t, q, v)
        G = self.G(q, t)
        MinvF = self.solve_mass(q, F)
        MinvGT = self.solve_mass(q, G.T)
        rhs = G @ MinvF + self.gamma(q, v, t)
        if stab is not None:
            rhs = rhs + stab
        lam = self.schur_solve(G @ MinvGT, rhs)
        return MinvF - MinvGT @ lam, lam

    @staticmethod
    def schur_solve(S: Array, rhs: Array) -> Array:
        """``S^{-1} rhs`` for ``S = G M^{-1} G^T`` by Cholesky, or by least squares if singular.

        Redundant constraints (``G`` of rank below ``m``) make ``S`` positive semidefinite
        only: its Cholesky factor then has a pivot at round-off level or breaks down (NaN).
        ``S`` is first scaled symmetrically to unit diagonal (``D S D``, so that constraints
        in different units are not taken for rank deficiency); when the smallest squared
        pivot of its Cholesky factor is below ``1e-12`` times the largest (or not finite),
        the minimum-norm least-squares solution (SVD, singular values below ``1e-12`` of the
        largest dropped) of the scaled system is used instead: its multipliers give
        ``G^T lam``, the unique constraint force. (``S`` is m x m, so the SVD is cheap.)
        """
        d = jnp.diag(S)
        D = jnp.where(d > 0, 1.0 / jnp.sqrt(jnp.where(d > 0, d, 1.0)), 1.0)
        Ss = S * D[:, None] * D[None, :]
        factor = jax.scipy.linalg.cho_factor(Ss, lower=True)
        pivots = jnp.diag(factor[0]) ** 2
        deficient = ~(jnp.min(pivots) > 1e-12 * jnp.max(pivots))
        y = jax.lax.cond(deficient, lambda: jnp.linalg.lstsq(Ss, D * rhs, rcond=1e-12)[0],
                         lambda: jax.scipy.linalg.cho_solve(factor, D * rhs))
        return D * y

    def invariant_values(self, q: Array, v: Array) -> Array:
        """Declared invariants beyond energy, stacked (empty when none)."""
        funcs = self.system.invariants
        if not funcs:
            return jnp.zeros(0)
        return jnp.stack([jnp.asarray(f(q, v)) for f in funcs.values()])
