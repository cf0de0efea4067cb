"""Car axis (IVP Test Set problem ``caraxis``): a rheonomic index-3 system.

A simple model of a car axis on a bumpy road (Mazzia and Magherini, *Test Set for IVP Solvers*, problem ``caraxis``, as distributed in the R package
deTestSet, ``src/Ex_car.f`` and ``R/ex_caraxis.R``). Coordinates ``q = (x_l, y_l, x_r,
y_r)``: the left and right wheel, each of mass ``k = M eps^2 / 2``, joined by an axis of
fixed length ``L``; each wheel hangs from the car body on a spring of unit stiffness and rest
length ``L_0``. The left spring is anchored at the origin, the right one at the road point
``(x_b(t), y_b(t))`` with ``y_b = r sin(w t)``, ``x_b = sqrt(L^2 - y_b^2)``, and the left
wheel is kept on the line through the origin perpendicular to that point:

.. math::

    k \\ddot q = -\\nabla U(q) + f(t, q) - G(q, t)^T \\lambda, \\qquad
    g(q, t) = \\begin{pmatrix} x_b(t) x_l + y_b(t) y_l \\\\
    (x_l - x_r)^2 + (y_l - y_r)^2 - L^2 \\end{pmatrix} = 0,

with ``U = (l_l - L_0)^2 / 2 + k g_0 (y_l + y_r)`` (left spring, ``l_l = |(x_l, y_l)|``, and
gravity ``g_0``) and the time-dependent right spring force ``f = -(l_r - L_0) (q_r -
b(t)) / l_r`` on the right wheel, ``l_r = |q_r - b(t)|``. Written through the System
interface: constant mass ``k I_4``, ``potential`` for ``U``, ``forces`` for the right spring
(it moves with the road, so it has no time-independent potential) and the rheonomic ``g``.
The total energy is not conserved (the road does work): the case tracks accuracy and drift.

Sign of the multipliers: the Test Set writes the constraint force as ``+G^T lambda``, this
suite as ``-G^T lambda``, so ``lambda_ours = -lambda_testset``.

Parameters (Test Set): ``eps = 1e-2``, ``M = 10``, ``L = 1``, ``L_0 = 1/2``, ``r = 0.1``,
``w = 10``, ``g_0 = 1``. Initial values (consistent, ``lambda(0) = 0``): ``q = (0, L_0, L,
L_0)``, ``qdot = (-L_0/L, 0, -L_0/L, 0)``; ``t_end = 3``.

Reference (published, version B of the Test Set's two): the 21-digit solution at ``t = 3``
of deTestSet ``R/ex_reference.R`` (quadruple-precision GAMD run), on all eight positions and
velocities; the two multipliers are in :data:`REF_LAMBDA` (already in our sign convention)
for the tests, which compare them with the index-1 multipliers of the final state. Version
A's multipliers are off by about 1e-10 and are not used.

Accuracy of the reference (:data:`REF_FLOOR`): version B's final state differs by 4.8e-12
(in ``y6``, the left wheel's vertical velocity; by at most 5e-13 elsewhere) from two
independent solutions in this suite that agree with each other to 1.1e-13:
``lobatto3ab4`` at ``h`` = 5e-4, 2.5e-4 and 1.25e-4 (4.85e-12, 4.84e-12, 4.74e-12) and
``baumgarte-dopri8`` at ``rtol`` = 1e-13, ``atol`` = 1e-15 (4.80e-12). The reference is
therefore itself off by about 5e-12, and errors at or below that say only that a run is
at least as accurate as it.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from problems import register
from problems.case import Case, Reference, make_case
from problems.mechanics import System

T_END = 3.0

#: Version B of the Test Set reference at t = 3: y1..y8 (positions, velocities).
REF_Y = (0.493455784275402809122e-1, 0.496989460230171153861, 0.104174252488542151681e1,
         0.373911027265361256927, -0.770583684040972357970e-1, 0.744686658723778553466e-2,
         0.175568157537232222276e-1, 0.770341043779251976443)
#: Bound on version B's own max-norm error in positions and velocities: the 4.8e-12 found
#: against two independent solutions (module docstring), plus their 1.1e-13 disagreement,
#: rounded up.
REF_FLOOR = 6e-12
#: Version B multipliers y9, y10, sign-flipped into this suite's convention.
REF_LAMBDA = (0.473688659084893324729e-2, 0.110468033125734368808e-2)


def road(t, r, w, L):
    """Road point ``(x_b(t), y_b(t))`` that anchors the right spring."""
    yb = r * jnp.sin(w * t)
    return jnp.sqrt(L * L - yb * yb), yb


def published(t: float):
    """Version B reference at ``t = 3``."""
    y = np.array(REF_Y)
    return y[:4], y[4:]


@register("car-axis")
def car_axis(eps: float = 1e-2, M: float = 10.0, L: float = 1.0, L0: float = 0.5,
             r: float = 0.1, w: float = 10.0, gravity: float = 1.0,
             t_end: float = T_END) -> Case:
    """The Test Set car axis; the reference exists only for the default parameters."""
    if eps <= 0 or M <= 0 or L <= 0:
        raise ValueError(f"car-axis: eps = {eps}, M = {M}, L = {L} must be positive")
    k = M * eps * eps / 2.0

    def potential(q):
        ll = jnp.sqrt(q[0] ** 2 + q[1] ** 2)
        return 0.5 * (ll - L0) ** 2 + k * gravity * (q[1] + q[3])

    def forces(t, q, v):
        xb, yb = road(t, r, w, L)
        dx, dy = q[2] - xb, q[3] - yb
        lr = jnp.sqrt(dx * dx + dy * dy)
        scale = (L0 - lr) / lr
        return jnp.array([0.0, 0.0, scale * dx, scale * dy])

    def constraints(q, t):
        xb, yb = road(t, r, w, L)
        return jnp.array([xb * q[0] + yb * q[1],
                          (q[0] - q[2]) ** 2 + (q[1] - q[3]) ** 2 - L * L])

    system = System(n=4, m=2, mass=np.full(4, k), potential=potential, forces=forces,
                    constraints=constraints, rheonomic=True)
    params = dict(eps=eps, M=M, L=L, L0=L0, r=r, w=w, gravity=gravity)
    default = params == dict(eps=1e-2, M=10.0, L=1.0, L0=0.5, r=0.1, w=10.0, gravity=1.0)
    reference = Reference(
        kind="published",
        source=("Test Set for IVP Solvers (Mazzia and Magherini), problem caraxis, version B "
                "(deTestSet R/ex_reference.R, GAMD in quadruple precision), 21 digits; "
                "scored on all positions and velocities; itself off by about 5e-12 in the "
                "velocities, found against two independent solutions (problems/car_axis.py)"),
        solution=published,
        scored=tuple(range(8)),
        times=(T_END,),
        floor=REF_FLOOR,
        span=(0.0, T_END),
    ) if default else None
    q0 = [0.0, L0, L, L0]
    v0 = [-L0 / L, 0.0, -L0 / L, 0.0]
    # Energy scale (only for reporting: energy is not conserved) from the spring energy of
    # a wheel displaced by the axis length.
    return make_case("car-axis", system, q0, v0, (0.0, t_end), params,
                     energy_scale=0.5 * L * L, reference=reference)
