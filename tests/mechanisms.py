"""Mechanisms the tests use that the suite does not ship.

- :func:`heavy_top`: a heavy symmetric top about a fixed point in Euler parameters (``n =
  4``, ``m = 1``), spelt with its mass matrix or with its kinetic energy (the same
  physics), with a reference in Euler angles from scipy at a tight tolerance.
- :func:`crank_rocker`: a damped, driven crank-rocker (three bars in bar angles, a
  configuration-dependent mass, rotary dampers at the four joints), no reference.
"""

from __future__ import annotations

from functools import lru_cache

import jax.numpy as jnp
import numpy as np

from problems import Reference, System, make_case
from problems.rigid_body import E_matrix, quat_mul, quaternion_mass, rotation


def _euler_quaternion(phi, theta, psi):
    """``q_z(phi) q_x(theta) q_z(psi)``: the rotation ``R_z(phi) R_x(theta) R_z(psi)``."""
    def qz(a):
        return np.array([np.cos(a / 2), 0.0, 0.0, np.sin(a / 2)])

    def qx(a):
        return np.array([np.cos(a / 2), np.sin(a / 2), 0.0, 0.0])

    return quat_mul(quat_mul(qz(phi), qx(theta)), qz(psi))


def heavy_top(spelling: str = "mass", A: float = 1.0, C: float = 0.4, mgl: float = 1.0,
              theta0: float = 0.6, spin: float = 10.0, t_end: float = 10.0):
    """A heavy symmetric top about a fixed point, in Euler parameters.

    ``q`` is the unit quaternion of the body's attitude (scalar first), ``g(q) = |q|^2 -
    1``; the inertia about the fixed point is ``J = diag(A, A, C)`` and the centre of mass
    lies on the body's symmetry axis, so ``U = mgl R_33(q) = mgl (q_0^2 - q_1^2 - q_2^2 +
    q_3^2)``. The kinetic energy ``omega^T J omega / 2`` with ``omega = 2 E(q) q'`` is
    completed by ``2 j_0 (q . q')^2`` (zero on the constraint manifold) to a positive
    definite mass, as :mod:`problems.rigid_body` does:

    - ``spelling="mass"``: ``mass = lambda q: 4 E^T J E + 4 j_0 q q^T``;
    - ``spelling="kinetic"``: ``kinetic = lambda q, v: 2 (E v)^T J (E v) + 2 j_0 (q . v)^2``.

    Released at nutation angle ``theta0`` with ``theta' = phi' = 0`` and ``psi' = spin``.

    Reference: the Lagrangian in Euler angles ``(phi, theta, psi)`` (``z-x-z``),
    ``L = A (theta'^2 + phi'^2 sin^2 theta) / 2 + C omega_3^2 / 2 - mgl cos theta`` with
    ``omega_3 = psi' + phi' cos theta`` and ``p_phi = A phi' sin^2 theta + C omega_3 cos
    theta`` conserved (Goldstein, *Classical Mechanics*, section 5.7), integrated by
    scipy's DOP853 at rtol = atol = 1e-13 from 0 to each requested time. Scored on all
    of ``(q, q')``.
    """
    if spelling not in ("mass", "kinetic"):
        raise ValueError(f"heavy_top: spelling = {spelling!r} must be 'mass' or 'kinetic'")
    J = jnp.array([A, A, C])
    j0 = (2 * A + C) / 3

    def potential(q):
        return mgl * rotation(q)[2, 2]

    if spelling == "mass":
        inertia = dict(mass=lambda q: quaternion_mass(q, J, j0))
    else:
        def kinetic(q, v):
            w = E_matrix(q) @ v
            return 2.0 * w @ (J * w) + 2.0 * j0 * (q @ v) ** 2
        inertia = dict(mass=None, kinetic=kinetic)
    system = System(n=4, m=1, potential=potential,
                    constraints=lambda q, t: jnp.array([q @ q - 1.0]), **inertia)

    omega3 = spin
    p_phi = C * omega3 * np.cos(theta0)

    def rates(theta, theta_dot):
        s, c = np.sin(theta), np.cos(theta)
        phi_dot = (p_phi - C * omega3 * c) / (A * s * s)
        return phi_dot, omega3 - phi_dot * c

    def rhs(t, x):
        theta, theta_dot = x[0], x[1]
        s, c = np.sin(theta), np.cos(theta)
        phi_dot, psi_dot = rates(theta, theta_dot)
        theta_ddot = (A * phi_dot ** 2 * s * c - C * omega3 * phi_dot * s + mgl * s) / A
        return [theta_dot, theta_ddot, phi_dot, psi_dot]

    @lru_cache(maxsize=64)
    def exact(t):
        from scipy.integrate import solve_ivp

        x = np.array([theta0, 0.0, 0.0, 0.0])
        if t > 0:
            x = solve_ivp(rhs, (0.0, t), x, method="DOP853", rtol=1e-13, atol=1e-13).y[:, -1]
        theta, theta_dot, phi, psi = x
        phi_dot, psi_dot = rates(theta, theta_dot)
        s, c = np.sin(theta), np.cos(theta)
        omega = np.array([phi_dot * s * np.sin(psi) + theta_dot * np.cos(psi),
                          phi_dot * s * np.cos(psi) - theta_dot * np.sin(psi),
                          phi_dot * c + psi_dot])
        q = _euler_quaternion(phi, theta, psi)
        return q, 0.5 * quat_mul(q, np.concatenate([[0.0], omega]))

    reference = Reference(
        kind="computed",
        source=("heavy symmetric top in Euler angles (Goldstein, section 5.7), scipy "
                "DOP853 at rtol = atol = 1e-13"),
        solution=lambda t: exact(float(t)), scored=tuple(range(8)), floor=1e-11)
    q0, v0 = exact(0.0)
    energy = 0.5 * C * omega3 ** 2 + mgl * np.cos(theta0)
    return make_case(f"heavy-top-{spelling}", system, q0, v0, (0.0, t_end),
                     dict(A=A, C=C, mgl=mgl, theta0=theta0, spin=spin, spelling=spelling),
                     energy_scale=energy, reference=reference)


def crank_rocker(l1: float = 1.0, l2: float = 3.5, l3: float = 3.0, d: float = 4.0,
                 torque: float = 40.0, damping: float = 2.0, g0: float = 9.81,
                 rate0: float = 6.0, t_end: float = 10.0):
    """A damped crank-rocker driven by a constant torque on the crank.

    Three uniform bars of unit mass in bar angles ``q = (phi_1, phi_2, phi_3)`` from the
    ground line: the crank (length ``l1``) about ``O = (0, 0)``, the coupler (``l2``) from
    the crank's tip to the rocker's, the rocker (``l3``) about ``D = (d, 0)``; the loop
    closes,

    .. math::

        g(q) = \\begin{pmatrix} l_1 \\cos\\phi_1 + l_2 \\cos\\phi_2 - l_3 \\cos\\phi_3 - d \\\\
        l_1 \\sin\\phi_1 + l_2 \\sin\\phi_2 - l_3 \\sin\\phi_3 \\end{pmatrix} = 0.

    Grashof with the crank shortest (``l1 + d <= l2 + l3``): the crank turns over, the
    rocker swings. Kinetic energy ``(l_1^2/3 + l_1^2) w_1^2/2 + l_1 l_2 \\cos(\\phi_1 -
    \\phi_2) w_1 w_2/2 + l_2^2 w_2^2/6 + l_3^2 w_3^2/6`` (the coupler's centre moves with
    the crank's tip), so ``M(q)`` depends on ``phi_1 - phi_2``; gravity ``g0`` in ``-y``
    at the bars' centres; a torque on the crank; rotary dampers of rate ``damping`` at
    the four joints (Rayleigh ``D = damping (w_1^2 + (w_2 - w_1)^2 + (w_3 - w_2)^2 +
    w_3^2) / 2``). Starts with the crank upright (``phi_1 = pi/2``), the coupler's tip
    above the ground line, the crank turning at ``rate0``.
    """
    def mass(q):
        c12 = 0.5 * l1 * l2 * jnp.cos(q[0] - q[1])
        return jnp.array([[l1 * l1 / 3 + l1 * l1, c12, 0.0],
                          [c12, l2 * l2 / 3, 0.0],
                          [0.0, 0.0, l3 * l3 / 3]])

    def potential(q):
        s = jnp.sin(q)
        return g0 * (0.5 * l1 * s[0] + l1 * s[0] + 0.5 * l2 * s[1] + 0.5 * l3 * s[2])

    joints = damping * np.array([[2.0, -1.0, 0.0], [-1.0, 2.0, -1.0], [0.0, -1.0, 2.0]])

    def forces(t, q, v):
        return jnp.array([torque, 0.0, 0.0]) - jnp.asarray(joints) @ v

    def constraints(q, t):
        return jnp.array([l1 * jnp.cos(q[0]) + l2 * jnp.cos(q[1]) - l3 * jnp.cos(q[2]) - d,
                          l1 * jnp.sin(q[0]) + l2 * jnp.sin(q[1]) - l3 * jnp.sin(q[2])])

    system = System(n=3, m=2, mass=mass, potential=potential, forces=forces,
                    constraints=constraints)
    # The closed loop at phi_1 = pi/2: the tip B of the coupler where the circles about
    # the crank's tip (radius l2) and about D (radius l3) meet, on the upper side.
    a = np.array([0.0, l1])
    dist = np.hypot(*(np.array([d, 0.0]) - a))
    along = (l2 ** 2 - l3 ** 2 + dist ** 2) / (2 * dist)
    unit = (np.array([d, 0.0]) - a) / dist
    b = a + along * unit + np.sqrt(l2 ** 2 - along ** 2) * np.array([-unit[1], unit[0]])
    q0 = np.array([np.pi / 2, np.arctan2(*(b - a)[::-1]), np.arctan2(b[1], b[0] - d)])
    G = np.array([[-l1 * np.sin(q0[0]), -l2 * np.sin(q0[1]), l3 * np.sin(q0[2])],
                  [l1 * np.cos(q0[0]), l2 * np.cos(q0[1]), -l3 * np.cos(q0[2])]])
    v0 = np.concatenate([[rate0], np.linalg.solve(G[:, 1:], -G[:, 0] * rate0)])
    return make_case("crank-rocker", system, q0, v0, (0.0, t_end),
                     dict(l1=l1, l2=l2, l3=l3, d=d, torque=torque, damping=damping, g0=g0,
                          rate0=rate0), energy_scale=0.5 * (4 * l1 * l1 / 3) * rate0 ** 2
                     + g0 * (l1 + l2 + l3))
