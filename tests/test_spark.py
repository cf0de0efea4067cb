"""Lobatto IIIA-IIIB (SPARK) and RATTLE: order, agreement, constraints, energy, failure."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import integrators
import problems
from benchmarks.execute import execute
from benchmarks.records import RunSpec
from integrators import Grid
from integrators.newton import deferred_fallback
from linalg.compiled import compile_lifted

SPARK = ["rattle", "lobatto3ab2", "lobatto3ab3", "lobatto3ab4"]


def solve(key, problem, h, t_end, **grid):
    case = problems.make(problem, t_end=t_end)
    traj = integrators.make(key, h=h).prepare(case, Grid(case.t0, t_end, **grid))()
    return case, traj


def position_error(case, traj):
    q_ref, _ = case.reference.solution(traj.t_final)
    return float(np.max(np.abs(traj.q_final - q_ref)))


@pytest.mark.parametrize("key, hs", [
    ("lobatto3ab2", [0.04, 0.02, 0.01, 0.005]),
    ("lobatto3ab3", [0.1, 0.05, 0.025, 0.0125]),
    ("lobatto3ab4", [0.2, 0.1, 0.05, 0.025]),
])
def test_observed_order_is_2s_minus_2(key, hs):
    errors = []
    for h in hs:
        case, traj = solve(key, "pendulum", h, 2.0)
        assert traj.status == "ok", traj.message
        errors.append(position_error(case, traj))
    errors = np.array(errors)
    # Errors near round-off (1e-12 after 2 s of a unit pendulum) carry no order
    # information and are masked; at least three points must remain for the fit.
    keep = errors > 1e-12
    assert keep.sum() >= 3, errors
    slope = np.polyfit(np.log(np.array(hs)[keep]), np.log(errors[keep]), 1)[0]
    nominal = {"lobatto3ab2": 2, "lobatto3ab3": 4, "lobatto3ab4": 6}[key]  # 2s - 2
    # The step sizes are in the asymptotic range, where the fitted slope matches the
    # nominal order to a few tenths.
    assert abs(slope - nominal) < 0.3, (slope, errors)


@pytest.mark.parametrize("problem, h, t_end", [("sps-receiver", 0.05, 50.0), ("pendulum", 0.01, 10.0)])
def test_rattle_equals_lobatto3ab2(problem, h, t_end):
    _, a = solve("rattle", problem, h, t_end)
    _, b = solve("lobatto3ab2", problem, h, t_end)
    # The two solve the same equations with different unknowns; the difference is
    # round-off of order 1e-16 per step, accumulated over at most 1000 steps, each
    # Newton stopping within twice its round-off floor (measured on the receiver: 1.4e-12
    # in v, 2e-13 while Newton iterated until the residual stopped halving).
    assert np.max(np.abs(a.q_final - b.q_final)) <= 1e-12
    assert np.max(np.abs(a.v_final - b.v_final)) <= 4e-12


@pytest.mark.parametrize("key", SPARK)
@pytest.mark.parametrize("problem, h, t_end", [("sps-receiver", 0.05, 50.0), ("pendulum", 0.01, 20.0)])
def test_constraints_hold_to_round_off_at_every_step(key, problem, h, t_end):
    _, traj = solve(key, problem, h, t_end)
    assert traj.status == "ok"
    # g = 0 and G v = 0 are solved to newton_tol = 1e-14 at every step; 1e-13 leaves a
    # decade for the round-off of evaluating g with O(1) coordinates.
    assert np.max(traj.windows["pos"]) <= 1e-13
    assert np.max(traj.windows["vel"]) <= 1e-13


@pytest.mark.parametrize("key", ["rattle", "lobatto3ab3"])
@pytest.mark.parametrize("problem", ["rigid-chain:N=2", "rigid-body", "andrews"])
def test_the_carried_velocity_and_mass_factors_are_those_of_the_carried_state(key, problem):
    # Both methods carry v = H_p(q, p) and the factors of a block-diagonal M(q) from one
    # step to the next rather than compute them again: they must be those of the (q, p)
    # carried with them (a stale v or factor would pass unnoticed by the step itself).
    # Andrews' mechanism is stiff: at h = 1e-3 its simplified Newton needs the exact
    # Jacobian within four steps. Without it (deferred_fallback) the step is a far smaller
    # program, which is all these steps need.
    case = problems.make(problem)
    mech, h = case.mech, 1e-4 if problem == "andrews" else 1e-3
    method = integrators.make(key, h=h)
    schur = method.linear_algebra(mech)
    state = method.start(mech, schur, jnp.asarray(case.q0), jnp.asarray(case.v0),
                         jnp.float64(case.t0))
    with deferred_fallback():
        step = compile_lifted(lambda state, t: method.step(mech, schur, state, t, h),
                              state, jnp.float64(case.t0))
    for k in range(5):
        state, code, _, _ = step(state, jnp.float64(case.t0 + k * h))
        assert int(code) == 0
    q, v = method.observe(mech, state)
    v_of_p = mech.H_p(q, state[1])
    assert np.max(np.abs(v - v_of_p)) <= 1e-13 * max(1.0, float(np.max(np.abs(v_of_p))))
    carried, fresh = state[-1], mech.mass_factor(q)
    assert (carried is None) == (fresh is None)
    for a, b in zip(jax.tree_util.tree_leaves(carried), jax.tree_util.tree_leaves(fresh)):
        assert np.max(np.abs(a - b)) <= 1e-14 * max(1.0, float(np.max(np.abs(b))))


@pytest.mark.slow
@pytest.mark.parametrize("key", ["rattle", "lobatto3ab3"])
def test_energy_error_is_bounded_without_secular_drift(key):
    case, traj = solve(key, "pendulum", 0.01, 1000.0, n_windows=200)
    assert traj.status == "ok" and traj.counts["n_steps"] == 100_000
    t, e = traj.windows["t"], traj.windows["energy"]
    slope = np.polyfit(t, e, 1)[0]
    # A symplectic method's energy error oscillates with a bounded amplitude: over
    # 1e5 steps the fitted trend must stay below a tenth of that amplitude (a first-order
    # drift would make it of the order of the amplitude itself).
    assert abs(slope) * (t[-1] - t[0]) <= 0.1 * e.max(), (slope, e.max())


def test_nonconvergence_is_recorded_as_failed_and_the_suite_goes_on():
    # At the seed's h = 0.5 the position projection of step 2 has no real solution: the
    # straight line q1(lambda) misses the constraint ellipse, so Newton cannot converge.
    bad = execute(RunSpec("sps-receiver", "rattle", h=0.5, t_end=50.0), repeats=1)
    good = execute(RunSpec("sps-receiver", "rattle", h=0.05, t_end=50.0), repeats=1)
    row = bad.row
    assert row["status"] == "failed"
    assert row["fail_step"] == 2 and row["fail_time"] == pytest.approx(0.5)
    assert "step 2" in row["message"] and "Newton" in row["message"]
    assert row["n_steps"] == 1 and row["max_pos_residual"] is not None
    assert good.row["status"] == "ok"


def test_pendulum_a01_long_horizon_reference_is_periodic():
    # The exact solution must return to the release point after whole periods; this
    # guards the argument reduction of the elliptic functions at t ~ 2000 s.
    case = problems.make("pendulum")
    period = 4 * 1.8540746773013719 / np.sqrt(9.81)  # 4 K(1/2) / omega
    q, v = case.reference.solution(843 * period)
    assert np.allclose(q, [1.0, 0.0], atol=1e-10) and np.allclose(v, 0.0, atol=1e-9)


def test_a_step_size_sweep_reuses_one_compiled_loop_with_identical_results():
    from integrators import loop

    case = problems.make("sps-receiver", t_end=5.0)
    grid = Grid(case.t0, case.t_end)
    loop._LOOPS.clear()
    first = integrators.make("lobatto3ab3", h=0.1).prepare(case, grid)
    second = integrators.make("lobatto3ab3", h=0.05).prepare(case, grid)
    other = integrators.make("lobatto3ab3:newton_tol=1e-12", h=0.05).prepare(case, grid)
    longer = integrators.make("lobatto3ab3", h=0.1).prepare(case.with_t_end(10.0),
                                                            Grid(case.t0, 10.0))
    assert second.compiled is first.compiled  # only h differs: one compilation
    assert longer.compiled is first.compiled  # so does t_end
    assert other.compiled is not first.compiled  # another option: another loop
    reused = second()
    assert reused.counts["n_steps"] == 100 and reused.t_final == pytest.approx(5.0)
    loop._LOOPS.clear()
    fresh = integrators.make("lobatto3ab3", h=0.05).prepare(case, grid)()
    assert np.array_equal(reused.q_final, fresh.q_final)
    for name in fresh.windows:
        assert np.array_equal(reused.windows[name], fresh.windows[name]), name
    assert np.array_equal(reused.samples["q"], fresh.samples["q"])
