"""IFToMM benchmark A02: the N four-bar mechanism, which passes singular configurations.

``N + 1`` cranks hinged to the ground at ``O_i = (i, 0)``, ``i = 0..N``, and ``N`` couplers
joining the tips ``B_{i-1}`` and ``B_i`` of neighbouring cranks: ``2N + 1`` uniform rods of
length 1 m and mass 1 kg forming ``N`` parallelogram loops in a row; gravity ``g_0`` in
``-y`` (IFToMM Technical Committee for Multibody Dynamics, Library of Computational
Benchmark Problems, problem A02; González et al., *Multibody System Dynamics* 16, 2006).

Natural coordinates: the crank tips, ``q = (x_0, y_0, ..., x_N, y_N)``, ``n = 2N + 2``. A
uniform rod between points ``a`` and ``b`` has kinetic energy ``m (|a'|^2 + a'.b' +
|b'|^2) / 6``, so the mass matrix is constant: ``1/3`` on ``B_i`` for each crank (its other
end is fixed) and the block ``[[1/3, 1/6], [1/6, 1/3]]`` on ``(B_{i-1}, B_i)`` for each
coupler, times ``I_2``. Gravity acts at the rods' midpoints:

.. math::

    U = g_0 \\Big(\\sum_{i=0}^N \\tfrac12 y_i + \\sum_{i=1}^N \\tfrac12 (y_{i-1} + y_i)\\Big),
    \\qquad
    g(q) = \\begin{pmatrix} |B_i - O_i|^2 - 1 & (i = 0..N) \\\\
    |B_i - B_{i-1}|^2 - 1 & (i = 1..N) \\end{pmatrix} = 0,

``m = 2N + 1`` constraints, one degree of freedom. When the cranks are horizontal all rows
of ``G`` point along ``x``: ``G`` drops to rank ``N + 1`` and the mechanism momentarily has
``N + 1`` degrees of freedom (bifurcation to non-parallelogram branches). Energy is
conserved.

Structure: the mass is given sparse and ``M^{-1}`` is dense, so above
:data:`linalg.schur.DENSE_KKT_MAX` constraints the linear algebra is the augmented
system's banded ``L D L^T`` (:mod:`linalg.kkt`, bandwidth 7 at any ``N``) and ``M`` is
solved banded: memory and cost per step grow like ``N``, and the general size limit
applies (``python -m benchmarks.perf.four_bar`` runs ``N = 4096``). The round-off of ``g``
is about ``eps N``, since the tips sit at ``x_i = i + cos(phi)``; Newton's convergence test
counts it (that benchmark's notes).

Initial values (our choice, documented): the specification's initial angle was not
available here; the cranks start vertical (``phi_0 = pi / 2`` from the ground line, as in
the specification's sketch and an OpenSim implementation of it), where the prescribed
initial velocity of ``B_0``, 1 m/s along ``+x``, is the whole velocity of the tip: the
crank rate is ``phi' = -1 / sin(phi_0)`` for any ``phi_0``. The mechanism then turns over
the bottom, through the singular horizontal configurations twice per turn. ``t_end = 20`` s.

Reference (exact): on the parallelogram branch every crank has the same angle ``phi`` and
the couplers translate, so ``I phi'' = -K cos(phi)`` with ``I = N + (N + 1)/3`` and ``K =
g_0 (N + (N + 1)/2)``: with ``theta = phi + pi/2`` a pendulum of frequency ``omega_0 =
sqrt(K / I)``, solved by Jacobi elliptic functions (rotation: ``theta = 2 am(u, k^2)``,
``u = F(theta_0/2, k^2) + c t``; libration: ``sin(theta/2) = k sn(u, k^2)``; Lawden,
*Elliptic Functions and Applications*, 1989, chapter 5). Scored on all positions and
velocities. A method that jumps to another branch at a singular configuration leaves the
exact solution there, and the final-state error shows it.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from scipy.special import ellipj, ellipk, ellipkinc

from problems import register
from problems.case import Case, Reference, make_case
from problems.mechanics import System


def mass_matrix(N: int) -> sp.csr_matrix:
    """Constant ``(2N + 2) x (2N + 2)`` mass matrix of the cranks and couplers (sparse:
    five entries per row at most)."""
    tip = np.full(N + 1, 1.0 / 3.0)
    tip[1:] += 1.0 / 3.0
    tip[:-1] += 1.0 / 3.0
    scalar = sp.diags([np.full(N, 1.0 / 6.0), tip, np.full(N, 1.0 / 6.0)], [-1, 0, 1])
    return sp.kron(scalar, sp.identity(2), format="csr")


def elliptic_F(phi: float, m: float) -> float:
    """Incomplete elliptic integral ``F(phi | m)`` for any real ``phi`` (odd, quasi-periodic)."""
    K = ellipk(m)
    j = np.round(phi / np.pi)
    return float(ellipkinc(phi - j * np.pi, m) + 2.0 * j * K)


def branch_angle(t: float, theta0: float, rate0: float, omega0: float):
    """``theta(t), theta'(t)`` of ``theta'' = -omega0^2 sin(theta)`` (exact)."""
    energy = 0.5 * rate0 ** 2 - omega0 ** 2 * np.cos(theta0)
    if energy > omega0 ** 2:
        # Rotation: (theta/2)' = s c sqrt(1 - m sin^2(theta/2)).
        c = np.sqrt(0.5 * (energy + omega0 ** 2))
        m = 2.0 * omega0 ** 2 / (energy + omega0 ** 2)
        s = np.sign(rate0)
        K = ellipk(m)
        u = elliptic_F(0.5 * theta0, m) + s * c * t
        # am(u + 2K) = am(u) + pi: reduce to |u| <= K where ellipj is most accurate.
        j = np.round(u / (2.0 * K))
        _, _, dn, am = ellipj(u - 2.0 * j * K, m)
        return 2.0 * (am + j * np.pi), 2.0 * s * c * dn
    # Libration: sin(theta/2) = k sn(u), theta' = 2 k omega0 cn(u).
    m = (energy + omega0 ** 2) / (2.0 * omega0 ** 2)
    k = np.sqrt(m)
    am0 = np.arctan2(np.sin(0.5 * theta0) / k, rate0 / (2.0 * k * omega0))
    K = ellipk(m)
    u = elliptic_F(am0, m) + omega0 * t
    sn, cn, _, _ = ellipj(np.fmod(u, 4.0 * K), m)
    return 2.0 * np.arcsin(k * sn), 2.0 * k * omega0 * cn


def exact_solution(t: float, N: int, gravity: float, phi0: float):
    """``(q, v)`` of the parallelogram motion at time ``t``."""
    omega0 = np.sqrt(gravity * (N + (N + 1) / 2.0) / (N + (N + 1) / 3.0))
    theta, rate = branch_angle(t, phi0 + 0.5 * np.pi, -1.0 / np.sin(phi0), omega0)
    # phi = theta - pi/2: B_i = (i + cos phi, sin phi) = (i + sin theta, -cos theta).
    x = np.arange(N + 1) + np.sin(theta)
    y = np.full(N + 1, -np.cos(theta))
    vx = np.full(N + 1, rate * np.cos(theta))
    vy = np.full(N + 1, rate * np.sin(theta))
    return np.stack([x, y], axis=1).ravel(), np.stack([vx, vy], axis=1).ravel()


@register("four-bar")
def four_bar(N: int = 40, gravity: float = 9.81, phi0: float = float(np.pi / 2),
             t_end: float = 20.0) -> Case:
    """The A02 N four-bar mechanism; ``phi0`` is the initial crank angle from the ground
    line (``pi/2``: vertical), ``B_0`` moving at 1 m/s along ``+x``."""
    if N < 1:
        raise ValueError(f"four-bar: N = {N} must be at least 1")
    if not 0.0 < phi0 < np.pi:
        raise ValueError(f"four-bar: phi0 = {phi0} must lie in (0, pi) so that B_0 can "
                         "move along +x")
    pivots = jnp.stack([jnp.arange(N + 1.0), jnp.zeros(N + 1)], axis=1)

    def constraints(q, t):
        B = q.reshape(N + 1, 2)
        crank = jnp.sum((B - pivots) ** 2, axis=1) - 1.0
        coupler = jnp.sum(jnp.diff(B, axis=0) ** 2, axis=1) - 1.0
        return jnp.concatenate([crank, coupler])

    def potential(q):
        y = q[1::2]
        return gravity * (0.5 * jnp.sum(y) + 0.5 * jnp.sum(y[1:] + y[:-1]))

    system = System(n=2 * N + 2, m=2 * N + 1, mass=mass_matrix(N), potential=potential,
                    constraints=constraints)
    reference = Reference(
        kind="exact",
        source=("parallelogram branch: pendulum I phi'' = -K cos(phi) in closed form "
                "through Jacobi elliptic functions (scipy.special.ellipj)"),
        solution=lambda t: exact_solution(t, N, gravity, phi0),
        scored=tuple(range(4 * N + 4)),
    )
    q0, v0 = exact_solution(0.0, N, gravity, phi0)
    return make_case("four-bar", system, q0, v0, (0.0, t_end),
                     dict(N=N, gravity=gravity, phi0=phi0),
                     energy_scale=gravity * (N + (N + 1) / 2.0), reference=reference,
                     rank_deficient="at the horizontal configurations (rank N + 1 of 2N + 1)")
