"""Cross-check of the compiled RATTLE and Lobatto IIIA-IIIB integrators against
``tests/independent.py``, a plain-numpy re-derivation that shares no code with them.

First the independent side is checked on its own (exact tableau conditions, convergence
order against the closed-form pendulum, symplecticity of the one-step map, RATTLE equal to
2-stage Lobatto IIIA-IIIB); then final states are compared through the public API only.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
from scipy.special import ellipj, ellipk

import independent as ind
from independent import Q5

# ----------------------------------------------------------------------------------------
# Tolerance of the comparison (final q and v, max-norm, absolute).
#
# Two correct implementations of the same method differ only by round-off, but here the
# round-off is amplified. The position constraint is imposed at the position level, so an
# O(eps) error in g moves the momenta by O(eps / (h |G|)) per step (more for s = 4, where
# the stage multipliers are coupled through the h^2 A*Ahat block); over N = 1000 steps
# these errors accumulate (random walk plus the linear phase drift of a periodic orbit).
# Measured on sps-receiver at h = 0.05, t = 50 (the worst case; the pendulum at h = 0.01,
# t = 10 gives ~1e-13): this module's double-precision final state differs from the same
# arithmetic in x87 extended precision (``dtype=np.longdouble``) by up to 9e-13 in v
# (RATTLE), the project's integrators from that extended-precision run by up to 6e-13,
# and the two sides from each other by up to 1.4e-12. A solver that stops short of the
# round-off floor adds to this: the project's RATTLE with ``newton_tol=1e-14`` (|g| left
# up to 1e-14 per step) lands 1.6e-11 away in v. 1e-10 is therefore well above round-off
# (about 70x the discrepancy seen with converged solvers, 6x the unconverged one) and
# still far below any discretisation effect: a wrong coefficient or a wrong equation
# changes the final state at the level of the local error, O(h^3)..O(h^7), i.e. 1e-4 to
# 1e-8 here (lobatto3 and lobatto4 themselves differ by 4e-6 on sps-receiver).
# ----------------------------------------------------------------------------------------
TOL = 1e-10

#: (independent method, project key)
METHODS = [("rattle", "rattle"), ("lobatto2", "lobatto3ab2"),
           ("lobatto3", "lobatto3ab3"), ("lobatto4", "lobatto3ab4")]
#: (problem, h, t_end)
RUNS = [("sps-receiver", 0.05, 50.0), ("pendulum", 0.01, 10.0)]


# ----------------------------------------------------------------------------------------
# The independent side on its own
# ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("s", [2, 3, 4])
def test_tableau_simplifying_assumptions_exact(s):
    """B(2s-2) but not B(2s-1); IIIA: C(s), D(s-2); IIIB: C(s-2), D(s) (exact arithmetic)."""
    A, Ah, b, c = ind.lobatto_tableau_exact(s)
    r = range(s)

    def B(k):
        return sum((b[j] * c[j] ** (k - 1) for j in r), Q5(0)) == Q5(Fraction(1, k))

    def C(M, k):
        return all(sum((M[i][j] * c[j] ** (k - 1) for j in r), Q5(0)) == c[i] ** k * Fraction(1, k)
                   for i in r)

    def D(M, k):
        return all(sum((b[i] * c[i] ** (k - 1) * M[i][j] for i in r), Q5(0))
                   == b[j] * (1 - c[j] ** k) * Fraction(1, k) for j in r)

    assert all(B(k) for k in range(1, 2 * s - 1)) and not B(2 * s - 1)
    assert all(C(A, k) for k in range(1, s + 1))
    assert all(D(A, k) for k in range(1, s - 1))
    assert all(C(Ah, k) for k in range(1, s - 1))
    assert all(D(Ah, k) for k in range(1, s + 1))
    # IIIB structure and the symplecticity relation b_i ahat_ij + b_j a_ji = b_i b_j
    assert all(Ah[i][0] == b[0] and Ah[i][s - 1].is_zero() for i in r)
    assert all((b[i] * Ah[i][j] + b[j] * A[j][i] - b[i] * b[j]).is_zero() for i in r for j in r)


def test_tableau_s4_closed_form():
    """s = 4 against the tabulated closed forms (Hairer & Wanner, Solving ODEs II, IV.5)."""
    A, Ah, b, c = ind.lobatto_tableau_exact(4)
    F = Fraction
    c_ref = [Q5(0), Q5(F(1, 2), F(-1, 10)), Q5(F(1, 2), F(1, 10)), Q5(1)]
    A_ref = [[Q5(0)] * 4,
             [Q5(F(11, 120), F(1, 120)), Q5(F(25, 120), F(-1, 120)),
              Q5(F(25, 120), F(-13, 120)), Q5(F(-1, 120), F(1, 120))],
             [Q5(F(11, 120), F(-1, 120)), Q5(F(25, 120), F(13, 120)),
              Q5(F(25, 120), F(1, 120)), Q5(F(-1, 120), F(-1, 120))],
             [Q5(F(1, 12)), Q5(F(5, 12)), Q5(F(5, 12)), Q5(F(1, 12))]]
    Ah_ref = [[Q5(F(1, 12)), Q5(F(-1, 24), F(-1, 24)), Q5(F(-1, 24), F(1, 24)), Q5(0)],
              [Q5(F(1, 12)), Q5(F(25, 120), F(1, 120)), Q5(F(25, 120), F(-13, 120)), Q5(0)],
              [Q5(F(1, 12)), Q5(F(25, 120), F(13, 120)), Q5(F(25, 120), F(-1, 120)), Q5(0)],
              [Q5(F(1, 12)), Q5(F(11, 24), F(-1, 24)), Q5(F(11, 24), F(1, 24)), Q5(0)]]
    assert c == c_ref
    assert b == [Q5(F(1, 12)), Q5(F(5, 12)), Q5(F(5, 12)), Q5(F(1, 12))]
    assert A == A_ref and Ah == Ah_ref
    # One rounding to double: within half an ulp of the exact value.
    Af = ind.lobatto_tableau(4)[0]
    assert abs(Af[1, 2] - (25 - 13 * 5 ** 0.5) / 120) <= 2 * np.spacing(abs(Af[1, 2]))


def _pendulum_exact(t, gravity=9.81):
    """Unit pendulum released at rest from (1, 0): sin(theta/2) = k sn(K - w t | k^2).

    With k = sin(pi/4): x = sin(theta) = 2 k sn dn, y = -cos(theta) = 2 k^2 sn^2 - 1.
    """
    m = 0.5
    k, w = np.sqrt(m), np.sqrt(gravity)
    sn, cn, dn, _ = ellipj(ellipk(m) - w * t, m)
    q = np.array([2 * k * sn * dn, 2 * m * sn * sn - 1])
    v = np.array([-2 * k * w * cn * (dn * dn - m * sn * sn), -4 * m * w * sn * cn * dn])
    return q, v


@pytest.mark.parametrize("method, order, hs", [
    ("rattle", 2, (0.04, 0.02, 0.01)),
    ("lobatto2", 2, (0.04, 0.02, 0.01)),
    ("lobatto3", 4, (0.1, 0.05, 0.025)),
    ("lobatto4", 6, (0.2, 0.1, 0.05)),
])
def test_own_order_of_convergence(method, order, hs):
    """Global error at t = 1 against the closed-form pendulum; orders 2, 2, 4, 6."""
    q_ex, v_ex = _pendulum_exact(1.0)
    errs = []
    for h in hs:
        q, p, max_g = ind.integrate("pendulum", method, h, 1.0)
        assert max_g <= 1e-14
        errs.append(max(np.max(np.abs(q - q_ex)), np.max(np.abs(p - v_ex))))
    rates = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all(np.abs(rates - order) < 0.25), (errs, rates)


def _pendulum_map(step, z, h):
    """One step in the canonical chart (theta, p_theta) of the unit pendulum."""
    th, om = z
    q = np.array([np.sin(th), -np.cos(th)])
    p = om * np.array([np.cos(th), np.sin(th)])
    q1, p1 = step(q, p, h)
    th1 = np.arctan2(q1[0], -q1[1])
    return np.array([th1, p1 @ np.array([np.cos(th1), np.sin(th1)])])


def _det_of_map(step, z=np.array([1.0, 0.7]), h=0.2, d=1e-5):
    J = np.empty((2, 2))
    for k in range(2):
        e = np.zeros(2)
        e[k] = d
        J[:, k] = (_pendulum_map(step, z + e, h) - _pendulum_map(step, z - e, h)) / (2 * d)
    return np.linalg.det(J)


def test_own_symplecticity():
    """The one-step maps preserve area on the constraint manifold (1 degree of freedom).

    Central differences (d = 1e-5) resolve det to ~1e-9; a non-symplectic control
    (Lobatto IIIA used for both p and q, s = 4) is off by 1e-3 at the same step.
    """
    prob = ind.PROBLEMS["pendulum"]()
    assert abs(_det_of_map(lambda q, p, h: ind.rattle_step(prob, q, p, h)[:2]) - 1) < 1e-9
    for s in (2, 3, 4):
        tab = ind.lobatto_tableau(s)
        det = _det_of_map(lambda q, p, h: ind.lobatto_step(prob, tab, q, p, h)[:2])
        assert abs(det - 1) < 1e-9, (s, det)
    A, _, b, c = ind.lobatto_tableau(4)
    det = _det_of_map(lambda q, p, h: ind.lobatto_step(prob, (A, A, b, c), q, p, h)[:2])
    assert abs(det - 1) > 1e-4


def test_own_rattle_is_lobatto2():
    """RATTLE is 2-stage Lobatto IIIA-IIIB; the closed-form and Newton solvers agree."""
    for name, h in (("sps-receiver", 0.05), ("pendulum", 0.01)):
        q_r, p_r, _ = ind.integrate(name, "rattle", h, 100 * h)
        q_l, p_l, _ = ind.integrate(name, "lobatto2", h, 100 * h)
        assert np.max(np.abs(np.r_[q_r - q_l, p_r - p_l])) < 1e-12


def test_own_roundoff_floor_rattle():
    """Double vs x87 extended precision, same arithmetic (basis of TOL; see above)."""
    if np.finfo(np.longdouble).eps >= np.finfo(np.float64).eps:
        pytest.skip("no extended precision long double on this platform")
    mass = ind.PROBLEMS["sps-receiver"]().mass
    q, p, _ = ind.integrate("sps-receiver", "rattle", 0.05, 50.0)
    q_x, p_x, _ = ind.integrate("sps-receiver", "rattle", 0.05, 50.0, dtype=np.longdouble)
    assert np.max(np.abs(np.r_[q - q_x, (p - p_x) / mass])) < TOL / 10  # 9e-13 measured


# ----------------------------------------------------------------------------------------
# The comparison with the project's integrators (public API only)
# ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("name, h, t_end", RUNS, ids=[r[0] for r in RUNS])
@pytest.mark.parametrize("mine, key", METHODS, ids=[m[1] for m in METHODS])
def test_final_state_agrees(name, h, t_end, mine, key):
    import integrators
    import problems
    from integrators import Grid

    case = problems.make(name, t_end=t_end)
    prob = ind.PROBLEMS[name]()
    # The integrators are compared from identical inputs: the case's initial values (the
    # pendulum's come from the elliptic closed form and are (1, 0), (0, 0) only to 3e-16).
    assert np.max(np.abs(case.q0 - prob.q0)) < 1e-15
    assert np.max(np.abs(case.v0 * prob.mass - prob.p0)) < 1e-15
    q, p, max_g = ind.integrate(name, mine, h, t_end, q0=case.q0, p0=case.v0 * prob.mass)
    v = p / prob.mass

    traj = integrators.make(key, h=h).prepare(case, Grid(case.t0, t_end))()
    assert traj.status == "ok", traj.message
    assert traj.counts["n_steps"] == ind.n_steps(h, t_end)
    assert abs(traj.t_final - t_end) <= 1e-12 * t_end

    dq = np.max(np.abs(np.asarray(traj.q_final) - q))
    dv = np.max(np.abs(np.asarray(traj.v_final) - v))
    assert max_g <= 1e-14
    assert np.max(traj.windows["pos"]) <= 1e-13
    assert dq <= TOL and dv <= TOL, f"{key} on {name}: |dq| = {dq:.3e}, |dv| = {dv:.3e}"
