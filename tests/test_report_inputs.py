"""What the report takes from other layers: the gate's rule for a regression (its history
must mark exactly what the gate fails) and a suite's accuracy targets."""

import pytest

from benchmarks import check, gate, suites


def test_the_history_and_the_gate_share_one_regression_rule():
    """One rule, defined once in benchmarks.gate: the gate's command imports it, and the
    report's history uses it (the report must not import the gate's command, which pulls
    in JAX)."""
    from reports import analysis

    assert check.compare is gate.compare and check.TOLERANCES is gate.TOLERANCES
    assert analysis.gate is gate


def test_a_suite_sets_its_accuracy_targets(tmp_path):
    body = '[[group]]\nproblems = ["pendulum"]\nintegrators = ["rattle"]\nh = [0.1]\n'
    path = tmp_path / "mine.toml"
    path.write_text("targets = [1e-6, 1e-10]\n" + body)
    assert suites.load(str(path)).targets == (1e-6, 1e-10)
    path.write_text(body)
    assert suites.load(str(path)).targets == ()
    path.write_text("targets = [0.0]\n" + body)
    with pytest.raises(suites.SuiteError, match=r"mine.toml:1: 'targets' = 0.0 must be positive"):
        suites.load(str(path))


@pytest.mark.slow
def test_the_command_line_report_uses_the_suite_targets(tmp_path):
    """A suite's ``targets`` reach the report that ``benchmarks.run`` builds."""
    from benchmarks import run

    suite = tmp_path / "mine.toml"
    suite.write_text('targets = [3e-3]\nrepeats = 1\n[[group]]\nproblems = ["pendulum"]\n'
                     'integrators = ["rattle"]\nh = [0.1]\nt_end = 1.0\n')
    assert run.main(["--suite", str(suite), "--out", str(tmp_path / "out"), "--jobs", "1"]) == 0
    report = (tmp_path / "out" / "report.md").read_text()
    assert "≤ 0.003" in report and "≤ 1e-08" not in report
