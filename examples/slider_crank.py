"""The slider-crank: a crank, a connecting rod and a slider, with an independent reference.

Written against the public API only (``problems.System``, ``problems.make_case``,
``problems.register``). Run it with::

    python -m benchmarks.run --load examples/slider_crank.py --problems slider-crank \
        --integrators rattle lobatto3ab3 ida-ggl baumgarte-dopri5 --h 0.01 --rtol 1e-8

The crank of length ``r`` turns about the origin; its mass ``m_crank`` is lumped at the
crank pin ``A``; the massless connecting rod of length ``l > r`` joins ``A`` to the slider
``B`` of mass ``m_slider``, which moves along the x axis. Gravity acts on the crank pin.
Coordinates ``q = (x_A, y_A, x_B)`` with the two constraints

.. math::

    x_A^2 + y_A^2 - r^2 = 0, \\qquad (x_B - x_A)^2 + y_A^2 - l^2 = 0,

one degree of freedom, and the energy ``H = (m_c (v_{Ax}^2 + v_{Ay}^2) + m_s v_B^2)/2 +
m_c g y_A`` conserved.

Reference, computed independently in the minimal coordinate, the crank angle ``theta``:
``x_A = r cos theta``, ``y_A = r sin theta``, ``x_B = r cos theta + sqrt(l^2 - r^2 sin^2
theta)``; with ``T = J(theta) theta'^2 / 2``, ``J = m_c r^2 + m_s x_B'(theta)^2`` and
``U = m_c g r sin theta``, Lagrange's equation ``J theta'' + J' theta'^2 / 2 + U' = 0`` is
integrated by SciPy's DOP853 at ``rtol = atol = 1e-13``.
"""

from __future__ import annotations

import functools

import jax.numpy as jnp
import numpy as np
from scipy.integrate import solve_ivp

from problems import Reference, System, make_case, register


def _slider(theta, r, l):
    """``x_B`` and its first two derivatives with respect to the crank angle."""
    s, c = np.sin(theta), np.cos(theta)
    D = np.sqrt(l * l - r * r * s * s)
    x = r * c + D
    dx = -r * s - r * r * s * c / D
    ddx = -r * c - r * r * (c * c - s * s) / D - r ** 4 * s * s * c * c / D ** 3
    return x, dx, ddx


@functools.lru_cache(maxsize=8)
def _minimal(r, l, m_crank, m_slider, gravity, theta0, omega0, t_end):
    """Dense solution ``theta(t), theta'(t)`` of the one-degree-of-freedom equation."""

    def rhs(t, y):
        theta, omega = y
        _, dx, ddx = _slider(theta, r, l)
        J = m_crank * r * r + m_slider * dx * dx
        dJ = 2.0 * m_slider * dx * ddx
        dU = m_crank * gravity * r * np.cos(theta)
        return [omega, -(0.5 * dJ * omega * omega + dU) / J]

    return solve_ivp(rhs, (0.0, t_end), [theta0, omega0], method="DOP853", rtol=1e-13,
                     atol=1e-13, dense_output=True).sol


def state(theta, omega, r, l):
    """``(q, v)`` of the mechanism at crank angle ``theta`` and rate ``omega``."""
    x, dx, _ = _slider(theta, r, l)
    q = np.array([r * np.cos(theta), r * np.sin(theta), x])
    v = omega * np.array([-r * np.sin(theta), r * np.cos(theta), dx])
    return q, v


@register("slider-crank")
def slider_crank(r: float = 0.5, l: float = 1.5, m_crank: float = 1.0,
                 m_slider: float = 2.0, gravity: float = 9.81, theta0: float = 0.0,
                 omega0: float = 5.0, t_end: float = 10.0):
    """The slider-crank released at crank angle ``theta0`` turning at ``omega0``."""
    if not 0 < r < l:
        raise ValueError(f"slider-crank: the crank r = {r} must be shorter than the rod "
                         f"l = {l} (and positive)")
    system = System(
        n=3, m=2,
        mass=np.array([m_crank, m_crank, m_slider]),
        potential=lambda q: m_crank * gravity * q[1],
        constraints=lambda q, t: jnp.array([q[0] ** 2 + q[1] ** 2 - r ** 2,
                                            (q[2] - q[0]) ** 2 + q[1] ** 2 - l ** 2]),
    )
    q0, v0 = state(theta0, omega0, r, l)
    args = (r, l, m_crank, m_slider, gravity, theta0, omega0, t_end)

    def solution(t):
        theta, omega = _minimal(*args)(t)
        return state(theta, omega, r, l)

    reference = Reference(kind="computed",
                          source="minimal coordinate (crank angle), SciPy DOP853, "
                                 "rtol = atol = 1e-13",
                          solution=solution, scored=tuple(range(6)),
                          # Computed up to t_end only: past it the dense output extrapolates.
                          span=(0.0, t_end))
    scale = m_crank * gravity * r + 0.5 * float(v0 @ (np.array([m_crank, m_crank,
                                                                 m_slider]) * v0))
    return make_case("slider-crank", system, q0, v0, (0.0, t_end),
                     dict(r=r, l=l, m_crank=m_crank, m_slider=m_slider, gravity=gravity,
                          theta0=theta0, omega0=omega0),
                     energy_scale=scale, reference=reference)
