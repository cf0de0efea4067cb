"""N-link planar pendulum chain in Cartesian coordinates (scalable).

``N`` point masses ``m = mass / N`` at ``q = (x_1, y_1, ..., x_N, y_N)`` joined by massless
rigid links of length ``l = length / N``, the first hinged at the origin; gravity ``g_0`` in
``-y``. With ``x_0 = y_0 = 0``,

.. math::

    m\\, \\ddot q = -\\nabla U(q) - G(q)^T \\lambda, \\qquad
    U = m g_0 \\sum_k y_k, \\qquad
    g_k(q) = (x_k - x_{k-1})^2 + (y_k - y_{k-1})^2 - l^2 = 0 \\quad (k = 1, \\dots, N).

``n = 2N`` coordinates, ``N`` constraints, ``N`` degrees of freedom. Constraint ``k``
involves only masses ``k-1`` and ``k``, so ``G`` is banded (bidiagonal in 2 x 1 blocks) and
``G M^{-1} G^T`` tridiagonal; the integrators of this suite use dense linear algebra, so the
chain measures how their cost grows with ``N`` (``N = 1`` is the A01 pendulum). Energy is
conserved.

Initial values: the chain straight, every link at ``theta0`` (default ``pi / 4``) from the
downward vertical, at rest. The free end then whips: for ``N >= 2`` the motion is chaotic
(``sensitive``) and the fastest local motion grows with ``N`` (transverse waves near the
pivot have frequencies of order ``N sqrt(g_0 / length)``), so stable steps shrink like
``1 / N``. Default ``N = 8``, ``length = 1`` m, ``mass = 1`` kg, ``g_0 = 9.81``,
``t_end = 5``.

Reference (computed, :mod:`problems.data`): the same chain in the ``N`` link angles
(minimal coordinates, an ODE written independently of the Cartesian DAE; see
:func:`problems.data.generate.chain_rhs`) integrated by scipy's DOP853 at ``rtol =
2.5e-14``, stored in ``problems/data/chain.json`` for ``N`` = 2, 4 and 8 with the other
parameters at their defaults, at ``t`` = 1 and 5, with per-entry error estimates.
Regenerate with ``python -m problems.data.generate chain``. Other ``N`` have no reference.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from problems import data, register
from problems.case import Case, make_case
from problems.double_pendulum import cartesian
from problems.mechanics import System


def link_constraints(q, l):
    """``|x_k - x_{k-1}|^2 - l^2`` for every link, with ``x_0`` the pivot at the origin.

    Written on the coordinate sequences ``q[0::2]`` and ``q[1::2]``, not on the points as an
    ``(N, 2)`` array summed over its short axis: the same numbers, but XLA:CPU compiles the
    steps that use ``g`` and its derivatives faster this way at large N, which keeps the
    time per step from growing faster than N.
    """
    x = jnp.concatenate([jnp.zeros(1), q[0::2]])
    y = jnp.concatenate([jnp.zeros(1), q[1::2]])
    dx, dy = jnp.diff(x), jnp.diff(y)
    return dx * dx + dy * dy - l * l


@register("chain")
def chain(N: int = 8, length: float = 1.0, mass: float = 1.0, gravity: float = 9.81,
          theta0: float = float(np.pi / 4), t_end: float = 5.0) -> Case:
    """The N-link chain released from rest, straight at ``theta0`` from the vertical."""
    if N < 1:
        raise ValueError(f"chain: N = {N} must be at least 1")
    if not (length > 0 and mass > 0):
        raise ValueError(f"chain: length = {length} and mass = {mass} must be positive")
    l, mk = length / N, mass / N
    system = System(
        n=2 * N, m=N,
        mass=np.full(2 * N, mk),
        potential=lambda q: mk * gravity * jnp.sum(q[1::2]),
        constraints=lambda q, t: link_constraints(q, l),
        sensitive=N >= 2,
    )
    params = dict(N=N, length=length, mass=mass, gravity=gravity, theta0=theta0)
    q0, v0 = cartesian(np.full(N, theta0), np.zeros(N), np.full(N, l))
    return make_case("chain", system, q0, v0, (0.0, t_end), params,
                     energy_scale=mass * gravity * length,
                     reference=data.reference("chain", params))
