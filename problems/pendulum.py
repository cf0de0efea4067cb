"""Planar pendulum in Cartesian coordinates (IFToMM benchmark A01).

Coordinates ``q = (x, y)`` of a point mass ``m`` on a massless link of length ``L``,
gravity ``gravity`` in ``-y``:

.. math::

    m \\ddot x = -2 x \\lambda, \\qquad m \\ddot y = -m g_0 - 2 y \\lambda, \\qquad
    g(q) = x^2 + y^2 - L^2 = 0.

Energy ``H = m |v|^2 / 2 + m g_0 y`` is conserved. The A01 set-up (IFToMM Technical
Committee for Multibody Dynamics, Library of Computational Benchmark Problems) releases the
mass at rest from ``(L, 0)`` and runs 2000 s, about 845 periods.

Reference (exact): with the angle ``theta`` from the downward vertical, ``x = L sin theta``,
``y = -L cos theta``, amplitude ``theta_0`` and ``k = sin(theta_0 / 2)``,

.. math::

    \\theta(t) = 2 \\arcsin\\big(k\\, \\mathrm{sn}(K(k) - \\omega t, k)\\big), \\qquad
    \\dot\\theta(t) = -2 k \\omega\\, \\mathrm{cn}(K(k) - \\omega t, k), \\qquad
    \\omega = \\sqrt{g_0 / L},

with ``K`` the complete elliptic integral of the first kind (the pendulum released at rest
from ``theta_0``; Lawden, *Elliptic Functions and Applications*, 1989, section 5.2).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from scipy.special import ellipj, ellipk

from problems import register
from problems.case import Case, Reference, make_case
from problems.mechanics import System


def exact_solution(t: float, L: float, gravity: float, theta0: float):
    """Position and velocity of the pendulum at time ``t`` (closed form above)."""
    k = np.sin(theta0 / 2.0)
    omega = np.sqrt(gravity / L)
    quarter = ellipk(k * k)
    # sn and cn have period 4K: reducing the argument first keeps the elliptic-function
    # evaluation at its best accuracy for t in the thousands of periods.
    u = np.fmod(quarter - omega * t, 4.0 * quarter)
    sn, cn, _, _ = ellipj(u, k * k)
    theta = 2.0 * np.arcsin(k * sn)
    theta_dot = -2.0 * k * omega * cn
    q = np.array([L * np.sin(theta), -L * np.cos(theta)])
    v = L * theta_dot * np.array([np.cos(theta), np.sin(theta)])
    return q, v


@register("pendulum")
def pendulum(L: float = 1.0, mass: float = 1.0, gravity: float = 9.81,
             theta0: float = float(np.pi / 2), t_end: float = 2000.0) -> Case:
    """IFToMM A01 pendulum; ``theta0`` is the release angle from the downward vertical."""
    if not (0 < L < np.inf and 0 < mass < np.inf and np.isfinite(gravity)):
        raise ValueError(f"pendulum: L = {L} and mass = {mass} must be positive and finite, "
                         f"gravity = {gravity} finite")
    system = System(
        n=2, m=1,
        mass=np.full(2, mass),
        potential=lambda q: mass * gravity * q[1],
        constraints=lambda q, t: jnp.array([q[0] ** 2 + q[1] ** 2 - L ** 2]),
    )
    q0, v0 = exact_solution(0.0, L, gravity, theta0)
    reference = Reference(
        kind="exact",
        source="closed form through Jacobi elliptic functions (scipy.special.ellipj)",
        solution=lambda t: exact_solution(t, L, gravity, theta0),
        scored=(0, 1),
    )
    return make_case("pendulum", system, q0, v0, (0.0, t_end),
                     dict(L=L, mass=mass, gravity=gravity, theta0=theta0),
                     energy_scale=mass * gravity * L, reference=reference)
