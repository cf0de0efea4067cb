"""A rheonomic test case with a closed-form solution, for the tests of the integrators.

A bead of unit mass slides without friction on a straight rod through the origin that is
driven to turn at the constant rate ``omega`` in the plane; no other forces. With the rod
angle ``omega t`` the constraint is

.. math::

    g(q, t) = -x \\sin(\\omega t) + y \\cos(\\omega t) = 0,

which depends on ``t`` (``g_t`` and ``g_tt`` are non-zero). Along the rod the distance
``r`` obeys ``r'' = omega^2 r``; released at ``r = 1`` with no radial speed,
``r(t) = cosh(omega t)``. The driving torque does work, so energy is not conserved.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from problems import Reference, System, make_case


def spinning_rod(omega: float = 1.0, t_end: float = 3.0):
    """The case, with its exact solution as the reference."""

    def exact(t):
        r, r_dot = np.cosh(omega * t), omega * np.sinh(omega * t)
        c, s = np.cos(omega * t), np.sin(omega * t)
        q = np.array([r * c, r * s])
        v = np.array([r_dot * c - r * omega * s, r_dot * s + r * omega * c])
        return q, v

    system = System(
        n=2, m=1, mass=np.ones(2), rheonomic=True,
        constraints=lambda q, t: jnp.array([-q[0] * jnp.sin(omega * t)
                                            + q[1] * jnp.cos(omega * t)]),
    )
    reference = Reference("exact", "r = cosh(omega t) along the rod", exact, scored=(0, 1))
    q0, v0 = exact(0.0)
    return make_case("spinning-rod", system, q0, v0, (0.0, t_end), {"omega": omega},
                     energy_scale=1.0, reference=reference)
