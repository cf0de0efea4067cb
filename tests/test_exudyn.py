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


@pytest.mark.parametrize("argv", [["--n", "0"], ["--h-chain", "-1e-5"], ["--rho-inf", "2"]])
def test_bad_settings_are_one_line_and_exit_2(argv, capsys):
    with pytest.raises(SystemExit) as stop:
        bench.main(argv)
    assert stop.value.code == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_chain_final_state_agrees_with_exudyn():
    exu = pytest.importorskip("exudyn")
    from exudyn import itemInterface as items

    args = bench.parser().parse_args(["--steps", "5", "--rounds", "1"])
    row = bench.compare(exu, items, "chain", 4, args)
    assert row["steps"] == row["exudyn_steps"] == 5
    assert row["final_q_difference"] <= bench.AGREEMENT
    assert row["final_v_difference"] <= bench.AGREEMENT
    assert row["agree"] and row["newton_per_step"] >= 1 and row["exudyn_newton_per_step"] >= 1


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
