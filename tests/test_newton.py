"""Newton's stopping rule, and on the structured path: where simplified Newton stalls, it is
not accepted."""

import contextlib
from collections import OrderedDict

import jax.numpy as jnp
import numpy as np
import pytest

import integrators
import integrators.loop
import problems
from integrators.base import Grid
import integrators.newton as newton_module
from integrators.newton import (AT_FLOOR, EPS, FROZEN_MIN, deferred_fallback, max_norm,
                                newton)
from linalg.dense import lu_factor, lu_solve, reused_factor, reused_solve
from problems.ensemble import draw


def test_newton_stops_where_quadratic_convergence_reaches_the_round_off_floor():
    # z^2 = 2 from 1.5: residuals 0.25, 6.9e-3, 6.0e-6, 4.5e-12, then 4.4e-16, within twice
    # the floor eps (1 + |J| |z|) = 5 eps after a contraction of 1e-4. Waiting for the
    # residual to stop halving took a fifth iteration that changed nothing.
    sol = newton(lambda z: z * z - 2.0, jnp.array([1.5]), 1e-16, 50)
    assert bool(sol.converged) and int(sol.iterations) == 4
    assert float(sol.residual) <= AT_FLOOR * EPS * 5.0
    assert abs(float(sol.z[0]) - np.sqrt(2.0)) <= EPS * np.sqrt(2.0)


def test_newton_does_not_stop_at_the_floor_while_contracting_slowly():
    # A double root, (z - 1)^2 from 2: Newton converges linearly, each iteration
    # contracting the residual by 1/4. Its residual 2.2e-16 after 26 iterations is within
    # twice the floor eps (1 + |J| |z|), but a contraction of 1/4 is not quadratic
    # convergence, so the iteration goes on, here to the tolerance.
    sol = newton(lambda z: (z - 1.0) ** 2, jnp.array([2.0]), 1e-16, 50)
    assert bool(sol.converged) and int(sol.iterations) == 27
    assert float(sol.residual) <= 1e-16


def test_simplified_newton_does_not_wait_at_the_floor():
    # lobatto3ab3 on the pendulum takes the structured path: simplified Newton, whose
    # correction of the multipliers (rows scaled by 1/h^2) never reaches round-off, so it
    # ends by its residual. Waiting for a residual at the floor to stop halving (it halves
    # by chance, 2.2e-16 to 1.1e-16) cost 5.44 to 5.67 iterations per step on these 16
    # lanes and 5.53 for one trajectory; ending at the floor after a residual within the
    # window, 4.80 to 4.86 and 4.81, with the constraints held as tightly.
    case = problems.make("pendulum").with_t_end(2.0)
    q0s, v0s = draw(case, 16, seed=0)
    method = integrators.make("lobatto3ab3", h=1e-2)
    grid = Grid(case.t0, case.t_end)
    for traj in [*method.prepare_ensemble(case, grid, q0s, v0s)(), method.prepare(case, grid)()]:
        assert str(traj.status) == "ok", traj.message
        assert traj.linear_solver != "dense"
        assert traj.counts["n_newton"] <= 5.0 * traj.counts["n_steps"]
        assert np.max(traj.windows["pos"]) <= 1e-14


def test_a_reused_factorisation_solves_as_a_fresh_one_full_rank_or_deficient():
    rng = np.random.default_rng(0)
    A = rng.standard_normal((20, 20))
    deficient = A.copy()
    deficient[7] = deficient[3]  # a redundant equation
    for M in (A, deficient):
        b = M @ rng.standard_normal(20)  # consistent
        F = reused_factor(jnp.asarray(M))
        assert bool(F.lu.deficient) == (M is deficient)
        x = np.asarray(reused_solve(F, jnp.asarray(b)))
        np.testing.assert_allclose(x, np.asarray(lu_solve(lu_factor(jnp.asarray(M)),
                                                          jnp.asarray(b))), rtol=0, atol=1e-12)
        np.testing.assert_allclose(M @ x, b, rtol=0, atol=1e-12)


@pytest.mark.parametrize("redundant", [False, True])
def test_dense_newton_on_many_unknowns_reuses_its_jacobian_and_reaches_the_same_root(
        redundant, monkeypatch):
    # 30 unknowns: Newton without an approximate Jacobian first iterates with the one at
    # the start, factorised once; it contracts linearly (more corrections than the exact
    # Newton's quadratic ones) to the same root. A redundant equation (row 7 repeats row
    # 3) makes every Jacobian rank deficient: the basic solutions of both agree.
    rng = np.random.default_rng(1)
    A = jnp.asarray(np.eye(30) * 4 + rng.standard_normal((30, 30)) * 0.3)
    b = jnp.asarray(rng.standard_normal(30))

    def residual(z):
        r = A @ z + 0.5 * jnp.sin(z) - b
        return r.at[7].set(r[3]) if redundant else r

    z0 = jnp.zeros(30)
    assert z0.size >= FROZEN_MIN
    frozen = newton(residual, z0, 1e-16, 100)
    monkeypatch.setattr(newton_module, "FROZEN_MIN", 10 ** 9)
    exact = newton(residual, z0, 1e-16, 100)
    assert bool(frozen.converged) and bool(exact.converged)
    assert int(frozen.iterations) > int(exact.iterations)  # linear, not quadratic
    assert float(max_norm(residual(frozen.z))) <= 1e-14
    np.testing.assert_allclose(np.asarray(frozen.z), np.asarray(exact.z), rtol=0, atol=1e-13)


def test_anderson_mixing_reaches_the_same_root_in_fewer_simplified_iterations():
    # (I + K) z + sin(z) / 100 = b with the frozen matrix I: I - J_0^{-1} J has its
    # eigenvalues spread over [-0.26, 0.01], so simplified Newton contracts slowly (23
    # corrections from z = b, measured) and mixing each correction with the previous one
    # removes much of that (17). The fallback is left out, so that each count is simplified
    # Newton's own.
    n = 40
    rng = np.random.default_rng(0)
    Q = np.linalg.qr(rng.standard_normal((n, n)))[0]
    K = jnp.asarray(Q @ np.diag(np.linspace(0.0, 0.25, n)) @ Q.T)
    b = jnp.asarray(rng.standard_normal(n))

    def residual(z):
        return (z[0] + K @ z[0] + 0.01 * jnp.sin(z[0]) - b,)

    def linear(z, r):
        return (-r[0],), 2.0 * max_norm(z)

    sols = []
    for anderson in (False, True):
        with deferred_fallback():
            sols.append(newton(residual, (b,), 1e-16, 60, linear, anderson=anderson))
    plain, mixed = sols
    assert bool(plain.converged) and bool(mixed.converged)
    assert int(mixed.iterations) <= 0.8 * int(plain.iterations), (plain.iterations,
                                                                  mixed.iterations)
    assert float(mixed.residual) <= 8 * EPS * (1 + 2 * float(max_norm(mixed.z)))
    assert np.max(np.abs(mixed.z[0] - plain.z[0])) <= 4 * EPS * np.max(np.abs(plain.z[0]))


# Verification runs of large mechanisms (10 to 20 s each, most of it compilation).
@pytest.mark.slow
def test_structured_rattle_crosses_a_singular_configuration_on_its_branch():
    # four-bar:N=1024 on the kkt path, over its first singular configuration (cranks
    # horizontal at t = 0.722). The tips sit at x_i = i + cos(phi), so g's round-off is
    # about eps N = 2.3e-13, above the old stall window (1e3 eps): with the default
    # tolerance the second step failed. Past that, simplified Newton with the nearly
    # singular S_0 at the crossing found a root off the parallelogram branch, where the
    # cranks stay horizontal and the error is O(1e-2) within a few steps. Now every step
    # converges to the round-off floor (measured max |g| 4.5e-13; the bar is the one
    # four-bar:N=4096 must meet) and the state stays on the exact branch to the method's
    # O(h^2) error (measured 8.9e-6 at t = 0.8; the bar is the error of h = 1e-3 over the
    # whole 20 s at N = 40, 1.15e-4). About 20 s, most of it compilation.
    case = problems.make("four-bar:N=1024").with_t_end(0.8)
    traj = integrators.make("rattle", h=1e-3, linear_solver="kkt").prepare(
        case, Grid(case.t0, case.t_end))()
    assert str(traj.status) == "ok", traj.message
    assert np.max(traj.windows["pos"]) <= 1e-10
    q_ref, v_ref = case.reference.solution(traj.t_final)
    error = max(np.max(np.abs(traj.q_final - q_ref)), np.max(np.abs(traj.v_final - v_ref)))
    assert error <= 1.15e-4


@pytest.mark.slow
def test_structured_generalized_alpha_accepts_the_round_off_of_large_coordinates():
    # genalpha's unknowns are scaled (beta h^2 a, beta h^2 lam) and small, but its
    # constraint rows are computed from q: four-bar:N=1024's tips sit near x = 1024, where
    # g's round-off is about eps N = 2.3e-13. With that floor taken from |z| alone the
    # first step stalled at 2.3e-13 and failed (as rigid-chain:N=1024 did in the scaling
    # benchmark); with Mechanics.rounding in the floor it converges. About 10 s.
    case = problems.make("four-bar:N=1024").with_t_end(0.01)
    for method in ("genalpha-ggl", "genalpha"):
        traj = integrators.make(method, h=1e-3, linear_solver="kkt").prepare(
            case, Grid(case.t0, case.t_end))()
        assert str(traj.status) == "ok", (method, traj.message)
        assert traj.counts["n_steps"] == 10
        assert np.max(traj.windows["pos"]) <= 1e-10


@pytest.mark.parametrize("key, limit", [("rattle", 6), ("lobatto3ab3:linear_solver=dense", 4)])
def test_the_loop_with_the_fallback_takes_over_at_the_step_that_failed_without_it(
        key, limit, monkeypatch):
    # RATTLE on chain:N=8 needs about 5.7 simplified iterations per step at h = 0.01; with a
    # limit of 6 some steps leave simplified Newton unconverged, and so do lobatto3ab3's
    # stages on the dense path (more than FROZEN_MIN unknowns: the frozen Jacobian) with 4.
    # The loop compiled without the fallback stops there, and the loop with it (compiled
    # then) takes that step again and goes on: the run ends as one whose loop held the
    # fallback from the start.
    case = problems.make("chain:N=8").with_t_end(1.0)
    method = integrators.make(key, h=1e-2, newton_max_iter=limit)
    grid = Grid(case.t0, case.t_end, n_windows=10, n_samples=11)
    monkeypatch.setattr(integrators.loop, "_LOOPS", OrderedDict())
    solve = method.prepare(case, grid)
    traj = solve()
    assert solve.late_setup_s > 0  # the fallback's loop was compiled in the solve
    monkeypatch.setattr(integrators.loop, "_LOOPS", OrderedDict())
    monkeypatch.setattr(integrators.loop, "deferred_fallback", contextlib.nullcontext)
    whole = method.prepare(case, grid)
    ref = whole()
    assert whole.late_setup_s == 0
    for run in (traj, ref):
        assert str(run.status) == "ok", run.message
        assert run.counts["n_steps"] == 100
    # The work counted is the method's: the attempt without the fallback is not counted.
    assert traj.counts == ref.counts
    assert np.allclose(traj.q_final, ref.q_final, rtol=0, atol=1e-13)
    assert np.allclose(traj.samples["q"], ref.samples["q"], rtol=0, atol=1e-13)
    assert set(traj.windows) == set(ref.windows)
    for name in traj.windows:
        assert np.allclose(traj.windows[name], ref.windows[name], rtol=0, atol=1e-13), name


def test_ensemble_lanes_that_fail_without_the_fallback_take_their_step_again_with_it(
        monkeypatch):
    # The same for an ensemble: its lanes fail without the fallback at different steps
    # (five of these six with a limit of 8 iterations), and those lanes run again with it.
    # Every lane ends as in an ensemble whose loop held the fallback from the start.
    case = problems.make("chain:N=8").with_t_end(1.0)
    q0s, v0s = draw(case, 6, seed=1)
    method = integrators.make("rattle", h=1e-2, newton_max_iter=8)
    grid = Grid(case.t0, case.t_end, n_windows=10, n_samples=11)
    monkeypatch.setattr(integrators.loop, "_LOOPS", OrderedDict())
    solve = method.prepare_ensemble(case, grid, q0s, v0s)
    lanes = solve()
    assert solve.late_setup_s > 0
    monkeypatch.setattr(integrators.loop, "_LOOPS", OrderedDict())
    monkeypatch.setattr(integrators.loop, "deferred_fallback", contextlib.nullcontext)
    whole = method.prepare_ensemble(case, grid, q0s, v0s)
    refs = whole()
    assert whole.late_setup_s == 0
    for lane, ref in zip(lanes, refs):
        assert str(lane.status) == str(ref.status) == "ok", lane.message
        assert lane.counts == ref.counts
        assert np.allclose(lane.q_final, ref.q_final, rtol=0, atol=1e-13)
        assert np.allclose(lane.samples["q"], ref.samples["q"], rtol=0, atol=1e-13)
        for name in ref.windows:
            assert np.allclose(lane.windows[name], ref.windows[name], rtol=0, atol=1e-13)


def test_a_run_that_simplified_newton_solves_never_compiles_the_fallback(monkeypatch):
    monkeypatch.setattr(integrators.loop, "_LOOPS", OrderedDict())
    case = problems.make("chain:N=8").with_t_end(0.2)
    solve = integrators.make("rattle", h=1e-2).prepare(case, Grid(case.t0, case.t_end))
    traj = solve()
    assert str(traj.status) == "ok" and traj.linear_solver == "banded"
    assert solve.late_setup_s == 0
    assert "bicgstab" not in solve.compiled.as_text()


@pytest.mark.parametrize("key, problem, bound", [
    ("rattle", "chain:N=4", 1e-13), ("lobatto3ab3", "chain:N=4", 1e-13),
    ("genalpha", "chain:N=4", 1e-13), ("genalpha-ggl", "chain:N=4", 1e-13),
    ("hht", "chain:N=4", 1e-13), ("genalpha", "pendulum", 1e-14), ("hht", "pendulum", 1e-14)])
def test_default_stop_reaches_the_discrete_solution_at_small_h(key, problem, bound):
    # Against the same run iterated to round-off (a tolerance no residual meets, so only
    # the round-off exits end Newton), 5000 steps of h = 1e-5: chain:N=4 is the structured
    # path (simplified Newton), the pendulum the dense one. For the generalized-alpha
    # members a stop on a residual in the units of q (equations of motion times beta h^2)
    # takes one iteration per step here and ends 1.9e-12 to 4.3e-11 away on the chain and
    # 9e-14 on the pendulum; in the units of v, 2e-15 to 4e-15 and 1.5e-16. The positions
    # are compared: v is determined only to about eps |q| gamma / (beta h), 4e-11 here (a
    # correction below an ulp of q moves v by that much).
    case = problems.make(problem).with_t_end(0.05)
    grid = Grid(case.t0, case.t_end)
    runs = [integrators.make(key, h=1e-5, **opts).prepare(case, grid)()
            for opts in ({}, {"newton_tol": 1e-24})]
    assert all(run.status.name == "OK" for run in runs)
    assert np.max(np.abs(runs[0].q_final - runs[1].q_final)) <= bound
