"""Newton's method on the structured path: where simplified Newton stalls, it is not accepted."""

import numpy as np
import pytest

import integrators
import problems
from integrators.base import Grid

# Verification runs of large mechanisms (10 to 20 s each, most of it compilation).
pytestmark = pytest.mark.slow


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
