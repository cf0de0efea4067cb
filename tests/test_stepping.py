"""Manual stepping (integrators.Stepper): the compiled loop's steps, one call at a time."""

import doctest

import jax
import jax.numpy as jnp
import numpy as np

import integrators
import integrators.fixed
import problems
from integrators import Grid, Stepper
from integrators.base import Failure


def test_manual_rattle_steps_reproduce_the_compiled_loop():
    # The same step function on the same arrays: the pendulum is autonomous, so the
    # stepper's time t + h (not the loop's t0 + k h) does not enter, and h = 0.01 divides
    # the horizon exactly, so both take the same h. Measured bit for bit; round-off is
    # allowed because XLA may fuse the loop's body differently from the lone step.
    case = problems.make("pendulum").with_t_end(3.0)
    method = integrators.make("rattle", h=0.01)
    traj = method.prepare(case, Grid(case.t0, case.t_end))()
    stepper = Stepper(method, case)
    state = stepper.init()
    for _ in range(300):
        state, code = stepper.step(state)
        assert code == Failure.NONE
    q, v = stepper.observe(state)
    assert np.max(np.abs(np.asarray(q) - traj.q_final)) <= 1e-14
    assert np.max(np.abs(np.asarray(v) - traj.v_final)) <= 1e-14
    assert {key: int(n) for key, n in state.counts.items()} == traj.counts


def test_a_batch_of_states_is_a_vmap_away():
    # Two lanes, one of them the case's initial state and one perturbed along the circle:
    # each lane steps exactly as it does alone.
    case = problems.make("pendulum")
    stepper = Stepper(integrators.make("rattle", h=0.01), case)
    angle = 0.1
    rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    lanes = [stepper.init(), stepper.init(rotation @ case.q0, rotation @ case.v0)]
    batch = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *lanes)
    stepped, codes = jax.vmap(stepper.step)(batch)
    assert list(np.asarray(codes)) == [0, 0]
    for i, lane in enumerate(lanes):
        alone, _ = stepper.step(lane)
        for a, b in zip(jax.tree_util.tree_leaves(alone), jax.tree_util.tree_leaves(stepped)):
            assert np.max(np.abs(np.asarray(a) - np.asarray(b)[i])) <= 1e-15


def test_a_failed_step_keeps_the_state_and_returns_its_code():
    # One Newton iteration cannot reach round-off (1e-16) on the pendulum's projection.
    case = problems.make("pendulum")
    stepper = Stepper(integrators.make("rattle:newton_max_iter=1", h=0.01), case)
    state = stepper.init()
    after, code = stepper.step(state)
    assert Failure(int(code)) is Failure.NEWTON and "Newton" in Failure.NEWTON.message
    assert float(after.t) == float(state.t)
    assert np.array_equal(stepper.observe(after)[0], stepper.observe(state)[0])
    assert int(after.counts["n_steps"]) == 0 and int(after.counts["n_newton"]) == 1


def test_the_docstring_example_runs():
    failures, _ = doctest.testmod(integrators.fixed, verbose=False)
    assert failures == 0
