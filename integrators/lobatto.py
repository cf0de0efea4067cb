"""Lobatto IIIA-IIIB partitioned Runge-Kutta methods for constrained Hamiltonian systems."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from integrators.fixed import FixedStep, newton_failure
from integrators.newton import max_norm, newton
from integrators.tableau import combine, lobatto
from problems.mechanics import Mechanics


@dataclass(frozen=True)
class LobattoIIIAIIIB(FixedStep):
    """The s-stage Lobatto IIIA-IIIB (SPARK) method of Jay (1996).

    For ``q' = H_p(q, p)``, ``p' = -H_q(q, p) + f(t, q, v) - G(q, t)^T lam``,
    ``g(q, t) = 0``, one step from ``(q0, p0)`` solves for the stages ``Q_i, P_i``, the
    multipliers ``Lam_i`` and ``p1``:

    .. math::

        Q_i &= q_0 + h \\sum_j a_{ij} H_p(Q_j, P_j), \\qquad
        P_i = p_0 + h \\sum_j \\hat a_{ij} U_j, \\\\
        U_j &= -H_q(Q_j, P_j) + f(t_j, Q_j, H_p(Q_j, P_j)) - G(Q_j, t_j)^T \\Lambda_j, \\\\
        q_1 &= q_0 + h \\sum_j b_j H_p(Q_j, P_j), \\qquad p_1 = p_0 + h \\sum_j b_j U_j, \\\\
        0 &= g(Q_i, t_i) \\; (i = 2, \\dots, s), \\qquad
        0 = G(q_1, t_1) H_p(q_1, p_1) + g_t(q_1, t_1),

    with ``a`` Lobatto IIIA, ``a_hat`` Lobatto IIIB (``Q_1 = q0`` and ``Q_s = q1``, so
    ``g = 0`` holds at every stage and at both step ends). Order ``2s - 2`` in ``q`` and
    ``p``; symplectic for ``f = 0`` and a scleronomic ``g``, and then energy errors stay
    bounded. Enforces ``g = 0`` at the stages and ``G v + g_t = 0`` at the step ends, to
    the Newton tolerance. The stage equations are solved together by Newton's method,
    warm-started from the previous step's multipliers.

    Newton's unknowns are the velocities ``V_j = H_p(Q_j, P_j)`` and ``v_1 = H_p(q_1,
    p_1)`` in place of the momenta, with ``P_j = M(Q_j) V_j`` and ``p_1 = M(q_1) v_1``
    (and ``H_q`` taken at ``V_j``): the same equations, whose residual then multiplies by
    the mass where it would otherwise solve with it. For a configuration-dependent mass
    that is a product in place of a factorisation of ``M(Q_j)`` at every stage and
    iteration, on the structured and the dense path alike; a constant mass costs the
    same either way. For
    a constant mass Newton's corrections are those of the momenta divided by the mass
    (Newton's method is affine invariant), but for the round-off where its stopping test
    ends them.

    The dense path (``linear_solver = "dense"``, or a mass that no structured solver
    takes) uses the exact autodiff Jacobian of the whole stage system, formed once per step
    from :data:`integrators.newton.FROZEN_MIN` unknowns on. The structured
    ones (:mod:`linalg`; chosen by default wherever the mass allows, even for one
    constraint: :meth:`integrators.fixed.FixedStep.dense_max`) use simplified Newton
    with the Jacobian frozen at ``(q_0, p_0)``, without the force Jacobian and the
    derivatives of ``G`` (exact for the linear part of a separable system), and eliminate
    the stage positions and momenta: with ``S_0 = G(q_0) M^{-1} G(q_0)^T`` the corrections
    of the multipliers solve

    .. math::

        h^2 \\sum_k (A \\hat A)_{ik} S_0 \\,\\delta\\Lambda_k
            = R^g_i - G_0 \\big(R^Q_i + h \\sum_j a_{ij} M^{-1} R^P_j\\big)
            \\quad (i = 2, \\dots, s), \\qquad
        h \\sum_k b_k S_0 \\,\\delta\\Lambda_k = R^v - G_0 M^{-1} R^p,

    (``R`` the residuals of the equations above), that is ``S_0 X B^T = R`` with an
    ``s x s`` matrix ``B``: one factorisation of ``S_0`` per step and ``s`` solves per
    iteration, memory ``O(s nnz(G))``. The stage velocities and positions follow as
    ``delta V_j = M^{-1} (-R^P_j - h sum_k a_hat_jk G_0^T delta Lambda_k)`` and
    ``delta Q_i = -R^Q_i + h sum_j a_ij delta V_j``, ``M`` factorised at ``q_0`` once per
    step.

    Parameters
    ----------
    h : float
        Step size (shrunk to divide the horizon evenly).
    stages : int
        Number of stages ``s >= 2``.
    newton_tol : float
        Max-norm residual tolerance of the stage equations; the default 1e-16 iterates to
        round-off (see :func:`integrators.newton.newton`).
    newton_max_iter : int
        Newton iteration limit per step; exceeding it fails the run. Simplified Newton
        converges linearly, at a rate that grows with ``h`` times the rate of change of
        ``G`` along the motion (about 0.3 for sps-ring at ``h = 0.1``: 20 iterations to
        round-off), hence the margin.
    linear_solver : {"auto", "dense", "banded", "superlu", "kkt"}
        How systems with ``G M^{-1} G^T`` are solved (:func:`linalg.schur.choose`).
    """

    h: float = 0.01
    stages: int = 3
    newton_tol: float = 1e-16
    newton_max_iter: int = 50
    linear_solver: str = "auto"

    family: ClassVar[str] = "Lobatto IIIA-IIIB (SPARK)"
    symplectic: ClassVar[bool] = True
    enforces: ClassVar[tuple[str, ...]] = ("position", "velocity")

    @property
    def nominal_order(self) -> int:
        return 2 * self.stages - 2

    def dense_max(self, mech: Mechanics) -> int:
        """None: Newton on the stage system is cheaper on the structured path from one
        constraint up (:meth:`integrators.fixed.FixedStep.dense_max`)."""
        return 0

    def check(self) -> None:
        super().check()
        if not 2 <= self.stages <= 6:
            raise ValueError(f"LobattoIIIAIIIB: stages = {self.stages} must lie in 2..6")

    def tableau(self):
        """``A``, ``A_hat``, ``b`` and ``B^{-1}`` of the eliminated multiplier system (class
        notes) as constants for :func:`integrators.tableau.combine`, and ``c`` as an array."""
        tab = lobatto(self.stages)
        A, Ah, b = tab.A, tab.A_hat, tab.b
        c = jnp.asarray(tab.c)
        # Rows of the eliminated multiplier system, divided by h^2 (position constraints
        # at stages 2..s) and by h (the velocity constraint): B = [(A A_hat)[1:]; b].
        B_inv = np.linalg.inv(np.vstack([(tab.A @ tab.A_hat)[1:], tab.b]))
        return A, Ah, b, c, B_inv

    def simplified(self, mech: Mechanics, schur, q0, p0, t, h, S0, K0):
        """Simplified Newton's correction for the stage system (see the class notes)."""
        s = self.stages
        A, Ah, b, c, B_inv = self.tableau()
        solve0 = mech.mass_solver(q0, K0)   # factorised once per step, not per iteration
        Minv = jax.vmap(solve0)
        weights = jnp.concatenate([jnp.full(s - 1, 1.0 / (h * h)), jnp.array([1.0 / h])])

        def linear(z, r):
            Q, V, _, _ = z
            ts = t + c * h
            # G at the current stage positions where it multiplies a residual: only
            # the Schur block is frozen at q0, which speeds up convergence when G
            # varies over the step.
            GQ = jax.vmap(mech.G_times)
            q1 = q0 + h * combine(b, V)
            RQ, RP, Rp, Rg, Rv = r
            rhs = jnp.concatenate([
                Rg - GQ(Q[1:], ts[1:], RQ[1:] + h * combine(A[1:], Minv(RP))),
                (Rv - mech.G_times(q1, t + h, solve0(Rp)))[None],
            ]) * weights[:, None]                                   # (s, m)
            dLam = combine(B_inv, schur.solve(S0, rhs.T).T)           # (s, m)
            force = jax.vmap(mech.GT)(Q, ts, dLam)
            dV = Minv(-RP - h * combine(Ah, force))
            dQ = -RQ + h * combine(A, dV)
            dv1 = solve0(-Rp - h * combine(b, force))
            # The residual's terms: the unknowns, and the momenta (about p0).
            return (dQ, dV, dLam, dv1), jnp.maximum(max_norm(z), max_norm(p0))

        return linear

    def start(self, mech: Mechanics, schur, q0, v0, t0):
        """``(q0, p0, v0, lam, S0, K0)``: zero multipliers, and on the structured path the
        factor of ``G M^{-1} G^T`` at ``q0`` (a placeholder on the dense one) and that of a
        block-diagonal ``M(q0)`` (:meth:`problems.mechanics.Mechanics.mass_factor`)."""
        if schur.name == "dense":
            return q0, mech.momentum(q0, v0), v0, jnp.zeros(mech.m), jnp.zeros(()), None
        return (q0, mech.momentum(q0, v0), v0, jnp.zeros(mech.m), schur.factor(q0, t0),
                mech.mass_factor(q0))

    def step(self, mech: Mechanics, schur, carry, t, h):
        """One step (:class:`integrators.fixed.FixedStep`)."""
        s = self.stages
        A, Ah, b, c, _ = self.tableau()
        dense = schur.name == "dense"
        q0, p0, v0, lam, S0, K0 = carry

        def residual(z):
            Q, V, Lam, v1 = z
            ts = t + c * h
            P = jax.vmap(mech.momentum)(Q, V)
            U = (-jax.vmap(mech.H_q)(Q, P, V) + jax.vmap(mech.external)(ts, Q, V)
                 - jax.vmap(mech.GT)(Q, ts, Lam))
            q1 = q0 + h * combine(b, V)
            return (Q - q0 - h * combine(A, V), P - p0 - h * combine(Ah, U),
                    mech.momentum(q1, v1) - p0 - h * combine(b, U),
                    jax.vmap(mech.g)(Q[1:], ts[1:]), mech.vel_residual(q1, v1, t + h))

        # The unknowns are the stage velocities V_j = H_p(Q_j, P_j) and v1 = H_p(q1, p1),
        # not the momenta (class notes), and (Q, V, Lam, v1) and the residual's five
        # blocks stay separate arrays: packed into one vector, every iteration sliced and
        # concatenated them, which cost more than the arithmetic on small systems
        # (:func:`newton`).
        z0 = (q0 + h * c[:, None] * v0, jnp.tile(v0, (s, 1)), jnp.tile(lam, (s, 1)), v0)
        if dense:
            sol = newton(residual, z0, self.newton_tol, self.newton_max_iter)
            S1, ok, jac = S0, True, sol.iterations
        else:
            sol = newton(residual, z0, self.newton_tol, self.newton_max_iter,
                         self.simplified(mech, schur, q0, p0, t, h, S0, K0))
        Q, V, Lam, v1 = sol.z
        q1 = q0 + h * combine(b, V)
        p1 = mech.momentum(q1, v1)
        K1 = None
        if not dense:
            # The next step's S_0 and M(q_0) factors.
            S1, K1 = schur.factor(q1, t + h), mech.mass_factor(q1)
            ok, jac = S0.ok, 1
        it = sol.iterations
        counts = {"n_f_evals": s * (it + 1), "n_jac_evals": jac, "n_newton": it,
                  "n_lin_solves": it}
        # v1 and M(q1)'s factors go to the next step: the loop observes v1 and the next
        # step starts from it, so that a configuration-dependent mass is factorised once
        # per step.
        return ((q1, p1, v1, Lam[-1], S1, K1), newton_failure(sol.converged, ok),
                sol.residual, counts)

    def observe(self, mech: Mechanics, carry):
        """``(q, v)``, both carried."""
        return carry[0], carry[2]
