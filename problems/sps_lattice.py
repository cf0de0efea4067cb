"""The receiver in three dimensions: a lattice of ``K`` zig-zag rings stacked along the spin axis.

The seed study (structure-preserving analysis of the 2-D deployment of the solar receiver
of a solar power satellite, DOI 10.6052/1672-6553-2014-032) reduces one cross section of a
rotationally periodic receiver to two radii and notes that, with the out-of-plane
constraints added, the approach carries over to the three-dimensional structure. This
problem is that structure: ``K`` copies of the full ring of :mod:`problems.sps_ring` (``N``
inner points of mass ``m``, ``N`` outer points of mass ``M``, rigid massless bars between
neighbours) at heights ``z = 0, H, ..., (K - 1) H``, joined by rigid massless bars, every
point free in 3-D in the frame that spins at the constant rate ``w`` about ``z``.

Coordinates
-----------
Ring by ring, and within ring ``k`` in the ring order of :mod:`problems.sps_ring`
(inner point ``i`` is ring point ``2i``, outer point ``i`` is ring point ``2i + 1``)::

    q = (x_00, y_00, z_00, x_01, y_01, z_01, ..., x_(K-1)(2N-1), y_..., z_...)   (n = 6 N K)

with ``x_kj`` the position of point ``j`` of ring ``k``. Symmetric initial values put
every ring on the seed's circles (inner radius ``r0`` at angles ``2 pi i / N``, outer
radius ``R0`` at ``2 pi i / N + pi / N``), ring ``k`` at ``z = k H``, at rest.

Constraints
-----------
With ``l_j`` the length of bar ``j`` of the symmetric ring (all equal to ``l``,
``l^2 = R0^2 + r0^2 - 2 R0 r0 cos(pi / N)``) and indices ``j`` taken mod ``2N``:

.. math::

    \\text{ring bars:}\\quad & |x_{k,j+1} - x_{kj}|^2 - l_j^2 = 0,
        && k < K,\\ j < 2N \\quad (2NK), \\\\
    \\text{axial bars:}\\quad & |x_{k+1,j} - x_{kj}|^2 - H^2 = 0,
        && k < K - 1,\\ j < 2N \\quad (2N(K-1)), \\\\
    \\text{braces:}\\quad & |x_{k+1,j+1} - x_{kj}|^2 - l_j^2 - H^2 = 0,
        && k < K - 1,\\ j \\text{ odd} \\quad (N(K-1)), \\\\
    \\text{hub:}\\quad & c_0 = 0, \\qquad (c_{K-1})_{x,y} = 0 \\text{ if } K > 1
        && (3 + 2[K > 1]),

where ``c_k = sum_j m_j x_kj / sum_j m_j`` is the centre of mass of ring ``k``. The brace
joins each outer point to the next ring's inner point that follows it around the ring;
over the synchronous deployment (every ring at the same ``(R, r)``, ``z`` fixed) its
projection on the ring plane is a ring bar, so every bar keeps its length.

Hub. In the rotating frame the centrifugal potential leaves six rigid motions of the
lattice free of the bars, and the hub removes five of them: (i) translation across the
axis, whose centre of mass obeys ``X'' = w^2 X`` (Coriolis off), so round-off would fling
the lattice off the axis as in :mod:`problems.sps_ring`; (ii) tilts about ``x`` and
``y``, on which the centrifugal potential has curvature ``w^2 (sum m rho^2 / 2 - sum m
(z - Z)^2)``, negative for a stack taller than it is wide, so that a tall lattice would
fall over exponentially; (iii) translation along ``z``, neutral, which a perturbed start
would turn into a uniform drift along the axis. Holding the centres of the first and the
last ring on the axis (a shaft with a bearing at each end) and the first one at height
zero removes exactly these: (i) moves both centres, (ii) moves the last one relative to
the first, (iii) lifts the first. The rotation about ``z`` stays free: it is the motion
whose momentum is conserved. A rotation about ``z`` turns the centres' ``x, y`` rows into
combinations of themselves and leaves the height row as it is, and no row depends on
time, so the hub forces do no work and exert no torque about the axis: both invariants
below survive. For ``K = 1`` the hub is the centre-of-mass row pair of
:mod:`problems.sps_ring` followed by the height row; the tilt of a single flat ring is
stable (its curvature is ``w^2 sum m rho^2 / 2 > 0``) and is left free.

Counts (``[K > 1]`` is 1 for ``K > 1``, else 0)::

    n   = 6 N K
    m   = 2 N K + 3 N (K - 1) + 3 + 2 [K > 1]
    dof = n - m = N K + 3 N - 3 - 2 [K > 1]

and ``G`` has full row rank at generic consistent configurations (the tests check it).

Structure of ``G``. The rows come ring by ring as well: ring 0's bars and hub rows, then
for each ``k = 0 .. K - 2`` the axial bars and braces between rings ``k`` and ``k + 1``
followed by ring ``k + 1``'s bars, and last the hub rows of ring ``K - 1``. Every row
touches one ring or two adjacent ones, so ``G`` is block lower-bidiagonal along the
stack (blocks of ``6N`` columns), and within a ring the bars form a cyclic band (bar
``2N - 1`` closes the ring); the hub rows fill the first and the last ring's columns.
For ``K = 1`` the rows are those of :mod:`problems.sps_ring` with its hub, plus the
height row, and the ``x, y`` motion is that problem's.

Energy and angular momentum
---------------------------
Centrifugal potential ``U = -w^2 sum m_kj (x_kj^2 + y_kj^2) / 2`` (no force along the
axis); with ``coriolis`` the gyroscopic force ``-2 m_kj w e_z x v_kj`` is applied
(System.forces). It does no work, so the Jacobi integral ``T + U`` is conserved either
way: derived as the energy without Coriolis, declared as the invariant ``jacobi`` with
it. Potential and constraints are symmetric under rotations about ``z``, so the angular
momentum about the axis is conserved and declared as ``angular_momentum``: ``sum m (x v_y
- y v_x)``, plus the frame's ``w sum m (x^2 + y^2)`` with Coriolis (the inertial one).

Relation to the reduced model: with symmetric initial values and Coriolis off, every ring
moves as the ring of :mod:`problems.sps_ring` does, whatever ``K``: the rings' motions
keep every axial bar and brace at its length with zero force (their multipliers and the
hub's vanish), so ``z`` stays fixed and each ring's ``(R, r)`` obeys
:mod:`problems.sps_receiver` exactly for ``N = 6``, until round-off asymmetry, amplified
by the instability of that motion, becomes visible (the case is flagged ``sensitive``).

Step size. The rings' ``(R, r)`` stay on the ellipse ``R^2 + r^2 - 2 R r cos(pi / N) =
l^2``, whose axes have the ratio ``sqrt((1 + cos(pi / N)) / (1 - cos(pi / N)))``: 3.7 for
``N = 6``, 10 for ``N = 16``. With the seed's radii the rings swing round its far tip
every half period, where inner and outer radii swap and the zig-zag flips through flat;
for ``N = 16`` the bar forces there reach about 400 times their initial value for about
0.1 s, and the step has to resolve that. A perturbed start makes it harder: the
instability of the symmetric motion grows, and with ``N = 16, K = 8, perturb = 0.01``
the lattice is crumpled by ``t = 11`` (ring radii from 0.1 to 2, heights off by up to
1.3), near configurations where ``G M^{-1} G^T`` is close to singular (smallest singular
value 3e-4 of the largest at ``t = 11.22``). There RATTLE at ``h = 0.01`` has no position
step: for the step from ``t = 11.22``, the smallest ``|g(q_1(lambda))|`` over all
``lambda`` that Levenberg-Marquardt finds from five starts is 5.6e-5, not 0 (measured).
At ``h = 0.005`` RATTLE on the dense path runs to ``t = 20`` (max ``|g|`` 8e-16, energy
error bounded at 1.4 % of its scale, angular momentum to 1e-13), while the
structured path's simplified Newton stops at ``t = 12.175``.

Perturbed initial values (``perturb > 0``): positions stay symmetric and the initial
velocity is a random tangent vector (standard normal entries scaled by ``perturb``,
seeded by ``seed``, projected onto ``G v = 0`` in the mass metric), as in
:mod:`problems.sps_ring`.

Parameters: ``N = 6``, ``K = 3``, ``M = 0.8``, ``m = 1``, ``w = 1``, ``R0 = 1``, ``r0 =
0.8`` (seed values), ``H = 0.5`` (about the bar length ``l``), ``coriolis = False`` (as in
the seed), ``perturb = 0``, ``seed = 0``, ``t_end = 50``. The bar length ``l`` follows
from ``N``, ``R0`` and ``r0`` (giving it as well would over-determine the ring) and is
recorded with the parameters. No reference: the symmetric case is checked against the
reduced model instead.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from problems import register
from problems.case import Case, make_case
from problems.mechanics import System
from problems.sps_ring import ring_positions, tangent_velocity


def lattice_counts(N: int, K: int) -> tuple[int, int]:
    """Numbers of coordinates and constraints of the ``N``-point, ``K``-ring lattice."""
    return 6 * N * K, 2 * N * K + 3 * N * (K - 1) + 3 + 2 * (K > 1)


@register("sps-lattice")
def sps_lattice(N: int = 6, K: int = 3, M: float = 0.8, m: float = 1.0, w: float = 1.0,
                R0: float = 1.0, r0: float = 0.8, H: float = 0.5, coriolis: bool = False,
                perturb: float = 0.0, seed: int = 0, t_end: float = 50.0) -> Case:
    """``K`` receiver rings of ``N`` outer and ``N`` inner points, stacked along the axis."""
    if N < 2:
        raise ValueError(f"sps-lattice: N = {N} must be at least 2")
    if K < 1:
        raise ValueError(f"sps-lattice: K = {K} must be at least 1")
    if not (0 < M < np.inf and 0 < m < np.inf):
        raise ValueError(f"sps-lattice: masses M = {M}, m = {m} must be positive and finite")
    if not (0 < R0 < np.inf and 0 < r0 < np.inf):
        raise ValueError(f"sps-lattice: radii R0 = {R0}, r0 = {r0} must be positive and finite")
    if not 0 < H < np.inf:
        raise ValueError(f"sps-lattice: ring spacing H = {H} must be positive and finite")
    if not np.isfinite(w):
        raise ValueError(f"sps-lattice: spin rate w = {w} must be finite")
    if not 0 <= perturb < np.inf:
        raise ValueError(f"sps-lattice: perturb = {perturb} must be >= 0 and finite")
    ring = ring_positions(N, R0, r0)
    lengths2 = np.sum((np.roll(ring, -1, axis=0) - ring) ** 2, axis=1)
    braces2 = lengths2[1::2] + H * H
    point_mass = np.where(np.arange(2 * N) % 2 == 0, m, M)
    pm = jnp.asarray(point_mass)
    ring_mass = float(np.sum(point_mass))
    n, n_constraints = lattice_counts(N, K)

    def constraints(q, t):
        x = q.reshape(K, 2 * N, 3)
        bars = jnp.sum((jnp.roll(x, -1, axis=1) - x) ** 2, axis=2) - lengths2
        first = [bars[0], pm @ x[0] / ring_mass]
        if K == 1:
            return jnp.concatenate(first)
        axial = jnp.sum((x[1:] - x[:-1]) ** 2, axis=2) - H * H
        # Outer point j (odd) of ring k to point j + 1 of ring k + 1.
        braces = jnp.sum((jnp.roll(x[1:], -1, axis=1)[:, 1::2] - x[:-1, 1::2]) ** 2,
                         axis=2) - braces2
        links = jnp.concatenate([axial, braces, bars[1:]], axis=1).ravel()
        return jnp.concatenate([*first, links, pm @ x[-1, :, :2] / ring_mass])

    def potential(q):
        x = q.reshape(K, 2 * N, 3)
        return -0.5 * w * w * jnp.sum(pm * jnp.sum(x[..., :2] ** 2, axis=2))

    def coriolis_force(t, q, v):
        u = v.reshape(K, 2 * N, 3)
        f = 2.0 * w * pm[:, None] * jnp.stack([u[..., 1], -u[..., 0], jnp.zeros_like(u[..., 2])],
                                              axis=2)
        return f.ravel()

    masses = np.tile(np.repeat(point_mass, 3), K)

    def kinetic(v):
        return 0.5 * jnp.sum(jnp.asarray(masses) * v * v)

    def angular_momentum(q, v):
        x, u = q.reshape(K, 2 * N, 3), v.reshape(K, 2 * N, 3)
        spin = jnp.sum(pm * (x[..., 0] * u[..., 1] - x[..., 1] * u[..., 0]))
        frame = w * jnp.sum(pm * jnp.sum(x[..., :2] ** 2, axis=2)) if coriolis else 0.0
        return spin + frame

    invariants = {"angular_momentum": angular_momentum}
    if coriolis:
        invariants["jacobi"] = lambda q, v: kinetic(v) + potential(q)
    system = System(n=n, m=n_constraints, mass=masses, potential=potential,
                    constraints=constraints, forces=coriolis_force if coriolis else None,
                    invariants=invariants, sensitive=True)
    heights = H * np.arange(K, dtype=np.float64)
    q0 = np.concatenate([np.broadcast_to(ring, (K, 2 * N, 2)),
                         np.broadcast_to(heights[:, None, None], (K, 2 * N, 1))],
                        axis=2).ravel()
    v0 = np.zeros(n)
    if perturb > 0:
        G = np.asarray(system.mech.G(jnp.asarray(q0), jnp.asarray(0.0)))
        noise = np.random.default_rng(seed).standard_normal(n)
        v0 = perturb * tangent_velocity(G, masses, noise)
    params = dict(N=N, K=K, M=M, m=m, w=w, R0=R0, r0=r0, H=H, coriolis=coriolis,
                  perturb=perturb, seed=seed, l=float(np.sqrt(lengths2[0])))
    # Energy scale: the initial centrifugal potential, K times the ring's.
    scale = 0.5 * K * N * w * w * (M * R0 ** 2 + m * r0 ** 2)
    return make_case("sps-lattice", system, q0, v0, (0.0, t_end), params, energy_scale=scale)
