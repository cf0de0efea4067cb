"""Andrews' mechanism at its two settings: the Test Set's (the default, unchanged) and the
IFToMM benchmark A03's (its duration and its energy balance with the motor's work)."""

import jax.numpy as jnp
import numpy as np
import pytest

import integrators
import problems
from integrators import Grid
from problems.andrews import PARAMS, Q0, T_END, energy_balance


def test_default_is_the_test_set_setting_unchanged():
    case = problems.make("andrews")
    assert problems.resolve("andrews") == problems.resolve("andrews:setting=testset")
    assert case.t_end == T_END == 0.03
    assert dict(case.params) == PARAMS
    assert case.energy_scale == PARAMS["mom"] * 16.0
    assert case.system.invariants == {}
    assert case.reference.times == (0.03,)
    assert np.array_equal(case.q0, np.array(Q0)) and not np.any(case.v0)


def test_iftomm_setting_runs_the_benchmark_duration_with_its_energy_balance():
    case = problems.make("andrews:setting=iftomm")
    default = problems.make("andrews")
    assert case.t_end == 0.05
    assert list(case.system.invariants) == ["energy_balance"]
    # The same mechanism and start: parameters and initial state as the Test Set's.
    assert dict(case.params) == dict(default.params)
    assert np.array_equal(case.q0, default.q0) and np.array_equal(case.v0, default.v0)
    # t_end overrides the setting's duration.
    assert problems.make("andrews:setting=iftomm,t_end=0.01").t_end == 0.01


def test_unknown_setting_is_refused():
    with pytest.raises(ValueError, match="setting = 'a03' must be one of testset, iftomm"):
        problems.make("andrews:setting=a03")


def test_energy_balance_is_the_benchmark_metric():
    """``I(q, v) - I(q0, v0) = T + V - E0 - tau (beta - beta0)``, with the kinetic energy
    ``T`` and the spring energy ``V`` written out here from the mass matrix and the
    spring's length, at a state away from the start."""
    from problems.andrews import mass_matrix, spring_length

    def kinetic_and_spring(q, v):
        T = 0.5 * v @ np.asarray(mass_matrix(jnp.asarray(q))) @ v
        V = 0.5 * PARAMS["c0"] * (float(spring_length(q[2])) - PARAMS["l0"]) ** 2
        return T + V

    q0, v0 = np.array(Q0), np.zeros(7)
    q = q0 + np.array([1.5, -1.2, 0.1, -0.3, 0.2, 0.3, 0.1])
    v = np.array([300.0, -400.0, 5.0, 8.0, 0.5, -8.0, 0.3])
    metric = (kinetic_and_spring(q, v) - kinetic_and_spring(q0, v0)
              - PARAMS["mom"] * (q[0] - q0[0]))
    change = float(energy_balance(jnp.asarray(q), jnp.asarray(v))
                   - energy_balance(jnp.asarray(q0), jnp.asarray(v0)))
    # The same sums in a different order: equal to round-off of energies of order 1e2 J.
    assert change == pytest.approx(metric, rel=1e-13, abs=0)


@pytest.mark.slow
def test_energy_balance_holds_to_round_off_in_a_tight_run():
    """Lobatto IIIA-IIIB with 4 stages (order 6) at h = 2e-5 over the first 0.01 s (beta
    turns 2.2 rad): the balance's error is round-off, 2.0e-15 measured (at h = 1e-5,
    3.6e-15: no step dependence). 1e-13 is a few hundred ulps of the kinetic and spring
    energies, of order 0.1 J here; a wrong sign of the motor's work would leave an error
    of 2 tau (beta - beta0) = 0.14 J."""
    case = problems.make("andrews:setting=iftomm,t_end=0.01")
    traj = integrators.make("lobatto3ab4", h=2e-5).prepare(case, Grid(case.t0, case.t_end))()
    assert traj.status == "ok", traj.message
    balance = np.asarray(traj.windows["inv:energy_balance"])
    assert np.max(balance) <= 1e-13
    # The drive is the potential -tau beta in H, so the balance is H - H0: the same
    # numbers as the energy error.
    assert np.allclose(balance, traj.windows["energy"], rtol=0, atol=1e-15)
