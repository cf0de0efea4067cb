"""Lobatto IIIA-IIIB partitioned Runge-Kutta methods for constrained Hamiltonian systems."""

from __future__ import annotations

from dataclasses import dataclass, replace

import jax
import jax.numpy as jnp

from integrators.base import Grid, Integrator
from integrators.loop import march
from integrators.newton import newton
from integrators.tableau import lobatto
from problems.case import Case


@dataclass(frozen=True)
class LobattoIIIAIIIB(Integrator):
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
    the Newton tolerance. The stage equations are solved together by Newton's method with
    the autodiff Jacobian (dense), warm-started from the previous step's multipliers.

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
        Newton iteration limit per step; exceeding it fails the run.
    """

    h: float = 0.01
    stages: int = 3
    newton_tol: float = 1e-16
    newton_max_iter: int = 20

    @property
    def order(self) -> int:
        return 2 * self.stages - 2

    def check(self) -> None:
        super().check()
        if not 2 <= self.stages <= 6:
            raise ValueError(f"LobattoIIIAIIIB: stages = {self.stages} must lie in 2..6")

    def prepare(self, case: Case, grid: Grid):
        self.check()
        mech = case.mech
        tab = lobatto(self.stages)
        s, n, m = self.stages, mech.n, mech.m
        A, Ah, b, c = (jnp.asarray(x) for x in (tab.A, tab.A_hat, tab.b, tab.c))

        def stage_forces(Q, P, Lam, t, h):
            V = jax.vmap(mech.H_p)(Q, P)
            ts = t + c * h
            U = (-jax.vmap(mech.H_q)(Q, P) + jax.vmap(mech.external)(ts, Q, V)
                 - jnp.einsum("jmn,jm->jn", jax.vmap(mech.G)(Q, ts), Lam))
            return V, U, ts

        def step(carry, t, h):
            q0, p0, lam = carry
            v0 = mech.H_p(q0, p0)

            def unpack(z):
                Q = z[: s * n].reshape(s, n)
                P = z[s * n: 2 * s * n].reshape(s, n)
                Lam = z[2 * s * n: 2 * s * n + s * m].reshape(s, m)
                return Q, P, Lam, z[2 * s * n + s * m:]

            def residual(z):
                Q, P, Lam, p1 = unpack(z)
                V, U, ts = stage_forces(Q, P, Lam, t, h)
                q1 = q0 + h * b @ V
                return jnp.concatenate([
                    (Q - q0 - h * A @ V).ravel(),
                    (P - p0 - h * Ah @ U).ravel(),
                    p1 - p0 - h * b @ U,
                    jax.vmap(mech.g)(Q[1:], ts[1:]).ravel(),
                    mech.vel_residual(q1, mech.H_p(q1, p1), t + h),
                ])

            z0 = jnp.concatenate([(q0 + h * c[:, None] * v0).ravel(), jnp.tile(p0, s),
                                  jnp.tile(lam, s), p0])
            sol = newton(residual, z0, self.newton_tol, self.newton_max_iter)
            Q, P, Lam, p1 = unpack(sol.z)
            q1 = q0 + h * b @ jax.vmap(mech.H_p)(Q, P)
            it = sol.iterations
            counts = {"n_f_evals": s * (it + 1), "n_jac_evals": it, "n_newton": it,
                      "n_lin_solves": it}
            return (q1, p1, Lam[-1]), jnp.where(sol.converged, 0, 1), sol.residual, counts

        # Compiled once; run eagerly, each autodiff operation would compile on its own.
        carry0 = jax.jit(lambda q0, v0: (q0, mech.momentum(q0, v0), jnp.zeros(m)))(
            jnp.asarray(case.q0), jnp.asarray(case.v0))
        return march(mech, grid, self.h, carry0, step,
                     lambda carry: (carry[0], mech.H_p(carry[0], carry[1])),
                     key=replace(self, h=None))
