"""The efficiency benchmark's C yardsticks end where our runs end, and the small dense
solves that keep LAPACK out of the compiled loops give LAPACK's results.

Timing is never asserted here (``python -m benchmarks.perf.efficiency`` measures it).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import integrators
import problems
from benchmarks.perf import efficiency
from benchmarks.perf.processes import compile_yardstick
from integrators import baumgarte
from integrators.base import Grid
from linalg import dense
from helpers import needs_cc


@pytest.fixture(scope="module")
def baumgarte_rk(tmp_path_factory):
    exe, note, _ = compile_yardstick("baumgarte_rk", tmp_path_factory.mktemp("yardstick"))
    assert exe is not None, note
    return exe


@pytest.mark.slow
@needs_cc
@pytest.mark.parametrize("problem", ["pendulum", "double-pendulum"])
def test_baumgarte_yardstick_ends_where_our_runs_end(baumgarte_rk, problem):
    # The same grid for rk4 (so the same state to round-off) and the same step control
    # for dopri5 (so the same accepted and rejected steps; the states agree far inside
    # the tolerance).
    case = problems.make(problem).with_t_end(2.0)
    grid = Grid(case.t0, case.t_end)
    rk4 = integrators.make("baumgarte-rk4:h=0.01")
    ours = rk4.prepare(case, grid)()
    theirs = efficiency._baumgarte_yardstick(baumgarte_rk, problem, "rk4", ["200"], case, rk4)
    assert ours.counts["n_steps"] == theirs["steps"] == 200
    dq, dv = efficiency.state_difference(theirs["y"], [*ours.q_final, *ours.v_final])
    assert max(dq, dv) <= 1e-12

    dopri5 = integrators.make("baumgarte-dopri5:rtol=1e-6,atol=1e-8")
    ours = dopri5.prepare(case, grid)()
    theirs = efficiency._baumgarte_yardstick(baumgarte_rk, problem, "dopri5",
                                             ["1e-06", "1e-08"], case, dopri5)
    assert ours.status == "ok"
    assert abs(ours.counts["n_steps"] - theirs["steps"]) <= 0.03 * theirs["steps"]
    assert abs(ours.counts["n_rejected"] - theirs["rejected"]) <= 0.03 * theirs["steps"]
    dq, dv = efficiency.state_difference(theirs["y"], [*ours.q_final, *ours.v_final])
    assert max(dq, dv) <= 1e-6


def test_the_double_pendulums_loop_calls_no_lapack():
    # A LAPACK call cannot fuse, and one in a loop's body costs at every pass even in a
    # branch that is not taken: the 2 x 2 Cholesky factor and the rank-deficient branch's
    # QR of the Schur complement are written out instead (dense.SMALL_DENSE).
    case = problems.make("double-pendulum").with_t_end(1.0)
    method = integrators.make("baumgarte-dopri5")
    control, params = method._loop(Grid(case.t0, case.t_end))
    solver = baumgarte.SOLVERS["dopri5"]()
    params, static, _ = baumgarte._static(case.mech, params, 10, solver, control, "auto")
    y0 = jnp.asarray(np.concatenate([case.q0, case.v0]))
    state = baumgarte.initial_state(y0, params, **static)
    text = baumgarte.run_one.lower(state, params, grid=Grid(case.t0, case.t_end),
                                   **static).compile().as_text()
    assert 'custom_call_target="lapack' not in text


def lapack_basic_solve(S, b):
    """The basic solution as :func:`linalg.dense.basic_solve` takes it with LAPACK."""
    Q, R, perm = jax.scipy.linalg.qr(S, pivoting=True)
    d = jnp.abs(jnp.diag(R))
    keep = d > dense.RANK_RTOL * d[0]
    R = jnp.where(keep[:, None], R, jnp.eye(S.shape[0]))
    y = jax.scipy.linalg.solve_triangular(R, jnp.where(keep, Q.T @ b, 0.0))
    return jnp.zeros_like(y).at[perm].set(y)


@pytest.mark.parametrize("m", [2, 3, 4])
def test_small_dense_solves_are_lapacks(m):
    rng = np.random.default_rng(m)
    cholesky = jax.jit(lambda S: (dense.small_cho_factor(S),
                                  jnp.tril(jax.scipy.linalg.cho_factor(S, lower=True)[0])))
    basic = jax.jit(lambda S, b: (dense.small_basic_solve(S, b), lapack_basic_solve(S, b)))
    for trial in range(20):
        B = rng.normal(size=(m, m - trial % 2))
        S = B @ B.T                              # rank m - 1 on odd trials
        b = S @ rng.normal(size=m)               # consistent
        if trial % 2 == 0:
            small, lapack = cholesky(S)
            np.testing.assert_allclose(small, lapack, rtol=1e-12, atol=1e-12)
        # The same unknowns are zero, and the others agree.
        small, lapack = basic(S, b)
        np.testing.assert_array_equal(small == 0, lapack == 0)
        np.testing.assert_allclose(small, lapack, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(S @ small, b, atol=1e-10)
