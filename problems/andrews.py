"""Andrews' squeezing mechanism (IVP Test Set problem ``andrews``; IFToMM benchmark A03).

A planar seven-body mechanism driven by a constant torque, with one spring and no gravity.
Coordinates (all angles, radians)::

    q = (beta, Theta, gamma, Phi, delta, Omega, epsilon)

(Hairer and Wanner, *Solving Ordinary Differential Equations II*, 2nd ed., 1996, section
VII.7; Mazzia and Magherini, *Test Set for IVP Solvers*, problem ``andrews``, as distributed
in the R package deTestSet, ``src/Ex_andrews.f``, subroutines ``andfunc`` and ``andsoln``.
Every equation and number below is transcribed from that source, with its 42 parameters in
SI units.) The equations of motion are

.. math::

    M(q)\\,\\ddot q = f(q, \\dot q) - G(q)^T \\lambda, \\qquad g(q) = 0 \\in \\mathbb R^6,

with the configuration-dependent, symmetric mass matrix ``M(q)`` of :func:`mass_matrix`,
the six loop-closure constraints of :func:`constraints` and

.. math::

    f(q, \\dot q) = \\tau e_1 - \\nabla U_s(q) + c(q, \\dot q),

where ``tau = mom`` is the constant drive torque on ``beta``, ``U_s = c_0 (l(gamma) - l_0)^2
/ 2`` the energy of the spring of stiffness ``c_0`` and rest length ``l_0`` whose current
length ``l(gamma)`` is the distance from the point D of body 3 to the fixed point C, and
``c(q, qdot)`` the Coriolis and centrifugal terms of ``M(q)``. The Test Set writes ``c``
out by hand (``f1, f2, f4 .. f7``); here it is not written: :class:`~problems.mechanics.
Mechanics` derives it from ``M(q)`` by automatic differentiation, and a test checks that the
two agree. The drive torque is written as the potential ``-tau beta``, so that

.. math::

    H(q, \\dot q) = \\tfrac12 \\dot q^T M(q) \\dot q + U_s(q) - \\tau \\beta

is the conserved energy balance (kinetic plus spring energy minus the work of the drive;
IFToMM benchmark A03 measures exactly this balance).

Initial values (t = 0): the Test Set's consistent state, at rest. Two settings
(``setting``):

* ``testset`` (the default): the Test Set's ``t_end = 0.03`` s (about 2.5 turns of
  ``beta``), scored against its published reference (below).
* ``iftomm``: the IFToMM benchmark A03 (Library of Computational Benchmark Problems of the
  IFToMM Technical Committee for Multibody Dynamics, problem "Andrews' squeezing
  mechanism"; Gonzalez, Dopico, Lugris and Cuadrado, Multibody Syst. Dyn. 16:179-190,
  2006): the same mechanism, parameters and initial configuration (its table gives the
  angles to three digits, ``beta_0 = -0.0620`` rad), simulated for 0.05 s (about 5.4
  turns), as the A03 page of the benchmarks' OpenSim reproduction states
  (rehabenggroup.github.io/MBSbenchmarksInOpenSim, ``benchmarks/A03_AndrewsMechanism``).
  Its metric is the energy balance with the work of the motor,
  ``T + V - E_0 - tau (beta - beta_0)`` with ``V = U_s``, declared as the invariant
  ``energy_balance`` (:func:`energy_balance`). With the drive written as the potential
  ``-tau beta`` this is ``H - H_0``: the invariant's error and the energy error are the
  same number, reported under the benchmark's name as well. The published reference
  exists at 0.03 s only, so a run to 0.05 s has no final error; the energy balance is
  what scores it.

``t_end`` overrides the setting's duration; 0 (its default) keeps it.

Reference (published): the Test Set's values at ``t = 0.03`` (PSIDE, rtol = atol = 1e-14,
Cray double precision). They are scored on the seven positions only, as the Test Set scores
them; their accuracy is about 1e-10 relative on the positions (so scd near 9.5 at best) and
5e-8 on the velocities, which are carried for completeness but not scored. In absolute
terms (:data:`REF_FLOOR`): 1e-10 of the largest position, ``beta`` = 15.8 rad, is 1.6e-9;
``lobatto3ab4`` at ``h`` = 5e-5, whose own error is about 1e-11 (its distance to the run at
``h`` = 1e-4 is 5.2e-10 and the method is of order 6), differs from the published positions
by 1.4e-9.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from problems import register
from problems.case import Case, Reference, make_case
from problems.mechanics import System

#: The 42 parameters of the Test Set (SI units).
PARAMS = dict(
    m1=0.04325, m2=0.00365, m3=0.02373, m4=0.00706, m5=0.07050, m6=0.00706, m7=0.05498,
    xa=-0.06934, ya=-0.00227, xb=-0.03635, yb=0.03273, xc=0.014, yc=0.072, c0=4530.0,
    i1=2.194e-6, i2=4.410e-7, i3=5.255e-6, i4=5.667e-7, i5=1.169e-5, i6=5.667e-7,
    i7=1.912e-5, d=28e-3, da=115e-4, e=2e-2, ea=1421e-5, rr=7e-3, ra=92e-5, l0=7785e-5,
    ss=35e-3, sa=1874e-5, sb=1043e-5, sc=18e-3, sd=2e-2, ta=2308e-5, tb=916e-5, u=4e-2,
    ua=1228e-5, ub=449e-5, zf=2e-2, zt=4e-2, fa=1421e-5, mom=33e-3,
)

#: Consistent initial positions (Test Set, ``yini``); all velocities are zero.
Q0 = (-0.0617138900142764496358948458001, 0.0, 0.455279819163070380255912382449,
      0.222668390165885884674473185609, 0.487364979543842550225598953530,
      -0.222668390165885884674473185609, 1.23054744454982119249735015568)

T_END = 0.03
#: The IFToMM benchmark A03's duration (module docstring).
IFTOMM_T_END = 0.05

#: ``setting`` -> its duration.
DURATIONS = {"testset": T_END, "iftomm": IFTOMM_T_END}
#: ``setting`` -> energy scale: the work the drive does over the setting's horizon, tau
#: times the angle beta turns, about 16 rad by 0.03 s and 34 rad by 0.05 s (the kinetic
#: energy at the end is of the same order).
ENERGY_SCALES = {"testset": PARAMS["mom"] * 16.0, "iftomm": PARAMS["mom"] * 34.0}

#: Bound on the published positions' own max-norm error (module docstring), rounded up.
REF_FLOOR = 2e-9

#: Published reference at t = 0.03 (Test Set, ``andsoln``): positions y1..y7, velocities
#: y8..y14.
REF_Q = (0.1581077119629904e+2, -0.1575637105984298e+2, 0.4082224013073101e-1,
         -0.5347301163226948e+0, 0.5244099658805304e+0, 0.5347301163226948e+0,
         0.1048080741042263e+1)
REF_V = (0.1139920302151208e+4, -0.1424379294994111e+4, 0.1103291221937134e+2,
         0.1929337464421385e+2, 0.5735699284790808e+0, -0.1929337464421385e+2,
         0.3231791658026955e+0)


def mass_matrix(q, p=PARAMS):
    """``M(q)`` (7 x 7, symmetric), entries as in the Test Set's ``andfunc``."""
    _, theta, _, phi, _, omega, _ = q
    m2, m4, m6 = p["m2"], p["m4"], p["m6"]
    da, rr, e, ea, zt = p["da"], p["rr"], p["e"], p["ea"], p["zt"]
    zf, fa, u = p["zf"], p["fa"], p["u"]
    M11 = (p["m1"] * p["ra"] ** 2 + m2 * (rr ** 2 - 2 * da * rr * jnp.cos(theta) + da ** 2)
           + p["i1"] + p["i2"])
    M21 = m2 * (da ** 2 - da * rr * jnp.cos(theta)) + p["i2"]
    M22 = m2 * da ** 2 + p["i2"]
    M33 = p["m3"] * (p["sa"] ** 2 + p["sb"] ** 2) + p["i3"]
    M44 = m4 * (e - ea) ** 2 + p["i4"]
    M54 = m4 * ((e - ea) ** 2 + zt * (e - ea) * jnp.sin(phi)) + p["i4"]
    M55 = (m4 * (zt ** 2 + 2 * zt * (e - ea) * jnp.sin(phi) + (e - ea) ** 2)
           + p["m5"] * (p["ta"] ** 2 + p["tb"] ** 2) + p["i4"] + p["i5"])
    M66 = m6 * (zf - fa) ** 2 + p["i6"]
    M76 = m6 * ((zf - fa) ** 2 - u * (zf - fa) * jnp.sin(omega)) + p["i6"]
    M77 = (m6 * ((zf - fa) ** 2 - 2 * u * (zf - fa) * jnp.sin(omega) + u ** 2)
           + p["m7"] * (p["ua"] ** 2 + p["ub"] ** 2) + p["i6"] + p["i7"])
    zero = jnp.zeros_like(theta)
    return jnp.array([
        [M11, M21, zero, zero, zero, zero, zero],
        [M21, M22, zero, zero, zero, zero, zero],
        [zero, zero, M33, zero, zero, zero, zero],
        [zero, zero, zero, M44, M54, zero, zero],
        [zero, zero, zero, M54, M55, zero, zero],
        [zero, zero, zero, zero, zero, M66, M76],
        [zero, zero, zero, zero, zero, M76, M77],
    ])


def spring_length(gamma, p=PARAMS):
    """Length of the spring from point D of body 3 to the fixed point C."""
    xd = p["sd"] * jnp.cos(gamma) + p["sc"] * jnp.sin(gamma) + p["xb"]
    yd = p["sd"] * jnp.sin(gamma) - p["sc"] * jnp.cos(gamma) + p["yb"]
    return jnp.sqrt((xd - p["xc"]) ** 2 + (yd - p["yc"]) ** 2)


def potential(q, p=PARAMS):
    """Spring energy minus the work potential of the drive: ``U_s(gamma) - tau beta``."""
    return 0.5 * p["c0"] * (spring_length(q[2], p) - p["l0"]) ** 2 - p["mom"] * q[0]


def constraints(q, t=None, p=PARAMS):
    """The six loop-closure constraints ``g(q)`` (Test Set ``andfunc``, ``g1 .. g6``)."""
    beta, theta, gamma, phi, delta, omega, eps = q
    rr, d, ss, e, zt, zf, u = p["rr"], p["d"], p["ss"], p["e"], p["zt"], p["zf"], p["u"]
    cx = rr * jnp.cos(beta) - d * jnp.cos(beta + theta)
    cy = rr * jnp.sin(beta) - d * jnp.sin(beta + theta)
    return jnp.array([
        cx - ss * jnp.sin(gamma) - p["xb"],
        cy + ss * jnp.cos(gamma) - p["yb"],
        cx - e * jnp.sin(phi + delta) - zt * jnp.cos(delta) - p["xa"],
        cy + e * jnp.cos(phi + delta) - zt * jnp.sin(delta) - p["ya"],
        cx - zf * jnp.cos(omega + eps) - u * jnp.sin(eps) - p["xa"],
        cy - zf * jnp.sin(omega + eps) + u * jnp.cos(eps) - p["ya"],
    ])


def testset_forces(q, v, p=PARAMS):
    """The Test Set's right-hand side ``f(q, qdot)`` written out by hand (``ff`` in
    ``andfunc``); used only to check the autodiff Coriolis terms and spring force."""
    beta, theta, gamma, phi, delta, omega, eps = q
    bp, tp, _, pp, dp, op, ep = v
    m2, m4, m6 = p["m2"], p["m4"], p["m6"]
    da, rr, e, ea, zt, zf, fa, u = (p[k] for k in ("da", "rr", "e", "ea", "zt", "zf", "fa", "u"))
    sc, sd = p["sc"], p["sd"]
    xd = sd * jnp.cos(gamma) + sc * jnp.sin(gamma) + p["xb"]
    yd = sd * jnp.sin(gamma) - sc * jnp.cos(gamma) + p["yb"]
    lang = jnp.sqrt((xd - p["xc"]) ** 2 + (yd - p["yc"]) ** 2)
    force = -p["c0"] * (lang - p["l0"]) / lang
    fx, fy = force * (xd - p["xc"]), force * (yd - p["yc"])
    return jnp.array([
        p["mom"] - m2 * da * rr * tp * (tp + 2 * bp) * jnp.sin(theta),
        m2 * da * rr * bp ** 2 * jnp.sin(theta),
        fx * (sc * jnp.cos(gamma) - sd * jnp.sin(gamma))
        + fy * (sd * jnp.cos(gamma) + sc * jnp.sin(gamma)),
        m4 * zt * (e - ea) * dp ** 2 * jnp.cos(phi),
        -m4 * zt * (e - ea) * pp * (pp + 2 * dp) * jnp.cos(phi),
        -m6 * u * (zf - fa) * ep ** 2 * jnp.cos(omega),
        m6 * u * (zf - fa) * op * (op + 2 * ep) * jnp.cos(omega),
    ])


def energy_balance(q, v, p=PARAMS):
    """IFToMM A03's energy balance up to its constant: ``T + U_s - tau beta``, whose change
    from ``t = 0`` is the benchmark's ``T + V - E_0 - tau (beta - beta_0)``."""
    return 0.5 * v @ (mass_matrix(q, p) @ v) + potential(q, p)


def published(t: float):
    """The published reference state at ``t = 0.03`` (positions and velocities)."""
    return np.array(REF_Q), np.array(REF_V)


@register("andrews")
def andrews(setting: str = "testset", t_end: float = 0.0) -> Case:
    """Andrews' squeezing mechanism from the Test Set's consistent initial state, at the
    Test Set's settings (``testset``) or the IFToMM benchmark's (``iftomm``); ``t_end`` 0
    (the default) takes the setting's duration."""
    if setting not in DURATIONS:
        raise ValueError(f"andrews: setting = {setting!r} must be one of "
                         f"{', '.join(DURATIONS)}")
    invariants = {"energy_balance": energy_balance} if setting == "iftomm" else {}
    system = System(n=7, m=6, mass=mass_matrix, potential=potential, constraints=constraints,
                    invariants=invariants)
    reference = Reference(
        kind="published",
        source=("Test Set for IVP Solvers (Mazzia and Magherini), problem andrews, "
                "subroutine andsoln: PSIDE at rtol = atol = 1e-14; positions accurate to "
                "about 1e-10 relative (2e-9 absolute), velocities to about 5e-8 (not "
                "scored)"),
        solution=published,
        scored=tuple(range(7)),
        times=(T_END,),
        floor=REF_FLOOR,
        span=(0.0, T_END),
    )
    return make_case("andrews", system, Q0, np.zeros(7), (0.0, t_end or DURATIONS[setting]),
                     dict(PARAMS), energy_scale=ENERGY_SCALES[setting], reference=reference)
