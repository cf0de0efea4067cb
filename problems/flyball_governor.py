"""IFToMM benchmark A05: the stiff flyball governor, its shaft driven at a constant rate.

A vertical shaft (along ``+z``, gravity ``g_0`` along ``-z``) carries at its top two rods
hinged on horizontal axes, each with a point mass at its far end, and a slider that moves
along the shaft and turns with it. The coupler rods of Watt's governor are replaced by two
stiff spring-dampers, from the midpoint of each rod to the slider: the benchmark's stiff
problem (IFToMM Technical Committee for Multibody Dynamics, Library of Computational
Benchmark Problems, problem A05 "Stiff flyball governor"; González et al., *Multibody
System Dynamics* 16, 2006). Its output is the slider's coordinate ``s(t)`` over 10 s.

Parameters (the specification's table, SI units): shaft and rods prismatic bars of ``1.0 x
0.01 x 0.01`` m, slider a cube of side 0.1 m, density 3000 kg/m^3 (so 0.3 kg bars and a
3 kg slider), two point masses of 5 kg, springs of stiffness ``K = 8e5`` N/m, damping ``C =
4e4`` N s/m and rest length 0.5 m; initially ``s = 0.5`` m, ``alpha = 30`` degrees, and the
shaft turns at ``omega = 2 pi`` rad/s.

Reading of the specification
----------------------------
The table and a sketch are all the public description gives (the specification as
transcribed with the OpenSim implementation of the library, RehabEngGroup's
MBSbenchmarksInOpenSim, ``benchmarks/A05_FlyballGovernor``; the geometry below is that of
its ``createModel.cpp`` and of Exudyn's ``stiffFlyballGovernorKT.py``, which agree):

* the shaft stands on the ground pivot at the origin and ends at height ``h = 1`` m; the
  rods hinge at its top, at ``A, B = (+-a, 0, h)`` in the shaft's frame with ``a = 0.05``
  m, half the slider's side, on axes perpendicular to the plane of shaft and rods;
* ``alpha`` is each rod's angle below the horizontal and ``s`` the height of the slider's
  centre above the shaft's lower end;
* each spring joins the midpoint of a rod to the centre of the slider's face on that side,
  ``(+-a, 0, s)``. Hinge, rod midpoint and attachment then form an equilateral triangle
  of side 0.5 m at ``s = 0.5``, ``alpha = 30`` degrees: the springs start at their rest
  length, which is what the parameters suggest;
* the table's rate ``2 pi`` rad/s is held by a drive (a rheonomic constraint on the shaft
  angle, ``phi = omega t``), the whole mechanism starting in rigid rotation at that rate.
  (The OpenSim implementation's model sets only that initial rate; with the drive the rate
  stays the table's throughout, and the drive's work enters the energy balance.)

Coordinates
-----------
Relative (joint) coordinates and one accumulator::

    q = (phi, s, theta_1, theta_2, w)

the shaft angle, the slider height, the rods' angles below the horizontal and the
coordinate ``w`` of the dissipated work (below). With the coupler rods replaced by springs
the governor is a tree, so joint coordinates are a minimal set: the only constraint is the
drive,

.. math::

    g(q, t) = \\phi - \\omega t = 0,

whose multiplier is (minus) the drive torque. The stiffness is in the force elements, not
in the constraints, which is what the benchmark tests; Cartesian or natural coordinates
would add only joint constraints to it. The kinetic energy of shaft, slider, bars (as
rigid prismatic bodies) and point masses is diagonal in these rates,

.. math::

    T = \\tfrac12 J_\\phi(\\theta_1, \\theta_2) \\dot\\phi^2 + \\tfrac12 m_c \\dot s^2
    + \\tfrac12 J_\\theta (\\dot\\theta_1^2 + \\dot\\theta_2^2),

with the moment of inertia about the shaft axis (:func:`spin_inertia`)

.. math::

    J_\\phi = J_0 + \\sum_i \\big[m_r (a + \\tfrac L2 \\cos\\theta_i)^2 + I_a \\sin^2\\theta_i
    + I_t \\cos^2\\theta_i + m_p (a + L \\cos\\theta_i)^2\\big],

``J_0`` the shaft's and slider's own, ``I_a = m_r b^2 / 6`` and ``I_t = m_r (L^2 + b^2) /
12`` a bar's moments about its axis and across it, and ``J_theta = m_r L^2 / 3 + m_r b^2 /
12 + m_p L^2`` a rod's moment about its hinge. The mass matrix is diagonal and depends on
the rod angles (its Coriolis and centrifugal forces come from autodiff); the potential is
gravity plus the springs, ``U = g_0 (m_c s + sum_i (m_r (h - L/2 sin theta_i) + m_p (h -
L sin theta_i))) + K sum_i (l_i - l_0)^2 / 2`` with the spring lengths ``l_i(s, theta_i)``
(:func:`spring_lengths`); the dampers give ``f = -C sum_i l_i' grad l_i``.

Energy balance
--------------
No function of the mechanism's state alone is conserved: the drive feeds work in and the
dampers take it out. The balance

.. math::

    T + U + W_d - W_\\omega - E_0 = 0

is declared as the invariant ``energy_balance``, both works written as state quantities:

* the drive's work. Gravity is parallel to the axis, the pivot's reactions pass through it
  and the springs are internal, so the drive torque alone changes the angular momentum
  about the axis, ``L_z = J_phi phi' = p_phi``: ``tau = L_z'``, and at the constant rate
  ``W_omega = int tau omega dt = omega (L_z - L_z(0))``, exactly;
* the dissipated work ``W_d = int C sum_i l_i'^2 dt`` is a history integral. The
  coordinate ``w`` carries it: a free unit mass driven by the force ``C sum_i l_i'^2``,
  so that its rate is ``w' = W_d``. Nothing else depends on ``w``; it adds one
  unconstrained, non-stiff equation to the system (and to every method's work and error
  control), in exchange for a balance every run measures.

So ``energy_balance(q, v) = T_m + U - omega L_z + w'``, with ``T_m`` the mechanism's kinetic
energy (without the accumulator's), is constant along exact solutions; its error is the
balance's. The case has no derived energy (it is driven and damped).

Stiffness
---------
The dampers are far above critical: linearised along the motion (the reference, at 401
points), the fastest eigenvalue of the index-1 ODE is real, between ``-4.4e2`` and
``-8.1e3`` 1/s, largest where ``s`` is near its initial 0.5 (there the slider, 3 kg, pushed
by two dampers inclined 30 degrees to the horizontal, alone gives ``2 C sin^2(30 deg) / m_c
= 6.7e3``; the rods' coupling adds the rest). The slow
eigenvalues are ``-K / C = -20`` 1/s and the mechanism's nearly undamped swing, ``+-4.65i``
(a period of 1.35 s). An explicit method must keep ``h |lambda|`` inside its stability
region: classical RK4 (``h |lambda| <= 2.785`` on the real axis) needs ``h <= 3.4e-4`` s
(``baumgarte-rk4`` runs at ``h`` = 3.3e-4 and turns non-finite at 3.6e-4).

Reference (computed, :mod:`problems.data`): the Lagrange equations in the three free
coordinates ``(s, theta_1, theta_2)`` with ``phi = omega t`` substituted, written out by
hand (:func:`problems.data.generate.governor_rhs`, not through this System), integrated by
scipy's DOP853 at ``rtol = atol = 2.5e-14`` (the stored states) and, independently, by
scipy's Radau at 1e-12; the difference of ``s`` between the two is the stored error
estimate (1.2e-13 at ``t`` = 10; 5.3e-13 over the whole state). Stored in
``problems/data/flyball-governor.json`` at ``t`` = 1, 5 and 10 s; scored on ``s`` only, the
benchmark's output (``s(10) = 0.8372762700890``).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from problems import data, register
from problems.case import Case, Perturbation, make_case
from problems.mechanics import System

#: Indices of the coordinates in ``q``.
PHI, S, THETA1, THETA2, WORK = range(5)

#: The specification's parameters (SI units; ``alpha`` in degrees).
PARAMS = dict(length=1.0, side=0.01, slider=0.1, density=3000.0, point_mass=5.0,
              stiffness=8e5, damping=4e4, rest_length=0.5, s0=0.5, alpha=30.0,
              omega=float(2.0 * np.pi), gravity=9.81)


def inertias(p: dict) -> dict:
    """Masses and moments of the bodies, from the dimensions and density of ``p``."""
    L, b, d, rho = p["length"], p["side"], p["slider"], p["density"]
    m_bar = rho * L * b * b
    m_slider = rho * d ** 3
    return dict(
        m_rod=m_bar, m_slider=m_slider,
        axial=m_bar * b * b / 6.0,                   # a bar about its own axis
        transverse=m_bar * (L * L + b * b) / 12.0,   # a bar across, through its centre
        # Shaft and slider about the shaft axis: constant parts of J_phi.
        J0=m_bar * b * b / 6.0 + m_slider * d * d / 6.0,
        # A rod and its point mass about the hinge.
        J_theta=m_bar * L * L / 3.0 + m_bar * b * b / 12.0 + p["point_mass"] * L * L,
    )


def spin_inertia(theta, p: dict):
    """``J_phi``: the moment of inertia about the shaft axis at rod angles ``theta``."""
    I = inertias(p)
    L, a = p["length"], p["slider"] / 2.0
    c, s = jnp.cos(theta), jnp.sin(theta)
    per_rod = (I["m_rod"] * (a + 0.5 * L * c) ** 2 + I["axial"] * s * s
               + I["transverse"] * c * c + p["point_mass"] * (a + L * c) ** 2)
    return I["J0"] + jnp.sum(per_rod)


def spring_lengths(q, p: dict):
    """Lengths of the two springs, rod midpoint to the slider face at ``(+-a, 0, s)``."""
    L, a, h = p["length"], p["slider"] / 2.0, p["length"]
    theta = q[THETA1:THETA2 + 1]
    # Hinge and attachment are both at distance a from the axis: the horizontal offset is
    # the rod's alone.
    dx = 0.5 * L * jnp.cos(theta)
    dz = h - 0.5 * L * jnp.sin(theta) - q[S]
    return jnp.sqrt(dx * dx + dz * dz)


@register("flyball-governor")
def flyball_governor(length: float = PARAMS["length"], side: float = PARAMS["side"],
                     slider: float = PARAMS["slider"], density: float = PARAMS["density"],
                     point_mass: float = PARAMS["point_mass"],
                     stiffness: float = PARAMS["stiffness"],
                     damping: float = PARAMS["damping"],
                     rest_length: float = PARAMS["rest_length"], s0: float = PARAMS["s0"],
                     alpha: float = PARAMS["alpha"], omega: float = PARAMS["omega"],
                     gravity: float = PARAMS["gravity"], t_end: float = 10.0) -> Case:
    """The A05 governor from rigid rotation at ``omega``, rods ``alpha`` degrees below the
    horizontal and the slider at ``s0``; the reference exists for the default parameters."""
    if not all(x > 0 for x in (length, side, slider, density, point_mass)):
        raise ValueError(f"flyball-governor: length = {length}, side = {side}, slider = "
                         f"{slider}, density = {density} and point_mass = {point_mass} "
                         "must be positive")
    if not (stiffness >= 0 and damping >= 0 and rest_length > 0):
        raise ValueError(f"flyball-governor: stiffness = {stiffness} and damping = "
                         f"{damping} must be non-negative, rest_length = {rest_length} "
                         "positive")
    p = dict(length=length, side=side, slider=slider, density=density,
             point_mass=point_mass, stiffness=stiffness, damping=damping,
             rest_length=rest_length, s0=s0, alpha=alpha, omega=omega, gravity=gravity)
    I = inertias(p)
    h = length
    lengths_jac = jax.jacfwd(lambda q: spring_lengths(q, p))

    def mass_matrix(q):
        theta = q[THETA1:THETA2 + 1]
        return jnp.diag(jnp.stack([spin_inertia(theta, p), jnp.asarray(I["m_slider"]),
                                   jnp.asarray(I["J_theta"]), jnp.asarray(I["J_theta"]),
                                   jnp.asarray(1.0)]))

    def potential(q):
        sin = jnp.sin(q[THETA1:THETA2 + 1])
        drop = jnp.sum(I["m_rod"] * (h - 0.5 * length * sin) + point_mass * (h - length * sin))
        stretch = spring_lengths(q, p) - rest_length
        return gravity * (I["m_slider"] * q[S] + drop) + 0.5 * stiffness * stretch @ stretch

    def forces(t, q, v):
        J = lengths_jac(q)
        rate = J @ v
        # The dampers (the lengths do not depend on w), and the accumulator pushed by the
        # power they dissipate.
        return (-damping * (J.T @ rate)).at[WORK].set(damping * (rate @ rate))

    def constraints(q, t):
        return jnp.array([q[PHI] - omega * t])

    def energy_balance(q, v):
        Mv = mass_matrix(q) @ v
        mechanism = 0.5 * (v @ Mv - v[WORK] ** 2)
        return mechanism + potential(q) - omega * Mv[PHI] + v[WORK]

    system = System(n=5, m=1, mass=mass_matrix, potential=potential, forces=forces,
                    constraints=constraints, rheonomic=True,
                    invariants={"energy_balance": energy_balance})
    q0 = np.array([0.0, s0, np.radians(alpha), np.radians(alpha), 0.0])
    v0 = np.array([omega, 0.0, 0.0, 0.0, 0.0])
    reference = data.reference("flyball-governor", p)
    if reference is not None:
        reference = dataclasses.replace(reference, scored=(S,))
    # Energy scale: the kinetic energy of the initial rigid rotation (169 J by default).
    spin = 0.5 * float(spin_inertia(jnp.asarray(q0[THETA1:THETA2 + 1]), p)) * omega ** 2
    return make_case("flyball-governor", system, q0, v0, (0.0, t_end), p,
                     energy_scale=spin if spin > 0 else point_mass * gravity * length,
                     reference=reference,
                     # An ensemble perturbs the mechanism, not the work done on it so far.
                     perturbation=Perturbation(fixed=(WORK,)))
