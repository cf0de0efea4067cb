"""Full planar model of the space solar power station's receiver ring (no symmetry reduction).

The seed study (structure-preserving analysis of the 2-D deployment of the solar receiver
of a solar power satellite, DOI 10.6052/1672-6553-2014-032; reduced form in
:mod:`problems.sps_receiver`) lumps the receiver's cross section into outer points of mass
``M`` and inner points of mass ``m``, joined by rigid massless bars in a zig-zag ring
``A-1-B-2-...-F-6-A``: inner point ``k`` is joined to outer points ``k`` and ``k - 1``.
Here the ring has ``N`` outer and ``N`` inner points, every one free in the plane that
spins at the constant rate ``w``. Coordinates, in the co-rotating frame, in ring order::

    q = (x_I0, y_I0, x_O0, y_O0, x_I1, y_I1, ..., x_O(N-1), y_O(N-1))   (n = 4N)

(inner point ``k`` at angle ``2 pi k / N``, outer point ``k`` at ``2 pi k / N + pi / N``
when symmetric). Bar ``j`` joins ring points ``j`` and ``j + 1 (mod 2N)``, and with
``hub`` (the default) the ring's centre of mass is held on the spin axis:

.. math::

    g_j(q) = |x_{j+1} - x_j|^2 - l_j^2 = 0, \\quad j = 0, \\dots, 2N - 1, \\qquad
    \\sum_i m_i x_i / \\sum_i m_i = 0,

``2N`` bar constraints (a cyclic band: ``G`` is block-bidiagonal plus one corner block)
and two hub rows, ``2N - 2`` degrees of freedom. The hub is a modelling choice the seed
does not need (its reduction fixes the centre): without it, the centre of mass of the ring
obeys ``X'' = w^2 X`` in the rotating frame when Coriolis is off, and round-off in its
initial value (1e-17) grows like ``e^{w t}`` to 1e4 by ``t = 50``, so the ring flies off
the axis. The seed's structure spins about its centre, which the hub expresses.
In the rotating frame every point feels the centrifugal force, written
as the potential ``U = -w^2 sum_i m_i |x_i|^2 / 2``, and, when ``coriolis`` is set, the
gyroscopic Coriolis force ``-2 m_i w e_z x v_i`` as an applied velocity-dependent force
(System.forces). The Coriolis force does no work, so ``T + U`` (the Jacobi integral) is
conserved either way: without Coriolis the suite derives it as the energy; with Coriolis
(applied forces switch the energy metric off) it is declared as the invariant ``jacobi``.
The angular momentum about the spin axis is conserved too (rotational symmetry of ``U``
and of the constraints), declared as ``angular_momentum``: ``sum m_i x_i x v_i`` without
Coriolis, and the inertial one, ``sum m_i (x_i x v_i + w |x_i|^2)``, with it.

Sensitivity: the symmetric motion is unstable. An asymmetric deformation of the ring
grows about as ``e^{0.7 t}`` (seed parameters; with or without Coriolis, with or without
the hub), so round-off alone breaks the symmetry visibly within 50 s: the case is flagged
``sensitive``.

Relation to the reduced model: with ``N = 6``, the seed's parameters, symmetric initial
values (every point on its ray, at rest) and Coriolis off, the motion keeps the dihedral
symmetry, every point moves along its ray, and ``(R, r)`` obeys :mod:`problems.sps_receiver`
exactly: ``T = N (M R'^2 + m r'^2) / 2 = 3 M R'^2 + 3 m r'^2``, ``U = -3 w^2 (M R^2 + m
r^2)``, and all ``2N`` bar constraints reduce to the one ``R^2 + r^2 - 2 R r cos(pi/6) =
l^2`` (their multipliers are each ``1/(2N)`` of the reduced one). The tests check it, to
1e-12, over the time before the round-off asymmetry, amplified by the instability above,
reaches that level (about ``t = 10``).

Perturbed initial values (``perturb > 0``): positions stay symmetric and the initial
velocity is a random tangent vector (standard normal entries scaled by ``perturb``, seeded
by ``seed``, projected onto ``G v = 0`` in the mass metric), which breaks the symmetry: a
scalable, non-symmetric problem.

Parameters: ``N = 6``, ``M = 0.8``, ``m = 1``, ``w = 1``, ``R0 = 1``, ``r0 = 0.8``
(seed values), ``coriolis = False`` (as in the seed), ``hub = True``, ``perturb = 0``,
``seed = 0``, ``t_end = 50``. No reference: the symmetric case is checked against the reduced model
instead.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from problems import register
from problems.case import Case, make_case
from problems.mechanics import System


def ring_positions(N: int, R: float, r: float) -> np.ndarray:
    """Symmetric ring: ``(2N, 2)`` points, inner and outer alternating."""
    angles = np.pi * np.arange(2 * N) / N
    radii = np.where(np.arange(2 * N) % 2 == 0, r, R)
    return np.stack([radii * np.cos(angles), radii * np.sin(angles)], axis=1)


def tangent_velocity(G: np.ndarray, masses: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Mass-orthogonal projection of ``v`` onto the null space of ``G``."""
    MinvGT = G.T / masses[:, None]
    return v - MinvGT @ np.linalg.solve(G @ MinvGT, G @ v)


@register("sps-ring")
def sps_ring(N: int = 6, M: float = 0.8, m: float = 1.0, w: float = 1.0, R0: float = 1.0,
             r0: float = 0.8, coriolis: bool = False, hub: bool = True, perturb: float = 0.0,
             seed: int = 0, t_end: float = 50.0) -> Case:
    """The full receiver ring of ``N`` outer and ``N`` inner points."""
    if N < 2:
        raise ValueError(f"sps-ring: N = {N} must be at least 2")
    if not (M > 0 and m > 0):
        raise ValueError(f"sps-ring: masses M = {M}, m = {m} must be positive")
    if perturb < 0:
        raise ValueError(f"sps-ring: perturb = {perturb} must be >= 0")
    points0 = ring_positions(N, R0, r0)
    lengths2 = np.sum((np.roll(points0, -1, axis=0) - points0) ** 2, axis=1)
    point_mass = np.where(np.arange(2 * N) % 2 == 0, m, M)
    masses = np.repeat(point_mass, 2)
    pm = jnp.asarray(point_mass)
    total_mass = float(np.sum(point_mass))

    # On the coordinate sequences q[0::2], q[1::2] rather than on (2N, 2) arrays of points,
    # as the chain's constraints are (problems.chain.link_constraints says why).
    def constraints(q, t):
        x, y = q[0::2], q[1::2]
        dx, dy = jnp.roll(x, -1) - x, jnp.roll(y, -1) - y
        bars = dx * dx + dy * dy - lengths2
        if not hub:
            return bars
        return jnp.concatenate([bars, jnp.stack([pm @ x, pm @ y]) / total_mass])

    def potential(q):
        x, y = q[0::2], q[1::2]
        return -0.5 * w * w * jnp.sum(pm * (x * x + y * y))

    def coriolis_force(t, q, v):
        u = v.reshape(2 * N, 2)
        return (2.0 * w * pm[:, None] * jnp.stack([u[:, 1], -u[:, 0]], axis=1)).ravel()

    def kinetic(v):
        return 0.5 * jnp.sum(jnp.asarray(masses) * v * v)

    def angular_momentum(q, v):
        x, y, vx, vy = q[0::2], q[1::2], v[0::2], v[1::2]
        spin = jnp.sum(pm * (x * vy - y * vx))
        frame = w * jnp.sum(pm * (x * x + y * y)) if coriolis else 0.0
        return spin + frame

    invariants = {"angular_momentum": angular_momentum}
    if coriolis:
        invariants["jacobi"] = lambda q, v: kinetic(v) + potential(q)
    system = System(n=4 * N, m=2 * N + 2 * hub, mass=masses, potential=potential,
                    constraints=constraints,
                    forces=coriolis_force if coriolis else None,
                    invariants=invariants, sensitive=True)
    q0 = points0.ravel()
    v0 = np.zeros(4 * N)
    if perturb > 0:
        G = np.asarray(system.mech.G(jnp.asarray(q0), jnp.asarray(0.0)))
        noise = np.random.default_rng(seed).standard_normal(4 * N)
        v0 = perturb * tangent_velocity(G, masses, noise)
    params = dict(N=N, M=M, m=m, w=w, R0=R0, r0=r0, coriolis=coriolis, hub=hub, perturb=perturb,
                  seed=seed, l=float(np.sqrt(lengths2[0])))
    # Energy scale: the initial centrifugal potential (as for the reduced model).
    scale = 0.5 * N * w * w * (M * R0 ** 2 + m * r0 ** 2)
    return make_case("sps-ring", system, q0, v0, (0.0, t_end), params, energy_scale=scale)
