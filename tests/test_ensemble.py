"""Ensembles: initial states drawn reproducibly, one compiled loop whose lanes equal single
runs, failures confined to their lanes, and the records, store and report that show them."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

import integrators
import problems
from benchmarks import run as cli
from benchmarks.plan import ENSEMBLE_GRID
from benchmarks.store import load_lanes, load_runs
from integrators.base import Grid
from problems.ensemble import draw


def _grid(case):
    return Grid(case.t0, case.t_end, **ENSEMBLE_GRID)


def test_draws_are_consistent_reproducible_and_lane_by_lane():
    case = problems.make("sps-receiver")
    q, v = draw(case, 6, seed=4)
    again, _ = draw(case, 9, seed=4)
    other, _ = draw(case, 6, seed=5)
    assert np.array_equal(q[0], case.q0) and np.array_equal(v[0], case.v0)
    np.testing.assert_array_equal(q, again[:6])  # a lane does not depend on the ensemble size
    assert not np.allclose(q[1:], other[1:])
    assert np.all(np.abs(q[1:] - case.q0).max(axis=1) > 1e-6)  # perturbed, not copied
    mech = case.mech
    for qi, vi in zip(q, v):
        pos, vel = problems.case.residuals(mech, qi, vi, case.t0)
        assert max(pos, vel) <= 1e-12


def test_ensemble_size_is_checked():
    with pytest.raises(ValueError, match="1 to"):
        draw(problems.make("pendulum"), 0)


@pytest.mark.parametrize("method, h", [("rattle", 0.05), ("lobatto3ab2", 0.05),
                                       ("genalpha", 0.05), ("baumgarte-rk4", 0.05)])
def test_each_lane_equals_its_single_run(method, h):
    case = problems.make("pendulum").with_t_end(5.0)
    q0s, v0s = draw(case, 5, seed=1)
    integ = integrators.make(method, h=h)
    lanes = integ.prepare_ensemble(case, _grid(case), q0s, v0s)()
    assert len(lanes) == 5
    for i, lane in enumerate(lanes):
        single = integ.prepare(case.with_initial(q0s[i], v0s[i]), _grid(case))()
        assert lane.status == single.status == "ok"
        # The same arithmetic, vectorised over the lanes: equal to round-off accumulated
        # over 100 steps (baumgarte-rk4's single run steps by t_{k+1} - t_k, the loop by h).
        np.testing.assert_allclose(lane.q_final, single.q_final, rtol=0, atol=1e-12)
        np.testing.assert_allclose(lane.v_final, single.v_final, rtol=0, atol=1e-12)
        # Maxima over the run (baumgarte-rk4's single run lays its windows out by time).
        for name in ("pos", "vel", "energy"):
            assert np.max(lane.windows[name]) == pytest.approx(np.max(single.windows[name]),
                                                               rel=1e-6, abs=1e-14)


def test_a_failing_lane_stops_only_itself():
    case = problems.make("pendulum").with_t_end(5.0)
    q0s, v0s = draw(case, 4, seed=2)
    v0s[2] *= 1e4  # still consistent (G v = 0 is linear in v); Newton cannot follow it
    integ = integrators.make("rattle", h=0.1)
    lanes = integ.prepare_ensemble(case, _grid(case), q0s, v0s)()
    assert lanes[2].status == "failed" and lanes[2].fail_step is not None
    for i in (0, 1, 3):
        single = integ.prepare(case.with_initial(q0s[i], v0s[i]), _grid(case))()
        assert lanes[i].status == "ok"
        assert lanes[i].counts["n_steps"] == single.counts["n_steps"] == 50
        np.testing.assert_allclose(lanes[i].q_final, single.q_final, rtol=0, atol=1e-13)


def test_sps_receiver_ensemble_keeps_every_lane_on_the_constraints():
    """256 perturbed lanes of RATTLE at h = 0.05 to t = 50: every lane ok with max |g| at
    round-off, and five lanes picked at random equal single runs from their states."""
    case = problems.make("sps-receiver")
    q0s, v0s = draw(case, 256, seed=0)
    integ = integrators.make("rattle", h=0.05)
    lanes = integ.prepare_ensemble(case, _grid(case), q0s, v0s)()
    assert all(lane.status == "ok" for lane in lanes)
    assert max(float(np.max(lane.windows["pos"])) for lane in lanes) <= 1e-12
    for i in np.random.default_rng(7).choice(256, 5, replace=False):
        single = integ.prepare(case.with_initial(q0s[i], v0s[i]), _grid(case))()
        np.testing.assert_allclose(lanes[i].q_final, single.q_final, rtol=0, atol=1e-12)
        np.testing.assert_allclose(lanes[i].v_final, single.v_final, rtol=0, atol=1e-12)


@pytest.mark.slow
def test_command_line_records_quantiles_lanes_and_report(tmp_path):
    out = tmp_path / "out"
    code = cli.main(["--problems", "pendulum", "--integrators", "rattle", "ida-ggl",
                     "--h", "0.05", "--rtol", "1e-6", "--t-end", "2", "--ensemble", "6",
                     "--seed", "3", "--jobs", "1", "--out", str(out)])
    assert code == 0
    runs = pd.read_csv(out / "runs.csv")
    assert set(runs["lanes"]) == {6} and set(runs["seed"]) == {3}
    assert list(runs.sort_values("integrator")["batched"]) == [0, 1]  # ida lane by lane
    assert (runs["failed_fraction"] == 0).all()
    assert (runs["pos_q0"] <= runs["pos_q50"]).all()
    assert (runs["pos_q50"] <= runs["pos_q100"]).all()
    assert np.allclose(runs["pos_q100"], runs["max_pos_residual"])  # the worst lane
    stored = load_runs(out / "driftbench.sqlite")
    lanes = load_lanes(out / "driftbench.sqlite", int(stored["run_id"].iloc[0]))
    assert list(lanes["seed"]) == list(range(6)) and (lanes["status"] == 0).all()
    assert lanes["final_state_error"].iloc[1:].isna().all()  # no reference off lane 0
    html = (out / "report.html").read_text()
    assert "Ensembles: pendulum" in html and "ensemble-distributions" in html


@pytest.mark.parametrize("argv, what", [(["--ensemble", "0"], "--ensemble 0"),
                                        (["--ensemble", "2", "--seed", "-1"], "--seed -1")])
def test_bad_ensemble_arguments_are_one_line(tmp_path, capsys, argv, what):
    code = cli.main(["--problems", "pendulum", "--integrators", "rattle", "--out",
                     str(tmp_path), *argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and what in err[0]


def test_bad_ensemble_in_a_suite_names_the_line(tmp_path, capsys):
    suite = tmp_path / "s.toml"
    suite.write_text('description = "x"\n[[group]]\nproblems = ["pendulum"]\n'
                     'integrators = ["rattle"]\nensemble = -3\n')
    code = cli.main(["--suite", str(suite), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "s.toml:5" in err[0] and "ensemble" in err[0]
