"""Planar double pendulum in Cartesian coordinates.

Two point masses ``m_1, m_2`` at ``q = (x_1, y_1, x_2, y_2)``, the first on a massless rod of
length ``L_1`` from the fixed pivot at the origin, the second on a rod of length ``L_2`` from
the first; gravity ``g_0`` in ``-y``:

.. math::

    \\mathrm{diag}(m_1, m_1, m_2, m_2)\\, \\ddot q = -\\nabla U(q) - G(q)^T \\lambda, \\qquad
    U = g_0 (m_1 y_1 + m_2 y_2),

    g(q) = \\begin{pmatrix} x_1^2 + y_1^2 - L_1^2 \\\\
    (x_2 - x_1)^2 + (y_2 - y_1)^2 - L_2^2 \\end{pmatrix} = 0.

Energy ``H = |v|_M^2 / 2 + U`` is conserved. Two degrees of freedom, two regimes chosen by
``energy`` (released from rest at the angles ``theta_1, theta_2`` of the rods from the
downward vertical):

* ``low``: ``theta = (0.2, 0.2)`` rad, small oscillations near the linear normal modes; the
  motion is regular (quasi-periodic) and errors grow at most linearly.
* ``high``: ``theta = (3 pi/4, 3 pi/4)``, both rods 45 degrees above the horizontal; the
  motion is chaotic (``sensitive``): nearby solutions separate exponentially, so a
  reference is meaningful only over a short horizon.

Default parameters ``m_1 = m_2 = 1`` kg, ``L_1 = L_2 = 1`` m, ``g_0 = 9.81``; ``t_end = 5``.

Reference (computed, :mod:`problems.data`): the same pendulum in the two angles (minimal
coordinates, an ODE written independently of the Cartesian DAE) integrated by scipy's
DOP853 at ``rtol = 2.5e-14``; stored for the default masses and lengths in
``problems/data/double-pendulum.json`` at ``t`` = 5, 100 and 1000 (``low``) and 2.5 and 5
(``high``), with the error estimate of each entry (difference to a run at ``rtol =
1e-12``). Regenerate with ``python -m problems.data.generate double-pendulum``.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from problems import data, register
from problems.case import Case, make_case
from problems.mechanics import System

#: Release angles (rad from the downward vertical) of the two regimes.
ANGLES = {"low": (0.2, 0.2), "high": (0.75 * np.pi, 0.75 * np.pi)}


def cartesian(theta, omega, lengths):
    """Positions and velocities of the chain of point masses for rod angles ``theta``
    (from the downward vertical) and angular velocities ``omega``."""
    theta, omega, lengths = (np.asarray(x, dtype=np.float64) for x in (theta, omega, lengths))
    x = np.cumsum(lengths * np.sin(theta))
    y = -np.cumsum(lengths * np.cos(theta))
    vx = np.cumsum(lengths * np.cos(theta) * omega)
    vy = np.cumsum(lengths * np.sin(theta) * omega)
    return np.stack([x, y], axis=1).ravel(), np.stack([vx, vy], axis=1).ravel()


@register("double-pendulum")
def double_pendulum(energy: str = "low", m1: float = 1.0, m2: float = 1.0, L1: float = 1.0,
                    L2: float = 1.0, gravity: float = 9.81, t_end: float = 5.0) -> Case:
    """The double pendulum released from rest in the ``energy`` regime (``low``/``high``)."""
    if energy not in ANGLES:
        raise ValueError(f"double-pendulum: energy = {energy!r} must be one of "
                         f"{', '.join(ANGLES)}")
    if not min(m1, m2, L1, L2) > 0:
        raise ValueError(f"double-pendulum: masses and lengths must be positive, got "
                         f"m1={m1}, m2={m2}, L1={L1}, L2={L2}")
    system = System(
        n=4, m=2,
        mass=np.array([m1, m1, m2, m2]),
        potential=lambda q: gravity * (m1 * q[1] + m2 * q[3]),
        constraints=lambda q, t: jnp.array([
            q[0] ** 2 + q[1] ** 2 - L1 ** 2,
            (q[2] - q[0]) ** 2 + (q[3] - q[1]) ** 2 - L2 ** 2,
        ]),
        sensitive=energy == "high",
    )
    params = dict(energy=energy, m1=m1, m2=m2, L1=L1, L2=L2, gravity=gravity)
    q0, v0 = cartesian(ANGLES[energy], (0.0, 0.0), (L1, L2))
    return make_case("double-pendulum", system, q0, v0, (0.0, t_end), params,
                     energy_scale=gravity * ((m1 + m2) * L1 + m2 * L2),
                     reference=data.reference("double-pendulum", params))
