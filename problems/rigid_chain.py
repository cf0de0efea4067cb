"""Spatial chain of ``N`` rigid bodies on spherical joints, in Euler parameters (scalable).

``N`` identical rigid bodies of mass ``m_b`` and principal inertia ``J = diag(J_1, J_2,
J_3)`` about the centre of mass hang under gravity ``g_0`` (along ``-z``) from a fixed
point at the origin. Each body carries two joint points on its body ``z`` axis, the upper
one at ``s^+ = (0, 0, l)`` and the lower one at ``s^- = (0, 0, -l)`` from its centre of
mass. The upper point of body 1 is held at the origin by a spherical joint, and the lower
point of body ``k`` is joined to the upper point of body ``k + 1`` by a spherical joint.

Coordinates
-----------
Body by body, the centre of mass ``x_k`` (3) and the unit quaternion (Euler parameters)
``e_k = (e_0, e_1, e_2, e_3)`` (4, scalar first) of the rotation ``R(e_k)`` from body to
space axes::

    q = (x_1, e_1, x_2, e_2, ..., x_N, e_N)      (n = 7N)

The body angular velocity is ``omega_k = 2 E(e_k) e_k'`` with ``E`` the 3 x 4 matrix of
:mod:`problems.rigid_body` (the same convention: Nikravesh, *Computer-Aided Analysis of
Mechanical Systems*, Prentice-Hall, 1988, where the kinetic energy of a body in Euler
parameters is written as a quadratic form with the matrix ``4 E^T J E``).

Mass
----
Block diagonal and configuration dependent, one 7 x 7 block per body:

.. math::

    M_k(e_k) = \\begin{pmatrix} m_b I_3 & 0 \\\\ 0 & 4 E(e_k)^T J E(e_k) + 4 j_0\\,
    e_k e_k^T \\end{pmatrix}, \\qquad j_0 = (J_1 + J_2 + J_3) / 3,

the same quaternion block as :mod:`problems.rigid_body`'s: ``4 E^T J E`` has
rank 3 (``E e = 0``), and the added ``4 j_0 e e^T`` makes it positive definite without
changing the motion on the manifold (``e . e' = 0`` there, and its force lies along the
normal of the unit-norm constraint, where the multiplier absorbs it).

Constraints
-----------
With ``R_k = R(e_k)``, ``u_k = x_k + R_k s^+`` (upper point), ``w_k = x_k + R_k s^-``
(lower point) and ``w_0 = 0`` (the fixed point):

.. math::

    \\text{unit norm:}\\quad & e_k \\cdot e_k - 1 = 0, && k = 1, \\dots, N \\quad (N), \\\\
    \\text{spherical joints:}\\quad & u_k - w_{k-1} = 0, && k = 1, \\dots, N \\quad (3N),

``m = 4N`` constraints, ordered body by body (the norm row of body ``k``, then the three
rows of its upper joint), so that the rows of body ``k`` involve only bodies ``k - 1`` and
``k``: ``G`` is block bidiagonal. ``3N`` degrees of freedom.

Forces and invariants
---------------------
Gravity only, ``U = m_b g_0 sum_k z_k``. The energy is conserved (derived by the suite).
The system is invariant under rotations about the vertical through the fixed point
(``x_k -> R_z x_k``, ``e_k -> q_z e_k``), so the angular momentum about that vertical,

.. math::

    L_z = \\sum_k \\left[ m_b (x_k \\times x_k')_z + (R(e_k) J \\omega_k)_z \\right],

is conserved too and is declared as the invariant ``L_z``. It is the momentum map
``p^T xi(q)`` of that linear symmetry for any ``v`` (the ``j_0`` term contributes
``4 j_0 (e . e') (e . xi_e) = 0`` because ``xi_e = (0, e_z) e / 2`` is orthogonal to
``e``), which symplectic constrained methods such as RATTLE keep to round-off.

Initial values
--------------
Body ``k`` (``k = 1, ..., N``) has the attitude ``q_z(phi_k) q_x(theta0) q_z(psi_k)``
(z-x-z Euler angles: its long axis tilted by ``theta0`` from the vertical towards the
azimuth ``phi_k = 0.9 (k - 1)``, turned about itself by ``psi_k = 0.4 (k - 1)``), so the
chain starts as a crooked helix. Positions follow down the chain from the fixed point
(``x_1 = -R_1 s^+``, ``x_{k+1} = w_k - R_{k+1} s^+``). Each body turns at the space angular
velocity ``Omega_k = precession e_z + spin R_k e_z`` (a swirl about the vertical and a
spin about its own long axis), and the velocities follow the same way (``x_1' = Omega_1
x (x_1 - 0)``, ``x_{k+1}' = w_k' + Omega_{k+1} x (x_{k+1} - w_k)``, ``e_k' = (0,
Omega_k) e_k / 2``), so both levels of every constraint hold to round-off for any ``N``.
``L_z != 0`` and the motion is fully three-dimensional.

Defaults: ``N = 4``, ``m_b = 1`` kg, ``l = 0.5`` m, ``J = (0.09, 0.11, 0.04)`` kg m^2 (close
to a uniform box of edges 0.6 x 0.3 x 1 m, whose inertia is ``(0.091, 0.113, 0.0375)``),
``g_0 = 9.81``, ``theta0 = 0.6`` rad, ``precession = 1`` rad/s, ``spin = 4`` rad/s,
``t_end = 10``. ``energy_scale = m_b g_0 l N^2 + T(0)``: the depth of the gravity well of
the chain hanging straight down, ``sum_k m_b g_0 (2k - 1) l``, plus the initial kinetic
energy (so that it stays positive without gravity).

Sensitivity and reference
-------------------------
``N = 1`` is a heavy asymmetric top about a fixed point on a principal axis (neither
Lagrange's nor Kovalevskaya's integrable case), which is not integrable in general; the
chain only adds degrees of freedom. Measured from the default start (RATTLE, ``h =
0.005``, ``theta0`` perturbed by 1e-9): for ``N = 1`` and ``2`` the two solutions stay
within 1e-7 of each other up to ``t = 100`` (regular motion there), while for ``N = 3, 4,
8`` the separation grows exponentially, to 1e-2 by ``t = 40``, 4e-2 by ``t = 30`` and
order one by ``t = 16``. The case is flagged ``sensitive`` for ``N >= 3`` (other starts may
be chaotic for smaller ``N`` too). There is no reference solution (as for
:mod:`problems.sps_ring`): runs are scored on constraint drift, energy and ``L_z``. The
physics is checked instead (``tests/test_problem_rigid_chain.py``): for ``N = 1`` the
accelerations of the index-1 solve agree with Euler's equations of the heavy top about the
fixed point, ``J_O omega' + omega x J_O omega = d x R^T (-m_b g_0 e_z)`` with ``d = (0, 0,
-l)`` and the shifted inertia ``J_O = J + m_b (l^2 I - d d^T)`` (Landau and Lifshitz,
*Mechanics*, 3rd ed., 1976, sections 32 and 36); for ``N = 2, 3`` they agree with an
independent Newton-Euler formulation in space axes with the joint reactions as unknowns.

The mass is given through the kinetic energy (``System.kinetic``),

.. math::

    T(q, v) = \\sum_k \\tfrac12 m_b |x_k'|^2 + \\tfrac12 e_k'^T \\big(4 E(e_k)^T J E(e_k) +
    4 j_0 e_k e_k^T\\big) e_k',

body by body. It is evaluated as ``m_b |x_k'|^2 / 2 + 2 (E e_k')^T J (E e_k') + 2 j_0 (e_k .
e_k')^2``, the same form without the 4 x 4 block: the suite differentiates ``T`` at every
evaluation of ``H_q``, and through the block that costs several times as much per body.
``M`` is never formed: its block-diagonal pattern is traced
from ``T``, its blocks are factorised one by one and the structured linear algebra runs on
``G L^{-T}`` (:mod:`linalg.blocks`), with cost linear in ``N``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from problems import register
from problems.case import Case, make_case
from problems.mechanics import System
from problems.rigid_body import E_matrix, quat_mul, rotation

#: Azimuth and self-rotation increments (rad per body) of the initial helix.
PHI_STEP, PSI_STEP = 0.9, 0.4


def joint_points(x, e, l):
    """Upper and lower joint points ``x + R(e) (0, 0, +-l)`` of every body (``(N, 3)`` each)."""
    axis = jax.vmap(rotation)(e)[:, :, 2]
    return x + l * axis, x - l * axis


def initial_state(N: int, l: float, theta0: float, precession: float, spin: float):
    """Consistent ``(q0, v0)`` of the module doc: a crooked helix, swirling and spinning."""
    half = lambda a: (np.cos(a / 2), np.sin(a / 2))  # noqa: E731
    e = np.empty((N, 4))
    for k in range(N):
        cz, sz = half(PHI_STEP * k)
        cx, sx = half(theta0)
        cp, sp = half(PSI_STEP * k)
        e[k] = quat_mul(quat_mul([cz, 0.0, 0.0, sz], [cx, sx, 0.0, 0.0]), [cp, 0.0, 0.0, sp])
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    R = np.asarray(jax.vmap(rotation)(jnp.asarray(e)))
    omega = precession * np.array([0.0, 0.0, 1.0]) + spin * R[:, :, 2]
    x, xd, ed = np.empty((N, 3)), np.empty((N, 3)), np.empty((N, 4))
    w, wd = np.zeros(3), np.zeros(3)  # the fixed point, then each lower joint point
    for k in range(N):
        x[k] = w - l * R[k, :, 2]
        xd[k] = wd + np.cross(omega[k], x[k] - w)
        ed[k] = 0.5 * quat_mul(np.concatenate([[0.0], omega[k]]), e[k])
        w = x[k] - l * R[k, :, 2]
        wd = xd[k] + np.cross(omega[k], w - x[k])
    q0 = np.concatenate([x, e], axis=1).ravel()
    v0 = np.concatenate([xd, ed], axis=1).ravel()
    return q0, v0


@register("rigid-chain")
def rigid_chain(N: int = 4, mass: float = 1.0, half_length: float = 0.5, J1: float = 0.09,
                J2: float = 0.11, J3: float = 0.04, gravity: float = 9.81,
                theta0: float = 0.6, precession: float = 1.0, spin: float = 4.0,
                t_end: float = 10.0) -> Case:
    """The chain of ``N`` rigid bodies, started as a tilted, swirling, spinning helix."""
    if N < 1:
        raise ValueError(f"rigid-chain: N = {N} must be at least 1")
    if not (mass > 0 and half_length > 0 and gravity >= 0):
        raise ValueError(f"rigid-chain: mass = {mass} and half_length = {half_length} must "
                         f"be positive and gravity = {gravity} non-negative")
    J = np.array([J1, J2, J3], dtype=np.float64)
    if not (np.all(J > 0) and np.all(2.0 * J <= J.sum())):
        raise ValueError(f"rigid-chain: J = {J.tolist()} is not the inertia of a body (need "
                         "positive moments, each at most the sum of the other two)")
    n, l, m_b = 7 * N, float(half_length), float(mass)
    Jd, j0 = jnp.asarray(J), float(J.mean())

    def kinetic(q, v):
        e, xd, ed = q.reshape(N, 7)[:, 3:], v.reshape(N, 7)[:, :3], v.reshape(N, 7)[:, 3:]
        half_omega = jnp.einsum("kij,kj->ki", jax.vmap(E_matrix)(e), ed)
        along = jnp.sum(e * ed, axis=1)
        return (0.5 * m_b * jnp.sum(xd * xd) + 2.0 * jnp.sum(Jd * half_omega * half_omega)
                + 2.0 * j0 * jnp.sum(along * along))

    def constraints(q, t):
        b = q.reshape(N, 7)
        e = b[:, 3:]
        upper, lower = joint_points(b[:, :3], e, l)
        above = jnp.concatenate([jnp.zeros((1, 3)), lower[:-1]])
        norm = jnp.sum(e * e, axis=1) - 1.0
        return jnp.concatenate([norm[:, None], upper - above], axis=1).ravel()

    def potential(q):
        return m_b * gravity * jnp.sum(q.reshape(N, 7)[:, 2])

    def angular_momentum_z(q, v):
        b, bd = q.reshape(N, 7), v.reshape(N, 7)
        x, e, xd, ed = b[:, :3], b[:, 3:], bd[:, :3], bd[:, 3:]
        orbital = m_b * jnp.sum(x[:, 0] * xd[:, 1] - x[:, 1] * xd[:, 0])
        omega = 2.0 * jnp.einsum("kij,kj->ki", jax.vmap(E_matrix)(e), ed)
        own = jnp.einsum("kj,kj->", jax.vmap(rotation)(e)[:, 2, :], Jd * omega)
        return orbital + own

    system = System(
        n=n, m=4 * N, mass=None, constraints=constraints, potential=potential,
        invariants={"L_z": angular_momentum_z}, sensitive=N >= 3, kinetic=kinetic,
    )
    q0, v0 = initial_state(N, l, theta0, precession, spin)
    energy_scale = m_b * gravity * l * N * N + float(kinetic(jnp.asarray(q0), jnp.asarray(v0)))
    if not energy_scale > 0:
        raise ValueError("rigid-chain: without gravity the chain must move (precession or "
                         "spin non-zero), or its energy has no scale")
    params = dict(N=N, mass=mass, half_length=half_length, J1=J1, J2=J2, J3=J3,
                  gravity=gravity, theta0=theta0, precession=precession, spin=spin)
    return make_case("rigid-chain", system, q0, v0, (0.0, t_end), params,
                     energy_scale=energy_scale)
