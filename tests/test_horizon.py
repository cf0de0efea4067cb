"""The horizon: ``--t-end`` (a suite's ``t_end``, the Python API's) reaches a problem's
factory where it takes ``t_end``, and no error is scored against a reference past the span
it declares.

The problems are a user's planar pendulum (released at rest from ``theta0 = 1``) whose
reference is computed by the factory up to a horizon (DOP853 on ``theta'' = -g sin theta``,
dense output, which past its end only extrapolates), as a heavy top's reference is;
independently of it, :func:`problems.pendulum.exact_solution` gives the exact motion.
"""

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

import problems
from benchmarks import run as cli
from benchmarks.execute import execute
from benchmarks.metrics import unscored
from benchmarks.plan import plan
from benchmarks.records import InputError, RunSpec
from problems import Reference
from problems.data import reference as stored
from problems.pendulum import exact_solution

USER = """
import jax.numpy as jnp
import numpy as np
from scipy.integrate import solve_ivp

from problems import Reference, System, make_case, register

GRAVITY, THETA0 = 9.81, 1.0


def computed(t_end):
    sol = solve_ivp(lambda t, y: [y[1], -GRAVITY * np.sin(y[0])], (0.0, t_end),
                    [THETA0, 0.0], method="DOP853", rtol=1e-13, atol=1e-13,
                    dense_output=True)

    def state(t):
        theta, omega = sol.sol(t)
        return (np.array([np.sin(theta), -np.cos(theta)]),
                omega * np.array([np.cos(theta), np.sin(theta)]))

    return Reference(kind="computed", source="DOP853 at rtol 1e-13", solution=state,
                     scored=(0, 1, 2, 3), floor=1e-10, span=(0.0, t_end))


def case(name, t_end, reference):
    system = System(n=2, m=1, mass=np.ones(2), potential=lambda q: GRAVITY * q[1],
                    constraints=lambda q, t: jnp.array([q @ q - 1.0]))
    q0, v0 = reference.solution(0.0)
    return make_case(name, system, q0, v0, (0.0, t_end), dict(t_end=t_end),
                     energy_scale=GRAVITY, reference=reference)


@register("horizon-pendulum")
def horizon_pendulum(t_end: float = 1.0):
    return case("horizon-pendulum", t_end, computed(t_end))


@register("horizon-whole")
def horizon_whole(t_end: int = 1):
    return case("horizon-whole", t_end, computed(t_end))


@register("horizon-fixed")
def horizon_fixed():
    return case("horizon-fixed", 1.0, computed(1.0))
"""

#: The factories' own horizon; the runs go to twice it.
DEFAULT, LONGER = 1.0, 2.0


@pytest.fixture(scope="module")
def user(tmp_path_factory):
    path = tmp_path_factory.mktemp("user") / "horizon_problems.py"
    path.write_text(USER)
    problems.load(str(path))
    return str(path)


def exact_error(q_final, v_final, t):
    """The max-norm error of a final ``(q, v)`` (as ``runs.csv`` holds them) against the
    exact motion at ``t``."""
    q, v = exact_solution(t, 1.0, 9.81, 1.0)
    y = np.concatenate([json.loads(q_final), json.loads(v_final)])
    return float(np.max(np.abs(y - np.concatenate([q, v]))))


def cli_runs(*argv):
    """The runs the command line plans for ``argv``, as the workers receive them."""
    runs, _, _ = cli.plan(cli.parser().parse_args(list(argv)))
    return plan(runs, "test")


def test_t_end_reaches_the_factory_and_scores_the_longer_run(user):
    (run,) = cli_runs("--load", user, "--problems", "horizon-pendulum", "--integrators",
                      "rattle", "--h", "0.01", "--t-end", str(LONGER))
    # The case, its recorded parameters and its reference are the longer horizon's.
    assert run.problem.kwargs["t_end"] == LONGER and run.run.t_end == LONGER
    assert json.loads(run.run.params) == {"t_end": LONGER}
    record = execute(run, repeats=1)
    assert record.ending.status == "ok" and record.ending.t_final == pytest.approx(LONGER)
    error = record.metrics.final_state_error
    # The method's error (RATTLE at h = 0.01, order 2), found again against the exact
    # motion to the reference's accuracy; a reference extrapolated from t = 1 to 2 would
    # be off by far more than the run.
    assert 1e-7 < error < 1e-2
    end = record.ending
    assert error == pytest.approx(exact_error(end.q_final, end.v_final, LONGER), abs=1e-9)
    assert not record.ending.message
    # The horizon given on the command line is the horizon given in the spec: one run.
    (same,) = cli_runs("--load", user, "--problems", f"horizon-pendulum:t_end={LONGER}",
                       "--integrators", "rattle", "--h", "0.01")
    assert same.run.run_key == run.run.run_key


@pytest.mark.slow
def test_the_python_api_s_t_end_reaches_the_factory(user):
    from benchmarks.api import sweep

    runs = sweep(["horizon-pendulum", "horizon-fixed"], "rattle", h=0.01, t_end=LONGER,
                 load=[user], jobs=1, log=None)
    scored, past = runs.iloc[0], runs.iloc[1]
    assert json.loads(scored["params"]) == {"t_end": LONGER} and scored["status"] == "ok"
    assert 1e-7 < scored["final_state_error"] == pytest.approx(
        exact_error(scored["q_final"], scored["v_final"], LONGER), abs=1e-9)
    assert math.isnan(past["final_state_error"]) and "outside the span" in past["message"]


def test_a_suite_s_t_end_and_the_command_line_s_reach_the_factory(user, tmp_path):
    suite = tmp_path / "horizon.toml"
    suite.write_text(f'description = "horizon"\nload = [{json.dumps(user)}]\n\n[[group]]\n'
                     f'problems = ["horizon-pendulum", "horizon-whole"]\n'
                     f'integrators = ["rattle"]\nh = [0.01]\nt_end = {LONGER}\n')
    runs = cli_runs("--suite", str(suite))
    assert [r.problem.kwargs["t_end"] for r in runs] == [LONGER, int(LONGER)]
    assert [json.loads(r.run.params)["t_end"] for r in runs] == [LONGER, int(LONGER)]
    runs = cli_runs("--suite", str(suite), "--t-end", "3")
    assert [r.problem.kwargs["t_end"] for r in runs] == [3.0, 3]
    assert [r.run.t_end for r in runs] == [3.0, 3.0]


def test_a_whole_number_t_end_takes_a_whole_horizon_and_is_no_size(user):
    spec = problems.at_horizon("horizon-whole", 200000.0)
    assert spec.kwargs["t_end"] == 200000 and isinstance(spec.kwargs["t_end"], int)
    problems.check_size(spec)  # a horizon is not a count of bodies
    with pytest.raises(InputError, match=r"horizon-whole.*t_end is a whole number.*2\.5"):
        cli_runs("--load", user, "--problems", "horizon-whole", "--integrators", "rattle",
                 "--h", "0.01", "--t-end", "2.5")


def test_no_final_error_past_the_reference_s_span(user):
    inside, past = plan([RunSpec("horizon-fixed", "rattle", h=0.01, t_end=t)
                         for t in (DEFAULT, LONGER)], "test")
    # A factory without t_end keeps its case; the horizon cuts it.
    assert past.problem.kwargs == {} and past.run.t_end == LONGER
    scored = execute(inside, repeats=1)
    end = scored.ending
    assert scored.metrics.final_state_error == pytest.approx(
        exact_error(end.q_final, end.v_final, DEFAULT), abs=1e-9)
    record = execute(past, repeats=1)
    assert record.ending.status == "ok" and record.ending.t_final == pytest.approx(LONGER)
    assert record.metrics.final_state_error is None and record.metrics.scd is None
    assert record.metrics.reference_floor is None
    assert record.ending.message == ("no final error: the run ends at t = 2, outside the "
                                     "span [0, 1] its reference is valid on")
    assert record.row["final_state_error"] is None or math.isnan(record.row["final_state_error"])


def test_an_ensemble_past_the_span_has_no_final_errors_and_says_why(user):
    (run,) = plan([RunSpec("horizon-fixed", "rattle", h=0.01, t_end=LONGER, lanes=2, seed=0)],
                  "test")
    record = execute(run, repeats=1)
    assert record.ending.status == "ok"
    assert np.isnan(record.lanes["final_state_error"]).all()
    assert record.metrics.final_state_error is None and record.spread.final_q100 is None
    assert "outside the span [0, 1]" in record.ending.message


def test_a_span_is_two_finite_ordered_times():
    def ref(**kw):
        return Reference("computed", "test", lambda t: (np.zeros(1), np.zeros(1)), (0,), **kw)

    for bad in [(0.0, math.nan), (1.0, 0.0), (0.0, math.inf), (0.0,)]:
        with pytest.raises(ValueError, match="span"):
            ref(span=bad)
    spanned = ref(span=(0.0, 5.0))
    assert spanned.available_at(0.0) and spanned.available_at(5.0 + 1e-13)
    assert not spanned.available_at(5.0 + 1e-9) and not spanned.available_at(-1e-9)
    timed = ref(span=(0.0, 5.0), times=(1.0, 5.0, 7.0))
    assert timed.available_at(5.0) and not timed.available_at(7.0)
    assert ref().available_at(1e9)


def test_stored_references_declare_their_span_and_runs_past_it_say_why():
    params = dict(N=2, length=1.0, mass=1.0, gravity=9.81, theta0=float(np.pi / 4))
    ref = stored("chain", params)
    assert ref.span == (0.0, 5.0)
    case = SimpleNamespace(reference=ref)
    ok = dict(status="ok", q_final=None, v_final=None)
    assert unscored(case, SimpleNamespace(t_final=5.0, **ok)) == ""
    assert unscored(case, SimpleNamespace(t_final=6.0, **ok)) == (
        "no final error: the run ends at t = 6, outside the span [0, 5] its reference is "
        "valid on")
    assert unscored(case, SimpleNamespace(t_final=2.0, **ok)) == (
        "no final error: the run ends at t = 2; the reference exists only at t = 1, 5")
    # A run that stopped says why in its own message.
    assert unscored(case, SimpleNamespace(t_final=6.0, status="failed")) == ""
