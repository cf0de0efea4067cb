"""IFToMM benchmark A04: Bricard's mechanism, an over-constrained spatial linkage.

Five rods (1 kg, 1 m, square cross-section of side ``a = 0.1`` m) and the ground form a
closed chain of six revolute joints at the points ``P_0 .. P_5``; gravity ``g_0`` in
``-y``; 10 s (IFToMM Technical Committee for Multibody Dynamics, Library of Computational
Benchmark Problems, problem A04; González et al., *Multibody System Dynamics* 16, 2006).
Grübler's count gives zero degrees of freedom, but the joint axes are arranged so that the
linkage moves with one (Bricard, 1897).

Geometry (initial configuration, the edges of a unit cube): ``P_0 = (0,0,0)``, ``P_1 =
(1,0,0)``, ``P_2 = (1,-1,0)``, ``P_3 = (1,-1,1)``, ``P_4 = (0,-1,1)``, ``P_5 = (0,0,1)``; rod
``k`` runs from ``P_k`` to ``P_{k+1}`` and the ground from ``P_5`` to ``P_0``. The joint
axis ``u_k`` at ``P_k`` is perpendicular to both rods meeting there: ``u_0 = e_y``, ``u_1 =
e_z``, ``u_2 = e_x``, ``u_3 = e_y``, ``u_4 = e_z``, ``u_5 = e_x`` (``P_0, P_5, u_0, u_5``
fixed). This is the specification's configuration as reconstructed from an OpenSim
implementation of A04; the mechanism starts there at rest.

Natural coordinates (García de Jalón): every rod ``k`` is the rigid body spanned by its two
points and the unit axes of its two joints, which are mutually orthogonal, and a revolute
joint is a shared point with a shared unit axis. ``q = (P_1, P_2, P_3, P_4, u_1, u_2, u_3,
u_4)``, ``n = 24``. With ``d_k = P_{k+1} - P_k`` the constraints are, for each rod ``k =
0..4``,

.. math::

    |d_k|^2 - 1 = 0, \\quad d_k \\cdot u_k = 0, \\quad d_k \\cdot u_{k+1} = 0, \\quad
    u_k \\cdot u_{k+1} = 0,

and ``|u_k|^2 - 1 = 0`` for ``k = 1..4``: ``m = 24`` equations, of which one is redundant
everywhere (``G`` has rank 23), leaving one degree of freedom. A material point of rod
``k`` is ``(1 - xi) P_k + xi P_{k+1} + eta u_k + zeta u_{k+1}``, so the mass matrix is
constant: per rod ``m [[1/3, 1/6], [1/6, 1/3]]`` on ``(P_k, P_{k+1})`` and ``m a^2 / 12``
on each of ``u_k, u_{k+1}`` (the cross-section's second moment), times ``I_3``. Gravity
acts at the midpoints: ``U = m g_0 sum_k (y(P_k) + y(P_{k+1})) / 2``. Energy is conserved.

Rank deficiency, per integrator family (what this suite does with it):

* RATTLE and Lobatto IIIA-IIIB: the Newton and projection matrices are singular; the
  shared linear solve (:func:`integrators.newton.solve`) detects the round-off pivot of
  the equilibrated LU and switches to a rank-revealing solve (QR with column pivoting),
  so these methods run and hold ``g = 0`` to the Newton tolerance.
* Baumgarte-stabilised RK: :meth:`Mechanics.accelerations` detects the singular Schur
  complement ``G M^{-1} G^T`` and takes its minimum-norm least-squares solution. Off the
  constraint manifold the redundancy is only approximate and the multipliers of the
  nearly dependent direction feed the drift: RK4 blows up at ``h = 0.005`` and above and
  needs ``h = 0.001``.
* IDA: SUNDIALS' dense LU would factorise the singular iteration matrix without notice
  and return meaningless states, so the IDA integrator checks the rank of ``G(q0)`` and
  fails with a message that names the rank deficiency.

Reference (computed, :mod:`problems.data`): the index-1 ODE of this System (accelerations
with minimum-norm multipliers) integrated by scipy's DOP853 at ``rtol = 2.5e-14``, the
states projected back onto the constraints, stored in ``problems/data/bricard.json`` at
``t`` = 1, 5 and 10 with error estimates; regenerate with ``python -m problems.data.generate
bricard``.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from problems import data, register
from problems.case import Case, make_case
from problems.mechanics import System

#: Initial joint points P_0..P_5 and joint axes u_0..u_5 (P_0, P_5, u_0, u_5 are fixed).
POINTS = np.array([[0, 0, 0], [1, 0, 0], [1, -1, 0], [1, -1, 1], [0, -1, 1], [0, 0, 1]],
                  dtype=np.float64)
AXES = np.array([[0, 1, 0], [0, 0, 1], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 0, 0]],
                dtype=np.float64)


def unpack(q):
    """All six points and six axes, fixed ones included, from ``q``."""
    free = q.reshape(8, 3)
    points = jnp.concatenate([jnp.asarray(POINTS[:1]), free[:4], jnp.asarray(POINTS[5:])])
    axes = jnp.concatenate([jnp.asarray(AXES[:1]), free[4:], jnp.asarray(AXES[5:])])
    return points, axes


def constraints(q, t=None):
    """The 24 rigid-body and joint constraints (23 independent)."""
    P, u = unpack(q)
    d = P[1:] - P[:-1]
    per_rod = jnp.stack([
        jnp.sum(d * d, axis=1) - 1.0,
        jnp.sum(d * u[:-1], axis=1),
        jnp.sum(d * u[1:], axis=1),
        jnp.sum(u[:-1] * u[1:], axis=1),
    ], axis=1).ravel()
    return jnp.concatenate([per_rod, jnp.sum(u[1:5] ** 2, axis=1) - 1.0])


def mass_matrix(rod_mass: float, section: float) -> np.ndarray:
    """Constant 24 x 24 mass matrix in natural coordinates."""
    # Scalar mass matrix over the 12 entities (P_0..P_5, u_0..u_5), then the free ones.
    S = np.zeros((12, 12))
    for k in range(5):
        p, r = k, k + 1
        S[np.ix_([p, r], [p, r])] += rod_mass * np.array([[1 / 3, 1 / 6], [1 / 6, 1 / 3]])
        S[6 + p, 6 + p] += rod_mass * section ** 2 / 12.0
        S[6 + r, 6 + r] += rod_mass * section ** 2 / 12.0
    free = [1, 2, 3, 4, 7, 8, 9, 10]
    return np.kron(S[np.ix_(free, free)], np.eye(3))


@register("bricard")
def bricard(rod_mass: float = 1.0, section: float = 0.1, gravity: float = 9.81,
            t_end: float = 10.0) -> Case:
    """Bricard's mechanism released from rest in the cube configuration."""
    if not (rod_mass > 0 and section > 0):
        raise ValueError(f"bricard: rod_mass = {rod_mass} and section = {section} must be "
                         "positive (the axes' inertia comes from the cross-section)")

    def potential(q):
        P, _ = unpack(q)
        return rod_mass * gravity * 0.5 * jnp.sum(P[1:, 1] + P[:-1, 1])

    system = System(n=24, m=24, mass=mass_matrix(rod_mass, section), potential=potential,
                    constraints=constraints)
    q0 = np.concatenate([POINTS[1:5].ravel(), AXES[1:5].ravel()])
    params = dict(rod_mass=rod_mass, section=section, gravity=gravity)
    return make_case("bricard", system, q0, np.zeros(24), (0.0, t_end), params,
                     energy_scale=5.0 * rod_mass * gravity,
                     reference=data.reference("bricard", params),
                     rank_deficient="everywhere: G has rank 23 of 24 (one redundant "
                                    "constraint)")
