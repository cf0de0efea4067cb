"""Radau IIA (radau5, radau5-ggl): the tableau and its transformed Newton system, the order
of the collocation method at fixed steps, the adaptive runs against exact solutions and
references, work counts, reuse of the compiled
loop, and failures as data."""

from __future__ import annotations

import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import integrators
import problems
from benchmarks.metrics import reference_error, summarize
from helpers import solve
from integrators import Grid, radau
from integrators.base import Failure, Status
from integrators.ida import consistent_values
from integrators.newton import newton
from linalg.dense import lu_factor, lu_solve
from problems import System, make_case
from rheonomic import spinning_rod

PENDULUM = problems.make("pendulum").with_t_end(10.0)


def run(key, case, **options):
    traj = integrators.make(key, **options).prepare(case, Grid(case.t0, case.t_end))()
    return traj, summarize(case, traj)


def test_tableau_is_radau_iia():
    tab = radau.radau_iia()
    s6 = math.sqrt(6.0)
    # Published closed forms (Hairer and Wanner 1996, IV.5 and IV.8), to a few ulps of
    # the largest coefficients (the nodes come from a polynomial's roots).
    np.testing.assert_allclose(tab.c, [(4 - s6) / 10, (4 + s6) / 10, 1.0], rtol=1e-14)
    np.testing.assert_allclose(tab.A[-1], [(16 - s6) / 36, (16 + s6) / 36, 1 / 9], rtol=1e-14)
    np.testing.assert_allclose(tab.e * tab.gamma,
                               [-(13 + 7 * s6) / 3, (-13 + 7 * s6) / 3, -1 / 3], rtol=1e-13)
    # gamma = 3.6378..., alpha +- i beta the complex pair (products and sums of the
    # eigenvalues of A^-1 are its determinant and trace).
    assert tab.gamma * (tab.alpha ** 2 + tab.beta ** 2) == pytest.approx(
        np.linalg.det(tab.A_inv), rel=1e-13)
    assert tab.gamma + 2 * tab.alpha == pytest.approx(np.trace(tab.A_inv), rel=1e-13)


@pytest.mark.parametrize("N, newton", [(5, True), (20, True), (20, False)])
def test_transformed_newton_system_is_the_kronecker_system(N, newton):
    """One real and one complex solve give the correction of the full 3N x 3N system
    ``(A^-1/h (x) B + I (x) J) dZ = -R``: the block-diagonalisation is exact, with the
    unrolled factorisation (N = 5) and with LAPACK's (N = 20, above INLINE_MAX), whose
    factors are solved by unrolled substitutions in Newton's loop and by LAPACK's
    triangular solves outside it."""
    tab = radau.radau_iia()
    rng = np.random.default_rng(3)
    h = 0.03
    J = rng.standard_normal((N, N))
    B = np.diag(np.r_[1.0, 1.0, 2.0, rng.uniform(1, 2, N - 5), 0.0, 0.0])
    R = rng.standard_normal((3, N))

    @jax.jit  # compiled once: eagerly every operation would compile on its own
    def transformed(J, B, R):
        E1, E2 = radau._factor(J, B, h, tab)
        rho = -(tab.T_inv @ R)
        d12 = radau._solve(E2, rho[1] + 1j * rho[2], newton)
        return tab.T @ jnp.stack([radau._solve(E1, rho[0], newton), d12.real, d12.imag])

    dZ = np.asarray(transformed(J, B, R))
    full = np.kron(tab.A_inv / h, B) + np.kron(np.eye(3), J)
    # A well-conditioned random system: agreement to round-off times its condition.
    np.testing.assert_allclose(dZ.ravel(), np.linalg.solve(full, -R.ravel()), rtol=0,
                               atol=1e-12 * np.max(np.abs(dZ)))


@pytest.mark.parametrize("dtype", [np.float64, np.complex128])
def test_inline_lu_solves_as_lapack_does(dtype):
    """The unrolled LU of small stage systems against LAPACK's: a system whose rows span
    sixteen orders of magnitude (equilibrated away) solved to round-off, and a rank-deficient
    consistent one given the same basic solution (the one rank policy)."""
    rng = np.random.default_rng(5)
    N = 6
    A = rng.standard_normal((N, N)) * np.logspace(-8, 8, N)[:, None]
    b = rng.standard_normal(N)
    if dtype is np.complex128:
        A = A + 1j * rng.standard_normal((N, N)) * np.logspace(-8, 8, N)[:, None]
        b = b + 1j * rng.standard_normal(N)
    deficient = A.copy()
    deficient[3] = 2.0 * deficient[1]
    b_def = deficient @ rng.standard_normal(N)

    @jax.jit
    def both(A, b):
        return radau.inline_lu_solve(radau.inline_lu_factor(A), b), lu_solve(lu_factor(A), b)

    x, _ = both(A, b)
    np.testing.assert_allclose(np.asarray(x), np.linalg.solve(A, b), rtol=1e-10)
    x, x_lapack = both(deficient, b_def)
    assert bool(radau.inline_lu_factor(deficient).deficient)
    np.testing.assert_allclose(np.asarray(x), np.asarray(x_lapack), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(deficient @ np.asarray(x), b_def, rtol=0,
                               atol=1e-9 * np.max(np.abs(b_def)))


@pytest.mark.parametrize("newton", [True, False])
@pytest.mark.parametrize("dtype", [np.float64, np.complex128])
def test_lapack_factors_solve_as_lu_solve_does(dtype, newton):
    """Above INLINE_MAX the stage systems are LAPACK's LU with its permutation kept, solved
    by unrolled substitutions in Newton's loop or LAPACK's triangular solves outside it: both
    give :func:`linalg.dense.lu_solve`'s solution, and its basic solution where the system
    is rank deficient (the one rank policy)."""
    rng = np.random.default_rng(7)
    N = radau.INLINE_MAX + 8
    A = rng.standard_normal((N, N)) * np.logspace(-8, 8, N)[:, None]
    if dtype is np.complex128:
        A = A + 1j * rng.standard_normal((N, N)) * np.logspace(-8, 8, N)[:, None]
    deficient = A.copy()
    deficient[3] = 2.0 * deficient[1]
    b = A @ rng.standard_normal(N)
    b_def = deficient @ rng.standard_normal(N)

    @jax.jit
    def both(A, b):
        F = radau.lapack_lu_factor(A)
        return radau._solve(F, b, newton), lu_solve(lu_factor(A), b), F.deficient

    x, x_lapack, flagged = both(A, b)
    assert not bool(flagged)
    np.testing.assert_allclose(np.asarray(x), np.asarray(x_lapack), rtol=1e-9, atol=0)
    x, x_lapack, flagged = both(deficient, b_def)
    assert bool(flagged)
    np.testing.assert_allclose(np.asarray(x), np.asarray(x_lapack), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(deficient @ np.asarray(x), b_def, rtol=0,
                               atol=1e-9 * np.max(np.abs(b_def)))


@pytest.mark.parametrize("formulation, orders", [("index3", (5, 3)), ("ggl", (5, 5))])
def test_order_at_fixed_steps(formulation, orders):
    """The stage equations the loop solves, solved to round-off at fixed steps over 1 s of
    the pendulum: halving h divides the position error by 2^5; the velocity error by 2^3
    on the index-3 form (Hairer, Lubich and Roche's order s for index-2 components) and
    2^5 on the stabilised form. Steps 0.05 and 0.025 keep both errors far above round-off
    (measured 3.5e-6 and 1.1e-7 in q on the index-3 form)."""
    mech = PENDULUM.mech
    form = radau.FORMULATIONS[formulation]
    R = form.residual(mech)
    y0, _ = consistent_values(mech, form.multiplier_blocks, 0.0, PENDULUM.q0, PENDULUM.v0)

    @partial(jax.jit, static_argnums=1)
    def march(h, steps):
        def step(y, k):
            sol = newton(lambda z: radau.stage_residual(R, k * h, y, h, z.reshape(3, -1))
                         .ravel(), jnp.zeros(3 * y.size), 1e-16, 20)
            return y + sol.z.reshape(3, -1)[2], sol.converged
        return jax.lax.scan(step, jnp.asarray(y0), jnp.arange(steps))

    q_ref, v_ref = PENDULUM.reference.solution(1.0)
    n, errors = mech.n, []
    for h in (0.05, 0.025):
        y, converged = march(h, round(1.0 / h))
        assert bool(jnp.all(converged))
        errors.append((np.max(np.abs(y[:n] - q_ref)), np.max(np.abs(y[n:2 * n] - v_ref))))
    for (coarse, fine), order in zip(zip(*errors), orders):
        assert abs(math.log2(coarse / fine) - order) < 0.3, (errors, order)


def test_index3_pendulum_bars():
    """The pendulum A01 over 10 s: final error at most 10 rtol and
    falling with it (measured 1.7, 0.6 and 0.18 rtol), and |g| within 1e-12 at every
    accepted step (every accepted step is measured into the window maxima; measured at
    most 7e-14: Newton iterates the constraint to round-off)."""
    errors = []
    for rtol in (1e-6, 1e-8, 1e-10):
        traj, m = run("radau5", PENDULUM, rtol=rtol)
        assert traj.status == Status.OK, traj.message
        assert traj.sampling.startswith("every internal step")
        errors.append(m["final_state_error"])
        assert m["final_state_error"] <= 10 * rtol, (rtol, m["final_state_error"])
        assert m["max_pos_residual"] <= 1e-12, (rtol, m["max_pos_residual"])
        # The velocity level is not enforced by the index-3 form: it drifts.
        assert m["max_vel_residual"] > 1e-10
    assert errors[0] > errors[1] > errors[2], errors


def test_ggl_pendulum_holds_both_levels():
    traj, m = run("radau5-ggl", PENDULUM, rtol=1e-8)
    assert traj.status == Status.OK, traj.message
    # Measured 3.0e-9; both levels to round-off (measured 4e-16 and 2e-14).
    assert m["final_state_error"] <= 10 * 1e-8
    assert m["max_pos_residual"] <= 1e-12 and m["max_vel_residual"] <= 1e-12


def test_work_counts_and_reuse_of_the_compiled_loop():
    """The counts add up as the docstring states, and another tolerance or horizon of the
    same system and options runs the same compiled loop."""
    short = PENDULUM.with_t_end(2.0)
    traj, _ = run("radau5", short, rtol=1e-6)
    c, lu = traj.counts, traj.extra["n_lu"]
    attempts = c["n_steps"] + c["n_rejected"]
    assert c["n_steps"] > 0 and c["n_newton"] >= attempts
    # Three residuals per iteration, one per accepted step, one at t0, at most one more
    # per attempt for the stiff filtering.
    assert 3 * c["n_newton"] + c["n_steps"] + 1 <= c["n_f_evals"] \
        <= 3 * c["n_newton"] + c["n_steps"] + 1 + attempts
    # Two solves per iteration and one per converged error estimate (plus filterings).
    assert 2 * c["n_newton"] < c["n_lin_solves"] <= 2 * c["n_newton"] + 2 * attempts
    # One Jacobian at t0, then at most one per attempt; a factorisation with each.
    assert 1 <= c["n_jac_evals"] <= attempts + 1 and c["n_jac_evals"] <= lu <= attempts + 1
    loops = dict(radau._CHUNKS)
    run("radau5", PENDULUM.with_t_end(3.0), rtol=1e-9, atol=1e-11)
    assert dict(radau._CHUNKS) == loops


def test_rheonomic_constraint_and_exact_solution():
    """The spinning rod (g_t, g_tt non-zero) against r = cosh(omega t) over 3 s."""
    traj, m = run("radau5", spinning_rod(), rtol=1e-8)
    assert traj.status == Status.OK, traj.message
    # Positions grow to cosh(3) = 10: a relative error of the order of rtol (measured
    # 2e-8).
    assert m["final_state_error"] <= 1e-6, m["final_state_error"]
    assert m["max_pos_residual"] <= 1e-12


def test_failures_are_data():
    traj, _ = run("radau5", PENDULUM, rtol=1e-8, max_steps=5)
    assert traj.status == Status.FAILED and traj.counts["n_steps"] == 5
    assert traj.message.startswith("max_steps = 5 accepted steps were reached")


@pytest.mark.slow
def test_non_finite_forces_fail_with_their_reason():
    """Forces that turn non-finite at t = 0.5: every retry fails until the step
    underflows, and the run says why."""
    system = System(n=2, m=1, mass=np.ones(2), potential=lambda q: 9.81 * q[1],
                    forces=lambda t, q, v: jnp.where(t > 0.5, jnp.nan, 0.0) * q,
                    constraints=lambda q, t: jnp.array([q @ q - 1.0]))
    case = make_case("nan-after-half", system, PENDULUM.q0, PENDULUM.v0, (0.0, 1.0), {},
                     energy_scale=1.0)
    traj, _ = run("radau5", case, rtol=1e-6)
    assert traj.status == Status.FAILED
    assert traj.message.startswith(Failure.NON_FINITE.message), traj.message
    assert 0.49 < traj.t_final <= 0.5 and np.all(np.isfinite(traj.q_final))


def test_options_are_checked():
    with pytest.raises(Exception, match="formulation"):
        integrators.make("radau5:formulation=index1")
    with pytest.raises(Exception, match="linear_solver"):
        integrators.make("radau5:linear_solver=sparse")
    integ = integrators.make("radau5-ggl", rtol=1e-7)
    assert integ.atol == 1e-7 and integ.enforces == ("position", "velocity")
    assert integrators.make("radau5").enforces == ("position",)


@pytest.mark.slow
def test_redundant_constraints_are_refused():
    traj, _ = run("radau5", problems.make("bricard"), rtol=1e-6)
    assert traj.status == Status.FAILED and traj.counts["n_steps"] == 0
    assert traj.message.startswith("G(q0) has rank 23 < m = 24"), traj.message


@pytest.mark.slow
def test_andrews_reaches_the_reference():
    """Andrews' mechanism at rtol 1e-10: both forms reach the reference within its floor
    (2e-9; measured 1.43e-9 stabilised, 1.96e-9 index 3). The index-3 form needs Newton
    past RADAU5's test (radau.NEWTON_TIGHT): without it, at the same 911 steps, the
    velocities' iteration error, which the index scaling lets be O(1/h), left 2.0e-8."""
    case, traj = solve("andrews", "radau5-ggl", rtol=1e-10)
    err, _ = reference_error(case, traj)
    assert err <= case.reference.floor, err
    case, traj = solve("andrews", "radau5", rtol=1e-10)
    err, _ = reference_error(case, traj)
    assert err <= case.reference.floor, err


@pytest.mark.slow
def test_car_axis_is_ok():
    case, traj = solve("car-axis", "radau5", rtol=1e-8)
    err, _ = reference_error(case, traj)
    # Measured 4.7e-7 at 1061 steps; the constraints (rheonomic) at round-off.
    assert err <= 1e-5
    assert np.max(traj.windows["pos"]) <= 1e-12


@pytest.mark.slow
def test_flyball_governor_reaches_the_reference_s():
    case, traj = solve("flyball-governor", "radau5", rtol=1e-8)
    err, _ = reference_error(case, traj)
    # The benchmark's bar: s(10) within 1e-6 at rtol 1e-8. Measured 2.1e-9 in 801 steps
    # (the stiff springs and dampers cost an L-stable method nothing).
    assert err <= 1e-6
    assert np.max(traj.windows["inv:energy_balance"]) <= 1e-6 * case.energy_scale


@pytest.mark.slow
@pytest.mark.parametrize("spec, kind, key", [
    ("chain:N=12", "banded", "radau5-ggl"), ("rigid-chain:N=3", "superlu", "radau5")])
def test_structured_stage_systems_agree_with_the_dense_ones(spec, kind, key):
    """The structured path (one factorisation of S = G M^-1 G^T serving the real and the
    complex stage system) against the dense LU of the exact iteration matrices, at rtol
    1e-9 over 0.5 s: the final positions agree to the tolerance's scale (measured 4.5e-13
    and 3.8e-13, and 1.3e-12 for radau5 on the banded chain; the rigid chain's mass is
    configuration-dependent and whitened blockwise), and the run records the solver that
    ran. Both formulations and both solvers: SchurStages serves every pair of them."""
    case = problems.make(spec).with_t_end(0.5)
    runs = {}
    for solver in ("dense", kind):
        traj = integrators.make(key, rtol=1e-9, atol=1e-9, linear_solver=solver).prepare(
            case, Grid(case.t0, case.t_end))()
        assert traj.status == Status.OK, traj.message
        assert traj.linear_solver == solver
        runs[solver] = traj.q_final
    assert np.max(np.abs(runs["dense"] - runs[kind])) <= 1e-9


def test_large_systems_take_the_structured_path():
    case = problems.make("chain:N=64").with_t_end(0.01)
    traj = integrators.make("radau5-ggl", rtol=1e-6, atol=1e-6).prepare(
        case, Grid(case.t0, case.t_end))()
    assert traj.status == Status.OK, traj.message
    assert traj.linear_solver == "banded"
    g = case.mech.g(jnp.asarray(traj.q_final), jnp.asarray(traj.t_final))
    assert np.max(np.abs(np.asarray(g))) <= 1e-12
