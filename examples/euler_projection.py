"""A user-written fixed-step integrator: symplectic Euler with coordinate projection.

Written against the public contract only (:class:`integrators.fixed.FixedStep`: ``start``,
``step``, ``observe`` and the traits); the shared compiled loop does the rest. Run it with::

    python -m benchmarks.run --load examples/euler_projection.py \
        --problems pendulum --integrators euler-projection --h 0.01

One step applies the semi-explicit (symplectic) Euler method to the index-1 equations of
motion ``q' = v``, ``v' = a(t, q, v)`` (``M a = f - G^T lambda`` with ``G a + gamma = 0``),
whose solutions keep ``g = 0`` and ``G v + g_t = 0``, and projects the result back onto
both, in the metric of ``M``:

.. math::

    \\tilde v &= v_n + h\\, a(t_n, q_n, v_n), \\qquad \\tilde q = q_n + h \\tilde v, \\\\
    q_{n+1} &= \\tilde q - M^{-1} G(\\tilde q)^T \\lambda, \\qquad g(q_{n+1}, t_{n+1}) = 0, \\\\
    v_{n+1} &= \\tilde v - M^{-1} G^T \\mu, \\qquad G v_{n+1} + g_t = 0
    \\quad (G \\text{ at } q_{n+1}).

This is the standard projection method of Hairer, Lubich and Wanner (Geometric Numerical
Integration, 2nd ed., Springer 2006, Section IV.4, Algorithm 4.2): projecting onto the
invariant manifold keeps the order of the underlying method, 1. The projection is not
symplectic, so neither is the method. ``lambda`` is found by Newton's method (an
``m x m`` system), ``mu`` by one solve with ``G M^{-1} G^T``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import jax.numpy as jnp

import integrators
from integrators.fixed import FixedStep, newton_failure
from integrators.newton import newton


@dataclass(frozen=True)
class EulerProjection(FixedStep):
    """Symplectic Euler on the index-1 equations with coordinate projection (order 1).

    Parameters
    ----------
    h : float
        Step size (shrunk to divide the horizon evenly).
    newton_tol, newton_max_iter
        The position projection's Newton tolerance (1e-16: to round-off) and limit.
    """

    h: float = 0.01
    newton_tol: float = 1e-16
    newton_max_iter: int = 20

    family: ClassVar[str] = "Euler with projection (user example)"
    enforces: ClassVar[tuple[str, ...]] = ("position", "velocity")
    nominal_order: ClassVar[int] = 1

    def start(self, mech, schur, q0, v0, t0):
        return q0, v0

    def step(self, mech, schur, carry, t, h):
        q, v = carry
        a, _ = mech.accelerations(t, q, v, schur=schur)
        v1 = v + h * a
        q1, t1 = q + h * v1, t + h

        def projected(lam):
            return q1 - mech.solve_mass(q1, mech.GT(q1, t1, lam))

        sol = newton(lambda lam: mech.g(projected(lam), t1), jnp.zeros(mech.m),
                     self.newton_tol, self.newton_max_iter)
        q1 = projected(sol.z)
        S = schur.factor(q1, t1)
        mu = schur.solve(S, mech.vel_residual(q1, v1, t1))
        v1 = v1 - mech.solve_mass(q1, mech.GT(q1, t1, mu))
        it = sol.iterations
        counts = {"n_f_evals": 1, "n_jac_evals": it + 2, "n_newton": it,
                  "n_lin_solves": it + 2}
        return (q1, v1), newton_failure(sol.converged, S.ok), sol.residual, counts

    def observe(self, mech, carry):
        return carry


integrators.register("euler-projection", f"{__name__}:EulerProjection")
