"""Each problem's reference is reproduced by at least one integrator to the digits it
supports, and the invariants each problem declares are kept by a symplectic method."""

import jax.numpy as jnp
import numpy as np
import pytest

import problems
from benchmarks.metrics import reference_error
from helpers import solve, state_error


@pytest.mark.slow
def test_andrews_positions_to_nine_digits():
    case, traj = solve("andrews", "lobatto3ab4", h=1e-4)
    _, scd = reference_error(case, traj)
    # The published positions are accurate to about 1e-10 relative (scd ~9.5 at best);
    # the sixth-order method at h = 1e-4 is well below that.
    assert scd >= 9.0
    # The energy balance (kinetic + spring - torque x beta) is conserved.
    assert case.mech.has_energy
    assert np.max(traj.windows["energy"]) <= 1e-6 * case.energy_scale


@pytest.mark.slow
def test_andrews_positions_to_nine_digits_by_a_second_family():
    # Baumgarte-stabilised DOPRI8 (an explicit, adaptive family) at a tight tolerance.
    case, traj = solve("andrews", "baumgarte-dopri8", rtol=1e-11, atol=1e-13)
    _, scd = reference_error(case, traj)
    assert scd >= 9.0


@pytest.mark.slow
def test_car_axis_all_ten_components_of_version_b():
    from problems.car_axis import REF_LAMBDA, REF_Y

    case, traj = solve("car-axis", "lobatto3ab4", h=1e-3)
    _, lam = case.mech.accelerations(jnp.asarray(traj.t_final), jnp.asarray(traj.q_final),
                                     jnp.asarray(traj.v_final))
    y = np.concatenate([traj.q_final, traj.v_final, np.asarray(lam)])
    # Version B is good to about 7e-12 in positions and velocities and 1e-15 in the
    # multipliers; the method's own error at h = 1e-3 is about 5e-12.
    assert np.max(np.abs(y - np.array(REF_Y + REF_LAMBDA))) <= 1e-9
    assert not case.mech.has_energy  # rheonomic: the road does work


@pytest.mark.parametrize("spec, h, tol", [
    # Regular motion: the stored reference is good to about 2e-12 at t = 5.
    ("double-pendulum", 0.01, 1e-10),
    # Chaotic: the reference's own error estimate at t = 5 is 2.3e-9.
    ("double-pendulum:energy=high", 2e-3, 1e-8),
    # N = 4 chain at t = 5: reference good to about 2e-12.
    ("chain:N=4", 2e-3, 1e-9),
])
def test_pendulum_chains_against_minimal_coordinates(spec, h, tol):
    case, traj = solve(spec, "lobatto3ab4", h=h)
    assert case.reference is not None and case.reference.kind == "computed"
    assert state_error(case, traj) <= tol


def test_chain_scales_to_a_thousand_links():
    case = problems.make("chain:N=1024")
    assert case.mech.n == 2048 and case.mech.m == 1024
    G = np.asarray(case.mech.G(jnp.asarray(case.q0), 0.0))
    rows, cols = np.nonzero(G)
    # Link k touches only the coordinates of masses k-1 and k: a band of width 4.
    assert np.all((cols >= 2 * rows - 2) & (cols <= 2 * rows + 1))
