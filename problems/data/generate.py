"""Regenerate the stored reference solutions: ``python -m problems.data.generate [NAME ...]``.

Every reference here comes from an integration that shares no code with the benchmarked
integrators, at tight tolerance, and is stored with an error estimate: the max-norm
difference of ``(q, v)`` to the same integration at a looser tolerance (``LOOSE_RTOL``),
which bounds the error of the looser run and so, conservatively, of the stored one.

* ``double-pendulum`` and ``chain``: the pendulum chain in minimal coordinates (the link
  angles from the downward vertical), :func:`chain_rhs`, written from the Lagrangian
  independently of the Cartesian DAE, by scipy's DOP853; mapped to Cartesian ``(q, v)``.
* ``bricard``: the index-1 (acceleration-level) ODE of the problem's own System, with the
  minimum-norm least-squares multipliers of :meth:`Mechanics.accelerations` (the
  constraints are redundant), by scipy's DOP853, and the stored states projected back onto
  ``g = 0`` and ``G v = 0``. This one shares the model with the benchmarked runs; what it
  checks is the integration.
* ``flyball-governor``: the Lagrange equations of the governor in its three free
  coordinates with the drive substituted, :func:`governor_rhs`, written out by hand
  independently of the problem's System, by scipy's DOP853; the error estimate of ``s``
  (the only scored component) is its difference to scipy's Radau at ``RADAU_RTOL``, a
  second method rather than a second tolerance (the problem is stiff, ``|lambda|`` up to
  about 1e4 1/s, and an implicit method shares neither the error behaviour nor the step
  sequence of the explicit one).

With no argument every file is regenerated.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
from scipy.integrate import solve_ivp

from problems.data import DATA_DIR

#: Tolerances of the stored run and of the run that estimates its error.
TIGHT_RTOL = 2.5e-14
LOOSE_RTOL = 1e-12


def chain_rhs(theta, omega, lengths, masses, gravity):
    """Angular accelerations of a planar chain of point masses in its link angles.

    With ``S_ij = sum_{k >= max(i, j)} m_k`` (the mass hanging below both links) the
    Lagrangian ``T - U`` with ``T = sum_ij L_i L_j S_ij cos(theta_i - theta_j) w_i w_j / 2``
    and ``U = -g sum_i L_i S_ii cos(theta_i)`` gives

    .. math::

        \\sum_j L_i L_j S_{ij} \\big(\\cos(\\theta_i - \\theta_j) \\ddot\\theta_j
        + \\sin(\\theta_i - \\theta_j) \\dot\\theta_j^2\\big) + g L_i S_{ii} \\sin\\theta_i = 0.
    """
    tail = np.cumsum(masses[::-1])[::-1]
    S = tail[np.maximum.outer(np.arange(len(masses)), np.arange(len(masses)))]
    LL = np.outer(lengths, lengths) * S
    diff = theta[:, None] - theta[None, :]
    A = LL * np.cos(diff)
    b = -(LL * np.sin(diff)) @ (omega * omega) - gravity * lengths * tail * np.sin(theta)
    return np.linalg.solve(A, b)


def integrate_chain(theta0, lengths, masses, gravity, times, rtol):
    """Cartesian ``(q, v)`` of the chain released from rest at ``theta0``, at ``times``."""
    from problems.double_pendulum import cartesian

    n = len(theta0)

    def rhs(t, y):
        return np.concatenate([y[n:], chain_rhs(y[:n], y[n:], lengths, masses, gravity)])

    sol = solve_ivp(rhs, (0.0, max(times)), np.concatenate([theta0, np.zeros(n)]),
                    method="DOP853", rtol=rtol, atol=rtol, t_eval=times)
    if sol.status != 0:
        raise RuntimeError(f"DOP853 failed: {sol.message}")
    return [cartesian(sol.y[:n, i], sol.y[n:, i], lengths) for i in range(len(times))]


def chain_entries(cases, times):
    """Entries for ``(params, theta0, lengths, masses, gravity)`` tuples at ``times``."""
    entries = []
    for params, theta0, lengths, masses, gravity in cases:
        tight = integrate_chain(theta0, lengths, masses, gravity, times, TIGHT_RTOL)
        loose = integrate_chain(theta0, lengths, masses, gravity, times, LOOSE_RTOL)
        for t, (q, v), (ql, vl) in zip(times, tight, loose):
            err = max(np.max(np.abs(q - ql)), np.max(np.abs(v - vl)))
            entries.append(dict(params=params, t=float(t), q=q.tolist(), v=v.tolist(),
                                error_estimate=float(err)))
            print(f"  {params} t={t:g}: error estimate {err:.2e}", file=sys.stderr)
    return entries


def double_pendulum():
    from problems.double_pendulum import ANGLES, double_pendulum as factory

    cases, times = [], {"low": [5.0, 100.0, 1000.0], "high": [2.5, 5.0]}
    entries = []
    for energy in ANGLES:
        params = factory(energy=energy).params
        g = params["gravity"]
        case = (params, np.array(ANGLES[energy]), np.array([params["L1"], params["L2"]]),
                np.array([params["m1"], params["m2"]]), g)
        entries += chain_entries([case], times[energy])
    return dict(
        method=("double pendulum in its two angles (minimal coordinates), scipy DOP853 at "
                f"rtol = atol = {TIGHT_RTOL:g}; error estimate = difference to "
                f"rtol = {LOOSE_RTOL:g}"),
        entries=entries,
    )


def chain():
    from problems.chain import chain as factory

    cases = []
    for N in (2, 4, 8):
        params = factory(N=N).params
        length, mass = params["length"], params["mass"]
        cases.append((params, np.full(N, params["theta0"]), np.full(N, length / N),
                      np.full(N, mass / N), params["gravity"]))
    return dict(
        method=("chain in its N link angles (minimal coordinates), scipy DOP853 at "
                f"rtol = atol = {TIGHT_RTOL:g}; error estimate = difference to "
                f"rtol = {LOOSE_RTOL:g}"),
        entries=chain_entries(cases, [1.0, 5.0]),
    )


def integrate_index1(case, times, rtol):
    """``(q, v)`` at ``times`` of the index-1 ODE ``q' = v, v' = a(t, q, v)`` of a case."""
    import jax
    import jax.numpy as jnp

    mech, n = case.mech, case.mech.n
    accel = jax.jit(lambda t, q, v: mech.accelerations(t, q, v)[0])

    def rhs(t, y):
        a = accel(jnp.asarray(t), jnp.asarray(y[:n]), jnp.asarray(y[n:]))
        return np.concatenate([y[n:], np.asarray(a)])

    sol = solve_ivp(rhs, (case.t0, max(times)), np.concatenate([case.q0, case.v0]),
                    method="DOP853", rtol=rtol, atol=rtol, t_eval=times)
    if sol.status != 0:
        raise RuntimeError(f"DOP853 failed: {sol.message}")
    return [(sol.y[:n, i], sol.y[n:, i]) for i in range(len(times))]


def bricard():
    from problems.bricard import bricard as factory
    from problems.case import project, residuals

    case = factory()
    times = [1.0, 5.0, 10.0]
    # The unprojected index-1 solution drifts off g = 0 by up to ~4e-10 at t = 10; the
    # stored states are projected back (mass-orthogonally, both levels), which removes
    # the drift's normal component and leaves the tangential error the estimate measures.
    tight = [project(case.mech, q, v, t)
             for t, (q, v) in zip(times, integrate_index1(case, times, TIGHT_RTOL))]
    loose = [project(case.mech, q, v, t)
             for t, (q, v) in zip(times, integrate_index1(case, times, LOOSE_RTOL))]
    entries = []
    for t, (q, v), (ql, vl) in zip(times, tight, loose):
        err = max(np.max(np.abs(q - ql)), np.max(np.abs(v - vl)))
        pos, vel = residuals(case.mech, q, v, t)
        entries.append(dict(params=dict(case.params), t=t, q=q.tolist(), v=v.tolist(),
                            error_estimate=float(err), residuals=[pos, vel]))
        print(f"  t={t:g}: error estimate {err:.2e}, |g| {pos:.1e}, |Gv| {vel:.1e}",
              file=sys.stderr)
    return dict(
        method=("index-1 ODE of the natural-coordinate System (minimum-norm multipliers), "
                f"scipy DOP853 at rtol = atol = {TIGHT_RTOL:g}, states projected onto g = 0 "
                "and G v = 0 (residuals stored with each entry); error estimate = "
                f"difference to rtol = {LOOSE_RTOL:g}"),
        entries=entries,
    )


#: Radau's tolerance for the flyball governor's second solve: scipy's Radau refuses
#: tolerances below ``1000 eps`` (2.2e-13) and needs minutes at that.
RADAU_RTOL = 1e-12


def governor_rhs(t, y, p):
    """The flyball governor's ODE in ``y = (s, theta_1, theta_2, w, s', theta_1',
    theta_2', w')`` with the shaft angle ``phi = omega t`` substituted.

    The Lagrangian ``T - U`` with ``T = J_phi(theta) omega^2 / 2 + m_c s'^2 / 2 + J_theta
    sum_i theta_i'^2 / 2`` (:mod:`problems.flyball_governor`) gives

    .. math::

        m_c \\ddot s = -m_c g_0 - \\sum_i F_i \\partial_s l_i, \\qquad
        J_\\theta \\ddot\\theta_i = \\tfrac12 \\omega^2 \\partial_{\\theta_i} J_\\phi
        + g_0 (m_r L / 2 + m_p L) \\cos\\theta_i - F_i \\partial_{\\theta_i} l_i,

    with the spring-damper tension ``F_i = K (l_i - l_0) + C l_i'``, and the dissipated
    work's accumulator ``w'' = C sum_i l_i'^2``.
    """
    L, b, d, rho, mp = p["length"], p["side"], p["slider"], p["density"], p["point_mass"]
    a, h = d / 2.0, L
    m_r, m_c = rho * L * b * b, rho * d ** 3
    I_axial, I_trans = m_r * b * b / 6.0, m_r * (L * L + b * b) / 12.0
    J_theta = m_r * L * L / 3.0 + m_r * b * b / 12.0 + mp * L * L
    s, theta, sd, thetad = y[0], y[1:3], y[4], y[5:7]
    c, sn = np.cos(theta), np.sin(theta)
    dx, dz = 0.5 * L * c, h - 0.5 * L * sn - s
    l = np.hypot(dx, dz)
    dl_ds, dl_dtheta = -dz / l, (-dx * 0.5 * L * sn - dz * 0.5 * L * c) / l
    rate = dl_ds * sd + dl_dtheta * thetad
    tension = p["stiffness"] * (l - p["rest_length"]) + p["damping"] * rate
    dJ_dtheta = (-m_r * L * (a + 0.5 * L * c) * sn + 2.0 * (I_axial - I_trans) * sn * c
                 - 2.0 * mp * L * (a + L * c) * sn)
    s_dd = -p["gravity"] - np.sum(tension * dl_ds) / m_c
    theta_dd = (0.5 * p["omega"] ** 2 * dJ_dtheta + p["gravity"] * (0.5 * m_r + mp) * L * c
                - tension * dl_dtheta) / J_theta
    w_dd = p["damping"] * np.sum(rate * rate)
    return np.concatenate([y[4:], [s_dd], theta_dd, [w_dd]])


def flyball_governor(times=(1.0, 5.0, 10.0)):
    from problems.flyball_governor import S, flyball_governor as factory

    case = factory()
    p, times = dict(case.params), list(times)
    y0 = np.concatenate([case.q0[1:], case.v0[1:]])
    solves = {}
    for method, rtol in (("DOP853", TIGHT_RTOL), ("Radau", RADAU_RTOL)):
        # Nothing depends on the accumulator w: its Jacobian column is zero, and Radau's
        # finite-difference Jacobian grows its step for that column until it overflows.
        with np.errstate(over="ignore"):
            sol = solve_ivp(governor_rhs, (case.t0, max(times)), y0, method=method,
                            rtol=rtol, atol=rtol, t_eval=times, args=(p,))
        if sol.status != 0:
            raise RuntimeError(f"{method} failed: {sol.message}")
        solves[method] = sol.y
        print(f"  {method} at rtol {rtol:g}: {sol.nfev} evaluations", file=sys.stderr)
    entries = []
    for i, t in enumerate(times):
        y, other = solves["DOP853"][:, i], solves["Radau"][:, i]
        q = np.concatenate([[p["omega"] * t], y[:4]])
        v = np.concatenate([[p["omega"]], y[4:]])
        err = abs(y[S - 1] - other[S - 1])
        entries.append(dict(params=p, t=t, q=q.tolist(), v=v.tolist(),
                            error_estimate=float(err),
                            state_difference=float(np.max(np.abs(y - other)))))
        print(f"  t={t:g}: s = {y[S - 1]:.15f}, error estimate {err:.2e}, state "
              f"difference {np.max(np.abs(y - other)):.2e}", file=sys.stderr)
    return dict(
        method=("Lagrange equations in (s, theta_1, theta_2) with phi = omega t, written "
                f"by hand, scipy DOP853 at rtol = atol = {TIGHT_RTOL:g}; error estimate of "
                f"s = difference to scipy Radau at rtol = atol = {RADAU_RTOL:g} "
                "(state_difference: the same over the whole state)"),
        entries=entries,
    )


GENERATORS = {"double-pendulum": double_pendulum, "chain": chain, "bricard": bricard,
              "flyball-governor": flyball_governor}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m problems.data.generate",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("names", nargs="*", help=f"files to regenerate: {', '.join(GENERATORS)}")
    args = parser.parse_args(argv)
    for name in args.names or list(GENERATORS):
        if name not in GENERATORS:
            parser.error(f"unknown reference {name!r}; known: {', '.join(GENERATORS)}")
        print(f"{name}:", file=sys.stderr)
        content = GENERATORS[name]()
        content = dict(problem=name, command=f"python -m problems.data.generate {name}",
                       **content)
        path = DATA_DIR / f"{name}.json"
        path.write_text(json.dumps(content, indent=1) + "\n")
        print(f"wrote {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
