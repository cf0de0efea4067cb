"""The C yardstick of ``radau5`` and ``radau5-ggl`` (``radau_pendulum``) takes the steps
ours take and ends where our runs end, and the Radau loop on the pendulum calls no LAPACK.
Timing is never asserted here (``python -m benchmarks.perf.efficiency`` measures it)."""

from __future__ import annotations

import shutil

import jax.numpy as jnp
import pytest

import integrators
import problems
from benchmarks.perf import efficiency
from benchmarks.perf.processes import compile_yardstick, state_difference
from integrators.base import Grid

needs_cc = pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None,
                              reason="no C compiler (cc or gcc) on PATH")


@pytest.fixture(scope="module")
def radau_pendulum(tmp_path_factory):
    exes = {}
    for formulation in ("index3", "ggl"):
        exe, note, _ = compile_yardstick("radau_pendulum", tmp_path_factory.mktemp(formulation),
                                         efficiency.radau_flags(formulation))
        assert exe is not None, note
        exes[formulation] = exe
    return exes


@needs_cc
@pytest.mark.parametrize("family, thet", [("radau5", None), ("radau5", -1.0),
                                          ("radau5-ggl", None)])
def test_radau_yardstick_ends_where_our_run_ends(radau_pendulum, family, thet):
    # The same algorithm from the same point: the same accepted and rejected steps,
    # Jacobians and factorisations (a different LU's round-off may move a decision late
    # in a long run, not in 1 s), and final states far inside the tolerance. thet = -1
    # (a Jacobian at every step) shows that the options reach the yardstick.
    rtol = 1e-8
    case = problems.make("pendulum").with_t_end(1.0)
    spec = f"{family}:rtol={rtol!r},atol=1e-10" + ("" if thet is None else f",thet={thet!r}")
    method = integrators.make(spec)
    ours = method.prepare(case, Grid(case.t0, case.t_end))()
    theirs = efficiency.radau_yardstick_run(efficiency.radau_yardstick_command(
        radau_pendulum[method.formulation], method, case, 1))
    assert ours.status == "ok"
    steps = theirs["steps"]
    assert abs(ours.counts["n_steps"] - steps) <= 0.02 * steps
    for key, c_key in (("n_rejected", "rejected"), ("n_jac_evals", "jacobians")):
        assert abs(ours.counts[key] - theirs[c_key]) <= 0.02 * steps
    assert abs(ours.extra["n_lu"] - theirs["lu"]) <= 0.02 * steps
    if thet is not None:
        assert theirs["jacobians"] >= steps and ours.counts["n_jac_evals"] >= steps
    dq, dv = state_difference(theirs["y"][:2 * case.mech.n], [*ours.q_final, *ours.v_final])
    assert max(dq, dv) <= 10 * rtol


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
