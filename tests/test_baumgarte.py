"""Baumgarte-stabilised explicit Runge-Kutta methods (diffrax tableaus, our step loop).

Accuracy against exact solutions (pendulum; a rheonomic spinning rod), convergence, the
drift of the unstabilised ODE and its damping, exact work counts, and failures as data. One
pendulum system is shared so that each solver's loop is compiled once for all tolerances.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

import integrators
import problems
from benchmarks.metrics import summarize
from integrators import baumgarte
from integrators.base import Grid, Status
from integrators.record import Recorder, window_and_slot
from linalg.compiled import equations
from rheonomic import spinning_rod

PENDULUM = problems.make("pendulum")


def run(spec: str, case, t_end: float):
    case = case.with_t_end(t_end)
    traj = integrators.make(spec).prepare(case, Grid(case.t0, case.t_end))()
    return traj, summarize(case, traj)


@pytest.mark.parametrize("solver", ["tsit5", "dopri5", "dopri8"])
def test_error_falls_with_tolerance(solver):
    errors = []
    for rtol in [1e-4, 1e-6, 1e-8, 1e-10]:
        traj, m = run(f"baumgarte-{solver}:rtol={rtol}", PENDULUM, 10.0)
        assert traj.status == Status.OK, traj.message
        assert traj.sampling.startswith("every internal step")
        errors.append(m["final_state_error"])
    # Tolerance proportionality of these pairs is good (measured 52- to 490-fold per
    # 100-fold cut): a 10-fold floor per cut is a generous slack.
    for coarse, fine in zip(errors, errors[1:]):
        assert fine <= coarse / 10, errors


def test_rk4_converges_at_order_four():
    errors = [run(f"baumgarte-rk4:h={h}", PENDULUM, 10.0)[1]["final_state_error"]
              for h in (0.01, 0.005, 0.0025)]
    # Halving h must cut the error by 2^4 = 16 asymptotically (measured 13 and 15);
    # 2^3.5 = 11 allows for the pre-asymptotic first pair.
    for coarse, fine in zip(errors, errors[1:]):
        assert coarse / fine >= 2 ** 3.5, errors


@pytest.mark.parametrize("spec", ["baumgarte-rk4:h=0.01", "baumgarte-dopri5:rtol=1e-8"])
def test_unstabilised_drift_grows_and_the_default_damps_it(spec):
    free, m_free = run(f"{spec},alpha=0,beta=0", PENDULUM, 100.0)
    damped, m_damped = run(spec, PENDULUM, 100.0)
    assert free.status == Status.OK and damped.status == Status.OK
    pos = free.windows["pos"]
    tenth = len(pos) // 10
    # Without stabilisation g'' = 0 holds only to the local error, so |g| grows (measured
    # about 100x from the first to the last tenth of the horizon); 10x is a safe floor.
    assert pos[-tenth:].max() >= 10 * pos[:tenth].max()
    # The default damping keeps |g| orders of magnitude lower (measured 1e4 to 7e4 x).
    assert m_damped["max_pos_residual"] <= 1e-2 * m_free["max_pos_residual"]


def test_dopri8_accuracy_and_damping_over_100_s():
    damped, m_damped = run("baumgarte-dopri8:rtol=1e-10", PENDULUM, 100.0)
    free, m_free = run("baumgarte-dopri8:rtol=1e-10,alpha=0,beta=0", PENDULUM, 100.0)
    assert damped.status == Status.OK and free.status == Status.OK
    # Final position error <= 1e-7 (measured 2.4e-8), and at least 10x
    # larger |g| without stabilisation (measured 1.4e4 x).
    assert m_damped["final_state_error"] <= 1e-7
    assert m_free["max_pos_residual"] >= 10 * m_damped["max_pos_residual"]


@pytest.mark.parametrize("spec, error_bound", [("baumgarte-dopri8:rtol=1e-10", 1e-9),
                                               ("baumgarte-rk4:h=0.005", 1e-7)])
def test_rheonomic_constraint_against_exact_solution(spec, error_bound):
    traj, m = run(spec, spinning_rod(), 3.0)
    assert traj.status == Status.OK, traj.message
    # Measured 4e-11 and 7e-9: the bounds leave a factor of about 15 to 25.
    assert m["final_state_error"] <= error_bound
    assert m["max_pos_residual"] <= 1e-7


def test_vector_field_evaluations_are_counted_exactly(monkeypatch):
    calls = []
    field = baumgarte.baumgarte_field

    def counted(mech, alpha, beta, schur=None):
        f = field(mech, alpha, beta, schur)

        def g(t, y, args):
            jax.debug.callback(lambda: calls.append(1))
            return f(t, y, args)

        return g

    monkeypatch.setattr(baumgarte, "baumgarte_field", counted)
    # A fresh system, so that the loop is traced (and compiled) with the counting field.
    case = problems.make("sps-receiver").with_t_end(5.0)
    for spec in ("baumgarte-dopri5:rtol=1e-7", "baumgarte-rk4:h=0.05"):
        calls.clear()
        traj = integrators.make(spec).prepare(case, Grid(case.t0, case.t_end))()
        assert traj.status == Status.OK
        assert traj.counts["n_f_evals"] == len(calls) == traj.counts["n_lin_solves"]
    assert traj.counts["n_f_evals"] == 4 * traj.counts["n_steps"] == 400


def test_failures_are_data():
    blown, _ = run("baumgarte-rk4:h=0.05,alpha=0,beta=0", PENDULUM, 100.0)
    assert blown.status == Status.FAILED and "non-finite" in blown.message
    assert 0 < blown.t_final < 100.0 and blown.fail_time == blown.t_final
    assert np.all(np.isfinite(blown.q_final))
    capped, _ = run("baumgarte-dopri5:rtol=1e-6,max_steps=10", PENDULUM, 10.0)
    assert capped.status == Status.FAILED and "max_steps = 10" in capped.message
    assert capped.counts["n_steps"] == 10 and capped.t_final < 10.0


def test_the_loop_records_a_run_as_the_host_recorder_would():
    # Every step kept as a sample (201 slots for 200 steps), so that the host's Recorder
    # can be fed the same points the compiled loop measured; steps land on window ends.
    case = problems.make("pendulum").with_t_end(2.0)
    grid = Grid(case.t0, case.t_end, n_windows=20, n_samples=201)
    traj = integrators.make("baumgarte-rk4:h=0.01").prepare(case, grid)()
    kept = traj.samples
    assert traj.status == Status.OK and len(kept["t"]) == 201
    recorder = Recorder(case.mech, grid)
    recorder.start(kept["t"][0], kept["q"][0], kept["v"][0])
    recorder.extend(kept["t"][1:], kept["q"][1:], kept["v"][1:])
    host = recorder.windows()
    assert list(host) == list(traj.windows) and len(host["t"]) == 20
    # The same points measured by two compiled programs: equal to round-off of |g|, |G v|
    # and H (the pendulum's energy is of order 10).
    for name, series in host.items():
        np.testing.assert_allclose(traj.windows[name], series, rtol=1e-12, atol=1e-14)


def test_a_step_on_a_window_end_counts_in_the_window_it_ends_in_the_loop_and_on_the_host():
    grid = Grid(0.0, 100.0, n_windows=1000)
    k = np.arange(1, 10001)
    t = 0.0 + k * (100.0 / 10000)                      # FixedSteps.grid_time
    expected = (k - 1) // 10
    host, _ = window_and_slot(t, grid)
    loop, _ = jax.jit(lambda t: window_and_slot(t, grid, jax.numpy))(t)
    assert np.array_equal(host, expected) and np.array_equal(np.asarray(loop), expected)


@pytest.mark.parametrize("name", sorted(baumgarte.SOLVERS))
def test_the_unrolled_step_is_diffrax_step(name):
    # erk_step writes the stages out instead of diffrax's stage loop; it must compute the
    # same step, error estimate and first-same-as-last stage (to round-off: the sums of
    # the stages may be ordered differently).
    import diffrax

    mech = PENDULUM.mech
    field = baumgarte.baumgarte_field(mech, 3.0, 3.0)
    term = diffrax.ODETerm(field)
    solver = baumgarte.SOLVERS[name]()
    y0 = jax.numpy.asarray(np.concatenate([PENDULUM.q0, PENDULUM.v0]) + [0.0, 1e-3, 0.5, 0.0])
    t0, t1 = 0.3, 0.35
    state = solver.init(term, t0, t1, y0, None)
    y1, error, _, state1, _ = solver.step(term, t0, t1, y0, None, state, False)
    ours, ours_error, f_last = baumgarte.erk_step(
        solver.tableau, field, t0, t1, y0, baumgarte.first_stage(solver, field, t0, y0))
    np.testing.assert_allclose(ours, y1, rtol=0, atol=1e-14)
    np.testing.assert_allclose(ours_error, error, rtol=0, atol=1e-15)
    if solver.tableau.fsal:
        np.testing.assert_allclose(f_last, state1[1], rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", sorted(baumgarte.SOLVERS))
def test_stages_in_a_loop_are_the_written_out_stages(name, monkeypatch):
    # A large field's stages are evaluated in a loop (ROLL_EQUATIONS): the same sums term
    # by term, which XLA may round differently; the error estimate, a cancellation of
    # O(1) terms, agrees to their round-off.
    case = problems.make("rigid-body")
    field = baumgarte.baumgarte_field(case.mech, 3.0, 3.0)
    solver = baumgarte.SOLVERS[name]()
    y0 = jax.numpy.asarray(np.concatenate([case.q0, case.v0]))
    t0, t1 = 0.3, 0.35

    def compiled(roll_from):
        # A new function each time: JAX's trace cache does not see ROLL_EQUATIONS.
        monkeypatch.setattr(baumgarte, "ROLL_EQUATIONS", roll_from)
        step = jax.jit(lambda y0: baumgarte.erk_step(
            solver.tableau, field, t0, t1, y0, baumgarte.first_stage(solver, field, t0, y0)))
        return step(y0), "while" in step.lower(y0).as_text()

    size = sum(1 for _ in equations(jax.make_jaxpr(field)(t0, y0, None).jaxpr))
    written, rolled = compiled(size + 1)
    assert not rolled
    looped, rolled = compiled(size)
    assert rolled
    (y, error, last), (y_loop, error_loop, last_loop) = written, looped
    np.testing.assert_allclose(y_loop, y, rtol=4e-16, atol=0)
    np.testing.assert_allclose(last_loop, last, rtol=1e-15, atol=1e-15)
    np.testing.assert_allclose(error_loop, error, rtol=0, atol=1e-16)
    if np.any(solver.tableau.b_error):
        assert np.max(np.abs(error)) > 1e-15  # an estimate, not round-off alone
