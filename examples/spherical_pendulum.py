"""A 3-D problem: the spherical pendulum, with a declared invariant and an exact reference.

Written against the public API only. Run it with::

    python -m benchmarks.run --load examples/spherical_pendulum.py \
        --problems spherical-pendulum --integrators rattle lobatto3ab3 --h 0.01

A point mass ``m`` on a massless rod of length ``L`` about a fixed point, gravity ``-z``:

.. math::

    m \\ddot q = -m g e_z - 2 q \\lambda, \\qquad g(q) = q \\cdot q - L^2 = 0.

Energy and the angular momentum about the vertical, ``L_z = m (x v_y - y v_x)``, are
conserved; ``L_z`` is declared as an invariant, so every run reports its error. Released
at cone angle ``alpha`` with the azimuthal rate ``Omega = sqrt(g / (L cos alpha))`` it is
the conical pendulum, whose exact motion is the circle

.. math::

    q(t) = (L \\sin\\alpha \\cos\\Omega t,\\; L \\sin\\alpha \\sin\\Omega t,\\; -L \\cos\\alpha),

the reference. ``spin`` scales the initial rate (1: the cone; otherwise the pendulum
nutates and has no closed-form reference, only its invariants).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from problems import Reference, System, make_case, register


def cone(t, L, alpha, rate):
    """Position and velocity on the circle of cone angle ``alpha`` at angular rate ``rate``."""
    rho = L * np.sin(alpha)
    q = np.array([rho * np.cos(rate * t), rho * np.sin(rate * t), -L * np.cos(alpha)])
    v = rate * np.array([-rho * np.sin(rate * t), rho * np.cos(rate * t), 0.0])
    return q, v


@register("spherical-pendulum")
def spherical_pendulum(L: float = 1.0, mass: float = 1.0, gravity: float = 9.81,
                       alpha: float = 0.8, spin: float = 1.0, t_end: float = 20.0):
    """The spherical pendulum released on the cone of angle ``alpha`` (``spin = 1``)."""
    if not (0 < L and 0 < mass and 0 < alpha < np.pi / 2):
        raise ValueError(f"spherical-pendulum: L = {L} and mass = {mass} must be positive, "
                         f"alpha = {alpha} in (0, pi/2)")
    system = System(
        n=3, m=1,
        mass=np.full(3, mass),
        potential=lambda q: mass * gravity * q[2],
        constraints=lambda q, t: jnp.array([q @ q - L ** 2]),
        invariants={"L_z": lambda q, v: mass * (q[0] * v[1] - q[1] * v[0])},
    )
    rate = np.sqrt(gravity / (L * np.cos(alpha)))
    q0, v0 = cone(0.0, L, alpha, spin * rate)
    reference = None
    if spin == 1.0:
        reference = Reference(kind="exact", source="conical pendulum, closed form",
                              solution=lambda t: cone(t, L, alpha, rate),
                              scored=tuple(range(6)))
    return make_case("spherical-pendulum", system, q0, v0, (0.0, t_end),
                     dict(L=L, mass=mass, gravity=gravity, alpha=alpha, spin=spin),
                     energy_scale=mass * gravity * L, reference=reference)
