"""The stiff flyball governor (IFToMM A05): the specification's parameters, consistent
initial values, the library's derivative checks, the hand-written ODE of the reference
against the System, the stored reference and its energy balance, and runs against it."""

import jax.numpy as jnp
import numpy as np
import pytest

import integrators
import problems
import test_problems as library
from benchmarks.metrics import reference_error
from helpers import solve
from integrators import Grid
from problems import data
from problems.case import residuals
from problems.data.generate import flyball_governor as regenerate, governor_rhs
from problems.flyball_governor import S, inertias, spring_lengths


@pytest.fixture(scope="module")
def case():
    return problems.make("flyball-governor")


def test_parameters_are_the_specification(case):
    assert case.params == dict(
        length=1.0, side=0.01, slider=0.1, density=3000.0, point_mass=5.0, stiffness=8e5,
        damping=4e4, rest_length=0.5, s0=0.5, alpha=30.0, omega=2 * np.pi, gravity=9.81)
    assert case.t_end == 10.0
    masses = inertias(case.params)
    # 1.0 x 0.01 x 0.01 m bars and a 0.1 m cube at 3000 kg/m^3.
    assert masses["m_rod"] == pytest.approx(0.3, rel=1e-14)
    assert masses["m_slider"] == pytest.approx(3.0, rel=1e-14)
    assert case.q0[S] == 0.5 and np.degrees(case.q0[2]) == pytest.approx(30.0, rel=1e-15)
    # The shaft turns at 2 pi rad/s, the rest rotates rigidly with it.
    np.testing.assert_array_equal(case.v0, [2 * np.pi, 0.0, 0.0, 0.0, 0.0])


def test_initial_values_are_consistent_and_the_springs_relaxed(case):
    # g = phi - omega t and G v + g_t = phi' - omega vanish exactly at (0, omega).
    assert residuals(case.mech, case.q0, case.v0, case.t0) == (0.0, 0.0)
    assert "projected" not in case.notes
    # The equilateral triangle of side 0.5 (module docstring): to round-off.
    np.testing.assert_allclose(np.asarray(spring_lengths(jnp.asarray(case.q0), case.params)),
                               0.5, rtol=1e-15)


@pytest.mark.parametrize("check", [
    library.test_constraint_jacobian_matches_finite_differences,
    library.test_time_derivatives_match_finite_differences,
    library.test_force_matches_finite_differences_of_the_lagrangian,
    library.test_hamiltonian_gradients_match_finite_differences,
    library.test_mass_matrix_is_symmetric_positive_definite,
    library.test_index1_flow_conserves_declared_invariants,
], ids=lambda f: f.__name__.removeprefix("test_"))
def test_library_checks(case, check):
    # The checks every library problem passes (tests/test_problems.py), on this one.
    check(case)


def test_energy_is_not_derived_but_balanced(case):
    # Driven and damped: no conserved energy; the balance is the declared invariant.
    assert not case.mech.has_energy
    assert list(case.system.invariants) == ["energy_balance"]


def test_hand_written_ode_is_the_systems_index1_flow(case):
    """The reference's ODE (problems.data.generate) and the System's accelerations agree at
    states off the initial one: the two share no code but the parameters."""
    p, mech = case.params, case.mech
    rng = np.random.default_rng(0)
    for _ in range(3):
        y = np.concatenate([case.q0[1:] + 0.1 * rng.standard_normal(4),
                            rng.standard_normal(4)])
        t = 0.3
        q = np.concatenate([[p["omega"] * t], y[:4]])
        v = np.concatenate([[p["omega"]], y[4:]])
        a, _ = mech.accelerations(jnp.asarray(t), jnp.asarray(q), jnp.asarray(v))
        expected = governor_rhs(t, y, p)[4:]
        # The same forces summed in another order: a few ulps of the largest (the
        # 8e5 N/m springs give accelerations up to 1e5 here).
        assert np.max(np.abs(np.asarray(a)[1:] - expected)) <= 1e-14 * np.max(np.abs(expected))
        # The drive holds the rate: a_0 is the drive's force less the multiplier's, both
        # divided by M_00, zero up to their rounding.
        assert abs(float(np.asarray(a)[0])) <= 1e-14 * np.max(np.abs(expected))


def test_reference_is_stored_scored_on_s_with_its_floor(case):
    ref = case.reference
    assert ref.kind == "computed" and ref.scored == (S,)
    assert ref.times == (1.0, 5.0, 10.0)
    entries = data.load("flyball-governor")["entries"]
    assert ref.floor == max(e["error_estimate"] for e in entries)
    # DOP853 at rtol 2.5e-14 and Radau at 1e-12 over 10 s of a stiff flow (|lambda| up to
    # 8e3 1/s) differ by 1.2e-13 in s; the bound leaves room for another platform's libm
    # and still puts the floor 1e4 below the benchmark's 1e-6.
    assert 0.0 < ref.floor <= 1e-10
    # A parameter set without stored entries has no reference.
    assert problems.make("flyball-governor:damping=1e4").reference is None


def test_reference_states_keep_the_energy_balance(case):
    """The stored states, from the hand-written ODE, satisfy the System's declared balance
    T + U + W_d - W_omega = E_0: the invariant and the reference check each other."""
    balance = case.system.invariants["energy_balance"]
    I0 = float(balance(jnp.asarray(case.q0), jnp.asarray(case.v0)))
    for t in case.reference.times:
        q, v = case.reference.solution(t)
        # Terms of 1e2 J (the rotation's energy) at the reference's 1e-12 relative accuracy.
        assert abs(float(balance(jnp.asarray(q), jnp.asarray(v))) - I0) <= 1e-9


def test_short_runs_are_ok(case):
    short = case.with_t_end(0.05)
    for key, options in (("ida-ggl", dict(rtol=1e-6, atol=1e-6)), ("genalpha", dict(h=1e-3))):
        traj = integrators.make(key, **options).prepare(short, Grid(short.t0, short.t_end))()
        assert traj.status == "ok", (key, traj.message)
        # The stiff transient is over in a few 1e-4 s; the balance holds to the tolerance
        # (times the 169 J energy scale) or to the method's error at h = 1e-3.
        assert np.max(traj.windows["inv:energy_balance"]) <= 1e-3, key


@pytest.mark.slow
def test_ida_ggl_reaches_the_reference_s():
    case, traj = solve("flyball-governor", "ida-ggl", rtol=1e-8, atol=1e-8)
    err, _ = reference_error(case, traj)
    # The benchmark's bar: s(10) within 1e-6 at rtol 1e-8. Measured 5.8e-7 (2974 steps);
    # the same forces summed in another order gave 4.0e-7 (2779 steps): an adaptive step
    # sequence follows round-off, and the error its tolerance allows moves with it.
    assert err <= 1e-6
    # The balance to the tolerance times the energy scale, over 10 s.
    assert np.max(traj.windows["inv:energy_balance"]) <= 1e-6 * case.energy_scale


@pytest.mark.slow
def test_reference_solves_agree_to_the_stored_floor():
    """Both solves rerun (DOP853 at 2.5e-14, Radau at 1e-12) to the first stored time
    (the whole horizon takes ten times as long): the stored state comes back, and their
    difference is within the stored error estimate."""
    stored = data.load("flyball-governor")["entries"]
    new, = regenerate(times=(stored[0]["t"],))["entries"]
    # Same code and arithmetic: the same numbers, up to the platform's libm.
    np.testing.assert_allclose(new["q"], stored[0]["q"], rtol=0, atol=1e-13)
    assert new["error_estimate"] <= max(e["error_estimate"] for e in stored) * 1.01
