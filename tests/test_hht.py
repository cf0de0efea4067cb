"""HHT-alpha as the generalized-alpha member alpha_m = 0: its coefficients, the members it
shares with Chung and Hulbert's choice (bit for bit), its order and constraint on the
pendulum, and the range of its parameter."""

import numpy as np
import pytest

import integrators
import problems
from integrators import Grid
from integrators.genalpha import Coefficients
from problems import SpecError


def solve(spec, h, t_end):
    case = problems.make("pendulum").with_t_end(t_end)
    traj = integrators.make(spec, h=h).prepare(case, Grid(case.t0, t_end))()
    assert traj.status == "ok", traj.message
    return case, traj


@pytest.mark.parametrize("alpha", [0.0, -0.05, -0.1, -0.3, -1 / 3])
def test_coefficients_are_hilber_hughes_taylor_in_the_family(alpha):
    c = Coefficients.hht(alpha)
    # HHT (1977): gamma = 1/2 - alpha, beta = (1 - alpha)^2 / 4; as a member of the family
    # (Chung and Hulbert 1993): alpha_m = 0, alpha_f = -alpha.
    assert (c.alpha_m, c.alpha_f) == (0.0, -alpha)
    assert c.gamma == 0.5 - alpha and c.beta == 0.25 * (1 - alpha) ** 2
    # The family's second-order condition and its beta; equal up to the rounding of the
    # different sums (one ulp).
    assert c.gamma == pytest.approx(0.5 - c.alpha_m + c.alpha_f, rel=1e-15, abs=0)
    assert c.beta == pytest.approx(0.25 * (c.gamma + 0.5) ** 2, rel=1e-15, abs=0)


@pytest.mark.parametrize("alpha", [0.0, -0.1, -0.3, -1 / 3])
def test_spectral_radius_at_infinity_is_one_plus_alpha_over_one_minus_alpha(alpha):
    """The amplification matrix of the step on ``x'' = -omega^2 x`` in the limit
    ``omega h -> oo`` (Hilber, Hughes and Taylor 1977: ``rho_inf = (1 + alpha) /
    (1 - alpha)``)."""
    am, af, gamma, beta = Coefficients.hht(alpha)
    # State (x, h v, h^2 a, h^2 acc); a step solves the position and velocity updates,
    # the averaging relation and the equation of motion at n+1, which, divided by
    # (omega h)^2, tends to x_{n+1} = 0.
    lhs = np.array([[1, 0, -beta, 0], [0, 1, -gamma, 0], [0, 0, 1 - am, -(1 - af)],
                    [1, 0, 0, 0]], dtype=float)
    rhs = np.array([[1, 1, 0.5 - beta, 0], [0, 1, 1 - gamma, 0], [0, 0, -am, af],
                    [0, 0, 0, 0]], dtype=float)
    rho = max(abs(np.linalg.eigvals(np.linalg.solve(lhs, rhs))))
    # -rho_inf is a double eigenvalue (a Jordan block), and at alpha = -1/3 the third one,
    # alpha / (1 + alpha), joins it: found to about eps^(1/2), or eps^(1/3) = 6e-6.
    assert rho == pytest.approx((1 + alpha) / (1 - alpha), abs=2e-5)


@pytest.mark.parametrize("alpha, rho, t_end", [(0.0, 1.0, 2.0), (-1 / 3, 0.5, 20.0)])
def test_shared_members_agree_with_genalpha(alpha, rho, t_end):
    """``alpha = 0`` is the trapezoidal rule (Newmark's average acceleration), which
    Chung and Hulbert's ``rho_inf = 1`` gives through ``alpha_m = alpha_f = 1/2`` (the
    averaging relation then keeps ``a = acc`` exactly); ``alpha = -1/3`` has the very
    coefficients of ``rho_inf = 1/2``. The latter do the same arithmetic, and the runs
    agree bit for bit. The former reach the same numbers by other operations (``x``
    against ``(x / 2) / (1 / 2)`` in the averaging relation), which XLA need not compile
    alike: they agree to round-off, which the index-3 trapezoidal rule magnifies in ``v``
    as ``eps / h`` per step (2.2e-12 after 2 s)."""
    _, hht = solve(f"hht:alpha={alpha!r}", 0.01, t_end)
    _, ga = solve(f"genalpha:rho_inf={rho}", 0.01, t_end)
    if alpha == 0.0:
        assert np.max(np.abs(hht.q_final - ga.q_final)) <= 1e-14
        assert np.max(np.abs(hht.v_final - ga.v_final)) <= 1e-10
        assert np.max(hht.windows["pos"]) <= 1e-15 and np.max(ga.windows["pos"]) <= 1e-15
        assert abs(hht.counts["n_newton"] - ga.counts["n_newton"]) <= 0.01 * ga.counts["n_newton"]
        return
    assert np.array_equal(hht.q_final, ga.q_final) and np.array_equal(hht.v_final, ga.v_final)
    assert np.array_equal(hht.windows["pos"], ga.windows["pos"])
    assert hht.counts["n_newton"] == ga.counts["n_newton"]


def test_order_two_and_the_constraint_at_round_off_on_the_pendulum():
    # The bar: alpha = -0.1 at h = 1e-3 and 5e-4 against the exact solution (elliptic
    # functions) after 10 s, about four periods. Measured: errors 1.45e-4 and 3.63e-5 in
    # q (6.0e-4 and 1.5e-4 in v), order 1.996 in both; max |g| 4.4e-16.
    hs = (1e-3, 5e-4)
    runs = [solve("hht:alpha=-0.1", h, 10.0) for h in hs]
    errs = []
    for case, traj in runs:
        q, v = case.reference.solution(traj.t_final)
        errs.append((np.max(np.abs(traj.q_final - q)), np.max(np.abs(traj.v_final - v))))
        # The index-3 form solves g = 0 by Newton to round-off at every step: a few ulps
        # of the unit length (the bar is 1e-12).
        assert np.max(traj.windows["pos"]) <= 1e-14
        # G v + g_t is not enforced: of the size of the velocity error.
        assert np.max(traj.windows["vel"]) > 1e-8
    for k in range(2):
        order = np.log2(errs[0][k] / errs[1][k])
        assert 1.8 <= order <= 2.2, (k, errs, order)


@pytest.mark.parametrize("bad", ["0.1", "-0.34", "nan"])
def test_alpha_outside_its_range_is_refused_in_one_line(bad):
    with pytest.raises(SpecError) as err:
        integrators.make(f"hht:alpha={bad}")
    message = str(err.value)
    assert f"alpha = {float(bad)}" in message and "[-1/3, 0]" in message
    assert "\n" not in message


def test_traits_and_options():
    method = integrators.make("hht")
    assert method.family == "generalized-alpha" and method.nominal_order == 2
    assert method.enforces == ("position",) and not method.symplectic
    assert method.options() == {"h": 0.01, "alpha": -0.3, "formulation": "index3",
                                "newton_tol": 1e-16, "newton_max_iter": 20,
                                "linear_solver": "auto"}
    assert integrators.make("hht:formulation=ggl").enforces == ("position", "velocity")
