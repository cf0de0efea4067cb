"""The C yardsticks of ``radau5`` and ``radau5-ggl`` (``radau5``) and of ``ida-ggl`` and
``ida-index1`` (``ida``) take the steps ours take and end where our runs end, on the pendulum
and on andrews (configuration-dependent mass, 20 to 26 unknowns: LAPACK's factorisations on
our side), and the Radau loop on the pendulum calls no LAPACK. Timing is never asserted here
(``python -m benchmarks.perf.efficiency`` measures it)."""

from __future__ import annotations

import jax.numpy as jnp
import pytest

import integrators
import problems
from benchmarks.perf import efficiency
from benchmarks.perf.processes import state_difference
from integrators.base import Grid
from helpers import needs_cc


#: Short horizons: the pendulum over 1 s, andrews over a tenth of its Test Set span.
HORIZONS = {"pendulum": 1.0, "andrews": 0.003}


@pytest.mark.slow
@needs_cc
@pytest.mark.parametrize("problem, family, thet", [
    ("pendulum", "radau5", None), ("pendulum", "radau5", -1.0), ("pendulum", "radau5-ggl", None),
    ("andrews", "radau5", None), ("andrews", "radau5-ggl", None)])
def test_radau_yardstick_ends_where_our_run_ends(tmp_path, problem, family, thet):
    # The same algorithm from the same point: the same accepted and rejected steps,
    # Jacobians and factorisations (a different LU's round-off may move a decision late
    # in a long run, not in a short one), and final states far inside the tolerance.
    # thet = -1 (a Jacobian at every step) shows that the options reach the yardstick.
    rtol = 1e-8
    case = problems.make(problem).with_t_end(HORIZONS[problem])
    spec = f"{family}:rtol={rtol!r},atol=1e-10" + ("" if thet is None else f",thet={thet!r}")
    method = integrators.make(spec)
    ours = method.prepare(case, Grid(case.t0, case.t_end))()
    exe = efficiency.compile_radau(tmp_path, method, case)
    theirs = efficiency.radau_yardstick_run(efficiency.radau_yardstick_command(
        exe, method, case, 1))
    assert ours.status == "ok"
    steps = theirs["steps"]
    assert steps >= 20
    assert abs(ours.counts["n_steps"] - steps) <= 0.02 * steps
    for key, c_key in (("n_rejected", "rejected"), ("n_jac_evals", "jacobians")):
        assert abs(ours.counts[key] - theirs[c_key]) <= 0.02 * steps
    assert abs(ours.extra["n_lu"] - theirs["lu"]) <= 0.02 * steps
    if thet is not None:
        assert theirs["jacobians"] >= steps and ours.counts["n_jac_evals"] >= steps
    dq, dv = state_difference(theirs["y"][:2 * case.mech.n], [*ours.q_final, *ours.v_final],
                              relative=True)
    assert max(dq, dv) <= 10 * rtol


@pytest.mark.slow
@needs_cc
@pytest.mark.parametrize("problem", ["pendulum", "andrews"])
@pytest.mark.parametrize("family", ["ida-ggl", "ida-index1"])
def test_ida_yardstick_ends_where_our_run_ends(tmp_path, problem, family):
    # The native driver and the yardstick make the same IDA calls on the same generated
    # functions: the same steps and the same final state to round-off.
    case = problems.make(problem).with_t_end(HORIZONS[problem])
    method = integrators.make(f"{family}:rtol=1e-8,atol=1e-10,driver=native")
    ours = method.prepare(case, Grid(case.t0, case.t_end))()
    exe = efficiency.compile_ida(efficiency.ida_model(tmp_path, case, method.formulation))
    theirs = efficiency.ida_yardstick_run(efficiency.ida_yardstick_command(exe, method, case, 1))
    assert ours.status == "ok"
    assert theirs["steps"] >= 20
    assert ours.counts["n_steps"] == theirs["steps"]
    dq, dv = state_difference(theirs["y"][:2 * case.mech.n], [*ours.q_final, *ours.v_final],
                              relative=True)
    assert max(dq, dv) <= 1e-12


def test_the_pendulums_radau_loop_calls_no_lapack():
    # A LAPACK call in a loop's body costs at every pass even in a branch that is never
    # taken (linalg.dense.rarely): the rank-deficient branch of the unrolled stage solves
    # takes the unrolled QR, real and complex, so the loop is all fused code.
    from integrators import radau
    from integrators.ida import consistent_values

    case = problems.make("pendulum").with_t_end(1.0)
    method = integrators.make("radau5")
    y0, yp0 = consistent_values(case.mech, 1, case.t0, case.q0, case.v0)
    params = radau.Params(*(jnp.asarray(x, jnp.float64) for x in (
        case.t_end, method.rtol, method.rtol, method.multiplier_atol, method.thet,
        method.fnewt, method.newton_tol, method.safety, method.first_step, method.max_step)),
        jnp.asarray(method.max_steps, jnp.int64))
    static = dict(mech=case.mech, formulation="index3", linear_solver="auto")
    state = radau.initial_state(jnp.asarray(y0), jnp.asarray(yp0),
                                jnp.asarray(case.t0, jnp.float64), params, **static)
    text = radau.run_chunk.lower(state, params, nit=method.newton_max_iter,
                                 **static).compile().as_text()
    assert 'custom_call_target="lapack' not in text
