"""Generalized-alpha, index 3 and stabilised index 2: order, constraints, multipliers, energy,
stability, Newton scaling, options, and agreement with an independent implementation."""

from functools import lru_cache

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree
import numpy as np
import pytest

import integrators
import integrators.genalpha
import problems
from benchmarks.execute import execute
from benchmarks.records import RunSpec
from integrators import Grid
from integrators.genalpha import Coefficients, velocity_scale
from integrators.newton import newton
from problems import SpecError

import independent as ind

FORMS = ["genalpha", "genalpha-ggl"]


@lru_cache(maxsize=None)
def base_case(problem):
    """One case per problem, so that runs share its compiled loops (keyed by the system)."""
    return problems.make(problem)


def solve(spec, problem, h, t_end):
    case = base_case(problem).with_t_end(t_end)
    traj = integrators.make(spec, h=h).prepare(case, Grid(case.t0, t_end))()
    return case, traj


def errors(case, traj):
    q_ref, v_ref = case.reference.solution(traj.t_final)
    return np.max(np.abs(traj.q_final - q_ref)), np.max(np.abs(traj.v_final - v_ref))


def energy_change(traj, gravity=9.81):
    """``H(t_end) - H(0)`` on the pendulum (unit mass and length, released at y = 0)."""
    return 0.5 * traj.v_final @ traj.v_final + gravity * traj.q_final[1]


def fitted_order(hs, errs):
    return np.polyfit(np.log(hs), np.log(errs), 1)[0]


@pytest.mark.parametrize("rho", [1.0, 0.8])
@pytest.mark.parametrize("key", FORMS)
def test_observed_order_2_in_q_and_v(key, rho):
    # Over 2 s (under one period): the index-3 form with rho_inf = 1 is unstable (see
    # test_index3_with_rho_one_breaks_down), but its errors need longer than this to grow.
    hs = np.array([0.02, 0.01, 0.005, 0.0025])
    errs = np.array([errors(*solve(f"{key}:rho_inf={rho}", "pendulum", h, 2.0)) for h in hs])
    # Round-off plateau (1e-12 after 2 s of a unit pendulum) masked; here every error is
    # above 1e-5, so all four points are fitted.
    keep = errs.min(axis=1) > 1e-12
    assert keep.sum() >= 3, errs
    for k in range(2):
        # The steps are in the asymptotic range: the slope matches 2 to a few hundredths
        # (1.98 to 2.00 measured); 0.1 leaves room for round-off without letting order 1
        # or 3 pass.
        assert abs(fitted_order(hs[keep], errs[keep, k]) - 2) < 0.1, (k, errs)


@pytest.mark.slow
@pytest.mark.parametrize("key", FORMS)
def test_order_from_final_positions_at_t_100(key):
    # Second order over a long horizon, at the default rho_inf: two runs over 100 s
    # (about 42 periods).
    hs = np.array([1e-3, 5e-4])
    errs = [errors(*solve(key, "pendulum", h, 100.0))[0] for h in hs]
    # Two points give the order exactly; after 42 periods the error is mostly phase, still
    # close to its asymptotic behaviour at these steps (1.94 and 1.95 measured).
    order = fitted_order(hs, errs)
    assert abs(order - 2.0) <= 0.2, (order, errs)


@pytest.mark.parametrize("problem, h, t_end", [("pendulum", 0.01, 20.0),
                                               ("sps-receiver", 0.05, 50.0)])
@pytest.mark.parametrize("key", FORMS)
def test_constraints_at_the_newton_tolerance_every_step(key, problem, h, t_end):
    _, traj = solve(key, problem, h, t_end)
    assert traj.status == "ok", traj.message
    # Newton iterates to round-off by default: |g| of O(1) coordinates then lies within a
    # few ulps of zero; 1e-13 leaves a decade (the bar is 1e-12).
    assert np.max(traj.windows["pos"]) <= 1e-13
    c = traj.counts
    # Work: one residual (one force evaluation) per iteration plus the starting one, one
    # Jacobian and one linear solve per iteration, and one G(q_n) per step for ggl.
    assert c["n_f_evals"] == c["n_newton"] + c["n_steps"]
    assert c["n_lin_solves"] == c["n_newton"]
    assert c["n_jac_evals"] == c["n_newton"] + (c["n_steps"] if key.endswith("ggl") else 0)
    if key == "genalpha-ggl":
        # Round-off again for the velocity constraint (its Newton row is scaled by
        # beta h / gamma, so round-off in that row is below 1e-16 / h).
        assert np.max(traj.windows["vel"]) <= 1e-13
    else:
        # Not enforced by the index-3 form: of the order of the velocity error, far above
        # round-off (2e-3 measured on both problems).
        assert np.max(traj.windows["vel"]) > 1e-6

    # A loose tolerance is what bounds the residuals: |g| is a row of the Newton residual
    # as it is, G v + g_t a row multiplied by beta h / gamma.
    tol = 1e-10
    _, loose = solve(f"{key}:newton_tol={tol}", problem, h, t_end)
    assert loose.status == "ok"
    assert np.max(loose.windows["pos"]) <= tol
    assert np.max(loose.windows["pos"]) > 1e-13  # it did stop early: the test has teeth
    if key == "genalpha-ggl":
        # rho_inf = 0.5 (the default): gamma = 5/6 and beta = 4/9 (Chung and Hulbert 1993,
        # alpha_m = 0, alpha_f = 1/3), so gamma / beta = 15/8.
        assert integrators.make(key).rho_inf == 0.5
        assert np.max(loose.windows["vel"]) <= tol * 15 / 8 / h


def multiplier_errors(key, h, steps, rho=0.9, t_start=0.2):
    """``lambda_n - lambda(t_n)`` for the first steps on the pendulum started in motion.

    The start is the exact A01 state at ``t_start`` (moving, where the constraint's
    curvature term does not vanish as it does at the release from rest); the exact
    multiplier of the unit pendulum is ``lambda = (|v|^2 - g y) / 2``.
    """
    case = base_case("pendulum")
    mech, exact = case.mech, case.reference.solution
    method = integrators.make(f"{key}:rho_inf={rho}", h=h)
    q0, v0 = exact(t_start)
    schur = mech.schur("dense")
    state = method.start(mech, schur, jnp.asarray(q0), jnp.asarray(v0), jnp.float64(t_start))
    step = jax.jit(lambda state, t: method.step(mech, schur, state, t, h))
    out = []
    for k in range(steps):
        state, code, _, _ = step(state, t_start + k * h)
        assert int(code) == 0
        q, v = exact(t_start + (k + 1) * h)
        out.append(float(state.lam[0]) - (v @ v - 9.81 * q[1]) / 2)
    return np.array(out)


def test_index3_multipliers_overshoot_in_the_first_steps_and_ggl_ones_do_not():
    e3 = {h: multiplier_errors("genalpha", h, 4) for h in (0.01, 0.005)}
    e2 = multiplier_errors("genalpha-ggl", 0.01, 4)
    # Measured: -0.10, +0.19, -0.28, +0.36 at h = 0.01 for lambda near 2.9 (the position
    # constraint pushes the O(h^3) position error of a step into an O(h) error of the
    # accelerations, which the double eigenvalue -rho_inf of the constraint modes makes
    # alternate and grow before it decays).
    assert np.all(np.sign(e3[0.01]) == [-1, 1, -1, 1]), e3
    assert np.all(np.diff(np.abs(e3[0.01])) > 0), e3
    # O(h): halving h halves the first error (ratio 2.04 measured).
    ratio = e3[0.01][0] / e3[0.005][0]
    assert abs(ratio - 2.0) < 0.2, (ratio, e3)
    # The index-2 form has no such transient: what is left is the O(h) start error of
    # a_0 = acc_0, small for rho_inf = 0.9 (0.0035 against 0.10 at the first step, 0.005
    # against 0.36 over four steps, measured).
    assert np.max(np.abs(e2)) < 0.05 * np.max(np.abs(e3[0.01])), (e2, e3)


@pytest.mark.parametrize("key", FORMS)
def test_energy_decays_at_third_order_for_rho_below_one(key):
    # rho_inf < 1 damps the resolved pendulum motion too, by O((omega h)^3) per period
    # (Chung and Hulbert 1993): the energy falls, and the loss over a fixed horizon shrinks
    # eightfold when h is halved (7.9 and 8.0 measured over 200 s).
    loss = {}
    for h in (0.01, 0.005):
        _, traj = solve(f"{key}:rho_inf=0.5", "pendulum", h, 200.0)
        assert traj.status == "ok", traj.message
        loss[h] = -energy_change(traj)
        assert loss[h] > 0, loss
    assert 6 < loss[0.01] / loss[0.005] < 10, loss


def test_energy_of_ggl_without_damping_drifts_slowly():
    # rho_inf = 1 is the trapezoidal rule, whose energy error stays bounded on its own; the
    # index-2 position correction G(q_n)^T mu breaks its symmetry in time and leaves a
    # slow, steady drift, O(h^3) per unit time (8.0 times smaller at half the step). Its
    # sign is as measured: upward (taking the correction direction at the new position
    # instead gave a downward drift of the same size).
    drift = {}
    for h in (0.01, 0.005):
        _, traj = solve("genalpha-ggl:rho_inf=1", "pendulum", h, 200.0)
        assert traj.status == "ok", traj.message
        drift[h] = energy_change(traj)
        # Steady: the final error is the largest (its window maxima grow all along).
        assert drift[h] > 0.8 * np.max(traj.windows["energy"]), drift
    assert 6 < drift[0.01] / drift[0.005] < 10, drift


def test_index3_with_rho_one_breaks_down():
    # Known failure with its cause: without damping the constraint modes of the index-3
    # form have the double eigenvalue -1, and on the pendulum's curved constraint their
    # errors grow until Newton no longer converges (t = 95.6 s at h = 0.01, measured; the
    # trapezoidal rule on index-3 equations is unstable, Cardona and Geradin 1989).
    _, bad = solve("genalpha:rho_inf=1", "pendulum", 0.01, 100.0)
    assert bad.status == "failed" and "Newton" in bad.message
    assert 20.0 < bad.fail_time < 100.0
    # Before it failed the velocity constraint was violated by orders of magnitude more
    # than the discretisation error (1e-3): the run had already blown up.
    assert np.max(bad.windows["vel"]) > 1.0
    # A smaller step does not cure it: the growth rate per unit time does not shrink with
    # h (the multiplier grows about twentyfold per second from t = 5 s at h = 1e-3, and
    # Newton fails at t = 17.7 s, measured), as for an instability of the method rather
    # than a step too large for the problem.
    _, small = solve("genalpha:rho_inf=1", "pendulum", 0.001, 20.0)
    assert small.status == "failed" and small.fail_time < 20.0
    # The same setting with damping, and the index-2 form without it, are fine.
    for spec in ("genalpha:rho_inf=0.8", "genalpha-ggl:rho_inf=1"):
        _, good = solve(spec, "pendulum", 0.01, 100.0)
        assert good.status == "ok" and np.max(good.windows["vel"]) < 1e-2, spec


@pytest.mark.parametrize("key", FORMS)
def test_newton_converges_at_tiny_steps(key):
    # Unscaled, the index-3 iteration matrix would have entries of size 1/h^2 = 1e10 next
    # to ones; scaled, it stays well conditioned and Newton converges as at large steps.
    _, traj = solve(key, "pendulum", 1e-5, 0.02)
    assert traj.status == "ok", traj.message
    # From a warm start 1e-5 s old, one or two iterations per step (1.2 and 1.3 on
    # average, measured).
    assert traj.counts["n_newton"] <= 3 * traj.counts["n_steps"]
    assert np.max(traj.windows["pos"]) <= 1e-13


@pytest.mark.slow
@pytest.mark.parametrize("key", FORMS)
def test_iteration_matrix_conditioning_does_not_grow_as_h_shrinks(key):
    case = base_case("sps-receiver")
    mech, n, m = case.mech, case.mech.n, case.mech.m
    method = integrators.make(key)
    c = Coefficients.from_rho_inf(method.rho_inf)
    state = method.start(mech, mech.schur("dense"), jnp.asarray(case.q0), jnp.asarray(case.v0),
                         jnp.float64(0.0))
    scaled, unscaled = [], []
    for h in (1e-2, 1e-5):
        residual, z0, _ = method.equations(mech, state, 0.0, h)
        # The unknowns and the rows are blocks; the matrix is over them flattened.
        x0, unravel = ravel_pytree(z0)
        J = np.asarray(jax.jacfwd(lambda x: ravel_pytree(residual(unravel(x)))[0])(x0))
        # The matrix the dense path factorises: the rows of the equations of motion (and
        # of the velocity constraint) divided back by velocity_scale (GeneralizedAlpha.step).
        w = velocity_scale(c, h)
        J = J / np.r_[np.full(n, w), np.ones(m), np.full(len(J) - n - m, w)][:, None]
        scaled.append(np.linalg.cond(J))
        # The same matrix for the unknowns (a_{n+1}, lambda_{n+1}, mu) and the equations
        # as written, without the scalings.
        rows = np.r_[np.full(n, c.beta * h * h), np.ones(m), np.full(len(J) - n - m,
                                                                      c.beta * h / c.gamma)]
        cols = np.r_[np.full(n + m, c.beta * h * h), np.ones(len(J) - n - m)]
        unscaled.append(np.linalg.cond(J / rows[:, None] * cols[None, :]))
    # Measured: 167 (index 3) and 168 (index 2) at both steps, scaled; unscaled, the
    # condition number grows with 1/h (index 2) or 1/h^2 (index 3), a factor of 1e3 or
    # 1e6 here.
    assert scaled[1] < 1.01 * scaled[0], scaled
    assert unscaled[1] > 1e2 * unscaled[0], unscaled


def structured_steps(key, problem, h, steps):
    """``steps`` steps of ``key`` on ``problem``'s structured path: the final state and the
    Newton iterations of each step."""
    case = base_case(problem)
    mech, method = case.mech, integrators.make(key, h=h)
    schur = method.linear_algebra(mech)
    assert schur.name != "dense"
    state = method.start(mech, schur, jnp.asarray(case.q0), jnp.asarray(case.v0),
                         jnp.float64(0.0))
    step = jax.jit(lambda state, t: method.step(mech, schur, state, t, h))
    iterations = []
    for k in range(steps):
        state, code, _, counts = step(state, k * h)
        assert int(code) == 0
        iterations.append(int(counts["n_newton"]))
    return state, np.array(iterations)


# Two compilations of the step per form.
@pytest.mark.slow
@pytest.mark.parametrize("key", FORMS)
def test_anderson_mixing_cuts_simplified_newton_where_the_chain_is_stiff(key, monkeypatch):
    # chain:N=16 at h = 0.01 (h N as in the scaling benchmark's chain:N=16384 at 1e-5):
    # the geometric stiffness of the links' tension that simplified Newton's matrix leaves
    # out is a fifth of c M there, and each plain correction leaves about that fraction of
    # the error: 14 to 17 corrections per step in the first ten steps, measured, and 11 to
    # 13 with the mixing. Both end at the same discrete solution: the stop is the same.
    mixed_state, mixed = structured_steps(key, "chain:N=16", 0.01, 10)
    monkeypatch.setattr(integrators.genalpha, "newton",
                        lambda *args, **kw: newton(*args, **{**kw, "anderson": False}))
    plain_state, plain = structured_steps(key, "chain:N=16", 0.01, 10)
    assert mixed.sum() <= 0.85 * plain.sum(), (mixed, plain)
    assert np.max(np.abs(mixed_state.q - plain_state.q)) <= 1e-14
    # v to what an ulp of q leaves it (gamma / (beta h) eps |q| = 4e-14), with a margin.
    assert np.max(np.abs(mixed_state.v - plain_state.v)) <= 1e-12


@pytest.mark.parametrize("bad", ["1.5", "-0.1", "nan"])
def test_rho_inf_outside_the_unit_interval_is_refused(bad):
    with pytest.raises(SpecError) as err:
        integrators.make(f"genalpha:rho_inf={bad}")
    message = str(err.value)
    assert "rho_inf" in message and "[0, 1]" in message and "\n" not in message


def test_a_diverging_index3_run_is_recorded_as_failed():
    # rho_inf = 0.9 at h = 0.1 on sps-receiver: the weakly damped constraint modes grow
    # until Newton fails at step 38 (measured); the record keeps what was computed.
    row = execute(RunSpec("sps-receiver", "genalpha:rho_inf=0.9", h=0.1, t_end=50.0),
                  repeats=1).row
    assert row["status"] == "failed" and "Newton" in row["message"]
    assert row["n_steps"] == row["fail_step"] - 1 and row["fail_step"] > 1
    assert row["max_pos_residual"] is not None


# Tolerance of the comparison with tests/independent.py: the two sides solve the same
# equations with different unknowns (unscaled q_{n+1} and lambda there, increments here)
# and different linear algebra, so they differ by round-off amplified along the run, as
# for RATTLE and Lobatto IIIA-IIIB (tests/test_independent.py, which explains 1e-10):
# 2e-12 was measured here. A wrong coefficient or equation moves the final state by the
# local error, 1e-6 or more at these steps.
TOL = 1e-10


@pytest.mark.parametrize("problem, h, t_end", [("pendulum", 0.01, 10.0),
                                               ("sps-receiver", 0.05, 50.0)])
@pytest.mark.parametrize("key", FORMS)
def test_agrees_with_an_independent_implementation(key, problem, h, t_end):
    # rho_inf = 0.5 keeps both forms stable here (near an instability, round-off is
    # amplified without bound and the comparison would say nothing).
    q, v = ind.genalpha_integrate(problem, h, t_end, rho=0.5, ggl=key.endswith("ggl"))
    _, traj = solve(f"{key}:rho_inf=0.5", problem, h, t_end)
    assert traj.status == "ok"
    assert np.max(np.abs(traj.q_final - q)) <= TOL
    assert np.max(np.abs(traj.v_final - v)) <= TOL


def test_independent_coefficients_match():
    for rho in (0.0, 0.5, 0.8, 1.0):
        assert np.allclose(Coefficients.from_rho_inf(rho), ind.genalpha_coefficients(rho),
                           rtol=0, atol=1e-15)
