"""Free asymmetric rigid body in unit-quaternion coordinates (torque-free Euler top).

Coordinates: the unit quaternion ``q = (q_0, q_1, q_2, q_3)`` (scalar first) of the
rotation ``R(q)`` from body to space axes; body angular velocity ``omega = 2 E(q) q'`` with

.. math::

    E(q) = \\begin{pmatrix} -q_1 & q_0 & q_3 & -q_2 \\\\ -q_2 & -q_3 & q_0 & q_1 \\\\
    -q_3 & q_2 & -q_1 & q_0 \\end{pmatrix},

the vector part of ``2 q^* q'``. Principal inertia ``J = diag(J_1, J_2, J_3)``. The
kinetic energy ``omega^T J omega / 2 = q'^T (4 E^T J E) q' / 2`` gives a 4 x 4 matrix of
rank 3 (``E q = 0``), so the mass matrix used here is

.. math::

    M(q) = 4 E(q)^T J E(q) + 4 j_0\\, q q^T, \\qquad j_0 = (J_1 + J_2 + J_3) / 3,

positive definite for ``q != 0`` (for ``|q| = 1`` the rows of ``(q^T; E)`` are orthonormal
and ``M`` has eigenvalues ``4 j_0, 4 J_1, 4 J_2, 4 J_3``). The added term is harmless on the
constraint manifold: ``q . q' = 0`` there, so it adds nothing to the kinetic energy, and
its contribution to the equations of motion lies along ``q``, the constraint normal, where
the multiplier absorbs it. Holonomic constraint ``g(q) = q . q - 1 = 0``; no potential and
no applied forces, so the energy ``H = q'^T M q' / 2`` (the kinetic energy on the manifold)
is conserved, and the spatial angular momentum ``L = R(q) J omega`` is declared as the
three invariants ``L_x, L_y, L_z``.

Initial values: ``omega(0) = (w1, 0, w3)`` in body axes, with space axes chosen so that
``L`` points along ``+z``. Defaults ``J = (1, 2, 3)``, ``w1 = w3 = 1`` (rotation about
the axis of largest inertia, ``L^2 > 2 E J_2``, elliptic modulus ``k^2 = 1/3``),
``t_end = 20`` (about three periods of ``omega``).

Reference (exact up to one quadrature): Jacobi's solution (Landau and Lifshitz,
*Mechanics*, 3rd ed., 1976, section 37). With ``2E = omega^T J omega``, ``L = |J omega|``,

.. math::

    \\omega_1 = A_1 \\mathrm{cn}\\,\\tau, \\quad \\omega_2 = A_2 \\mathrm{sn}\\,\\tau, \\quad
    \\omega_3 = A_3 \\mathrm{dn}\\,\\tau, \\quad \\tau = \\lambda t,

``A_1^2 = (2EJ_3 - L^2) / (J_1 (J_3 - J_1))``, ``A_2^2 = (2EJ_3 - L^2) / (J_2 (J_3 -
J_2))``, ``A_3^2 = (L^2 - 2EJ_1) / (J_3 (J_3 - J_1))``, ``lambda^2 = (J_3 - J_2)(L^2 -
2EJ_1) / (J_1 J_2 J_3)``, ``k^2 = (J_2 - J_1)(2EJ_3 - L^2) / ((J_3 - J_2)(L^2 - 2EJ_1))``.
The attitude ``R = R_z(phi) R_x(theta) R_z(psi)`` has ``cos(theta) = J_3 omega_3 / L``,
``tan(psi) = J_1 omega_1 / (J_2 omega_2)`` and ``phi' = L (J_1 omega_1^2 + J_2
omega_2^2) / (J_1^2 omega_1^2 + J_2^2 omega_2^2)``; ``phi`` is the one quadrature (periodic
integrand, integrated over one period once and over the remainder at each ``t`` by
adaptive Gauss-Kronrod to 1e-13). The quaternion ``q_z(phi) q_x(theta) q_z(psi)`` is made
continuous in ``t`` by taking ``psi`` continuous through the amplitude ``am(tau)``. Scored
on all components of ``(q, q')``.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from scipy.special import ellipj, ellipk

from problems import register
from problems.case import Case, Reference, make_case
from problems.mechanics import System


def E_matrix(q):
    """``E(q)`` with ``omega_body = 2 E(q) q'``."""
    q0, q1, q2, q3 = q
    return jnp.array([[-q1, q0, q3, -q2], [-q2, -q3, q0, q1], [-q3, q2, -q1, q0]])


def rotation(q):
    """Rotation matrix ``R(q)`` (body to space) of a unit quaternion."""
    q0, q1, q2, q3 = q
    return jnp.array([
        [q0 * q0 + q1 * q1 - q2 * q2 - q3 * q3, 2 * (q1 * q2 - q0 * q3), 2 * (q1 * q3 + q0 * q2)],
        [2 * (q1 * q2 + q0 * q3), q0 * q0 - q1 * q1 + q2 * q2 - q3 * q3, 2 * (q2 * q3 - q0 * q1)],
        [2 * (q1 * q3 - q0 * q2), 2 * (q2 * q3 + q0 * q1), q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3],
    ])


def quaternion_mass(e, J, j0):
    """The 4 x 4 mass ``4 E(e)^T diag(J) E(e) + 4 j0 e e^T`` of a body in Euler parameters
    (module notes; ``J`` the principal inertia, ``j0`` their mean)."""
    Ee = E_matrix(e)
    return 4.0 * Ee.T @ (J[:, None] * Ee) + 4.0 * j0 * jnp.outer(e, e)


def quat_mul(a, b):
    """Quaternion product ``a b`` (scalar first), numpy."""
    a0, av, b0, bv = a[0], np.asarray(a[1:]), b[0], np.asarray(b[1:])
    return np.concatenate([[a0 * b0 - av @ bv], a0 * bv + b0 * av + np.cross(av, bv)])


class EulerTop:
    """Jacobi's closed-form solution of the torque-free asymmetric top (see module doc)."""

    def __init__(self, J, w1: float, w3: float):
        J1, J2, J3 = self.J = tuple(float(x) for x in J)
        w = np.array([w1, 0.0, w3])
        self.twoE = float(np.sum(np.array(self.J) * w * w))
        self.L = float(np.linalg.norm(np.array(self.J) * w))
        L2, twoE = self.L ** 2, self.twoE
        self.A1 = np.sqrt((twoE * J3 - L2) / (J1 * (J3 - J1)))
        self.A2 = np.sqrt((twoE * J3 - L2) / (J2 * (J3 - J2)))
        self.A3 = np.sqrt((L2 - twoE * J1) / (J3 * (J3 - J1)))
        self.rate = np.sqrt((J3 - J2) * (L2 - twoE * J1) / (J1 * J2 * J3))
        self.m = (J2 - J1) * (twoE * J3 - L2) / ((J3 - J2) * (L2 - twoE * J1))
        self.K = ellipk(self.m)
        # omega_1^2 and omega_2^2 have period 2K in tau, and so has phi'.
        self.period = 2.0 * self.K / self.rate
        self.phi_period = self._phi_integral(0.0, self.period)

    def omega(self, t: float) -> np.ndarray:
        sn, cn, dn, _ = ellipj(self.rate * t, self.m)
        return np.array([self.A1 * cn, self.A2 * sn, self.A3 * dn])

    def _phi_rate(self, t: float) -> float:
        J1, J2, _ = self.J
        w1, w2, _ = self.omega(t)
        return self.L * (J1 * w1 * w1 + J2 * w2 * w2) / (J1 * J1 * w1 * w1 + J2 * J2 * w2 * w2)

    def _phi_integral(self, a: float, b: float) -> float:
        # Imported here: scipy.integrate is slow to import, which every process that
        # imports the problems (the command line, each worker) would pay for nothing.
        from scipy.integrate import quad

        value, _ = quad(self._phi_rate, a, b, epsabs=1e-13, epsrel=1e-13, limit=200)
        return value

    def angles(self, t: float) -> tuple[float, float, float]:
        """Euler angles ``(phi, theta, psi)``, continuous in ``t``."""
        J1, J2, J3 = self.J
        turns = np.floor(t / self.period)
        phi = turns * self.phi_period + self._phi_integral(0.0, t - turns * self.period)
        tau = self.rate * t
        # am(tau + 2jK) = am(tau) + j pi, so psi is continued through whole half-turns.
        j = np.round(tau / (2.0 * self.K))
        sn, cn, dn, am = ellipj(tau - 2.0 * j * self.K, self.m)
        chi = np.arctan2(J2 * self.A2 * np.sin(am), J1 * self.A1 * np.cos(am)) + j * np.pi
        theta = np.arccos(J3 * self.A3 * dn / self.L)
        return phi, theta, 0.5 * np.pi - chi

    def state(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Quaternion ``q`` and its rate ``q' = q (0, omega) / 2`` at time ``t``."""
        phi, theta, psi = self.angles(t)
        qz = lambda a: np.array([np.cos(a / 2), 0.0, 0.0, np.sin(a / 2)])  # noqa: E731
        qx = lambda a: np.array([np.cos(a / 2), np.sin(a / 2), 0.0, 0.0])  # noqa: E731
        q = quat_mul(quat_mul(qz(phi), qx(theta)), qz(psi))
        v = 0.5 * quat_mul(q, np.concatenate([[0.0], self.omega(t)]))
        return q, v


@register("rigid-body")
def rigid_body(J1: float = 1.0, J2: float = 2.0, J3: float = 3.0, w1: float = 1.0,
               w3: float = 1.0, t_end: float = 20.0) -> Case:
    """Torque-free asymmetric top, ``omega(0) = (w1, 0, w3)``, ``J1 < J2 < J3``."""
    if not 0 < J1 < J2 < J3:
        raise ValueError(f"rigid-body: need 0 < J1 < J2 < J3, got {J1}, {J2}, {J3}")
    if not (w1 > 0 and w3 > 0):
        raise ValueError(f"rigid-body: w1 = {w1} and w3 = {w3} must be positive")
    w = np.array([w1, 0.0, w3])
    J = np.array([J1, J2, J3])
    if not np.sum((J * w) ** 2) > J2 * np.sum(J * w * w):
        raise ValueError("rigid-body: the closed form used here needs L^2 > 2 E J2 "
                         f"(rotation about the J3 axis); omega(0) = {w.tolist()} gives "
                         "the other regime")
    Jd = jnp.asarray(J)
    j0 = float(np.mean(J))

    def mass(q):
        return quaternion_mass(q, Jd, j0)

    def momentum_component(i):
        return lambda q, v: (rotation(q) @ (Jd * (2.0 * E_matrix(q) @ v)))[i]

    system = System(
        n=4, m=1, mass=mass,
        constraints=lambda q, t: jnp.array([q @ q - 1.0]),
        invariants={f"L_{axis}": momentum_component(i) for i, axis in enumerate("xyz")},
    )
    top = EulerTop(J, w1, w3)
    reference = Reference(
        kind="exact",
        source=("Jacobi's solution of the Euler top (Landau and Lifshitz, Mechanics, "
                "section 37) through scipy.special.ellipj, precession angle by adaptive "
                "quadrature to 1e-13"),
        solution=top.state,
        scored=tuple(range(8)),
    )
    q0, v0 = top.state(0.0)
    return make_case("rigid-body", system, q0, v0, (0.0, t_end),
                     dict(J1=J1, J2=J2, J3=J3, w1=w1, w3=w3),
                     energy_scale=0.5 * top.twoE, reference=reference)
