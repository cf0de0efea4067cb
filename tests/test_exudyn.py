"""The Exudyn benchmark's model is the suite's: its generalized-alpha and ``genalpha`` end in
the same state (:mod:`benchmarks.perf.exudyn`)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from benchmarks.perf import exudyn as bench


def test_missing_exudyn_is_one_line_and_exit_2(monkeypatch, capsys, tmp_path):
    monkeypatch.setitem(sys.modules, "exudyn", None)   # import exudyn raises ImportError
    assert bench.main(["--n", "4", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == bench.INSTALL and "pip install 'exudyn'" in err
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("argv", [["--n", "0"], ["--h-chain", "-1e-5"], ["--rho-inf", "2"],
                                  ["--steps", "1"], ["--best-of", "0"],
                                  ["--exudyn-rtol", "0"]])
def test_bad_settings_are_one_line_and_exit_2(argv, capsys):
    with pytest.raises(SystemExit) as stop:
        bench.main(argv)
    assert stop.value.code == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_chain_final_state_agrees_with_exudyn():
    exu = pytest.importorskip("exudyn")
    from exudyn import itemInterface as items

    # The default 100 steps, each solve the fastest of 3: the time per step is a
    # difference of solves, which 5 steps timed once left to the load (not positive with
    # the other test worker busy).
    args = bench.parser().parse_args(["--rounds", "1"])
    row = bench.compare(exu, items, "chain", 4, args)
    assert row["status"] == "ok", row["status"]
    assert row["steps"] == row["exudyn_steps"] == 100
    assert row["final_q_difference"] <= bench.AGREEMENT
    assert row["final_v_difference"] <= bench.AGREEMENT
    assert row["agree"] and row["newton_per_step"] >= 1 and row["exudyn_newton_per_step"] >= 1
    # The chain's equations are the suite's: the judged solve is the timed one.
    assert row["equations"] == "the suite's"
    assert row["suite_v_difference"] == row["final_v_difference"]
    assert (row["exudyn_rtol"], row["exudyn_atol"]) == bench.EXUDYN_TOLERANCES["chain"]


@pytest.mark.slow
def test_rigid_chain_agrees_in_exudyns_rigid_body_equations():
    """The suite's rigid chain ends O(h^2) away from Exudyn's (the Lagrange and the
    Newton-Euler equations differ off e . e' = 0); with that term taken off as a force,
    ours ends where Exudyn's does."""
    exu = pytest.importorskip("exudyn")
    from exudyn import itemInterface as items

    args = bench.parser().parse_args(["--steps", "20", "--rounds", "1", "--best-of", "1"])
    row = bench.compare(exu, items, "rigid-chain", 2, args)
    assert row["status"] == "ok" and row["equations"] == "Exudyn's rigid-body"
    assert (row["exudyn_rtol"], row["exudyn_atol"]) == bench.EXUDYN_TOLERANCES["rigid-chain"]
    assert row["final_q_difference"] <= 1e-3 * bench.AGREEMENT
    assert row["final_v_difference"] <= 1e-1 * bench.AGREEMENT and row["agree"]
    assert row["suite_v_difference"] > 1e2 * row["final_v_difference"]


def test_agreement_allows_exudyns_velocity_rounding():
    from integrators.genalpha import Coefficients

    c = Coefficients.from_rho_inf(0.5)
    eps = np.finfo(np.float64).eps
    v_round = bench.velocity_rounding(np.array([3.0, -1000.0]), 5e-4, 0.5)
    assert v_round == pytest.approx(bench.ROUNDING_UNITS * eps * 1000.0 * c.gamma
                                    / (c.beta * 5e-4))
    assert bench.agrees(1e-10, 2e-9, 3e-9) and not bench.agrees(1e-10, 2e-9, 1e-10)
    assert bench.agrees(1e-10, 9e-10, 0.0) and not bench.agrees(2e-9, 0.0, 1.0)


def test_time_per_step_is_beyond_the_fixed_cost():
    # Per round (t_S - t_1) / (S - 1), the median over rounds.
    assert bench.marginal([1.0, 2.0, 1.5], [0.1, 0.2, 0.2], 10) == pytest.approx(1.3 / 9)
    runs = iter([{"wall": 3.0, "cpu": 1.0, "id": 0}, {"wall": 2.0, "cpu": 1.5, "id": 1}])
    assert bench.fastest(lambda: next(runs), 2) == {"wall": 2.0, "cpu": 1.0, "id": 1}


def test_a_marginal_time_swamped_by_load_is_a_status(monkeypatch):
    exu = pytest.importorskip("exudyn")
    from exudyn import itemInterface as items

    monkeypatch.setattr(bench, "marginal", lambda long, short, steps: 0.0)
    args = bench.parser().parse_args(["--steps", "2", "--rounds", "1", "--best-of", "1"])
    row = bench.compare(exu, items, "chain", 2, args)
    assert row["status"].startswith("the marginal time per step is not positive")
    assert "ratio_per_step" not in row


def test_a_different_chain_in_exudyn_is_detected():
    """The comparison can fail: Exudyn's chain under 1 % less gravity ends elsewhere."""
    exu = pytest.importorskip("exudyn")
    from exudyn import itemInterface as items

    import integrators
    import problems
    from integrators.base import Grid

    h, steps = bench.STEP["chain"], 5
    case = problems.make("chain:N=4").with_t_end(steps * h)
    other = problems.make("chain:N=4,gravity=9.7119").with_t_end(steps * h)
    sim = bench.settings(exu, h, steps, 0.5, 1e-8, 1e-10)
    container, mbs = bench.chain_model(exu, items, other)  # the container owns mbs
    theirs = bench.exudyn_solve(exu, mbs, sim, np.asarray(other.q0))
    ours = integrators.make(f"genalpha:h={h}").prepare(case, Grid(case.t0, case.t_end))()
    assert ours.status == "ok"
    assert np.max(np.abs(theirs["v"] - np.asarray(ours.v_final))) > 1e3 * bench.AGREEMENT


def test_a_failed_solve_is_a_row_and_the_run_goes_on(monkeypatch, tmp_path, capsys):
    pytest.importorskip("exudyn")
    import json

    def stopped(exu, mbs, sim, q0):
        raise RuntimeError("Exudyn stopped after 1 of 2 steps")

    monkeypatch.setattr(bench, "exudyn_solve", stopped)
    code = bench.main(["--problems", "chain", "--n", "2", "3", "--steps", "2", "--rounds", "1",
                       "--out", str(tmp_path)])
    assert code == 1
    rows = json.loads((tmp_path / "exudyn.json").read_text())["rows"]
    assert [(r["N"], r["status"]) for r in rows] == [
        (2, "Exudyn stopped after 1 of 2 steps"), (3, "Exudyn stopped after 1 of 2 steps")]
    assert "chain            3" in capsys.readouterr().out
