"""What a solve of the compiled fixed-step loop (:func:`integrators.loop.march`) hands to
the host: the rows of its windows and samples that the plan uses (to the next power of
two), not the grid's whole buffers, in one copy, with the values of a grid of exactly
those rows bit for bit, solve after solve, for one run, an ensemble, and runs retaken
with the fallback."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import integrators
import problems
from integrators.base import Failure, Grid
from integrators.loop import march, rows_copied
from integrators.newton import _deferred
from problems.ensemble import draw


def same(a, b):
    """``a`` and ``b`` (trajectories) equal bit for bit."""
    assert (a.status, a.message, a.t_final, a.counts) == (b.status, b.message, b.t_final,
                                                          b.counts)
    np.testing.assert_array_equal(a.q_final, b.q_final, strict=True)
    np.testing.assert_array_equal(a.v_final, b.v_final, strict=True)
    for record in ("windows", "samples"):
        x, y = getattr(a, record), getattr(b, record)
        assert x.keys() == y.keys()
        for key in x:
            np.testing.assert_array_equal(x[key], y[key], strict=True)


def poison(solve) -> None:
    """Fill the sample buffers that ``solve`` (a prepared solve, or a function that calls
    one) hands to its next call with NaN: a solve that read a row it did not write would
    carry the NaN into its records."""
    seen, todo = set(), [solve]
    while todo:
        fn = todo.pop()
        if id(fn) in seen or not callable(fn):
            continue
        seen.add(id(fn))
        code, cells = getattr(fn, "__code__", None), getattr(fn, "__closure__", None) or ()
        for name, cell in zip(code.co_freevars if code else (), cells):
            value = cell.cell_contents
            if name == "spare":
                value[:] = [tuple(jnp.full(b.shape, jnp.nan, b.dtype) for b in buffers)
                            for buffers in value]
                return
            todo.append(value)
    raise AssertionError("no sample buffers found in the solve's closure")


@pytest.fixture
def handed(monkeypatch):
    """The shapes of the arrays of each ``jax.device_get`` call, in call order."""
    calls = []
    device_get = jax.device_get

    def watched(x):
        calls.append([np.shape(a) for a in jax.tree_util.tree_leaves(x)])
        return device_get(x)

    monkeypatch.setattr(jax, "device_get", watched)
    return calls


def test_rows_copied_are_the_used_ones_to_the_next_power_of_two():
    assert [rows_copied(used, 2000) for used in (1, 2, 3, 11, 16, 17, 1500)] == \
        [1, 2, 4, 16, 16, 32, 2000]


@pytest.mark.parametrize("problem, name, lanes", [("chain:N=4", "genalpha", 0),
                                                   ("pendulum", "rattle", 3)])
def test_a_solve_copies_the_rows_its_plan_uses_and_the_values_of_a_grid_of_those(
        problem, name, lanes, handed):
    # 10 steps record 10 windows and 11 samples: 16 rows of each reach the host, of the
    # default grid's 1000 and 2000, whose solve matches a grid of exactly 10 and 11. (No
    # step fails, so no loop is retaken: one copy per solve.)
    case = problems.make(problem)
    method = integrators.make(name)
    case = case.with_t_end(case.t0 + 10 * method.h)
    grids = Grid(case.t0, case.t_end), Grid(case.t0, case.t_end, n_windows=10, n_samples=11)
    if lanes:
        q0s, v0s = draw(case, lanes, seed=0)
        solve, exact = (method.prepare_ensemble(case, grid, q0s, v0s) for grid in grids)
    else:
        solve, exact = (method.prepare(case, grid) for grid in grids)
    reference = exact()
    handed.clear()
    first = solve()
    poison(solve)
    again = solve()
    assert len(handed) == 2  # one copy to the host per solve
    n, columns = case.mech.n, len((reference[0] if lanes else reference).windows) - 1
    lead = (lanes,) if lanes else ()
    for shapes in handed:
        assert shapes[5:8] == [lead + (16, columns), lead + (16, n), lead + (16, n)]
    runs = zip(first, again, reference) if lanes else [(first, again, reference)]
    for one, two, reference in runs:
        assert one.status == "ok" and one.counts["n_steps"] == 10
        assert len(one.samples["t"]) == 11 and len(one.windows["t"]) == 10
        same(one, reference)
        same(two, reference)  # buffers handed on full of NaN change nothing


@pytest.mark.parametrize("lanes", [False, True])
def test_a_run_retaken_with_the_fallback_keeps_its_records(lanes, handed):
    # Without the fallback (the first loop of every path) the step fails for lane 1
    # at step 3; the loop with it takes that step again. The result is that of a loop that
    # never failed, bit for bit, and each of the two copies to the host is of the used
    # rows only.
    case = problems.make("pendulum").with_t_end(1.0)
    q0s, v0s = draw(case, 3, seed=0)
    h = 0.1

    def stepper(failing: bool):
        def step(carry, t, h):
            q, v, lane = carry
            k = jnp.round((t - case.t0) / h)
            fails = failing & (lane == 1) & (k == 3) & _deferred.get()
            code = jnp.where(fails, Failure.NEWTON, Failure.NONE)
            return (q + h * v, v, lane), code, jnp.asarray(0.0), {"n_newton": jnp.asarray(1)}
        return step

    carry0 = ((jnp.asarray(q0s), jnp.asarray(v0s), jnp.arange(3)) if lanes else
              (jnp.asarray(q0s[1]), jnp.asarray(v0s[1]), jnp.asarray(1)))
    grid = Grid(case.t0, case.t_end)
    retaken, plain = (march(case.mech, grid, h, carry0, stepper(failing),
                            lambda carry: carry[:2], linear_solver=solver, lanes=lanes)
                      for failing, solver in ((True, "banded"), (False, "dense")))
    reference = plain()
    handed.clear()
    runs = retaken()
    poison(retaken)
    twice = retaken()
    assert retaken.late_setup_s > 0  # the loop with the fallback ran
    assert len(handed) == 4  # the first loop's copy, then the retaken loop's, per solve
    for shapes in handed:
        assert {s[-2] for s in shapes[6:8]} == {16}
    if not lanes:
        runs, twice, reference = [runs], [twice], [reference]
    for one, two, ref in zip(runs, twice, reference):
        assert one.status == "ok" and one.counts["n_steps"] == 10
        same(one, ref)
        same(two, ref)


@pytest.mark.parametrize("lanes", [False, True])
def test_a_run_that_fails_midway_records_only_what_it_reached(lanes):
    # Lane 1 fails at its fourth step with and without the fallback: its records end
    # there, and stay so when the buffers it is handed are full of NaN.
    case = problems.make("pendulum").with_t_end(1.0)
    q0s, v0s = draw(case, 3, seed=0)

    def step(carry, t, h):
        q, v, lane = carry
        fails = (lane == 1) & (jnp.round((t - case.t0) / h) == 3)
        return ((q + h * v, v, lane), jnp.where(fails, Failure.NEWTON, Failure.NONE),
                jnp.asarray(0.0), {"n_newton": jnp.asarray(1)})

    carry0 = ((jnp.asarray(q0s), jnp.asarray(v0s), jnp.arange(3)) if lanes else
              (jnp.asarray(q0s[1]), jnp.asarray(v0s[1]), jnp.asarray(1)))
    solve = march(case.mech, Grid(case.t0, case.t_end), 0.1, carry0, step,
                  lambda carry: carry[:2], linear_solver="banded", lanes=lanes)
    first = solve()
    poison(solve)
    again = solve()
    if not lanes:
        first, again = [first], [again]
    failed = first[1 if lanes else 0]
    assert failed.status == "failed" and failed.counts["n_steps"] == 3
    for one, two in zip(first, again):
        same(one, two)
        for record in (two.windows, two.samples):
            assert all(np.isfinite(np.asarray(a)).all() for a in record.values())

