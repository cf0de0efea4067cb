"""RATTLE: the constrained Stoermer-Verlet method with position and velocity projections."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import jax.numpy as jnp

from integrators.fixed import FixedStep, newton_failure
from integrators.newton import max_norm, newton
from linalg.dense import solve
from problems.mechanics import Mechanics


@dataclass(frozen=True)
class Rattle(FixedStep):
    """RATTLE (Andersen 1983; Leimkuhler and Skeel 1994).

    One step from ``(q0, p0)`` with ``F(t, q, p) = -H_q(q, p) + f(t, q, H_p(q, p))``:

    .. math::

        p_{1/2} &= p_0 + \\tfrac h2 \\big(F(t_0, q_0, p_{1/2}) - G(q_0, t_0)^T \\lambda\\big), \\\\
        q_1 &= q_0 + \\tfrac h2 \\big(H_p(q_0, p_{1/2}) + H_p(q_1, p_{1/2})\\big), \\qquad
        0 = g(q_1, t_1), \\\\
        p_1 &= p_{1/2} + \\tfrac h2 \\big(F(t_1, q_1, p_{1/2}) - G(q_1, t_1)^T \\mu\\big), \\qquad
        0 = G(q_1, t_1) H_p(q_1, p_1) + g_t(q_1, t_1).

    Order 2, symplectic for ``f = 0`` and a scleronomic ``g``; enforces ``g = 0`` and
    ``G v + g_t = 0`` at every step end. It is the 2-stage Lobatto IIIA-IIIB method, so it
    agrees with ``lobatto3ab2`` to round-off.

    The position projection is solved by Newton's method. For a separable Hamiltonian
    (constant mass, no applied forces) ``p_{1/2}`` and ``q_1`` are explicit in ``lambda``
    and the unknown is ``lambda`` alone (m x m Jacobian ``-h^2/2 G(q_1) M^{-1} G(q_0)^T``);
    otherwise the unknown is ``(p_{1/2}, q_1, lambda)``, and the position equation is taken
    times ``M(q_0)^{-1} M(q_1)`` (a product with ``M(q_1)``, where ``H_p(q_1, p_{1/2})``
    would factorise ``M(q_1)`` at every iterate), with ``M(q_0)`` factorised once per step
    for every solve at ``q_0`` (:meth:`problems.mechanics.Mechanics.mass_solver`). The
    velocity projection is linear in ``mu`` (one m x m solve) because ``H_p`` is linear in
    ``p``.

    The structured paths (:mod:`linalg`; chosen by default wherever the mass allows,
    but for a separable system with one constraint: :meth:`dense_max`) use simplified
    Newton instead: the Jacobian is replaced by ``-h^2/2 S_0`` with the Schur complement
    ``S_0 = G(q_0) M^{-1} G(q_0)^T``, whose factor is the previous step's velocity
    projection matrix, so each step factorises ``S`` once (at ``q_1``, for the velocity
    projection) and ``G`` is never formed. Where the frozen Jacobian does not converge,
    Newton with the exact Jacobian (matrix-free) takes over, preconditioned by ``S``
    factorised afresh at the ``q_1`` of its first iterate (without forces; by ``S_0`` with
    them). With forces or a configuration-dependent mass the same elimination reduces the
    correction of ``(p_{1/2}, q_1, lambda)`` to one solve with ``S_0``. Newton starts from the
    previous step's ``mu``, the constraint force at ``q_0`` (``lambda`` is that at the
    previous ``q_0``): a closer guess, which the frozen Jacobian's small region of
    convergence needs where a step starts at a singular configuration. There ``S_0`` is
    nearly singular, and the ``lambda`` that solves the step is large along the
    constraints that are dependent at ``q_0`` (their forces nearly cancel); carried into
    the next step, whose ``G`` no longer cancels them, it would start Newton far from the
    solution (on four-bar:N=1024 Newton then finds another root, off the parallelogram
    branch). The dense path, whose exact Newton converges from there, keeps
    ``lambda``.

    Parameters
    ----------
    h : float
        Step size (shrunk to divide the horizon evenly).
    newton_tol : float
        Max-norm residual tolerance of the position projection; the default 1e-16 iterates to
        round-off (see :func:`integrators.newton.newton`).
    newton_max_iter : int
        Newton iteration limit per step. On the structured path simplified Newton gets this
        many, then Newton with the exact Jacobian as many more
        (:func:`integrators.newton.newton`); exceeding both fails the run. Simplified Newton
        converges linearly, slowly where the constraint forces are large (on
        sps-lattice:N=16,K=8 at h = 0.005, where the rings flip through flat and the bar
        forces peak, it needed more than 20 iterations), hence the margin.
    linear_solver : {"auto", "dense", "banded", "superlu", "kkt"}
        How systems with ``G M^{-1} G^T`` are solved (:func:`linalg.schur.choose`).
    """

    h: float = 0.01
    newton_tol: float = 1e-16
    newton_max_iter: int = 50
    linear_solver: str = "auto"

    family: ClassVar[str] = "RATTLE"
    symplectic: ClassVar[bool] = True
    enforces: ClassVar[tuple[str, ...]] = ("position", "velocity")
    nominal_order: ClassVar[int] = 2

    def dense_max(self, mech: Mechanics) -> int:
        """One constraint for a separable Hamiltonian, none otherwise
        (:meth:`integrators.fixed.FixedStep.dense_max`): there the dense Newton's unknown is
        the one multiplier, its Jacobian a number and its solve a division, with no LAPACK
        call, and it beats the structured path; from two constraints on the structured
        path is the faster (``python -m benchmarks.perf.crossover``)."""
        return 1 if mech.separable else 0

    def forces(self, mech: Mechanics, solve=None):
        """``(t, q, p) -> (F(t, q, p), H_p(q, p))`` with ``F(t, q, p) = -H_q(q, p) + f(t, q,
        H_p(q, p))``; ``solve``, where given, is ``M(q)^{-1}`` of the one ``q`` it is called at
        (:meth:`problems.mechanics.Mechanics.mass_solver`)."""

        def F(t, q, p):
            v = mech.H_p(q, p) if solve is None else solve(p)
            return -mech.H_q(q, p, v) + mech.external(t, q, v), v

        return F

    def position(self, mech: Mechanics, schur):
        """The position projection ``(q0, p0, F0, S0, lam, t, h, solve0) -> (p_half, q1,
        sol, extra_f)`` for the system's structure (``solve0``: ``M(q0)^{-1}``,
        :meth:`problems.mechanics.Mechanics.mass_solver`; ``extra_f``: whether each residual
        evaluates ``F``)."""

        def position_separable(q0, p0, F0, G0, lam, t, h, solve0):
            def half(lam):
                p_half = p0 + 0.5 * h * (F0 - G0.T @ lam)
                return p_half, q0 + h * solve0(p_half)

            sol = newton(lambda lam: mech.g(half(lam)[1], t + h), lam,
                         self.newton_tol, self.newton_max_iter)
            return (*half(sol.z), sol, 0)

        def position_separable_structured(q0, p0, F0, S0, lam, t, h, solve0):
            def half(lam):
                p_half = p0 + 0.5 * h * (F0 - mech.GT(q0, t, lam))
                return p_half, q0 + h * solve0(p_half)

            # The residual g(q1) is computed from q1 = q0 + h M^-1 p_half: besides the
            # terms in lam, q0's rounding reaches it as |G||q0| (coordinates of size N
            # put g's round-off at eps N).
            data = mech.rounding(q0, t)

            def frozen(S):
                def linear(lam, r):
                    # J = -h^2/2 G(q1) M^-1 G(q0)^T, approximated by -h^2/2 S; |J||lam| is
                    # bounded by h^2/2 ||S|| |lam|.
                    return (schur.solve(S, r) * (2.0 / (h * h)),
                            0.5 * h * h * S.norm * jnp.max(jnp.abs(lam)) + data)
                return linear

            sol = newton(lambda lam: mech.g(half(lam)[1], t + h), lam,
                         self.newton_tol, self.newton_max_iter, frozen(S0),
                         lambda lam: frozen(schur.factor(half(lam)[1], t + h)))
            return (*half(sol.z), sol, 0)

        def position_general(q0, p0, F0, S0, lam, t, h, solve0):
            F0_at = self.forces(mech, solve0)

            def residual(z):
                # The position equation is taken times M(q0)^-1 M(q1):
                # M0^-1 M1 (q1 - q0 - h/2 v_half) - h/2 v_half, the same roots and rounding
                # (M0^-1 M1 is near the identity) with a product with M(q1) in place of a
                # solve, which would factorise a configuration-dependent M(q1) afresh at
                # every iterate.
                p_half, q1, lam = z
                F_half, v_half = F0_at(t, q0, p_half)
                return (p_half - p0 - 0.5 * h * (F_half - mech.GT(q0, t, lam)),
                        solve0(mech.mass_times(q1, q1 - q0 - 0.5 * h * v_half)) - 0.5 * h * v_half,
                        mech.g(q1, t + h))

            # The unknowns and the residual's blocks stay separate arrays (:func:`newton`).
            z0 = (p0, q0 + h * solve0(p0), lam)
            if schur.name == "dense":
                sol = newton(residual, z0, self.newton_tol, self.newton_max_iter)
                p_half, q1, lam = sol.z
                return p_half, q1, sol._replace(z=lam), 1

            def linear(z, r):
                # Frozen at q0 without the force Jacobian: dp = -r1 - h/2 G0^T dlam,
                # dq = -r2 + h M^-1 dp and G0 dq = -r3 give
                # h^2/2 S0 dlam = r3 - G0 (r2 + h M^-1 r1).
                r1, r2, r3 = r
                rhs = r3 - mech.G_times(q0, t, r2 + h * solve0(r1))
                dlam = schur.solve(S0, rhs) * (2.0 / (h * h))
                dp = -r1 - 0.5 * h * mech.GT(q0, t, dlam)
                dq = -r2 + h * solve0(dp)
                return (dp, dq, dlam), max_norm(z)

            sol = newton(residual, z0, self.newton_tol, self.newton_max_iter, linear)
            p_half, q1, lam = sol.z
            return p_half, q1, sol._replace(z=lam), 1

        if mech.separable:
            return position_separable if schur.name == "dense" else position_separable_structured
        return position_general

    def start(self, mech: Mechanics, schur, q0, v0, t0):
        """``(q0, p0, v0, F0, S0, lam, K0)``: ``S0`` is ``G(q0)`` on the dense path, the
        factor of ``G M^{-1} G^T`` at ``q0`` otherwise; the multipliers start at zero;
        ``K0`` is the factor of a block-diagonal ``M(q0)``
        (:meth:`problems.mechanics.Mechanics.mass_factor`; ``None`` for any other mass)."""
        p0 = mech.momentum(q0, v0)
        first = mech.G(q0, t0) if schur.name == "dense" else schur.factor(q0, t0)
        return (q0, p0, v0, self.forces(mech)(t0, q0, p0)[0], first, jnp.zeros(mech.m),
                mech.mass_factor(q0))

    def step(self, mech: Mechanics, schur, carry, t, h):
        """One step (:class:`integrators.fixed.FixedStep`)."""
        q0, p0, _, F0, S0, lam, K0 = carry
        p_half, q1, sol, extra_f = self.position(mech, schur)(q0, p0, F0, S0, lam, t, h,
                                                              mech.mass_solver(q0, K0))
        t1 = t + h
        K1 = mech.mass_factor(q1)
        solve1 = mech.mass_solver(q1, K1)
        F1 = self.forces(mech, solve1)(t1, q1, p_half)[0]
        base = p_half + 0.5 * h * F1
        rhs = mech.vel_residual(q1, solve1(base), t1)
        if schur.name == "dense":
            G1 = mech.G(q1, t1)
            mu = solve(0.5 * h * G1 @ solve1(G1.T), rhs)
            p1, S1, ok = base - 0.5 * h * G1.T @ mu, G1, True
        else:
            S1 = schur.factor(q1, t1)
            mu = schur.solve(S1, rhs) * (2.0 / h)
            p1, ok = base - 0.5 * h * mech.GT(q1, t1, mu), S1.ok
        it = sol.iterations
        # G1 (or the factor of S1) is the next step's (first same as last), and so is
        # F1 with a separable H; the general projection evaluates F once per residual.
        counts = {"n_f_evals": 1 + extra_f * (it + 1), "n_jac_evals": it + 1,
                  "n_newton": it, "n_lin_solves": it + 1}
        # The next step's first guess of lam: mu on the structured path (docstring).
        guess = sol.z if schur.name == "dense" else mu
        # v1 = H_p(q1, p1) with M(q1) as factorised above, and that factor, are carried to
        # the next step: computed afresh where the loop observes v1 and where the next step
        # starts, a configuration-dependent mass would be factorised twice more per step.
        return ((q1, p1, solve1(p1), F1, S1, guess, K1), newton_failure(sol.converged, ok),
                sol.residual, counts)

    def observe(self, mech: Mechanics, carry):
        """``(q, v)``, both carried."""
        return carry[0], carry[2]
