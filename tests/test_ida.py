"""IDA on the GGL (index 2) and acceleration-level (index 1) forms.

Accuracy against exact solutions (pendulum; a rheonomic spinning rod), the constraint
behaviour of each form, the analytic iteration matrix, the multipliers' weights in the
error test, and failures as data. One pendulum system is shared so that its compiled
functions serve every test.
"""

from __future__ import annotations

import numpy as np
import pytest

import integrators
import problems
from benchmarks.metrics import summarize
from benchmarks.execute import execute
from benchmarks.records import RunSpec
from integrators.base import Grid, Status
from integrators.ida import (EXCLUDED, FORMULATIONS, consistent_values, dae_residual,
                             iteration_matrix)
from rheonomic import spinning_rod

PENDULUM = problems.make("pendulum")


def run(spec: str, case, t_end: float):
    case = case.with_t_end(t_end)
    traj = integrators.make(spec).prepare(case, Grid(case.t0, case.t_end))()
    return traj, summarize(case, traj)


def test_ggl_error_falls_with_tolerance():
    rtols = [1e-4, 1e-6, 1e-8, 1e-10]
    errors = []
    for rtol in rtols:
        traj, m = run(f"ida-ggl:rtol={rtol}", PENDULUM, 10.0)
        assert traj.status == Status.OK, traj.message
        assert traj.counts["n_newton"] == traj.counts["n_f_evals"] >= traj.counts["n_steps"] > 0
        assert traj.counts["n_jac_evals"] > 0 and traj.counts["n_rejected"] >= 0
        assert traj.sampling.endswith("native driver)")
        errors.append(m["final_state_error"])
    # BDF's global error is only roughly proportional to the tolerance, and a phase error
    # at a fixed time can partly cancel: each 100-fold cut must buy at least a 4-fold
    # smaller error (measured: 44, 99 and 24-fold), and the sweep at least 1e4 overall.
    for coarse, fine in zip(errors, errors[1:]):
        assert fine <= coarse / 4, errors
    assert errors[-1] <= errors[0] * 1e-4, errors


@pytest.mark.slow
def test_ggl_holds_the_constraint_over_1000_s():
    rtol = 1e-5
    traj, m = run(f"ida-ggl:rtol={rtol}", PENDULUM, 1000.0)
    assert traj.status == Status.OK, traj.message
    assert traj.sampling.startswith("every internal step")
    # g = 0 is one of the equations IDA's Newton solves: it holds to the Newton tolerance,
    # a fraction of the weighted error tolerance per component, not to round-off (measured
    # peak 7 rtol, median 1 rtol); 20 rtol leaves room without hiding growth.
    assert m["max_pos_residual"] <= 20 * rtol
    pos = traj.windows["pos"]
    assert len(pos) == 1000
    # No drift: the last 100 s see no larger violations than the first 100 s (x2 for noise).
    assert pos[-100:].max() <= 2 * pos[:100].max()


def test_index1_drifts_and_ggl_does_not():
    index1, m1 = run("ida-index1:rtol=1e-8", PENDULUM, 50.0)
    ggl, m2 = run("ida-ggl:rtol=1e-8", PENDULUM, 50.0)
    assert index1.status == Status.OK and ggl.status == Status.OK
    # The index-1 form only keeps d^2 g/dt^2 = 0: errors in g and G v integrate up, so
    # |g| grows with t (measured per tenth of the horizon: 4e-6, 2e-5, ... 4e-4, steadily).
    # A 10 % dip between tenths and a 20x rise overall (measured 99x) leave room for noise.
    tenths = index1.windows["pos"].reshape(10, -1).max(axis=1)
    assert np.all(tenths[1:] >= 0.9 * tenths[:-1]), tenths
    assert tenths[-1] >= 20 * tenths[0], tenths
    # GGL holds g = 0 to the Newton tolerance (measured: 3e-8 against 4e-4).
    assert m1["max_pos_residual"] >= 100 * m2["max_pos_residual"]


def test_multipliers_never_limit_the_step():
    default, _ = run("ida-ggl:rtol=1e-6", PENDULUM, 2.0)
    smaller, _ = run("ida-ggl:rtol=1e-6,multiplier_atol=1e20", PENDULUM, 2.0)
    assert default.status == smaller.status == Status.OK
    assert integrators.make("ida-ggl").multiplier_atol == EXCLUDED
    # Weights of 1e-20 and 1e-30 are both nil next to those of q and v: IDA must take
    # exactly the same steps and produce the same state, bit for bit.
    assert default.counts == smaller.counts
    assert np.array_equal(default.q_final, smaller.q_final)
    # With the multipliers in the error test IDA does not get through the horizon even
    # with 4x the steps (measured: 20000 steps reach t = 0.078 of 2 s).
    limit = 4 * default.counts["n_steps"]
    included, _ = run(f"ida-ggl:rtol=1e-6,multiplier_atol=1e-6,max_steps={limit}",
                      PENDULUM, 2.0)
    assert included.status == Status.FAILED and included.t_final < 2.0
    assert f"max_steps = {limit}" in included.message


def test_index1_multiplier_in_the_error_test_hits_round_off():
    default, m = run("ida-index1:rtol=1e-9", PENDULUM, 2.0)
    assert default.status == Status.OK and integrators.make("ida-index1").multiplier_atol == EXCLUDED
    # lam comes from v', whose round-off grows like eps / h: in the error test at this
    # tolerance it drives the step down (measured 24589 steps against 708), so 10x the
    # default's steps do not cover the horizon.
    limit = 10 * default.counts["n_steps"]
    included, _ = run(f"ida-index1:rtol=1e-9,multiplier_atol=1e-9,max_steps={limit}",
                      PENDULUM, 2.0)
    assert included.status == Status.FAILED and included.t_final < 2.0


@pytest.mark.parametrize("formulation", sorted(FORMULATIONS))
@pytest.mark.parametrize("case", [PENDULUM, spinning_rod()], ids=["pendulum", "spinning-rod"])
def test_iteration_matrix_matches_finite_differences(formulation, case):
    mech = case.mech
    blocks = FORMULATIONS[formulation].multiplier_blocks
    y0, yp0 = consistent_values(mech, blocks, 0.3, case.q0, case.v0)
    rng = np.random.default_rng(7)
    # A point off the solution: every term of the matrix matters there.
    y = y0 + 0.1 * rng.standard_normal(y0.shape)
    yp = yp0 + 0.1 * rng.standard_normal(y0.shape)
    t, cj = 0.3, 37.0
    J = np.asarray(iteration_matrix(t, y, yp, cj, mech=mech, formulation=formulation))

    def F(y_, yp_):
        return np.asarray(dae_residual(t, y_, yp_, mech=mech, formulation=formulation))

    J_fd = np.empty_like(J)
    for j in range(len(y)):
        delta = 1e-6 * max(1.0, abs(y[j]))
        e = np.zeros_like(y)
        e[j] = delta
        # Along column j, y moves by e and y' by cj e: the column of dF/dy + cj dF/dy'.
        J_fd[:, j] = (F(y + e, yp + cj * e) - F(y - e, yp - cj * e)) / (2 * delta)
    # Central differences are accurate to O(delta^2) + O(eps / delta), about 1e-10 here.
    assert np.max(np.abs(J - J_fd)) <= 1e-6 * max(1.0, np.max(np.abs(J)))


@pytest.mark.parametrize("formulation", sorted(FORMULATIONS))
def test_difference_quotient_jacobian_is_an_option_and_its_calls_are_counted(formulation):
    ours, m_ours = run(f"ida-{formulation}:rtol=1e-8", PENDULUM, 5.0)
    dq, m_dq = run(f"ida-{formulation}:rtol=1e-8,jacobian=difference-quotient", PENDULUM, 5.0)
    assert ours.status == dq.status == Status.OK
    size = 2 * PENDULUM.mech.n + FORMULATIONS[formulation].multiplier_blocks * PENDULUM.mech.m
    # IDA's Newton evaluates the residual once per iteration; its difference quotients add
    # one call per component of y per Jacobian. Our counts must add up to exactly that.
    assert ours.counts["n_f_evals"] == ours.counts["n_newton"]
    assert dq.counts["n_f_evals"] == dq.counts["n_newton"] + size * dq.counts["n_jac_evals"]
    # Either Jacobian gives an answer within the same tolerance band (measured 1e-6, 3e-6).
    assert m_dq["final_state_error"] <= 10 * m_ours["final_state_error"]


@pytest.mark.parametrize("spec, error_bound", [("ida-ggl:rtol=1e-8", 4e-5),
                                               ("ida-index1:rtol=1e-8", 4e-5)])
def test_rheonomic_constraint_against_exact_solution(spec, error_bound):
    traj, m = run(spec, spinning_rod(), 3.0)
    assert traj.status == Status.OK, traj.message
    # |y| grows to cosh(3) = 10 and the tolerance is relative: a global error of a few
    # hundred rtol |y| is BDF's usual (measured 3.9e-6 and 1.9e-6).
    assert m["final_state_error"] <= error_bound
    assert m["max_pos_residual"] <= 1e-6 and m["max_vel_residual"] <= 1e-6


@pytest.mark.parametrize("driver", ["native", "scikit-sundae"])
def test_failures_are_failed_rows_and_the_suite_goes_on(driver):
    records = [execute(spec, repeats=1) for spec in (
        RunSpec("pendulum", f"ida-ggl:driver={driver}", rtol=1e-20, t_end=1.0),
        RunSpec("pendulum", f"ida-ggl:max_steps=50,driver={driver}", rtol=1e-6, t_end=1.0),
        RunSpec("pendulum", f"ida-ggl:driver={driver}", rtol=1e-6, t_end=1.0),
    )]
    unattainable, too_many, healthy = (r.row for r in records)
    assert unattainable["status"] == Status.FAILED
    assert "Could not satisfy demanded accuracy" in unattainable["message"]
    assert "too much accuracy requested" in unattainable["message"]
    assert too_many["status"] == Status.FAILED and "max_steps = 50" in too_many["message"]
    assert too_many["n_steps"] == 50 and too_many["t_final"] < 1.0
    assert too_many["fail_time"] == too_many["t_final"] and too_many["fail_step"] == 51
    assert healthy["status"] == Status.OK and healthy["t_final"] == 1.0


@pytest.mark.parametrize("linsolver", ["dense", "sparse"])
def test_redundant_constraints_fail_at_set_up_with_the_rank(linsolver):
    # bricard's 24 constraints have rank 23. Neither linear solver stops on the singular
    # iteration matrix by itself (SuperLU_MT cut the step to 1e-30 for 337 s), so the rank
    # is checked at set-up on either path.
    case = problems.make("bricard").with_t_end(2.0)
    traj = integrators.make("ida-ggl", linsolver=linsolver).prepare(
        case, Grid(case.t0, case.t_end))()
    assert traj.status == "failed" and traj.counts["n_steps"] == 0
    assert "rank 23 < m = 24" in traj.message


@pytest.mark.parametrize("formulation", sorted(FORMULATIONS))
def test_native_driver_takes_the_binding_steps(formulation):
    # The same IDA settings and the same residual: the first steps agree exactly, and
    # where round-off in the residuals (C against XLA's code) first changes a step-size
    # decision the runs part by the method's own error, not more.
    native, m_native = run(f"ida-{formulation}:rtol=1e-8,atol=1e-10,driver=native",
                           PENDULUM, 10.0)
    binding, m_binding = run(f"ida-{formulation}:rtol=1e-8,atol=1e-10,driver=scikit-sundae",
                             PENDULUM, 10.0)
    assert native.status == binding.status == Status.OK
    assert native.sampling.endswith("native driver)")
    assert binding.sampling.endswith("scikit-sundae)") and binding.extra["callback_s"] > 0
    steps = native.counts["n_steps"], binding.counts["n_steps"]
    assert max(steps) <= 1.05 * min(steps), steps
    assert native.counts["n_f_evals"] == native.counts["n_newton"]
    errors = m_native["final_state_error"], m_binding["final_state_error"]
    assert max(errors) <= 3 * min(errors), errors
    assert np.max(np.abs(native.q_final - binding.q_final)) <= 2 * max(errors)


def test_native_driver_is_refused_where_it_cannot_run():
    with pytest.raises(ValueError, match="driver = 'native' takes linsolver = 'dense'"):
        integrators.make("ida-ggl:driver=native,linsolver=sparse").check()
    with pytest.raises(ValueError, match="driver = 'gcc' is not one of"):
        integrators.make("ida-ggl:driver=gcc").check()


def test_without_a_compiler_auto_keeps_the_binding_and_says_why(monkeypatch):
    monkeypatch.setenv("CC", "/nonexistent/cc")
    monkeypatch.setattr("integrators.sundials.cache_folder",
                        lambda: __import__("pathlib").Path(__import__("tempfile").mkdtemp()))
    traj, m = run("ida-ggl:rtol=1e-6", PENDULUM, 1.0)
    assert traj.status == Status.OK
    assert "scikit-sundae; native driver not built:" in traj.sampling
