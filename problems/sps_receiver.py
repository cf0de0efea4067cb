"""Reduced planar model of a space solar power station's receiver during deployment.

The seed study (structure-preserving analysis of the 2-D deployment of the solar receiver
of a solar power satellite, DOI 10.6052/1672-6553-2014-032) lumps the receiver's cross
section into six outer points of mass ``M`` on a circle of radius ``R`` and six inner
points of mass ``m`` on a concentric circle of radius ``r``, neighbours joined by rigid
massless bars of length ``l`` at a fixed angular offset of ``pi/6``. The plane spins at a
constant rate ``w``; in the co-rotating frame, with the Coriolis force neglected as in the
seed, the generalised coordinates ``q = (R, r)`` obey

.. math::

    T = 3 M \\dot R^2 + 3 m \\dot r^2, \\qquad
    U = -3 w^2 (M R^2 + m r^2), \\qquad
    g(q) = R^2 + r^2 - 2 R r \\cos(\\pi/6) - l^2 = 0,

so the mass matrix is ``diag(6M, 6m)`` and the energy ``H = T + U`` is conserved. The
quadratic form in ``g`` is positive definite, so the constraint is an ellipse in the
``(R, r)`` plane and the motion stays bounded although the centrifugal potential is
unbounded below.

Seed values: ``M = 0.8``, ``m = 1``, ``w = 1``, ``R0 = 1``, ``r0 = 0.8`` (so
``l = 0.504``), released from rest; the seed integrates ``t`` in ``[0, 50]`` with a 2-stage
symplectic PRK at ``h = 0.5`` and reports ``|g| <= 2e-9``.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from problems import register
from problems.case import Case, make_case
from problems.mechanics import System

COS = float(np.cos(np.pi / 6))


def bar_length_squared(R: float, r: float) -> float:
    """``l^2`` of the bars for radii ``R`` and ``r``."""
    return R * R + r * r - 2.0 * R * r * COS


@register("sps-receiver")
def sps_receiver(M: float = 0.8, m: float = 1.0, w: float = 1.0, R0: float = 1.0,
                 r0: float = 0.8, t_end: float = 50.0) -> Case:
    """The seed's reduced receiver model, released from rest at ``(R0, r0)``."""
    if not (0 < M < np.inf and 0 < m < np.inf and np.isfinite(w)):
        raise ValueError(f"sps-receiver: masses M = {M}, m = {m} must be positive and finite, "
                         f"w = {w} finite")
    l2 = bar_length_squared(R0, r0)
    system = System(
        n=2, m=1,
        mass=np.array([6.0 * M, 6.0 * m]),
        potential=lambda q: -3.0 * w * w * (M * q[0] ** 2 + m * q[1] ** 2),
        constraints=lambda q, t: jnp.array([bar_length_squared(q[0], q[1]) - l2]),
    )
    # Energy is scaled by the size of the initial centrifugal potential.
    scale = 3.0 * w * w * (M * R0 ** 2 + m * r0 ** 2)
    return make_case("sps-receiver", system, [R0, r0], [0.0, 0.0], (0.0, t_end),
                     dict(M=M, m=m, w=w, R0=R0, r0=r0, l=float(np.sqrt(l2))),
                     energy_scale=scale)
